"""Observation operator: what the camera sees of the FE model, as a DIC recording would (paper §4).

The data flows in three steps:

1. :func:`visible_faces` finds the boundary faces of a Hex20 mesh that an orthographic camera sees,
   by line of sight (ray tests on the triangulated boundary), in the reference configuration.
2. :class:`ObservationOperator` places observation points on those faces (the mesh nodes, as in the
   paper, or an arbitrary DIC grid located on the Quad8 faces) and maps nodal displacements to the
   observed components there by the face shape functions.
3. :func:`interpolate_in_time` takes FE load steps to frame times (:func:`frame_times`).

Units: mm for coordinates and displacements; time normalized to [0, 1] (or s, consistently).
Face sets are ``(element, face)`` rows with ``face`` 0..5 = Abaqus S1..S6, as in :class:`Mesh`.
"""
from __future__ import annotations

import importlib.util

import numpy as np
import scipy.sparse as sp
import torch
import trimesh

from torchfra.fem.elements import HEX20_FACES, QUAD8_NATURAL, quad8_shape
from torchfra.fem.mesh import Mesh, MeshError

# A Quad8 face as 6 triangles: the four corners cut off, the mid-edge quad split in two. Reversed
# so that the triangle normals point out of the element (HEX20_FACES order points into it).
_QUAD8_TRIANGLES = np.array([[0, 4, 7], [4, 1, 5], [5, 2, 6], [6, 3, 7], [4, 5, 6], [4, 6, 7]])[:, ::-1]
# Natural points of a face that rays are cast towards: the centre and four interior points.
_RAY_SAMPLES = np.array([[0.0, 0.0], [-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])


class ObservationError(ValueError):
    """Invalid observation input; the message names the point, face or time at fault."""


# -- faces and their geometry ------------------------------------------------------------------------

def boundary_faces(mesh: Mesh) -> np.ndarray:
    """Element faces not shared by two elements: (k, 2) rows ``(element, face)``, sorted.

    Faces are matched by their four corner node ids, so coincident but unmerged nodes make a seam.
    """
    corners = np.sort(mesh.elements[:, HEX20_FACES[:, :4]].reshape(-1, 4), axis=1)
    _, inverse, counts = np.unique(corners, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if counts.max(initial=0) > 2:
        row = int(np.flatnonzero(counts[inverse] > 2)[0])
        raise MeshError(
            f"face S{row % 6 + 1} of element {row // 6} (corner nodes {corners[row].tolist()}) is shared "
            f"by {counts[inverse[row]]} elements; a valid mesh shares a face between at most two"
        )
    rows = np.flatnonzero(counts[inverse] == 1)
    return np.stack([rows // 6, rows % 6], axis=1)


def _face_rows(mesh: Mesh, faces) -> np.ndarray:
    if isinstance(faces, str):
        return mesh.face_set(faces)
    rows = np.asarray(faces, dtype=np.int64).reshape(-1, 2)
    if rows.size and (rows[:, 0].min() < 0 or rows[:, 0].max() >= mesh.n_elements or rows[:, 1].min() < 0
                      or rows[:, 1].max() > 5):
        raise ObservationError(
            f"face rows must be (element in 0..{mesh.n_elements - 1}, face in 0..5); got rows spanning "
            f"elements {rows[:, 0].min()}..{rows[:, 0].max()}, faces {rows[:, 1].min()}..{rows[:, 1].max()}"
        )
    return rows


def _face_nodes(mesh: Mesh, faces: np.ndarray) -> np.ndarray:
    """Quad8 node ids (k, 8) of face rows, ``HEX20_FACES`` order."""
    return mesh.elements[faces[:, 0][:, None], HEX20_FACES[faces[:, 1]]]


def _face_map(Xf: np.ndarray, st: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quad8 map of M (face, point) pairs. Xf: (M, 8, 3) face nodes, st: (M, 2).
    Returns N (M, 8), x (M, 3) and dx/dst (M, 3, 2)."""
    N, dN = quad8_shape(st)
    return N, np.einsum("ma,mai->mi", N, Xf), np.einsum("mak,mai->mik", dN, Xf)


def boundary_trimesh(mesh: Mesh, faces=None) -> trimesh.Trimesh:
    """The faces (default: all boundary faces) as a triangle surface, 6 triangles per Quad8 face in
    face order (triangle ``t`` belongs to face row ``t // 6``), normals pointing out of the body.
    Vertices are all mesh nodes (mm), so vertex ``i`` is node ``i``."""
    rows = boundary_faces(mesh) if faces is None else _face_rows(mesh, faces)
    triangles = _face_nodes(mesh, rows)[:, _QUAD8_TRIANGLES].reshape(-1, 3)
    return trimesh.Trimesh(vertices=mesh.nodes, faces=triangles, process=False, validate=False)


# -- line of sight ------------------------------------------------------------------------------------

def _trimesh_rays_available() -> bool:
    # trimesh's ray engines need rtree (pure-triangle engine) or embreex (Embree).
    return any(importlib.util.find_spec(m) is not None for m in ("rtree", "embreex"))


def _first_hits_parallel(triangles: np.ndarray, origins: np.ndarray, direction: np.ndarray,
                         chunk: int = 1024) -> np.ndarray:
    """First triangle hit by each ray ``origins + s * direction`` (s >= 0), -1 if none.

    All rays share one direction (an orthographic camera), so the test is 2-D: a ray hits a
    triangle whose projection onto the image plane contains the ray's foot point; the first hit is the
    one with the smallest ray parameter. Edges count as inside, so a ray through a shared edge hits.
    triangles: (T, 3, 3), origins: (R, 3), direction: (3,) unit.
    """
    helper = np.eye(3)[np.argmin(np.abs(direction))]
    e1 = np.cross(direction, helper)
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(direction, e1)], axis=1)
    tri2, q2 = triangles @ basis, origins @ basis
    tri_s, ray_s0 = triangles @ direction, origins @ direction
    lo, hi = tri2.min(axis=1), tri2.max(axis=1)
    scale = max(float(np.ptp(tri2)), 1.0)
    eps = 1e-10 * scale
    v0, v1 = tri2[:, 1] - tri2[:, 0], tri2[:, 2] - tri2[:, 0]
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    flat = np.abs(den) > 1e-14 * scale**2  # edge-on triangles have no area to hit
    first = np.full(len(origins), -1, dtype=np.int64)
    for start in range(0, len(origins), chunk):
        q = q2[start : start + chunk]
        near = np.all((q[:, None] >= lo[None] - eps) & (q[:, None] <= hi[None] + eps), axis=2) & flat[None]
        r, t = np.nonzero(near)
        w = q[r] - tri2[t, 0]
        l1 = (w[:, 0] * v1[t, 1] - v1[t, 0] * w[:, 1]) / den[t]
        l2 = (v0[t, 0] * w[:, 1] - w[:, 0] * v0[t, 1]) / den[t]
        inside = (l1 >= -1e-10) & (l2 >= -1e-10) & (l1 + l2 <= 1 + 1e-10)
        r, t, l1, l2 = r[inside], t[inside], l1[inside], l2[inside]
        s = (1 - l1 - l2) * tri_s[t, 0] + l1 * tri_s[t, 1] + l2 * tri_s[t, 2] - ray_s0[start + r]
        ahead = s >= 0
        r, t, s = r[ahead], t[ahead], s[ahead]
        order = np.lexsort((s, r))
        r_sorted = r[order]
        keep = np.ones(len(order), dtype=bool)
        keep[1:] = r_sorted[1:] != r_sorted[:-1]
        first[start + r_sorted[keep]] = t[order][keep]
    return first


def visible_faces(
    mesh: Mesh,
    camera_direction=(1.0, 0.0, 0.0),
    *,
    require: str = "all",
    min_facing: float = 1e-3,
    engine: str = "auto",
) -> np.ndarray:
    """Boundary faces seen by an orthographic camera placed far on the ``+camera_direction`` side and
    looking along ``-camera_direction`` (paper §4: the camera sees the front y-z face, normal +x).

    A boundary face is a candidate if its outward normal at its centre makes a cosine above
    ``min_facing`` with ``camera_direction`` (faces seen edge-on or from behind are not observed).
    Rays are cast from the camera towards the face centre and four interior points (natural
    coordinates (+-0.5, +-0.5)); a sample is seen if the first triangle of the boundary surface its
    ray hits belongs to that face. ``require="all"`` keeps faces whose samples are all seen (no part
    hidden), ``"any"`` keeps partly hidden faces too. Reference configuration.

    engine: ``"trimesh"`` (``Trimesh.ray.intersects_first``, needs ``rtree`` or ``embreex``),
    ``"numpy"`` (exact 2-D test for parallel rays, no extra dependency) or ``"auto"`` (trimesh if
    usable). Returns (k, 2) rows ``(element, face)`` sorted by element then face.
    """
    d = np.asarray(camera_direction, dtype=np.float64).reshape(-1)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        raise ObservationError(f"camera_direction must be a finite non-zero 3-vector, got {camera_direction}")
    d = d / np.linalg.norm(d)
    if require not in ("all", "any"):
        raise ObservationError(f"require must be 'all' or 'any', got {require!r}")
    if engine == "auto":
        engine = "trimesh" if _trimesh_rays_available() else "numpy"
    if engine not in ("trimesh", "numpy"):
        raise ObservationError(f"engine must be 'auto', 'trimesh' or 'numpy', got {engine!r}")
    if engine == "trimesh" and not _trimesh_rays_available():
        raise ObservationError("engine='trimesh' needs the rtree (or embreex) package: pip install rtree, "
                               "or use engine='numpy'")

    faces = boundary_faces(mesh)
    Xf = mesh.nodes[_face_nodes(mesh, faces)]  # (F, 8, 3)
    _, _, J = _face_map(Xf, np.zeros((len(faces), 2)))
    outward = -np.cross(J[:, :, 0], J[:, :, 1])
    facing = outward @ d / np.linalg.norm(outward, axis=1)
    candidate = np.flatnonzero(facing > min_facing)
    S = len(_RAY_SAMPLES)
    _, targets, _ = _face_map(np.repeat(Xf[candidate], S, axis=0), np.tile(_RAY_SAMPLES, (len(candidate), 1)))

    extent = np.linalg.norm(np.ptp(Xf.reshape(-1, 3), axis=0))
    origins = targets + (2.0 * extent + 1.0) * d  # outside the bounding box, on the camera side
    surface = boundary_trimesh(mesh, faces)
    if engine == "trimesh":
        hit = surface.ray.intersects_first(origins, np.broadcast_to(-d, origins.shape).copy())
    else:
        hit = _first_hits_parallel(surface.triangles, origins, -d)
    seen = (np.where(hit >= 0, hit // len(_QUAD8_TRIANGLES), -1) == np.repeat(candidate, S)).reshape(-1, S)
    keep = seen.all(axis=1) if require == "all" else seen.any(axis=1)
    return faces[candidate[keep]]


# -- points on faces ----------------------------------------------------------------------------------

def _project(Xf: np.ndarray, p: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of M Quad8 faces Xf (M, 8, 3) to points p (M, 3): Gauss-Newton on (s, t),
    clipped to the face [-1, 1]^2 (so a point beside the face lands on its edge).
    Returns st (M, 2) and distance (M,) in mm."""
    st = np.zeros((len(p), 2))
    for _ in range(iterations):
        _, x, J = _face_map(Xf, st)
        A = np.einsum("mik,mil->mkl", J, J)
        b = np.einsum("mik,mi->mk", J, p - x)
        new = np.clip(st + np.linalg.solve(A, b[..., None])[..., 0], -1.0, 1.0)
        step = np.max(np.abs(new - st), initial=0.0)
        st = new
        if step < 1e-14:
            break
    _, x, _ = _face_map(Xf, st)
    return st, np.linalg.norm(p - x, axis=1)


def _locate(Xf: np.ndarray, points: np.ndarray, tol: float,
            chunk: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face row (P,), natural coordinates (P, 2) and distance (P,) of each point's closest face among
    those whose bounding box (grown by tol) holds it; face -1 and distance inf where none does."""
    lo, hi = Xf.min(axis=1), Xf.max(axis=1)
    pad = tol + 1e-9 * max(float(np.ptp(Xf.reshape(-1, 3))), 1.0)
    pairs = []
    for start in range(0, len(points), chunk):
        p = points[start : start + chunk, None]
        near = np.all((p >= lo[None] - pad) & (p <= hi[None] + pad), axis=2)
        pairs.append(np.argwhere(near) + [start, 0])
    pi, fi = np.concatenate(pairs).T if pairs else (np.zeros(0, dtype=np.int64),) * 2
    st_pairs, dist_pairs = _project(Xf[fi], points[pi])
    face = np.full(len(points), -1, dtype=np.int64)
    st = np.zeros((len(points), 2))
    dist = np.full(len(points), np.inf)
    order = np.lexsort((dist_pairs, pi))
    first = np.ones(len(order), dtype=bool)
    first[1:] = pi[order][1:] != pi[order][:-1]
    best = order[first]
    face[pi[best]], st[pi[best]], dist[pi[best]] = fi[best], st_pairs[best], dist_pairs[best]
    return face, st, dist


def regular_grid(mesh: Mesh, faces, spacing) -> np.ndarray:
    """A DIC-like regular grid of points (P, 3) in mm on a planar face set, like a camera's subset grid.

    The grid axes are the two coordinate axes least aligned with the face normal, projected onto the
    plane (for the front face x = const: y and z). ``spacing`` (mm, one value or one per axis) sets the
    pitch; the grid is centred within the bounds of the faces, and points off the faces (holes,
    re-entrant corners) are dropped. Ordered with the first axis running fastest.
    """
    rows = _face_rows(mesh, faces)
    if len(rows) == 0:
        raise ObservationError("regular_grid needs at least one face; the face set is empty")
    h = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (2,))
    if not np.all(h > 0):
        raise ObservationError(f"grid spacing must be positive (mm), got {spacing}")
    Xf = mesh.nodes[_face_nodes(mesh, rows)]
    X = Xf.reshape(-1, 3)
    centre = X.mean(axis=0)
    normal = np.linalg.svd(X - centre)[2][-1]
    extent = float(np.linalg.norm(np.ptp(X, axis=0)))
    deviation = float(np.abs((X - centre) @ normal).max())
    if deviation > 1e-9 * extent:
        raise ObservationError(
            f"regular_grid needs a planar face set, but its nodes lie up to {deviation:.3g} mm off their "
            "best-fit plane; place the points yourself and pass them to ObservationOperator"
        )
    axes = []
    for k in np.sort(np.argsort(np.abs(normal))[:2]):
        e = np.eye(3)[k] - (np.eye(3)[k] @ normal) * normal
        for a in axes:
            e -= (e @ a) * a
        axes.append(e / np.linalg.norm(e))
    ticks = []
    for a, step in zip(axes, h):
        c = (X - centre) @ a
        lo, hi = c.min(), c.max()
        n = int(np.floor((hi - lo) / step + 1e-9))
        ticks.append(lo + 0.5 * (hi - lo - n * step) + step * np.arange(n + 1))
    A, B = np.meshgrid(*ticks, indexing="xy")
    points = centre + A.reshape(-1, 1) * axes[0] + B.reshape(-1, 1) * axes[1]
    _, _, dist = _locate(Xf, points, 0.0)
    return points[dist <= 1e-9 * extent]


class ObservationOperator:
    """Observed displacement components at points on visible faces, by the face shape functions.

    mesh: the Hex20 mesh (reference coordinates, mm).
    faces: (k, 2) face rows (e.g. from :func:`visible_faces`) or the name of a face set.
    points: ``"nodes"`` (every node of the faces, as in the paper) or (P, 3) reference coordinates
        in mm of points on the faces (a DIC grid; each is located on its closest face by Newton).
    point_ids: (P,) ids used in messages and recordings; default the node ids for ``"nodes"``,
        0..P-1 otherwise.
    components: observed displacement components, default (1, 2) = y and z (paper §4).
    tol: farthest (mm) a given point may lie from the faces; a point farther off raises (``np.inf``: none
        does, for points seen on a settled body, :class:`SettledPoints`).

    Attributes: ``points`` (P, 3) mm, ``point_ids`` (P,), ``face`` (P,) row of ``faces`` holding each
    point, ``st`` (P, 2) its natural coordinates there, ``node_index``/``node_weight`` (P, m) the
    non-zero interpolation weights, ``weights`` the same as a sparse (P, n_nodes) matrix (per component).
    """

    def __init__(self, mesh: Mesh, faces, points="nodes", *, point_ids=None, components=(1, 2),
                 tol: float = 1e-3):
        self.faces = _face_rows(mesh, faces)
        if len(self.faces) == 0:
            raise ObservationError("no faces to observe: the face set is empty (check the camera direction)")
        self.components = tuple(int(c) for c in components)
        if not self.components or any(c not in (0, 1, 2) for c in self.components):
            raise ObservationError(f"components must be displacement components in 0..2, got {components}")
        self.n_nodes = mesh.n_nodes
        face_nodes = _face_nodes(mesh, self.faces)
        self.face_nodes = face_nodes
        Xf = mesh.nodes[face_nodes]
        if isinstance(points, str):
            if points != "nodes":
                raise ObservationError(f"points must be 'nodes' or a (P, 3) array, got {points!r}")
            nodes, first = np.unique(face_nodes.ravel(), return_index=True)
            self.points = mesh.nodes[nodes]
            self._set_ids(nodes if point_ids is None else point_ids)
            self.face, self.st = first // 8, QUAD8_NATURAL[first % 8].copy()  # exact: N is 0 or 1 there
        else:
            self.points = np.asarray(points, dtype=np.float64)
            if self.points.ndim != 2 or self.points.shape[1] != 3 or not np.all(np.isfinite(self.points)):
                raise ObservationError(f"points must be a finite (P, 3) array in mm, got shape {self.points.shape}")
            self._set_ids(np.arange(len(self.points)) if point_ids is None else point_ids)
            self.face, self.st, dist = _locate(Xf, self.points, tol)
            self._check_on_face(Xf, dist, tol)
        N, _ = quad8_shape(self.st)
        index = face_nodes[self.face]
        # Keep only the non-zero weights (a node point has one), largest count over points.
        order = np.argsort(N == 0, axis=1, kind="stable")
        m = int((N != 0).sum(axis=1).max(initial=1))
        self.node_index = np.take_along_axis(index, order, axis=1)[:, :m]
        self.node_weight = np.take_along_axis(N, order, axis=1)[:, :m]
        rows = np.repeat(np.arange(len(self.points)), m)
        self.weights = sp.csr_matrix((self.node_weight.ravel(), (rows, self.node_index.ravel())),
                                     shape=(len(self.points), self.n_nodes))
        self.weights.eliminate_zeros()
        self._weights_cache: dict = {}

    def _set_ids(self, ids) -> None:
        self.point_ids = np.asarray(ids).reshape(-1)
        if self.point_ids.shape != (len(self.points),):
            raise ObservationError(f"point_ids must have one id per point ({len(self.points)}), "
                                   f"got shape {self.point_ids.shape}")

    def _check_on_face(self, Xf: np.ndarray, dist: np.ndarray, tol: float) -> None:
        bad = np.flatnonzero(~(dist <= tol))
        if bad.size == 0:
            return
        i = int(bad[0])
        if not np.isfinite(dist[i]):  # outside every face's box: measure against all faces
            dist[i] = _project(Xf, np.broadcast_to(self.points[i], (len(Xf), 3)))[1].min()
        raise ObservationError(
            f"observation point id {self.point_ids[i]} (row {i}) at {np.round(self.points[i], 6).tolist()} mm "
            f"lies {dist[i]:.4g} mm from the nearest observed face (tolerance {tol:g} mm); {bad.size} of "
            f"{len(self.points)} points are off the faces. Give reference coordinates on the visible "
            "face, drop the point, or raise tol"
        )

    @property
    def n_points(self) -> int:
        return len(self.points)

    def __call__(self, u):
        """Observations of displacements u: (..., n_nodes, 3) mm, e.g. (N, n_nodes, 3) or
        (N, T, n_nodes, 3); torch tensor or numpy array. Returns (..., P, len(components)) mm, same type.
        A model's ``Solution.u`` may carry more nodes than the mesh (embedded fiber nodes are appended
        after the mesh's own): the mesh's nodes, which come first, are the ones observed."""
        if u.ndim < 2 or u.shape[-1] != 3 or u.shape[-2] < self.n_nodes:
            raise ObservationError(
                f"displacements must have shape (..., {self.n_nodes}, 3) (n_nodes of the observed mesh, more when "
                f"a model appends nodes after them), got {tuple(u.shape)}"
            )
        u = u[..., : self.n_nodes, :]
        # One sparse product over the node axis: (P, n_nodes) @ (n_nodes, everything else).
        lead, C = tuple(u.shape[:-2]), len(self.components)
        if isinstance(u, torch.Tensor):
            flat = u[..., list(self.components)].movedim(-2, 0).reshape(self.n_nodes, -1)
            out = torch.sparse.mm(self._torch_weights(u.dtype, u.device), flat)
            return out.reshape(self.n_points, *lead, C).movedim(0, -2)
        flat = np.moveaxis(np.asarray(u)[..., list(self.components)], -2, 0).reshape(self.n_nodes, -1)
        return np.moveaxis((self.weights @ flat).reshape(self.n_points, *lead, C), 0, -2)

    def _torch_weights(self, dtype, device) -> torch.Tensor:
        key = (dtype, device)
        if key not in self._weights_cache:
            W = self.weights.tocoo()
            index = torch.as_tensor(np.stack([W.row, W.col]), dtype=torch.int64, device=device)
            values = torch.as_tensor(W.data, dtype=dtype, device=device)
            self._weights_cache[key] = torch.sparse_coo_tensor(  # built from a valid SciPy matrix: no checks needed
                index, values, W.shape, check_invariants=False).coalesce()
        return self._weights_cache[key]

    def nearest_point(self, y: float, z: float) -> int:
        """Row of the observation point whose reference (y, z) is nearest to (y, z) mm (the paper's
        tracked node is (0, 40) on the front face). ``point_ids[row]`` is its id."""
        return int(np.argmin(np.hypot(self.points[:, 1] - y, self.points[:, 2] - z)))


# -- time ---------------------------------------------------------------------------------------------

def frame_times(n_frames: int = 100) -> np.ndarray:
    """Normalized frame times (n_frames,): every 1/n_frames, from 1/n_frames to 1 (paper: 0.01 .. 1.00)."""
    if n_frames < 1:
        raise ObservationError(f"n_frames must be >= 1, got {n_frames}")
    return np.arange(1, n_frames + 1) / n_frames


def interpolate_in_time(times_src, values, times_dst, axis: int = 1, atol: float = 1e-9):
    """Linear interpolation of FE load steps to frame times.

    times_src: (T,) strictly increasing times of the load steps; values: (..., T, ...) with time on
    ``axis`` (default 1: members first, e.g. (N, T, P, 2)), torch tensor (differentiable, same
    dtype/device) or numpy array; times_dst: (K,) times wanted, each within
    [times_src[0] - atol, times_src[-1] + atol]. Returns values with that axis of length K.
    Exact at the source times and for data linear in time.
    """
    ts = np.asarray(times_src.cpu() if isinstance(times_src, torch.Tensor) else times_src, dtype=np.float64)
    td = np.asarray(times_dst.cpu() if isinstance(times_dst, torch.Tensor) else times_dst, dtype=np.float64)
    ts, td = ts.reshape(-1), td.reshape(-1)
    axis = axis % values.ndim
    if values.shape[axis] != len(ts):
        raise ObservationError(
            f"values have {values.shape[axis]} entries on time axis {axis} (shape {tuple(values.shape)}) but "
            f"there are {len(ts)} source times; pass the axis that holds the load steps"
        )
    step = np.diff(ts)
    if len(ts) == 0 or np.any(~(step > 0)) or not np.all(np.isfinite(ts)):
        k = int(np.flatnonzero(~(step > 0))[0]) + 1 if np.any(~(step > 0)) else 0
        raise ObservationError(f"source times must be finite and strictly increasing; times_src[{k}] = "
                               f"{ts[k] if len(ts) else 'missing'} breaks that")
    outside = (td < ts[0] - atol) | (td > ts[-1] + atol) | ~np.isfinite(td)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        raise ObservationError(
            f"frame time times_dst[{k}] = {td[k]:g} is outside the solved range [{ts[0]:g}, {ts[-1]:g}] "
            f"({int(outside.sum())} of {len(td)} frames are); solve further or drop those frames"
        )
    td = np.clip(td, ts[0], ts[-1])
    if len(ts) == 1:
        lo_idx, hi_idx, w = np.zeros(len(td), dtype=np.int64), np.zeros(len(td), dtype=np.int64), np.zeros(len(td))
    else:
        lo_idx = np.clip(np.searchsorted(ts, td, side="right") - 1, 0, len(ts) - 2)
        hi_idx = lo_idx + 1
        w = (td - ts[lo_idx]) / (ts[hi_idx] - ts[lo_idx])
    shape = [1] * values.ndim
    shape[axis] = len(td)
    if isinstance(values, torch.Tensor):
        lo = values.index_select(axis, torch.as_tensor(lo_idx, device=values.device))
        hi = values.index_select(axis, torch.as_tensor(hi_idx, device=values.device))
        w = torch.as_tensor(w, dtype=values.dtype, device=values.device).reshape(shape)
    else:
        lo, hi, w = np.take(values, lo_idx, axis=axis), np.take(values, hi_idx, axis=axis), w.reshape(shape)
    return (1 - w) * lo + w * hi


# -- a reference state that moves: points seen on the settled body ------------------------------------

class SettledPoints:
    """A recording's points located on the settled body of a model with preloads (the sagged body of a
    DIC reference image), and what they see of its displacements from that state.

    The points' coordinates are those of the reference image: positions on the body settled under its
    weight, ``X + u_ref``. Each is located on the operator's faces in that state by its observed
    components (``x(s, t)[c] = point[c]``, Newton on the face's natural coordinates from the closest
    point), so the material point behind it moves with the parameters that move ``u_ref``; the
    observations are ``u - u_ref`` there.

    op: the operator whose faces and components are used (built on the mesh's own coordinates);
    nodes: (n_nodes, 3) the settled coordinates ``X + u_ref``; points: (P, 3) the recording's points.
    Attributes: ``face``, ``st``, ``N`` (P, 8) face shape functions, ``dN`` (P, 8, 2), ``index`` (P, 8)
    node ids, ``A`` (P, 2, 2) the observed components' ``dx/d(s, t)``, ``offset`` (P,) the largest
    natural coordinate beyond the face (> 0: the point lies beside its face, by extrapolation).
    """

    def __init__(self, op: ObservationOperator, nodes: np.ndarray, points: np.ndarray, iterations: int = 30):
        self.components = op.components
        self.n_nodes = op.n_nodes
        face_nodes = op.face_nodes
        Xf = np.asarray(nodes, dtype=np.float64)[face_nodes]
        points = np.asarray(points, dtype=np.float64)
        face, st, _ = _locate(Xf, points, np.inf)
        c = list(self.components[:2])
        Xp = Xf[face]
        for _ in range(iterations):
            _, x, J = _face_map(Xp, st)
            A = J[:, c, :]
            step = np.linalg.solve(A, (points[:, c] - x[:, c])[..., None])[..., 0]
            st = st + step
            if np.abs(step).max(initial=0.0) < 1e-13:
                break
        self.face, self.st = face, st
        self.N, dN = quad8_shape(st)
        self.dN = dN
        self.index = face_nodes[face]
        self.A = np.einsum("pak,pai->pik", dN, Xp)[:, c, :]
        self.offset = np.abs(st).max(axis=1) - 1.0
        self.points = points

    def observe(self, field: np.ndarray) -> np.ndarray:
        """(S, n, 3, ...) nodal fields -> (S, P, len(components), ...) at the points."""
        f = np.asarray(field)[:, : self.n_nodes][:, :, list(self.components)]
        return np.einsum("pa,spac...->spc...", self.N, f[:, self.index])

    def moving_term(self, u_rel: np.ndarray, du_ref: np.ndarray) -> np.ndarray:
        """The part of ``d(observations)/dz`` that comes from the points' material positions moving with
        the reference state: ``d/d(s,t)[N_a u_rel_a] . d(s,t)/dz`` with ``d(s,t)/dz = -A^-1 N_a du_ref_a``.

        u_rel: (S, n, 3) displacements from the reference state; du_ref: (n, 3, d) its sensitivities.
        Returns (S, P, len(components), d)."""
        c = list(self.components[:2])
        g = np.einsum("pa,pacd->pcd", self.N, du_ref[: self.n_nodes][self.index][:, :, c])
        dst = -np.linalg.solve(self.A, g)  # (P, 2, d)
        f = np.asarray(u_rel)[:, : self.n_nodes][:, :, list(self.components)]
        G = np.einsum("pak,spac->spck", self.dN, f[:, self.index])
        return np.einsum("spck,pkd->spcd", G, dst)
