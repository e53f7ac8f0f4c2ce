"""Rigid registration of a DIC reference point cloud onto the model's camera-visible face (DESIGN §8).

DIC coordinates are in the camera's frame. A similarity ``x = s R p + t`` (rotation R, translation t,
uniform scale s, 1 unless asked for) places the reference points p on the face in the model frame
(mm, z along the actuator); displacements measured in the camera frame turn with it,
``u_model = s R u_camera``.

The transform is refined by iterative closest points (ICP) from an initial guess:

- initial guess: user landmarks (pairs of DIC and model points, at least 3 not on one line) by the
  closed-form least-squares similarity of Umeyama (1991, IEEE PAMI 13(4), Eqs. 40-42); without
  landmarks, the principal axes of the cloud laid on those of the face in each of the 4 right-handed
  sign combinations, the best fit kept (an error if two fit equally well: a symmetric face);
- ``method="point"``: each point is paired with its closest face point and the Umeyama similarity of
  the pairs is the next transform (Besl & McKay 1992);
- ``method="plane"``: a Gauss-Newton step on the signed distances along the face normals at the
  closest points (Chen & Medioni 1992). A flat face fixes only 3 of the 6 (7 with scale) degrees of
  freedom, its normal and offset; the rest (in-plane translation and rotation, scale) come from the
  landmarks, which count only in those directions, so a landmark picked with a depth error does not
  tilt the fit. With no landmarks for them the registration is refused, naming how many are free.

A point farther than ``tol`` (mm) from the face is an outlier: left out of the fit and listed by id.
Everything is deterministic (no random sampling). Units: mm in the model frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import block_diag
from scipy.spatial import cKDTree

_RANK_TOL = 1e-9  # relative singular value below which a direction counts as undetermined


class RegistrationError(ValueError):
    """A registration that cannot be done as asked; the message says what is missing."""


@dataclass
class Similarity:
    """``x = s R p + t``; R (3, 3) a rotation, t (3,) mm, s > 0."""

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    @classmethod
    def identity(cls) -> "Similarity":
        return cls(np.eye(3), np.zeros(3), 1.0)

    def points(self, p: np.ndarray) -> np.ndarray:
        """(..., 3) points in the source frame -> the target frame."""
        return self.s * np.asarray(p) @ self.R.T + self.t

    def vectors(self, u: np.ndarray) -> np.ndarray:
        """(..., 3) displacements: turned and scaled, not shifted (NaN stays NaN)."""
        return self.s * np.asarray(u) @ self.R.T


# -- faces ---------------------------------------------------------------------------------------------

class PlaneFace:
    """A rectangle ``origin + a axes[0] + b axes[1]``, ``lo <= (a, b) <= hi``; normal ``axes[0] x axes[1]``."""

    flat = True

    def __init__(self, origin, axes, lo, hi, clamped=None):
        self.origin = np.asarray(origin, dtype=np.float64)
        axes = np.asarray(axes, dtype=np.float64)
        if axes.shape != (2, 3) or abs(axes[0] @ axes[1]) > 1e-12 or not np.allclose(np.linalg.norm(axes, axis=1), 1):
            raise RegistrationError(f"a plane face needs two orthonormal in-plane axes, got {axes.tolist()}")
        self.axes = axes
        self.normal = np.cross(axes[0], axes[1])
        self.lo, self.hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        # (in-plane axis 0 or 1, its value): the face's edge where the body is held, e.g. the clamped base
        self.clamped = clamped

    @property
    def centre(self) -> np.ndarray:
        return self.origin + 0.5 * (self.lo + self.hi) @ self.axes

    def half_turns(self) -> list[tuple[str, "Similarity"]]:
        """The rigid motions other than the identity that map the rectangle onto itself and keep its
        normal: the half turn about the normal through the centre, and the quarter turns of a square."""
        c, n = self.centre, self.normal
        turns = [("a half turn about the face normal", _rotation(np.pi * n))]
        if np.isclose(*(self.hi - self.lo), rtol=1e-9):
            turns += [("a quarter turn about the face normal", _rotation(0.5 * np.pi * n)),
                      ("a quarter turn about the face normal", _rotation(-0.5 * np.pi * n))]
        return [(what, Similarity(R, c - R @ c)) for what, R in turns]

    def distance_to_clamp(self, x: np.ndarray) -> np.ndarray | None:
        """(P,) mm from the clamped edge, in the face's plane (None: no clamped edge known)."""
        if self.clamped is None:
            return None
        axis, value = self.clamped
        return np.abs((x - self.origin) @ self.axes[axis] - value)

    def closest(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest face points (P, 3) of x (P, 3) and the face normal there (P, 3)."""
        ab = np.clip((x - self.origin) @ self.axes.T, self.lo, self.hi)
        return self.origin + ab @ self.axes, np.broadcast_to(self.normal, x.shape)

    def samples(self, n: int = 41) -> tuple[np.ndarray, np.ndarray]:
        a, b = np.meshgrid(np.linspace(self.lo[0], self.hi[0], n), np.linspace(self.lo[1], self.hi[1], n))
        pts = self.origin + np.stack([a.ravel(), b.ravel()], 1) @ self.axes
        return pts, np.ones(len(pts))


def front_face(width_x: float = 16.0, width_y: float = 16.0, length: float = 60.0) -> PlaneFace:
    """The actuator's camera-visible front face x = +w_x/2, y in [-w_y/2, w_y/2], z in [0, L], clamped
    at z = 0; the defaults are the paper's actuator (``ActuatorGeometry``'s: x = +8 mm, y in [-8, 8],
    z in [0, 60])."""
    return PlaneFace((width_x / 2, 0.0, 0.0), ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), (-width_y / 2, 0.0),
                     (width_y / 2, length), clamped=(1, 0.0))


class TriangleFace:
    """A triangulated surface (vertices (n, 3) mm, triangles (m, 3)) with normals towards the camera."""

    def __init__(self, vertices, triangles):
        import trimesh

        self.mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(triangles),
                                    process=False, validate=False)
        normals = self.mesh.face_normals
        self.flat = bool(np.abs(normals - normals[0]).max(initial=0.0) < 1e-12)

    def closest(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import trimesh

        q, _, tri = trimesh.proximity.closest_point(self.mesh, x)
        return np.asarray(q), self.mesh.face_normals[tri]

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        return self.mesh.triangles_center, self.mesh.area_faces


def mesh_face(mesh, camera_direction=(1.0, 0.0, 0.0), faces=None) -> TriangleFace:
    """The faces of a Hex20 mesh an orthographic camera along ``camera_direction`` sees
    (:func:`torchfra.observation.operator.visible_faces`), or ``faces`` (face rows or a face set's name), as triangles."""
    from torchfra.observation.operator import boundary_trimesh, visible_faces

    surface = boundary_trimesh(mesh, visible_faces(mesh, camera_direction) if faces is None else faces)
    return TriangleFace(surface.vertices, surface.faces)


class SampleFace:
    """A face given by sample points (n, 3) mm (and optionally their unit normals): the closest face
    point is the nearest sample. Point-to-point ICP against samples is exact only where the samples
    are the registered points' own true positions (a reference measured or registered before); for a
    face known as a surface use :class:`PlaneFace` or :class:`TriangleFace`."""

    flat = False

    def __init__(self, points, normals=None):
        self.points = np.asarray(points, dtype=np.float64)
        self.normals = None if normals is None else np.asarray(normals, dtype=np.float64)
        self.tree = cKDTree(self.points)

    def closest(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        _, i = self.tree.query(x)
        return self.points[i], None if self.normals is None else self.normals[i]

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points, np.ones(len(self.points))


# -- closed form -----------------------------------------------------------------------------------------

def umeyama(src, dst, weights=None, scale: bool = False) -> Similarity:
    """Weighted least-squares similarity taking src (n, 3) onto dst (n, 3): minimizes
    sum_i w_i |s R src_i + t - dst_i|^2 over rotations R (det +1), t and, if ``scale``, s
    (Umeyama 1991, Eqs. 40-42). Needs 3 pairs not on one line."""
    a, b = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=np.float64)
    if len(a) < 3:
        raise RegistrationError(f"a rotation needs at least 3 point pairs not on one line, got {len(a)}")
    w = w / w.sum()
    mu_a, mu_b = w @ a, w @ b
    A, B = a - mu_a, b - mu_b
    spread = np.linalg.svd(np.sqrt(w)[:, None] * A, compute_uv=False)
    if spread[1] <= 1e-9 * max(spread[0], 1e-300):
        raise RegistrationError("the point pairs lie on one line (or on one point): their rotation about that "
                                "line is undetermined; give 3 or more pairs spread over the face")
    U, D, Vt = np.linalg.svd((w[:, None] * B).T @ A)
    S = np.ones(3)
    S[2] = np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0
    R = (U * S) @ Vt
    s = float((D * S).sum() / (w @ (A * A).sum(axis=1))) if scale else 1.0
    return Similarity(R, mu_b - s * R @ mu_a, s)


def _skew(a: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) with skew(a) @ b = a x b."""
    z = np.zeros(a.shape[:-1])
    return np.stack([np.stack([z, -a[..., 2], a[..., 1]], -1), np.stack([a[..., 2], z, -a[..., 0]], -1),
                     np.stack([-a[..., 1], a[..., 0], z], -1)], -2)


def _rotation(theta: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by |theta| about theta."""
    angle = float(np.linalg.norm(theta))
    K = _skew(theta / angle) if angle > 0 else np.zeros((3, 3))
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


# -- result ----------------------------------------------------------------------------------------------

@dataclass
class Registration:
    """Where the reference points landed: ``transform`` (camera -> model), ``distance`` (P,) mm of each
    transformed point to the face, ``on_face`` (P, 3) its closest face point, ``inlier`` (P,) within
    ``tol``; ``landmark_error`` (L,) mm of the landmarks after registration (empty without)."""

    transform: Similarity
    point_ids: np.ndarray
    distance: np.ndarray
    on_face: np.ndarray
    inlier: np.ndarray
    tol: float
    method: str = "identity"
    iterations: int = 0
    converged: bool = True
    landmark_error: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def outlier_ids(self) -> np.ndarray:
        return self.point_ids[~self.inlier]

    @property
    def rms(self) -> float:
        d = self.distance[self.inlier]
        return float(np.sqrt(np.mean(d ** 2))) if d.size else float("nan")

    @property
    def max(self) -> float:
        return float(self.distance[self.inlier].max(initial=0.0)) if self.inlier.any() else float("nan")


def evaluate(points, face, transform: Similarity, tol: float = 0.5, point_ids=None, **info) -> Registration:
    """Distances of ``transform(points)`` to the face, the closest face points and the inliers."""
    p = _check_points(points)
    ids = np.arange(len(p)) if point_ids is None else np.asarray(point_ids).reshape(-1)
    if ids.shape != (len(p),):
        raise RegistrationError(f"point_ids must have one id per point ({len(p)}), got shape {ids.shape}")
    x = transform.points(p)
    q, _ = face.closest(x)
    d = np.linalg.norm(x - q, axis=1)
    return Registration(transform, ids, d, q, d <= tol, tol, **info)


def _check_points(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise RegistrationError(f"points must be a finite (P, 3) array, got shape {p.shape}")
    return p


# -- ICP -------------------------------------------------------------------------------------------------

_MIRROR = np.diag([1.0, 1.0, -1.0])  # turns a left-handed frame into a right-handed one


def register(points, face, *, landmarks=None, point_ids=None, scale: bool = False, method: str | None = None,
             tol: float = 0.5, max_iter: int = 100, left_handed: bool = False) -> Registration:
    """Similarity placing ``points`` (P, 3, camera frame) on ``face``.

    landmarks: ``(src (L, 3), dst (L, 3))`` pairs, DIC point -> model point (mm), L >= 3 not on a line:
    the initial guess, and on a flat face the in-plane placement. method: ``"plane"`` (default for
    plane and triangle faces) or ``"point"`` (default for sample faces). tol: farthest a point may lie
    from the face (mm) to count in the fit; farther ones are listed as outliers. left_handed: the
    camera frame is left-handed, so the transform is a reflection (det R = -1): the frame's z axis
    is turned over first and a rotation fitted to the rest.
    """
    if left_handed:
        mirrored = None if landmarks is None else tuple(np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in landmarks)
        if mirrored is not None:
            mirrored = (mirrored[0] @ _MIRROR, mirrored[1])
        reg = register(_check_points(points) @ _MIRROR, face, landmarks=mirrored, point_ids=point_ids, scale=scale,
                       method=method, tol=tol, max_iter=max_iter)
        reg.transform = Similarity(reg.transform.R @ _MIRROR, reg.transform.t, reg.transform.s)
        return reg
    p = _check_points(points)
    if len(p) < 3:
        raise RegistrationError(f"registration needs at least 3 points, got {len(p)}")
    method = method or ("point" if isinstance(face, SampleFace) else "plane")
    if method not in ("point", "plane"):
        raise RegistrationError(f"method must be 'point' or 'plane', got {method!r}")
    if method == "plane" and isinstance(face, SampleFace) and face.normals is None:
        raise RegistrationError("point-to-plane registration needs face normals; give SampleFace normals "
                                "or use method='point'")
    if landmarks is not None:
        src, dst = (np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in landmarks)
        if src.shape != dst.shape or not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
            raise RegistrationError(f"landmarks must be finite pairs of points, got {src.shape} and {dst.shape}")
        T, it, ok = _icp(p, face, umeyama(src, dst, scale=scale), method, scale, tol, max_iter, src, dst)
        err = np.linalg.norm(T.points(src) - dst, axis=1)
        return evaluate(p, face, T, tol, point_ids, method=method, iterations=it, converged=ok, landmark_error=err)
    fits = []
    for T0 in _principal_guesses(p, face, scale):
        T, it, ok = _icp(p, face, T0, method, scale, tol, max_iter)
        fits.append((evaluate(p, face, T, tol, point_ids, method=method, iterations=it, converged=ok)))
    fits.sort(key=lambda r: (-int(r.inlier.sum()), r.rms))
    best, second = fits[0], fits[1]
    apart = np.abs(best.transform.points(p) - second.transform.points(p)).max()
    if second.inlier.sum() == best.inlier.sum() and second.rms <= best.rms + 0.1 * tol and apart > tol:
        raise RegistrationError(
            f"the points fit the face equally well in more than one orientation (RMS {best.rms:.3g} and "
            f"{second.rms:.3g} mm, placements up to {apart:.3g} mm apart): the face is symmetric for this "
            "cloud; give landmarks (3 or more DIC point -> model point pairs)")
    return best


def _principal_guesses(p: np.ndarray, face, scale: bool) -> list[Similarity]:
    """The cloud's principal axes laid on the face's, in the 4 right-handed sign combinations."""
    fp, fw = face.samples()
    fw = fw / fw.sum()
    mu_p, mu_f = p.mean(axis=0), fw @ fp
    var_p, E_p = np.linalg.eigh(np.cov((p - mu_p).T, bias=True))
    var_f, E_f = np.linalg.eigh(((fp - mu_f) * fw[:, None]).T @ (fp - mu_f))
    s = float(np.sqrt(var_f.sum() / var_p.sum())) if scale else 1.0
    guesses = []
    for signs in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1)):
        R = (E_f * signs) @ E_p.T
        if np.linalg.det(R) < 0:
            R = (E_f * np.multiply(signs, (1, 1, -1))) @ E_p.T
        guesses.append(Similarity(R, mu_f - s * R @ mu_p, s))
    return guesses


