"""Observation operator: line of sight, interpolation on the faces, interpolation in time."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import block_with_cavity

from torchfra import fem
from torchfra.fem.elements import HEX20_FACES, quad8_shape
from torchfra.fem.structured import box_mesh, ring_sector_mesh
from torchfra.observation.operator import (
    ObservationError,
    ObservationOperator,
    boundary_faces,
    frame_times,
    interpolate_in_time,
    regular_grid,
    visible_faces,
)

# rtree (a declared dependency) gives trimesh its ray engine: both engines are always tested.
ENGINES = ["numpy", "trimesh"]

SIDES = {"xmax": (1, 0, 0), "xmin": (-1, 0, 0), "ymax": (0, 1, 0), "ymin": (0, -1, 0),
         "zmax": (0, 0, 1), "zmin": (0, 0, -1)}


def rows(a) -> set:
    return {tuple(r) for r in np.asarray(a).tolist()}


def actuator_box(distortion=0.0):
    """The actuator's outer box (16 x 16 x 60 mm, y centred, front face x = +8), no cavity."""
    return box_mesh((16.0, 16.0, 60.0), (4, 4, 12), origin=(-8.0, -8.0, 0.0), distortion=distortion)


def remove_elements(mesh: fem.Mesh, drop) -> fem.Mesh:
    """The mesh without elements ``drop`` (unused nodes stay); face sets renumbered."""
    keep = np.setdiff1d(np.arange(mesh.n_elements), drop)
    remap = -np.ones(mesh.n_elements, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    face_sets = {k: np.stack([remap[v[:, 0]], v[:, 1]], 1) for k, v in mesh.face_sets.items()}
    return fem.Mesh(mesh.nodes, mesh.elements[keep], mesh.node_sets, {k: v[v[:, 0] >= 0] for k, v in face_sets.items()})


def element_at(mesh: fem.Mesh, centre) -> int:
    return int(np.argmin(np.linalg.norm(mesh.nodes[mesh.elements].mean(1) - np.asarray(centre), axis=1)))


def face_facing(mesh: fem.Mesh, element: int, direction) -> tuple[int, int]:
    """The face of an element whose outward normal is ``direction`` (axis-aligned bricks)."""
    X = mesh.nodes[mesh.elements[element]]
    centre = X.mean(0)
    for f in range(6):
        n = X[HEX20_FACES[f, :4]].mean(0) - centre
        if np.allclose(n / np.linalg.norm(n), direction):
            return element, f
    raise AssertionError("no such face")


def points_on_faces(mesh, faces, n, seed=0):
    """n random points on the Quad8 faces (exactly on them, curved or not), mm."""
    rng = np.random.default_rng(seed)
    f = rng.integers(0, len(faces), n)
    st = rng.uniform(-1, 1, (n, 2))
    Xf = mesh.nodes[mesh.elements[faces[f, 0][:, None], HEX20_FACES[faces[f, 1]]]]
    return np.einsum("pa,pai->pi", quad8_shape(st)[0], Xf)


# -- line of sight ------------------------------------------------------------------------------------

def test_boundary_faces_of_a_box():
    mesh = box_mesh((2.0, 3.0, 4.0), (2, 3, 4))
    expected = set().union(*(rows(mesh.face_sets[s]) for s in SIDES))
    assert rows(boundary_faces(mesh)) == expected


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("distortion", [0.0, 0.3])
def test_a_box_shows_the_face_towards_the_camera(engine, distortion):
    mesh = actuator_box(distortion)
    for side, d in SIDES.items():
        assert rows(visible_faces(mesh, d, engine=engine)) == rows(mesh.face_sets[side]), side
    oblique = rows(visible_faces(mesh, (1, 1, 1), engine=engine))
    assert oblique == rows(mesh.face_sets["xmax"]) | rows(mesh.face_sets["ymax"]) | rows(mesh.face_sets["zmax"])


@pytest.mark.parametrize("engine", ENGINES)
def test_a_part_behind_another_is_hidden(engine):
    # Three bricks in a row along x, the middle one removed: two disjoint blocks.
    mesh = remove_elements(box_mesh((3.0, 1.0, 1.0), (3, 1, 1)), [1])
    back = face_facing(mesh, element_at(mesh, (0.5, 0.5, 0.5)), (1, 0, 0))
    front = face_facing(mesh, element_at(mesh, (2.5, 0.5, 0.5)), (1, 0, 0))
    assert back in rows(boundary_faces(mesh))  # exposed and facing the camera, yet behind the front block
    assert rows(visible_faces(mesh, (1, 0, 0), engine=engine)) == {front}
    assert rows(visible_faces(mesh, (-1, 0, 0), engine=engine)) == {face_facing(mesh, back[0], (-1, 0, 0))}


@pytest.mark.parametrize("engine", ENGINES)
def test_cavity_faces_are_not_seen(engine):
    mesh = block_with_cavity(3, 3.0)
    cavity = rows(mesh.face_sets["cavity"])
    assert cavity <= rows(boundary_faces(mesh))
    for side, d in SIDES.items():
        seen = rows(visible_faces(mesh, d, engine=engine))
        assert seen == rows(mesh.face_sets[side]) and not seen & cavity


@pytest.mark.parametrize("engine", ENGINES)
def test_curved_half_tube_hides_its_far_inner_wall(engine):
    # Half tube, angle 0..180 deg about z, seen from +x: the outer wall at angles below 90 deg is seen;
    # the inner wall beyond 90 deg faces +x but lies behind the near half.
    mesh = ring_sector_mesh(2.0, 5.0, 180.0, 3.0, (2, 10, 2))
    centres = mesh.nodes[mesh.elements].mean(1)
    angle = np.degrees(np.arctan2(centres[:, 1], centres[:, 0]))
    outer = mesh.face_sets["xmax"]
    assert rows(visible_faces(mesh, (1, 0, 0), engine=engine)) == rows(outer[angle[outer[:, 0]] < 90])
    inner_far = mesh.face_sets["xmin"][angle[mesh.face_sets["xmin"][:, 0]] > 90]
    assert len(inner_far) == 10 and not rows(inner_far) & rows(visible_faces(mesh, (1, 0, 0), require="any"))


@pytest.mark.parametrize("engine", ENGINES)
def test_partly_hidden_face_needs_require_any(engine):
    # 2 x 2 x 1 bricks with the front (x = 1..2) brick at y = 1..2 removed: the notch floor at x = 1,
    # y in [1, 2] is seen from (3, -1, 0) only for y > 4/3 (the brick at y = 0..1 hides the rest).
    mesh = remove_elements(box_mesh((2.0, 2.0, 1.0), (2, 2, 1)), [3])
    notch = face_facing(mesh, element_at(mesh, (0.5, 1.5, 0.5)), (1, 0, 0))
    assert notch in rows(visible_faces(mesh, (1, 0, 0), engine=engine))
    assert notch in rows(visible_faces(mesh, (3, -1, 0), require="any", engine=engine))
    assert notch not in rows(visible_faces(mesh, (3, -1, 0), require="all", engine=engine))


def test_engines_agree_off_axis():
    for mesh in (block_with_cavity(3, 3.0), ring_sector_mesh(2.0, 5.0, 180.0, 3.0, (2, 10, 2)), actuator_box(0.3)):
        for d in [(1, 0.3, -0.2), (-0.4, 1, 0.5), (0.2, -0.1, -1)]:
            assert rows(visible_faces(mesh, d, engine="numpy")) == rows(visible_faces(mesh, d, engine="trimesh"))


def test_bad_camera_direction_is_refused():
    with pytest.raises(ObservationError, match="camera_direction"):
        visible_faces(actuator_box(), (0, 0, 0))


# -- interpolation on the faces -----------------------------------------------------------------------

def affine(X, seed=1):
    rng = np.random.default_rng(seed)
    A, b = rng.normal(size=(3, 3)), rng.normal(size=3)
    return X @ A.T + b


def test_node_points_reproduce_nodal_values_exactly():
    mesh = actuator_box(0.3)
    op = ObservationOperator(mesh, visible_faces(mesh))
    front = np.sort(mesh.node_sets["xmax"])
    assert np.array_equal(op.point_ids, front) and np.array_equal(op.points, mesh.nodes[front])
    u = torch.randn(3, 4, mesh.n_nodes, 3, generator=torch.Generator().manual_seed(0))
    assert torch.equal(op(u), u[:, :, front][..., [1, 2]])
    assert torch.equal(op(u[:, 0]), u[:, 0, front][..., [1, 2]])
    assert np.array_equal(op(u.numpy()), u[:, :, front][..., [1, 2]].numpy())
    tracked = op.nearest_point(0.0, 40.0)
    assert np.array_equal(op.points[tracked], [8.0, 0.0, 40.0])
    # a model's Solution.u appends embedded (fiber) nodes after the mesh's: those are not observed
    with_fibers = torch.cat([u, torch.randn(3, 4, 7, 3, dtype=u.dtype)], dim=2)
    assert torch.equal(op(with_fibers), op(u))
    with pytest.raises(ObservationError, match="shape"):
        op(u[:, :, :-1])


@pytest.mark.parametrize("mesh_name", ["distorted box", "half tube"])
def test_affine_field_is_exact_at_arbitrary_face_points(mesh_name):
    if mesh_name == "distorted box":
        mesh = actuator_box(0.3)
    else:  # curved faces: the located (s, t) must satisfy x(s, t) = point
        mesh = ring_sector_mesh(2.0, 5.0, 180.0, 3.0, (2, 10, 2))
    faces = visible_faces(mesh)
    points = points_on_faces(mesh, faces, 200)
    op = ObservationOperator(mesh, faces, points, components=(0, 1, 2))
    assert op.weights.shape == (200, mesh.n_nodes)
    u = affine(mesh.nodes)
    expected = affine(points)
    assert np.abs(op(u) - expected).max() < 1e-11
    members = torch.as_tensor(np.stack([u, 2 * u]))
    got = op(members).numpy()
    assert np.abs(got - np.stack([expected, 2 * expected])).max() < 1e-11


def test_dic_grid_points_and_points_at_nodes():
    mesh = actuator_box(0.3)
    faces = visible_faces(mesh)
    grid = regular_grid(mesh, faces, 1.0)
    assert grid.shape == (17 * 61, 3) and np.all(grid[:, 0] == 8.0)
    assert np.allclose(np.unique(grid[:, 1]), np.arange(-8.0, 8.5, 1.0))
    op = ObservationOperator(mesh, faces, grid)
    assert np.abs(op(affine(mesh.nodes)) - affine(grid)[:, 1:]).max() < 1e-11
    at_nodes = ObservationOperator(mesh, faces, mesh.nodes[mesh.node_sets["xmax"]])
    u = np.random.default_rng(2).normal(size=(mesh.n_nodes, 3))
    assert np.abs(at_nodes(u) - u[mesh.node_sets["xmax"]][:, 1:]).max() < 1e-12


def test_point_off_the_face_is_named():
    mesh = actuator_box()
    faces = visible_faces(mesh)
    points = regular_grid(mesh, faces, 4.0)
    ids = 1000 + np.arange(len(points))
    off = points.copy()
    off[5, 0] += 0.1
    with pytest.raises(ObservationError, match=r"point id 1005 \(row 5\).* 0\.1 mm from"):
        ObservationOperator(mesh, faces, off, point_ids=ids)
    far = points.copy()
    far[7] = (8.0, 0.0, 100.0)  # beyond the top of the face: 40 mm off
    with pytest.raises(ObservationError, match=r"point id 1007 .* 40 mm from"):
        ObservationOperator(mesh, faces, far, point_ids=ids)
    ObservationOperator(mesh, faces, off, point_ids=ids, tol=0.2)


def test_regular_grid_follows_the_face_outline():
    # L-shaped front face: the brick at y, z in [1, 2] removed from a 1 x 2 x 2 block.
    mesh = remove_elements(box_mesh((1.0, 2.0, 2.0), (1, 2, 2)), [3])
    grid = regular_grid(mesh, visible_faces(mesh), 0.25)
    assert len(grid) == 81 - 16
    assert not np.any((grid[:, 1] > 1) & (grid[:, 2] > 1))
    with pytest.raises(ObservationError, match="planar"):
        notched = remove_elements(box_mesh((2.0, 2.0, 1.0), (2, 2, 1)), [3])
        regular_grid(notched, visible_faces(notched), 0.25)


def test_wrong_displacement_shape_is_refused():
    mesh = actuator_box()
    op = ObservationOperator(mesh, visible_faces(mesh))
    with pytest.raises(ObservationError, match=f"{mesh.n_nodes}, 3"):
        op(torch.zeros(2, mesh.n_nodes - 1, 3))


def test_observations_are_differentiable():
    mesh = actuator_box()
    op = ObservationOperator(mesh, visible_faces(mesh), points_on_faces(mesh, visible_faces(mesh), 30))
    u = torch.zeros(2, mesh.n_nodes, 3, requires_grad=True)
    op(u)[..., 0].sum().backward()
    assert torch.allclose(u.grad[0, :, 1], torch.as_tensor(op.weights.sum(axis=0)).reshape(-1).double())
    assert torch.all(u.grad[:, :, [0, 2]] == 0)


# -- interpolation in time ----------------------------------------------------------------------------

def test_frame_times():
    t = frame_times()
    assert len(t) == 100 and t[0] == 0.01 and t[-1] == 1.0 and np.allclose(np.diff(t), 0.01)


@pytest.mark.parametrize("kind", ["torch", "numpy"])
def test_time_interpolation_is_exact_for_linear_data(kind):
    steps = np.array([0.0, 0.02, 0.05, 0.1, 0.17, 0.3, 0.42, 0.6, 0.77, 0.9, 1.0])  # uneven load steps
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(4, 1, 5, 2)), rng.normal(size=(4, 1, 5, 2))
    values = a + b * steps[None, :, None, None]  # (N, T, P, 2)
    frames = frame_times()
    expected = a + b * frames[None, :, None, None]
    if kind == "torch":
        got = interpolate_in_time(torch.as_tensor(steps), torch.as_tensor(values), frames).numpy()
    else:
        got = interpolate_in_time(steps, values, frames)
    assert got.shape == (4, 100, 5, 2) and np.abs(got - expected).max() < 1e-13
    moved = interpolate_in_time(steps, np.moveaxis(values, 1, -1), frames, axis=-1)
    assert np.abs(moved - np.moveaxis(expected, 1, -1)).max() < 1e-13
    assert np.array_equal(interpolate_in_time(steps, values, steps[[0, 4, -1]]), values[:, [0, 4, -1]])


def test_time_interpolation_refuses_to_extrapolate():
    steps = np.linspace(0.0, 0.8, 9)  # a member that stopped at 80 % of the load
    values = np.zeros((2, 9, 3, 2))
    with pytest.raises(ObservationError, match=r"times_dst\[80\] = 0.81 is outside .*0, 0.8"):
        interpolate_in_time(steps, values, frame_times())
    with pytest.raises(ObservationError, match="strictly increasing"):
        interpolate_in_time(steps[::-1], values, [0.5])
    with pytest.raises(ObservationError, match="time axis"):
        interpolate_in_time(steps, values, [0.5], axis=2)
