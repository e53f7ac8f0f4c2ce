"""Rigid registration of DIC reference points onto the camera-visible face."""
import numpy as np
import pytest

from torchfra.actuator.geometry import ActuatorGeometry
from torchfra.fem.structured import box_mesh
from torchfra.observation.registration import (
    PlaneFace,
    RegistrationError,
    SampleFace,
    Similarity,
    evaluate,
    front_face,
    mesh_face,
    register,
    umeyama,
)

NORMAL = np.array([1.0, 0.0, 0.0])
CORNERS = np.array([[8.0, -8.0, 0.0], [8.0, 8.0, 0.0], [8.0, 8.0, 60.0], [8.0, -8.0, 60.0]])


def random_rotation(rng) -> np.ndarray:
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def face_points(drop_corner: bool = False):
    """A DIC-like grid on the front face x = 8 (1.75 x 4 mm pitch) and smooth displacements."""
    y, z = np.meshgrid(np.arange(-7.0, 7.01, 1.75), np.arange(2.0, 58.1, 4.0))
    X = np.stack([np.full(y.size, 8.0), y.ravel(), z.ravel()], axis=1)
    if drop_corner:  # no points in the top right corner: the cloud has no symmetry
        X = X[~((X[:, 1] > 3.0) & (X[:, 2] > 45.0))]
    U = np.stack([0.3 * np.sin(X[:, 2] / 20), -0.004 * X[:, 2] ** 2, 0.05 * X[:, 2] + 0.1 * X[:, 1]], axis=1)
    return X, U


def to_camera(X, U, rng, scale=1.0):
    """A random camera frame: the truth T (camera -> model) and the points/displacements seen there."""
    T = Similarity(random_rotation(rng), rng.uniform(-300, 300, 3), scale)
    return T, (X - T.t) @ T.R / T.s, U @ T.R / T.s


def assert_recovered(reg, T, U_cam, U, atol=1e-6):
    assert np.abs(reg.transform.R - T.R).max() < atol
    assert np.abs(reg.transform.t - T.t).max() < atol
    assert abs(reg.transform.s - T.s) < atol
    assert np.abs(reg.transform.vectors(U_cam) - U).max() < 1e-9