def _icp(p, face, T: Similarity, method, scale, tol, max_iter, src=None, dst=None):
    """Refine T; returns (T, iterations, converged)."""
    extent = float(np.sqrt(((p - p.mean(0)) ** 2).sum(1).mean())) * T.s or 1.0
    previous = None
    for it in range(1, max_iter + 1):
        x = T.points(p)
        q, n = face.closest(x)
        d = np.linalg.norm(x - q, axis=1)
        # A rough start leaves every point far off: admit 3x the median until the fit settles.
        inlier = d <= max(tol, 3.0 * float(np.median(d)))
        if inlier.sum() < 3:
            raise RegistrationError(f"fewer than 3 points lie within {tol:g} mm of the face after "
                                    f"{it} iterations; check the landmarks, units and scale")
        if method == "point":
            T_new = umeyama(p[inlier], q[inlier], scale=scale)
            step = float(np.abs(T_new.points(p[inlier]) - x[inlier]).max())
        else:
            nl = None if src is None else face.closest(T.points(src))[1]
            T_new, step = _plane_step(T, x[inlier], q[inlier], n[inlier], scale, src, dst, nl)
        T = T_new
        if step <= 1e-12 * extent and previous is not None and np.array_equal(previous, inlier):
            return T, it, True
        previous = inlier
    return T, max_iter, False


