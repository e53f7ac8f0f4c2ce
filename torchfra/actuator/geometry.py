"""The fiber-reinforced actuator of the paper (§2, §4; DESIGN §3): geometry, Hex20 mesh, fibers.

Body ``[-w_x/2, w_x/2] x [-w_y/2, w_y/2] x [0, L]`` (mm), z along the length, base z = 0. A
cylindrical cavity of radius ``r_c`` with its axis at ``(0, e)`` runs over ``z in [z0, z1]``
between two solid endcaps. Two counter-wound helices of radius ``R`` about the cavity axis,

    X_h(s) = (R cos th, e + R sin th, z0 + s L_c),  th = th_0 +/- s L_c / (R tan alpha),  s in [0, 1],

with the pitch angle ``alpha`` between fiber and circumferential direction: each helix advances
``2 pi R tan(alpha)`` per turn and has length ``L_c / sin(alpha)``.

Cross-section blocks (swept along z with layer boundaries at z0 and z1): an O-grid square of
half-width ``a`` around the cavity (a ring of ``4 n_c x n_r`` elements from the circle to the
square; mid-edge nodes on the arc), rectangles filling the rest of the outer square on a
tensor grid, and, in the endcap layers only, a core that fills the cavity disk (an inner square
plus four sectors out to the circle). With the paper's numbers ``a = 3`` and the O-grid square
touches the face y = +8, as does the helix.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from torchfra.fem.elements import HEX20_FACES, HEX20_NATURAL, hex20_shape
from torchfra.fem.embedding import embedding_weights, locate_points
from torchfra.fem.mesh import Mesh
from torchfra.fem.params import ParameterInfo

__all__ = [
    "ActuatorGeometry", "GeometryError", "actuator_mesh", "build_actuator_model", "element_sets", "embedding_weights",
    "fiber_mesh", "helix_points", "locate_points",
]


class GeometryError(ValueError):
    """Impossible actuator geometry; the message names the dimension at fault."""


@dataclass(frozen=True)
class ActuatorGeometry:
    """Dimensions (mm, degrees) of the actuator; defaults are the paper's (§4).

    width_x, width_y, length: body (x, y cross-section centred on the z axis; z from the base).
    cavity_offset: y of the cavity axis (x = 0); endcap_base, endcap_top: solid lengths closing it.
    pitch_deg: angle between fiber and circumferential direction, in (0, 90).
    helix_start_deg: angle of both helices at z = z0, measured about the cavity axis from +x.
    resolution: mesh density knob (>= 1): ``resolution + 1`` elements along each side of the
    O-grid square (a quarter of the cavity circle); other counts follow that element size.
    axial_aspect: axial element length / in-plane element length at the O-grid square.
    tol: relative slack of the fibers-inside-the-body check (the paper's helix touches y = +8).
    """

    width_x: float = 16.0
    width_y: float = 16.0
    length: float = 60.0
    cavity_radius: float = 2.0
    cavity_offset: float = 5.0
    endcap_base: float = 10.0
    endcap_top: float = 10.0
    fiber_diameter: float = 0.1
    helix_radius: float = 3.0
    pitch_deg: float = 2.0
    helix_start_deg: float = 0.0
    resolution: int = 2
    axial_aspect: float = 2.0
    tol: float = 1e-9

    # -- derived quantities -----------------------------------------------------------------------
    @property
    def cavity_z(self) -> tuple[float, float]:
        return self.endcap_base, self.length - self.endcap_top

    @property
    def cavity_length(self) -> float:
        return self.length - self.endcap_base - self.endcap_top

    @property
    def cavity_volume(self) -> float:
        return math.pi * self.cavity_radius**2 * self.cavity_length

    @property
    def body_volume(self) -> float:
        return self.width_x * self.width_y * self.length - self.cavity_volume

    @property
    def helix_lead(self) -> float:
        """Axial advance per turn, 2 pi R tan(alpha) (mm)."""
        return 2 * math.pi * self.helix_radius * math.tan(math.radians(self.pitch_deg))

    @property
    def helix_turns(self) -> float:
        return self.cavity_length / self.helix_lead

    @property
    def helix_length(self) -> float:
        """Length of one helix, L_c / sin(alpha) (mm)."""
        return self.cavity_length / math.sin(math.radians(self.pitch_deg))

    @property
    def fiber_area(self) -> float:
        return math.pi * self.fiber_diameter**2 / 4

    @property
    def ogrid_half_width(self) -> float:
        """Half-width ``a`` of the O-grid square: 1.5 r_c, limited by the outer faces."""
        hx, hy, e = self.width_x / 2, self.width_y / 2, self.cavity_offset
        return min(1.5 * self.cavity_radius, hx, hy - e, hy + e)

    # -- checks ----------------------------------------------------------------------------------
    def validate(self, helices: bool = True) -> "ActuatorGeometry":
        """Raise GeometryError naming the dimension if the geometry cannot be built; returns self."""
        for name in ("width_x", "width_y", "length", "cavity_radius", "endcap_base", "endcap_top",
                     "fiber_diameter", "helix_radius", "axial_aspect"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise GeometryError(f"{name} = {v!r} must be a finite positive number (mm)")
        if not math.isfinite(self.cavity_offset) or not math.isfinite(self.helix_start_deg):
            raise GeometryError("cavity_offset and helix_start_deg must be finite numbers")
        if not isinstance(self.resolution, (int, np.integer)) or self.resolution < 1:
            raise GeometryError(f"resolution = {self.resolution!r} must be an integer >= 1")
        if not 0 < self.pitch_deg < 90:
            raise GeometryError(f"pitch_deg = {self.pitch_deg!r} must lie strictly between 0 and 90 degrees")
        hx, hy, r, e, R = self.width_x / 2, self.width_y / 2, self.cavity_radius, self.cavity_offset, self.helix_radius
        if abs(e) + r >= hy:
            raise GeometryError(
                f"the cavity crosses the outer wall y = {math.copysign(hy, e or 1):g}: |cavity_offset| + cavity_radius "
                f"= {abs(e):g} + {r:g} >= width_y / 2 = {hy:g}; reduce cavity_offset or cavity_radius"
            )
        if r >= hx:
            raise GeometryError(
                f"the cavity crosses the outer walls x = +/-{hx:g}: cavity_radius = {r:g} >= width_x / 2 = {hx:g}"
            )
        if self.endcap_base + self.endcap_top >= self.length:
            raise GeometryError(
                f"the endcaps leave no cavity: endcap_base + endcap_top = {self.endcap_base:g} + {self.endcap_top:g} "
                f">= length = {self.length:g}"
            )
        if not helices:  # the fibers are given by the caller, not by the helices
            return self
        if R <= r:
            raise GeometryError(
                f"helix_radius = {R:g} <= cavity_radius = {r:g}: the fibers would run inside the cavity"
            )
        slack = self.tol * max(hx, hy)
        if abs(e) + R > hy + slack:
            raise GeometryError(
                f"the fibers leave the body through y = {math.copysign(hy, e or 1):g}: |cavity_offset| + helix_radius "
                f"= {abs(e):g} + {R:g} > width_y / 2 = {hy:g}; reduce helix_radius or cavity_offset"
            )
        if R > hx + slack:
            raise GeometryError(
                f"the fibers leave the body through x = +/-{hx:g}: helix_radius = {R:g} > width_x / 2 = {hx:g}"
            )
        return self


# -- cross-section -----------------------------------------------------------------------------------
@dataclass
class _Patch:
    """A mapped quadrilateral block of the cross-section: ``(u, v) in [0, 1]^2 -> (x, y)``,
    positively oriented, ``nu x nv`` elements, present in the z layers whose region is in ``regions``."""

    mapping: object
    nu: int
    nv: int
    name: str
    regions: tuple[str, ...]


def _count(length: float, h: float) -> int:
    return max(1, int(math.floor(length / h + 0.5)))


def _sector(center, side: int, square_half: float, circle_r: float):
    """Block between side ``side`` (0 = bottom, 1 = right, 2 = top, 3 = left) of a square of half-width
    ``square_half`` and the matching quarter of a concentric circle of radius ``circle_r``. u runs
    outwards (from the circle to the square for the ring, from the square to the circle for the
    core), v counter-clockwise: e_r x e_theta = +e_z keeps the bricks positively oriented. Circle
    points are equally spaced in angle, square points in length; lines of constant v are straight."""
    cx, cy = center
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
    c0, c1 = corners[side], corners[(side + 1) % 4]
    th0 = math.radians(225 + 90 * side)

    def mapping(uv):
        u, v = uv[:, 0], uv[:, 1]
        th = th0 + v * math.pi / 2
        arc = circle_r * np.stack([np.cos(th), np.sin(th)], 1)
        sq = square_half * ((1 - v)[:, None] * c0 + v[:, None] * c1)
        start, end = (arc, sq) if circle_r < square_half else (sq, arc)
        return np.array([cx, cy]) + (1 - u)[:, None] * start + u[:, None] * end

    return mapping


def _divisions(geom: ActuatorGeometry) -> dict:
    """Element counts of every block from the resolution (see ActuatorGeometry)."""
    a, r = geom.ogrid_half_width, geom.cavity_radius
    n_c = geom.resolution + 1
    h_sq = 2 * a / n_c
    h_arc = 0.5 * math.pi * r / n_c
    h_out = 1.25 * h_sq
    h_z = geom.axial_aspect * h_sq
    ring_mean = 0.5 * ((a - r) + (math.sqrt(2) * a - r))
    core_half = 0.4 * r
    return dict(
        n_c=n_c, h_out=h_out, core_half=core_half,
        n_r=_count(ring_mean, h_arc),
        n_k=_count(r - core_half, h_arc),
        n_cavity=2 * _count(geom.cavity_length / 2, h_z),  # even: z = z0 + 3/4 L_c is a node
        n_base=_count(geom.endcap_base, h_z),
        n_top=_count(geom.endcap_top, h_z),
    )


def _cross_section(geom: ActuatorGeometry, div: dict) -> list[_Patch]:
    hx, hy, e, r = geom.width_x / 2, geom.width_y / 2, geom.cavity_offset, geom.cavity_radius
    a, n_c, h = geom.ogrid_half_width, div["n_c"], div["h_out"]
    tol = geom.tol * max(hx, hy)
    centre = (0.0, e)
    all_z = ("base", "cavity", "top")
    patches = []
    for side in range(4):
        patches.append(_Patch(_sector(centre, side, a, r), div["n_r"], n_c, f"ring{side}", all_z))
        patches.append(_Patch(_sector(centre, side, div["core_half"], r), div["n_k"], n_c, f"core{side}",
                              ("base", "top")))
    b = div["core_half"]
    patches.append(_Patch(lambda uv: np.array([0.0, e]) + b * (2 * uv - 1), n_c, n_c, "core_centre", ("base", "top")))

    # tensor grid of rectangles around the O-grid square; zero-width bands are dropped
    x_bands = [(-hx, -a), (-a, a), (a, hx)]
    y_cuts = [-hy] + ([0.0] if -hy + h / 4 < 0.0 < e - a - h / 4 else []) + [e - a]
    y_bands = list(zip(y_cuts[:-1], y_cuts[1:])) + [(e - a, e + a), (e + a, hy)]
    x_bands = [bd for bd in x_bands if bd[1] - bd[0] > tol]
    y_bands = [bd for bd in y_bands if bd[1] - bd[0] > tol]

    for xb in x_bands:
        for yb in y_bands:
            if xb == (-a, a) and yb == (e - a, e + a):
                continue
            nx = n_c if xb == (-a, a) else _count(xb[1] - xb[0], h)
            ny = n_c if yb == (e - a, e + a) else _count(yb[1] - yb[0], h)

            def mapping(uv, xb=xb, yb=yb):
                return np.stack([xb[0] + (xb[1] - xb[0]) * uv[:, 0], yb[0] + (yb[1] - yb[0]) * uv[:, 1]], 1)

            patches.append(_Patch(mapping, nx, ny, "body", all_z))
    return patches


# -- mesh --------------------------------------------------------------------------------------------
def _z_layers(geom: ActuatorGeometry, div: dict) -> list[tuple[float, float, str]]:
    z0, z1 = geom.cavity_z
    layers = []
    for lo, hi, n, region in ((0.0, z0, div["n_base"], "base"), (z0, z1, div["n_cavity"], "cavity"),
                              (z1, geom.length, div["n_top"], "top")):
        zs = np.linspace(lo, hi, n + 1)
        layers += [(float(zs[k]), float(zs[k + 1]), region) for k in range(n)]
    return layers


def _merge_nodes(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge points closer than ``tol``: returns unique nodes ordered by (z, y, x) and the index of
    each input point's node."""
    pairs = cKDTree(points).query_pairs(tol, output_type="ndarray")
    n = points.shape[0]
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_nodes, label = connected_components(graph, directed=False)
    first = np.full(n_nodes, n)
    np.minimum.at(first, label, np.arange(n))
    nodes = points[first]
    order = np.lexsort((nodes[:, 0], nodes[:, 1], nodes[:, 2]))
    rank = np.empty(n_nodes, dtype=np.int64)
    rank[order] = np.arange(n_nodes)
    return nodes[order], rank[label]


def actuator_mesh(geom: ActuatorGeometry | None = None) -> Mesh:
    """Structured Hex20 mesh of the actuator body (Abaqus C3D20 node order).

    Node sets: ``base`` (z = 0), ``top`` (z = L), ``front`` (x = +w_x/2, the face the camera sees),
    ``back`` (x = -w_x/2), ``ypos`` (y = +w_y/2, the cavity side), ``yneg`` (y = -w_y/2),
    ``cavity`` (nodes of the cavity surface), ``all``.
    Face sets: the same outer faces, ``exterior`` (all of them) and ``cavity``: the closed cavity
    surface (the ring's inner faces over the cavity length plus the endcap core faces at z0, z1).
    """
    geom = (geom or ActuatorGeometry()).validate(helices=False)
    div = _divisions(geom)
    patches = _cross_section(geom, div)
    layers = _z_layers(geom, div)
    blocks = []
    for p in patches:
        i, j = np.meshgrid(np.arange(p.nu), np.arange(p.nv), indexing="ij")
        u = (i.reshape(-1, 1) + (1 + HEX20_NATURAL[None, :, 0]) / 2) / p.nu
        v = (j.reshape(-1, 1) + (1 + HEX20_NATURAL[None, :, 1]) / 2) / p.nv
        xy = p.mapping(np.stack([u.ravel(), v.ravel()], 1)).reshape(-1, 20, 2)
        blocks.append((p, xy))
    coords = []
    for z_lo, z_hi, region in layers:
        z = z_lo + (1 + HEX20_NATURAL[:, 2]) / 2 * (z_hi - z_lo)
        for p, xy in blocks:
            if region in p.regions:
                coords.append(np.concatenate([xy, np.broadcast_to(z[None, :, None], (xy.shape[0], 20, 1))], 2))
    coords = np.concatenate(coords)  # (E, 20, 3)
    size = max(geom.width_x, geom.width_y, geom.length)
    nodes, index = _merge_nodes(coords.reshape(-1, 3), 1e-7 * size)
    elements = index.reshape(-1, 20)
    node_sets, face_sets = _named_sets(geom, nodes, elements)
    return Mesh(nodes, elements, node_sets, face_sets)


def _named_sets(geom: ActuatorGeometry, nodes: np.ndarray, elements: np.ndarray):
    hx, hy, L = geom.width_x / 2, geom.width_y / 2, geom.length
    tol = 1e-6 * max(hx, hy, L)
    x, y, z = nodes.T
    on = {
        "base": np.abs(z) < tol, "top": np.abs(z - L) < tol,
        "front": np.abs(x - hx) < tol, "back": np.abs(x + hx) < tol,
        "ypos": np.abs(y - hy) < tol, "yneg": np.abs(y + hy) < tol,
    }
    z0, z1 = geom.cavity_z
    on["cavity"] = (np.hypot(x, y - geom.cavity_offset) < geom.cavity_radius + tol) & (z > z0 - tol) & (z < z1 + tol)

    # boundary faces: corner quadruples that belong to one element only
    faces = elements[:, HEX20_FACES]  # (E, 6, 8)
    key = np.sort(faces[:, :, :4].reshape(-1, 4), axis=1)
    _, inverse, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = np.flatnonzero(count[inverse.ravel()] == 1)
    ef = np.stack([boundary // 6, boundary % 6], 1)
    face_nodes = faces.reshape(-1, 8)[boundary]
    face_sets, claimed = {}, np.zeros(boundary.size, dtype=bool)
    for name, mask in on.items():
        hit = mask[face_nodes].all(axis=1)
        face_sets[name] = ef[hit]
        claimed |= hit
    if not claimed.all():
        k = int(np.flatnonzero(~claimed)[0])
        raise AssertionError(f"boundary face {ef[k].tolist()} of the actuator mesh belongs to no named surface")
    face_sets["exterior"] = ef[~on["cavity"][face_nodes].all(axis=1)]
    node_sets = {name: np.flatnonzero(mask) for name, mask in on.items()}
    node_sets["cavity"] = np.unique(face_nodes[on["cavity"][face_nodes].all(axis=1)])
    node_sets["all"] = np.arange(nodes.shape[0])
    return node_sets, face_sets


# -- fibers ------------------------------------------------------------------------------------------
def helix_points(geom: ActuatorGeometry, s: np.ndarray | None = None, points_per_turn: int = 16) -> np.ndarray:
    """Points of both helices at arc parameters ``s in [0, 1]`` (z = z0 + s L_c), shape (2, n, 3).

    Helix 0 winds counter-clockwise seen from +z as z grows, helix 1 clockwise; both start at
    ``helix_start_deg``. Without ``s``: ``points_per_turn`` equally spaced points per turn.
    """
    geom.validate()
    if s is None:
        s = np.linspace(0.0, 1.0, int(math.ceil(geom.helix_turns * points_per_turn)) + 1)
    s = np.asarray(s, dtype=np.float64)
    z0, _ = geom.cavity_z
    R, e = geom.helix_radius, geom.cavity_offset
    sweep = 2 * math.pi * geom.helix_turns * s
    th0 = math.radians(geom.helix_start_deg)
    out = []
    for sign in (1.0, -1.0):
        th = th0 + sign * sweep
        out.append(np.stack([R * np.cos(th), e + R * np.sin(th), z0 + geom.cavity_length * s], 1))
    return np.stack(out)


def fiber_mesh(geom: ActuatorGeometry, elements_per_turn: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Line3 truss elements on both helices: nodes ``X_fiber (n, 3)`` and ``conn (m, 3)`` with rows
    (end, end, middle) as ``line3_shape`` (s = -1, +1, 0). Each helix has
    ``ceil(turns * elements_per_turn)`` elements of equal arc length; nodes lie on the helix.

    elements_per_turn: default ``4 (resolution + 1)``, the number of ring elements around the cavity.
    """
    geom.validate()
    per_turn = 4 * (geom.resolution + 1) if elements_per_turn is None else int(elements_per_turn)
    if per_turn < 2:
        raise GeometryError(f"elements_per_turn = {elements_per_turn!r} must be at least 2")
    n_el = max(1, int(math.ceil(geom.helix_turns * per_turn - 1e-9)))
    X = helix_points(geom, np.linspace(0.0, 1.0, 2 * n_el + 1)).reshape(-1, 3)
    k = np.arange(n_el)
    one = np.stack([2 * k, 2 * k + 2, 2 * k + 1], 1)
    conn = np.concatenate([one, one + 2 * n_el + 1])
    return X, conn


# -- model ---------------------------------------------------------------------------------------------
def element_sets(geom: ActuatorGeometry, mesh: Mesh) -> dict[str, np.ndarray]:
    """Element sets by centroid: ``endcap_base``, ``endcap_top``, ``cavity_layers`` (z in [z0, z1]),
    ``core`` (the endcap bricks inside the cavity disk)."""
    c = mesh.nodes[mesh.elements[:, :8]].mean(1)
    z0, z1 = geom.cavity_z
    r = np.hypot(c[:, 0], c[:, 1] - geom.cavity_offset)
    return {
        "endcap_base": np.flatnonzero(c[:, 2] < z0), "endcap_top": np.flatnonzero(c[:, 2] > z1),
        "cavity_layers": np.flatnonzero((c[:, 2] > z0) & (c[:, 2] < z1)),
        "core": np.flatnonzero(r < geom.cavity_radius),
    }


CAVITY_OFFSET = ParameterInfo(
    "delta_y", "mm", 0.0, -1.0, 0.5,
    "shift of the cavity along y from its nominal axis (a misplaced mould core), outer surfaces fixed; "
    "at most half the 1 mm wall between the paper's cavity and the face y = +8, at most 1 mm the other way")


def cavity_offset_field(mesh: Mesh) -> np.ndarray:
    """Morph field of a cavity shifted along +y: 1 on the cavity surface, 0 on the outer surfaces
    (base, top and sides), harmonic in between (:func:`fem.morph.harmonic_field`)."""
    from torchfra.fem.morph import harmonic_field

    return harmonic_field(mesh, mesh.node_set("cavity"), mesh.face_set_nodes("exterior"), (0.0, 1.0, 0.0))


# When the body's weight acts, relative to a DIC recording's reference image
WEIGHT = {
    "before_reference": "the weight acts before the reference image (a real recording): the body settles under it "
                        "first and the recording sees the pressure's displacements from the sagged state",
    "with_load": "the weight ramps with the pressure from the unloaded body (the reference image unloaded and "
                 "weightless): an explicit option, for recordings made that way",
}


def build_actuator_model(geom: ActuatorGeometry | None = None, formulation: str = "hybrid",
                         elements_per_turn: int | None = None, integration: str = "full",
                         material=None, base: str = "clamp", gravity=None, fiber_modulus="E_fiber",
                         cavity_offset: bool = False, fibers=None, fiber_pitch: bool = False,
                         weight: str = "before_reference"):
    """The paper's actuator model (§2, §4): Neo-Hookean Hex20 body, embedded Line3 fibers, clamped
    base, rigid flat top, conservative pressure ``P`` in the closed cavity.

    Parameters of the model: ``C10``, ``D1`` (body), ``E_fiber`` (fibers), ``P`` (cavity pressure).

    Candidate physics (DESIGN §1.4) switch on here, each at its null exactly the paper's model:
    ``material`` (default ``NeoHookean()``; e.g. ``MooneyRivlin()`` adds ``C01``), ``base="compliant"``
    (``ElasticSupport`` springs ``c_n``, ``c_t`` under the base instead of the clamp), ``gravity`` (a
    direction vector: self-weight with parameter ``density``; ``weight``, a key of :data:`WEIGHT`, says
    whether it acts before the reference image, the default, or ramps with the load), ``fiber_modulus`` (the fibers' modulus
    parameter name, or a callable ``element centroids (m, 3) -> names (m,)`` to give fiber segments
    their own moduli, e.g. a debonded stretch), ``cavity_offset=True`` (a misplaced mould core:
    parameter ``delta_y``, mm, moves the cavity along y relative to the outer surfaces by a
    harmonic morph of the mesh, :data:`CAVITY_OFFSET`; the fibers follow the material they sit in).
    ``fiber_pitch=True`` (fibers wound at another pitch than drawn: parameter ``fiber_pitch``, deg,
    null ``geom.pitch_deg``; :class:`fem.FiberPitch` winds the same trusses at each member's pitch and
    embeds them where they fall; not with given ``fibers`` or per-segment moduli; with
    ``cavity_offset`` a member may move one of the two, not both).
    ``fibers``: ``(X (n, 3), conn (m, 3))`` Line3 fiber nodes and connectivity to embed in place of
    the geometry's helices (e.g. fiber paths measured on a specimen).
    ``integration="full"`` (3x3x3, the C3D20H analogue) by default: with the paper's reduced 2x2x2
    rule the fiber-free ring next to the pressurized cavity has a spurious mode that the cavity
    pressure's load stiffness drives negative (resolution 2 stopped at 52 % load: three negative
    tangent eigenvalues, modes alternating sign node to node in that ring; with 3x3x3 the same mode
    is ~20x stiffer and full load is reached without cutbacks).
    Returns ``(model, info)``; ``info`` holds ``geometry``, ``mesh``, ``fiber_nodes`` (model node
    ids), ``fiber_conn`` (model node ids, (m, 3)), ``fiber_hosts``/``fiber_xi`` (host element and
    natural coordinates of every fiber node), ``element_sets``, ``tracked_node`` (mesh node on the
    front face nearest to y = 0, z = z0 + 3/4 L_c: the paper's (0, 40)) and counts ``elements``,
    ``nodes``, ``fiber_elements``, ``fiber_nodes_count``, ``dofs`` (reduced unknowns).
    """
    from torchfra import fem

    geom = (geom or ActuatorGeometry()).validate(helices=fibers is None)
    mesh = actuator_mesh(geom)
    model = fem.Model(mesh)
    if base not in ("clamp", "compliant"):
        raise ValueError(f"base must be 'clamp' or 'compliant', got {base!r}")
    if weight not in WEIGHT:
        raise ValueError(f"weight must be one of {sorted(WEIGHT)}, got {weight!r}")
    model.add(fem.Hex20Solid(mesh, material or fem.NeoHookean(), formulation, integration=integration))
    X_fiber, conn = fiber_mesh(geom, elements_per_turn) if fibers is None else (
        np.asarray(fibers[0], dtype=np.float64), np.asarray(fibers[1], dtype=np.int64))
    hosts, xi = locate_points(mesh, X_fiber)
    N, _ = hex20_shape(xi)
    fiber_nodes = model.add_nodes(X_fiber)
    if callable(fiber_modulus):
        names = np.asarray(fiber_modulus(X_fiber[conn].mean(axis=1)))
        for name in np.unique(names):
            model.add(fem.Truss(model.X, fiber_nodes[conn[names == name]], area=geom.fiber_area, modulus=str(name)))
    else:
        model.add(fem.Truss(model.X, fiber_nodes[conn], area=geom.fiber_area, modulus=fiber_modulus))
    for k, node in enumerate(fiber_nodes):
        model.embed(int(node), mesh.elements[hosts[k]], N[k])
    fem.support_face(model, "base", compliant=base == "compliant")
    if gravity is not None:
        model.add(fem.Gravity(mesh, direction=gravity, preload=weight == "before_reference"))
    model.rigid("top")
    model.add(fem.CavityPressure(mesh, "cavity", pressure="P"))
    if fiber_pitch:
        if fibers is not None or callable(fiber_modulus):
            raise ValueError("fiber_pitch winds the geometry's own helices at another pitch: it cannot be combined "
                             "with given fibers or per-segment fiber moduli")
        model.add(fem.FiberPitch(mesh, (0.0, geom.cavity_offset), geom.helix_radius, geom.cavity_z, geom.pitch_deg,
                                 geom.helix_start_deg, conn.shape[0] // 2, geom.fiber_area, modulus=fiber_modulus))
    if cavity_offset:
        model.morph("delta_y", cavity_offset_field(mesh), CAVITY_OFFSET)

    front = mesh.node_set("front")
    z0, _ = geom.cavity_z
    target = np.array([geom.width_x / 2, 0.0, z0 + 0.75 * geom.cavity_length])
    tracked = int(front[np.argmin(np.linalg.norm(mesh.nodes[front] - target, axis=1))])
    constrained = np.union1d(mesh.node_set("base"), mesh.node_set("top"))
    info = dict(
        geometry=geom, mesh=mesh, fiber_nodes=fiber_nodes, fiber_conn=fiber_nodes[conn], fiber_hosts=hosts,
        fiber_xi=xi, element_sets=element_sets(geom, mesh), tracked_node=tracked,
        elements=mesh.n_elements, nodes=mesh.n_nodes, fiber_elements=conn.shape[0],
        fiber_nodes_count=fiber_nodes.size, dofs=3 * (mesh.n_nodes - constrained.size) + 6,
    )
    return model, info