def test_umeyama_recovers_a_similarity_and_refuses_collinear_pairs():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 3))
    T = Similarity(random_rotation(rng), rng.normal(size=3), 2.5)
    fit = umeyama(a, T.points(a), scale=True)
    assert np.allclose(fit.R, T.R, atol=1e-12) and np.allclose(fit.t, T.t, atol=1e-12) and abs(fit.s - 2.5) < 1e-12
    assert np.allclose(umeyama(a, T.points(a)).R @ umeyama(a, T.points(a)).R.T, np.eye(3), atol=1e-12)
    line = np.outer(np.arange(4.0), [1.0, 2.0, 3.0])
    with pytest.raises(RegistrationError, match="one line"):
        umeyama(line, line)
    with pytest.raises(RegistrationError, match="at least 3"):
        umeyama(a[:2], a[:2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_plane_face_with_landmarks_recovers_the_transform_and_reports_outliers(seed):
    rng = np.random.default_rng(seed)
    X, U = face_points()
    T, P, U_cam = to_camera(X, U, rng)
    outliers = [5, 40, 77]
    P[outliers] += 2.0 * NORMAL @ T.R  # 2 mm in front of the face (a background speckle)
    # Landmarks picked with a depth error along the view (up to ~1 mm): the face fixes that direction.
    src = (CORNERS - T.t) @ T.R + rng.normal(size=(4, 1)) * (NORMAL @ T.R)
    reg = register(P, front_face(), landmarks=(src, CORNERS), point_ids=np.arange(100, 100 + len(P)), tol=0.5)
    assert reg.converged and reg.method == "plane"
    assert_recovered(reg, T, U_cam, U)
    assert reg.outlier_ids.tolist() == [100 + i for i in outliers]
    assert np.allclose(reg.distance[outliers], 2.0, atol=1e-9)
    assert reg.rms < 1e-9 and reg.max < 1e-9
    assert np.allclose(reg.on_face[reg.inlier], X[reg.inlier], atol=1e-9)
    assert reg.landmark_error.max() > 0.05  # the depth errors stay in the landmarks, not in the fit


def test_plane_face_fits_a_scale_from_landmarks():
    rng = np.random.default_rng(3)
    X, U = face_points()
    T, P, U_cam = to_camera(X, U, rng, scale=0.02)  # a pixel-like camera frame
    src = (CORNERS - T.t) @ T.R / T.s + 0.3 * rng.normal(size=(4, 1)) * (NORMAL @ T.R)
    reg = register(P, front_face(), landmarks=(src, CORNERS), scale=True)
    assert_recovered(reg, T, U_cam, U)


def test_landmark_errors_along_the_face_move_the_fit_by_as_much():
    rng = np.random.default_rng(4)
    X, U = face_points()
    T, P, _ = to_camera(X, U, rng)
    shift = np.array([0.0, 0.2, -0.1])  # every landmark picked 0.22 mm off along the face
    reg = register(P, front_face(), landmarks=((CORNERS - T.t) @ T.R, CORNERS + shift))
    placed = reg.transform.points(P)
    assert np.allclose(placed, X + shift, atol=1e-9)  # the plane exact, in-plane off by the picking error


def test_triangle_face_from_a_mesh():
    rng = np.random.default_rng(5)
    face = mesh_face(box_mesh((16.0, 16.0, 60.0), (2, 2, 3), origin=(-8.0, -8.0, 0.0)))
    assert face.flat
    X, U = face_points()
    T, P, U_cam = to_camera(X, U, rng)
    P[[0, 9]] -= 1.5 * NORMAL @ T.R  # behind the face
    src = (CORNERS - T.t) @ T.R
    reg = register(P, face, landmarks=(src, CORNERS), tol=0.5)
    assert_recovered(reg, T, U_cam, U)
    assert reg.outlier_ids.tolist() == [0, 9]


def test_sample_face_point_to_point_with_scale_and_no_landmarks():
    """Point-to-point ICP against the points' own true positions, from the principal axes alone."""
    rng = np.random.default_rng(6)
    X, U = face_points(drop_corner=True)
    T, P, U_cam = to_camera(X, U, rng, scale=1.7)
    outliers = [2, 30, 61]
    P[outliers] += 2.0 * NORMAL @ T.R / T.s
    reg = register(P, SampleFace(X), scale=True, tol=0.5)
    assert reg.method == "point" and reg.converged
    assert_recovered(reg, T, U_cam, U)
    assert reg.outlier_ids.tolist() == outliers
    again = register(P, SampleFace(X), scale=True, tol=0.5)  # deterministic
    assert np.array_equal(again.transform.R, reg.transform.R) and np.array_equal(again.transform.t, reg.transform.t)


def test_symmetric_face_without_landmarks_is_refused():
    rng = np.random.default_rng(7)
    X, U = face_points()
    _, P, _ = to_camera(X, U, rng)
    with pytest.raises(RegistrationError, match="more than one orientation"):
        register(P, SampleFace(X))


def test_flat_face_without_landmarks_is_refused():
    rng = np.random.default_rng(8)
    X, U = face_points()
    _, P, _ = to_camera(X, U, rng)
    with pytest.raises(RegistrationError, match="3 of the 6 degrees of freedom undetermined"):
        register(P, front_face())
    with pytest.raises(RegistrationError, match="4 of the 7"):
        register(P, front_face(), scale=True)


def test_evaluate_identity_measures_distances_to_the_bounded_face():
    face = PlaneFace((8.0, 0.0, 0.0), ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), (-8.0, 0.0), (8.0, 60.0))
    P = np.array([[8.0, 0.0, 30.0], [8.2, 1.0, 2.0], [8.0, 11.0, 30.0], [5.0, 0.0, 10.0]])
    reg = evaluate(P, face, Similarity.identity(), tol=0.5, point_ids=[7, 8, 9, 10])
    assert np.allclose(reg.distance, [0.0, 0.2, 3.0, 3.0])
    assert reg.outlier_ids.tolist() == [9, 10]
    assert np.allclose(reg.on_face[1], [8.0, 1.0, 2.0])
    assert np.isclose(reg.rms, np.sqrt(0.02)) and np.isclose(reg.max, 0.2)


def test_front_face_defaults_are_the_actuators():
    g = ActuatorGeometry()
    face = front_face()
    assert np.allclose(face.normal, NORMAL) and face.origin[0] == g.width_x / 2
    assert face.lo.tolist() == [-g.width_y / 2, 0.0] and face.hi.tolist() == [g.width_y / 2, g.length]