def _plane_step(T: Similarity, x, q, n, scale, src, dst, nl) -> tuple[Similarity, float]:
    """One Gauss-Newton step on r_i = n_i . (x_i - q_i) about the centroid c of the closest points:
    x_new = c + (1 + ds) R(dtheta) (x - c) + dt, so dr_i = dtheta . (a_i x n_i) + n_i . dt + ds n_i . a_i
    with a_i = q_i - c (q, not x: a flat face then has exactly zero rows in its free directions).
    The face's free directions are solved from the landmarks alone, from their offsets along the face
    (the components along the face normal nl at each landmark are the face's to fix)."""
    c = q.mean(axis=0)
    a = q - c
    L = float(np.sqrt((a ** 2).sum(1).mean())) or 1.0
    cols = [np.cross(a, n) / L, n] + ([(n * a).sum(1, keepdims=True) / L] if scale else [])
    J = np.concatenate(cols, axis=1)
    r = (n * (x - q)).sum(1)
    U, S, Vt = np.linalg.svd(J, full_matrices=False)  # m >= dof rows: Vt holds the null space too
    rank = int((S > _RANK_TOL * S[0]).sum())
    delta = Vt[:rank].T @ ((U[:, :rank].T @ -r) / S[:rank])
    free = Vt[rank:].T
    dof = J.shape[1]
    if free.shape[1]:
        if src is None:
            raise RegistrationError(
                f"the face leaves {free.shape[1]} of the {dof} degrees of freedom undetermined (a flat face "
                "fixes only its normal and offset; in-plane position, rotation and scale need more): give "
                "landmarks, 3 or more DIC point -> model point pairs not on one line")
        xl = T.points(src)
        al = xl - c
        Jl = np.concatenate([-_skew(al) / L, np.broadcast_to(np.eye(3), (len(al), 3, 3))]
                            + ([al[:, :, None] / L] if scale else []), axis=2).reshape(-1, dof)
        Pl = block_diag(*(np.eye(3) - nl[:, :, None] * nl[:, None, :]))
        A = Pl @ Jl @ free
        b = -Pl @ ((xl - dst).ravel() + Jl @ delta)
        sa = np.linalg.svd(A, compute_uv=False)
        if sa[-1] <= _RANK_TOL * max(sa[0], 1e-300):
            raise RegistrationError(
                f"the face and the {len(src)} landmarks leave a degree of freedom undetermined; spread the "
                "landmarks over the face (3 or more, not on one line)")
        delta = delta + free @ np.linalg.lstsq(A, b, rcond=None)[0]
    dtheta, dt = delta[:3] / L, delta[3:6]
    ds = delta[6] / L if scale else 0.0
    Rd = _rotation(dtheta)
    T_new = Similarity(Rd @ T.R, (1 + ds) * Rd @ (T.t - c) + c + dt, (1 + ds) * T.s)
    return T_new, float(np.linalg.norm(delta))


# -- orientation checks ----------------------------------------------------------------------------------

@dataclass
class Orientation:
    """How a registration's orientation was settled: ``by`` (``"landmarks"``, ``"landmarks and the
    response"``, ...), the camera side check (``camera_side`` mm, the registered camera's distance in
    front of the face along ``view``, NaN where it was not checked, and ``camera_note``) and the
    response's rank correlation with the distance from the clamp (``response_correlation``, NaN where
    not used); ``text`` says it in a sentence."""

    by: str
    camera_side: float
    camera_note: str
    response_correlation: float
    text: str


MIN_RESPONSE_CORRELATION = 0.5  # rank correlation of |u| with distance from the clamp that decides an orientation


def _response_correlation(face, transform: "Similarity", points, displacement) -> float:
    """Spearman rank correlation, over the points, of each point's largest displacement (any frame)
    with its distance from the face's clamped edge once placed by ``transform``; NaN if not defined."""
    from scipy.stats import spearmanr

    if displacement is None or not hasattr(face, "distance_to_clamp"):
        return float("nan")
    d = face.distance_to_clamp(transform.points(points))
    if d is None:
        return float("nan")
    with np.errstate(invalid="ignore"):
        m = np.nanmax(np.linalg.norm(np.asarray(displacement, dtype=np.float64), axis=-1), axis=0)
    ok = np.isfinite(m)
    if ok.sum() < 3 or np.ptp(m[ok]) <= 1e-9 * max(np.abs(m[ok]).max(), 1e-300) or np.ptp(d[ok]) == 0:
        return float("nan")
    return float(spearmanr(m[ok], d[ok]).statistic)


def check_orientation(reg: Registration, points, face, *, camera=None, view=None, displacement=None,
                      camera_note: str = "") -> Orientation:
    """Refuse a registration whose orientation the data contradict, and say how it was settled.

    points: (P, 3) the registered points (camera frame); camera: ``("point", (3,))`` the camera's
    position or ``("direction", (3,))`` the direction from the scene towards it, in the camera frame;
    None: unknown (not checked, ``camera_note`` says why). view: (3,) model direction from the face
    towards the camera (``--camera``). displacement: (K, P, 3) of the points (any frame: only their
    lengths count), the response to pressure.

    Checks: (1) the registered camera lies on the ``view`` side of the face, else the landmarks are
    mirrored (or the frame's handedness or the camera side was given wrong); (2) on a face with a
    symmetry (a rectangle turned by half a turn about its normal) whose turned placement fits the
    points as well, the response decides: a clamped body moves least at its clamp, so the rank
    correlation of each point's displacement with its distance from the clamp must be positive and
    larger than for the turned placement. A response that prefers the turned placement is refused (the
    landmarks are paired with the wrong corners); one that cannot tell (no clamp known, no motion) leaves
    the landmarks alone to decide, said so.
    """
    p = _check_points(points)
    T = reg.transform
    side, note = float("nan"), camera_note
    if camera is not None and view is not None:
        kind, v = camera
        view = np.asarray(view, dtype=np.float64) / np.linalg.norm(view)
        if hasattr(face, "centre"):
            centre = face.centre
        else:
            pts, w = face.samples()
            centre = np.average(pts, axis=0, weights=w)
        if kind == "point":
            side = float((T.points(np.asarray(v, dtype=np.float64)) - centre) @ view)
        else:
            d = T.vectors(np.asarray(v, dtype=np.float64))
            side = float(d @ view / np.linalg.norm(d))
        if not side > 0:
            where = f"{-side:.4g} mm behind the face" if kind == "point" else "looking at the face from behind"
            raise RegistrationError(
                f"the registered camera is {where} (the face is seen from {_signed_axis(view)}): a rotation puts "
                "the camera there only if the landmarks are mirrored (left and right, or top and bottom, swapped): "
                "check the landmark pairs; if they are right, the export's frame is left-handed (give "
                "--left-handed), the camera sees the other face (--camera), or the camera is elsewhere in the "
                "DIC frame (--dic-camera)")
        note = (f"the camera registered {side:.4g} mm in front of the face" if kind == "point" else
                "the camera registered in front of the face")
    turns = face.half_turns() if hasattr(face, "half_turns") else []
    rival = None
    for what, S in turns:
        alt = evaluate(p, face, Similarity(S.R @ T.R, S.R @ T.t + S.t, T.s), reg.tol, reg.point_ids)
        if alt.inlier.sum() >= reg.inlier.sum() and alt.rms <= reg.rms + 0.1 * reg.tol:
            rival = (what, alt)
            break
    rho = _response_correlation(face, T, p, displacement)
    if rival is None:
        by = "the fit (no other placement fits the points as well)"
        if reg.landmark_error.size:
            by = "the landmarks (no other placement fits the points as well)"
        return Orientation(by, side, note, rho, f"orientation: {by}; {note or 'camera side not checked'}")
    what, alt = rival
    rho_alt = _response_correlation(face, alt.transform, p, displacement)
    if np.isfinite(rho) and np.isfinite(rho_alt) and rho_alt > rho and rho_alt >= MIN_RESPONSE_CORRELATION:
        raise RegistrationError(
            f"the points fit the face equally well turned by {what}, and the response to pressure chooses the turned "
            f"placement: the displacement grows away from the clamped edge there (rank correlation {rho_alt:.2f}) "
            f"but towards it as the landmarks place the points ({rho:.2f}); the landmarks are paired with the wrong "
            "corners (diagonally opposite ones?): check their pairs")
    if np.isfinite(rho) and rho >= MIN_RESPONSE_CORRELATION and rho > rho_alt:
        by = "the landmarks, confirmed by the response"
        detail = (f"the face fits as well turned by {what}; the displacement grows away from the clamped edge "
                  f"(rank correlation {rho:.2f}, turned {rho_alt:.2f})")
    elif reg.landmark_error.size:
        by = "the landmarks alone"
        detail = (f"the face fits as well turned by {what} and the response cannot tell (rank correlation "
                  f"{rho:.2f}, turned {rho_alt:.2f}): the landmarks' pairs decide")
    else:
        raise RegistrationError(f"the points fit the face equally well turned by {what} and neither landmarks nor "
                                "the response tell the two apart; give landmarks")
    return Orientation(by, side, note, rho, f"orientation: {by} ({detail}); {note or 'camera side not checked'}")


def _signed_axis(v: np.ndarray) -> str:
    i = int(np.argmax(np.abs(v)))
    return f"{'+' if v[i] > 0 else '-'}{'xyz'[i]}" if np.isclose(abs(v[i]), 1.0) else f"direction {v.round(3).tolist()}"
