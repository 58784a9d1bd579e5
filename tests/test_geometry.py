"""Tests for ssgc.geometry: conventions checked against scipy, round trips, edge cases."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import stats
from scipy.spatial.transform import Rotation

from ssgc import geometry as g

N = 200
HYP = settings(max_examples=100, deadline=None)


def to_scipy(q: np.ndarray) -> Rotation:
    """wxyz -> scipy's xyzw."""
    return Rotation.from_quat(np.roll(q, -1, axis=-1))


def from_scipy(r: Rotation) -> np.ndarray:
    return np.roll(r.as_quat(), 1, axis=-1)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def quats(rng: np.random.Generator) -> np.ndarray:
    return g.random_quat(rng, N)


# Hypothesis strategies -------------------------------------------------------------------

finite = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False, allow_infinity=False)


@st.composite
def unit_quats(draw: st.DrawFn) -> np.ndarray:
    q = np.array(draw(st.tuples(finite, finite, finite, finite)))
    norm = np.linalg.norm(q)
    if norm < 1e-3:
        q = np.array([1.0, 0.0, 0.0, 0.0])
        norm = 1.0
    return q / norm


@st.composite
def unit_axes(draw: st.DrawFn) -> np.ndarray:
    v = np.array(draw(st.tuples(finite, finite, finite)))
    norm = np.linalg.norm(v)
    if norm < 1e-3:
        return np.array([0.0, 0.0, 1.0])
    return v / norm


# Agreement with scipy --------------------------------------------------------------------


def test_identity_constant() -> None:
    np.testing.assert_array_equal(g.IDENTITY_QUAT, [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(g.quat_to_matrix(g.IDENTITY_QUAT), np.eye(3))
    assert not g.IDENTITY_QUAT.flags.writeable


def test_quat_to_matrix_matches_scipy(quats: np.ndarray) -> None:
    np.testing.assert_allclose(g.quat_to_matrix(quats), to_scipy(quats).as_matrix(), atol=1e-12)


def test_matrix_to_quat_matches_scipy(quats: np.ndarray) -> None:
    R = to_scipy(quats).as_matrix()
    expected = g.quat_canonical(from_scipy(Rotation.from_matrix(R)))
    np.testing.assert_allclose(g.matrix_to_quat(R), expected, atol=1e-12)


def test_multiply_matches_scipy(rng: np.random.Generator) -> None:
    a = g.random_quat(rng, N)
    b = g.random_quat(rng, N)
    expected = (to_scipy(a) * to_scipy(b)).as_matrix()
    np.testing.assert_allclose(g.quat_to_matrix(g.quat_multiply(a, b)), expected, atol=1e-12)


def test_multiply_composes_like_matrices(rng: np.random.Generator) -> None:
    a = g.random_quat(rng, N)
    b = g.random_quat(rng, N)
    np.testing.assert_allclose(
        g.quat_to_matrix(g.quat_multiply(a, b)),
        g.quat_to_matrix(a) @ g.quat_to_matrix(b),
        atol=1e-12,
    )


def test_rotate_matches_scipy_and_matrix(rng: np.random.Generator, quats: np.ndarray) -> None:
    v = rng.normal(size=(N, 3))
    rotated = g.quat_rotate(quats, v)
    np.testing.assert_allclose(rotated, to_scipy(quats).apply(v), atol=1e-12)
    np.testing.assert_allclose(
        rotated, (g.quat_to_matrix(quats) @ v[..., None])[..., 0], atol=1e-12
    )


def test_rpy_matches_scipy(rng: np.random.Generator) -> None:
    rpy = rng.uniform(-np.pi, np.pi, size=(N, 3))
    expected = Rotation.from_euler("xyz", rpy)
    np.testing.assert_allclose(g.rpy_to_matrix(rpy), expected.as_matrix(), atol=1e-12)
    q = g.rpy_to_quat(rpy)
    np.testing.assert_allclose(
        g.quat_canonical(q), g.quat_canonical(from_scipy(expected)), atol=1e-12
    )
    np.testing.assert_allclose(g.quat_to_matrix(q), g.rpy_to_matrix(rpy), atol=1e-12)


def test_rpy_single_axes_match_definition() -> None:
    a = 0.3
    c, s = np.cos(a), np.sin(a)
    Rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(g.rpy_to_matrix([a, 0, 0]), Rx, atol=1e-15)
    np.testing.assert_allclose(g.rpy_to_matrix([0, a, 0]), Ry, atol=1e-15)
    np.testing.assert_allclose(g.rpy_to_matrix([0, 0, a]), Rz, atol=1e-15)
    np.testing.assert_allclose(g.rpy_to_matrix([0.1, 0.2, 0.3]), _rz(0.3) @ _ry(0.2) @ _rx(0.1))


def _rx(a: float) -> np.ndarray:
    return g.rpy_to_matrix([a, 0.0, 0.0])


def _ry(a: float) -> np.ndarray:
    return g.rpy_to_matrix([0.0, a, 0.0])


def _rz(a: float) -> np.ndarray:
    return g.rpy_to_matrix([0.0, 0.0, a])


def test_quat_to_rpy_matches_scipy(rng: np.random.Generator) -> None:
    rpy = np.column_stack(
        [
            rng.uniform(-np.pi, np.pi, N),
            rng.uniform(-1.5, 1.5, N),
            rng.uniform(-np.pi, np.pi, N),
        ]
    )
    q = from_scipy(Rotation.from_euler("xyz", rpy))
    np.testing.assert_allclose(g.quat_to_rpy(q), to_scipy(q).as_euler("xyz"), atol=1e-10)


def test_axis_angle_matches_scipy(rng: np.random.Generator) -> None:
    axis = rng.normal(size=(N, 3))
    angle = rng.uniform(-2 * np.pi, 2 * np.pi, N)
    unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    expected = Rotation.from_rotvec(unit * angle[:, None])
    q = g.axis_angle_to_quat(axis, angle)
    np.testing.assert_allclose(g.quat_to_matrix(q), expected.as_matrix(), atol=1e-12)
    assert np.all(g.is_unit_quat(q))

    out_axis, out_angle = g.quat_to_axis_angle(q)
    rotvec = expected.as_rotvec()  # scipy: angle in [0, π]
    np.testing.assert_allclose(out_angle, np.linalg.norm(rotvec, axis=-1), atol=1e-10)
    np.testing.assert_allclose(out_axis * out_angle[:, None], rotvec, atol=1e-10)


# Round trips -----------------------------------------------------------------------------


@HYP
@given(unit_quats())
def test_quat_matrix_round_trip(q: np.ndarray) -> None:
    back = g.matrix_to_quat(g.quat_to_matrix(q))
    # Compare up to sign: the canonical sign flips discontinuously when w is ~0, so
    # tiny rounding may legitimately pick the other representative there.
    sign = 1.0 if np.dot(back, q) >= 0.0 else -1.0
    np.testing.assert_allclose(back, sign * q, atol=1e-12)
    assert back[0] >= 0.0
    np.testing.assert_array_equal(back, g.quat_canonical(back))
    assert g.quat_angle(q, back) < 1e-7


@HYP
@given(
    st.floats(-np.pi + 1e-6, np.pi - 1e-6),
    st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3),
    st.floats(-np.pi + 1e-6, np.pi - 1e-6),
)
def test_rpy_round_trip(roll: float, pitch: float, yaw: float) -> None:
    rpy = np.array([roll, pitch, yaw])
    np.testing.assert_allclose(g.quat_to_rpy(g.rpy_to_quat(rpy)), rpy, atol=1e-9)


@HYP
@given(unit_quats())
def test_quat_rpy_quat_round_trip_everywhere(q: np.ndarray) -> None:
    rpy = g.quat_to_rpy(q)
    assert -np.pi <= rpy[0] <= np.pi
    assert -np.pi / 2 <= rpy[1] <= np.pi / 2
    assert -np.pi <= rpy[2] <= np.pi
    assert g.quat_angle(q, g.rpy_to_quat(rpy)) < 1e-7


@pytest.mark.parametrize("pitch", [np.pi / 2, -np.pi / 2])
def test_rpy_gimbal_lock_reproduces_rotation(pitch: float) -> None:
    rpy = np.array([0.7, pitch, -0.4])
    R = g.rpy_to_matrix(rpy)
    back = g.quat_to_rpy(g.rpy_to_quat(rpy))
    assert abs(back[1] - pitch) < 1e-7
    np.testing.assert_allclose(g.rpy_to_matrix(back), R, atol=1e-12)


@HYP
@given(unit_axes(), st.floats(0.0, np.pi))
@example(axis=np.array([0.0, 0.0, 1.0]), angle=3.5227507007828882e-161)  # norm underflow
def test_axis_angle_round_trip(axis: np.ndarray, angle: float) -> None:
    q = g.axis_angle_to_quat(axis, angle)
    out_axis, out_angle = g.quat_to_axis_angle(q)
    assert abs(out_angle - angle) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(out_axis), 1.0)
    if 1e-6 < angle < np.pi - 1e-6:
        np.testing.assert_allclose(out_axis, axis, atol=1e-8)
    assert g.quat_angle(q, g.axis_angle_to_quat(out_axis, out_angle)) < 1e-9


def test_axis_angle_identity_and_unnormalised_axis() -> None:
    axis, angle = g.quat_to_axis_angle(g.IDENTITY_QUAT)
    np.testing.assert_array_equal(axis, [1.0, 0.0, 0.0])
    assert angle == 0.0
    q = g.axis_angle_to_quat([0.0, 0.0, 5.0], np.pi / 2)
    np.testing.assert_allclose(q, [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    with pytest.raises(ValueError):
        g.axis_angle_to_quat([0.0, 0.0, 0.0], 1.0)


def test_axis_angle_beyond_pi_is_folded() -> None:
    q = g.axis_angle_to_quat([0.0, 0.0, 1.0], 1.5 * np.pi)
    axis, angle = g.quat_to_axis_angle(q)
    np.testing.assert_allclose(angle, 0.5 * np.pi)
    np.testing.assert_allclose(axis, [0.0, 0.0, -1.0], atol=1e-15)


# Robustness near 180 degrees ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("diag", "expected"),
    [
        ((1, -1, -1), (0, 1, 0, 0)),
        ((-1, 1, -1), (0, 0, 1, 0)),
        ((-1, -1, 1), (0, 0, 0, 1)),
        ((1, 1, 1), (1, 0, 0, 0)),
    ],
)
def test_matrix_to_quat_half_turns(diag: tuple[int, ...], expected: tuple[int, ...]) -> None:
    q = g.matrix_to_quat(np.diag(np.array(diag, dtype=float)))
    np.testing.assert_array_equal(q, np.array(expected, dtype=float))
    assert not np.any(np.signbit(q))  # no -0.0 in canonical output


@pytest.mark.parametrize("eps", [0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3])
def test_matrix_to_quat_near_half_turn(rng: np.random.Generator, eps: float) -> None:
    axis = rng.normal(size=(N, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    for angle in (np.pi - eps, np.pi + eps):
        q = g.axis_angle_to_quat(axis, angle)
        R = g.quat_to_matrix(q)
        back = g.matrix_to_quat(R)
        assert np.all(g.is_unit_quat(back, tol=1e-12))
        assert np.all(g.quat_angle(q, back) < 1e-8)
        np.testing.assert_allclose(g.quat_to_matrix(back), R, atol=1e-12)
        assert np.all(back[:, 0] >= 0.0)


def test_matrix_to_quat_tolerates_slightly_non_orthonormal(quats: np.ndarray) -> None:
    R = g.quat_to_matrix(quats) * (1.0 + 1e-9)
    back = g.matrix_to_quat(R)
    assert np.all(g.is_unit_quat(back, tol=1e-12))
    assert np.all(g.quat_angle(quats, back) < 1e-8)


# Canonical form, normalisation, conjugate ------------------------------------------------


@pytest.mark.parametrize(
    ("q", "expected"),
    [
        ((-0.5, 0.5, -0.5, 0.5), (0.5, -0.5, 0.5, -0.5)),
        ((0.5, 0.5, -0.5, 0.5), (0.5, 0.5, -0.5, 0.5)),
        ((0.0, -1.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)),
        ((0.0, 0.0, -0.6, 0.8), (0.0, 0.0, 0.6, -0.8)),
        ((-0.0, 0.0, 0.0, -1.0), (0.0, 0.0, 0.0, 1.0)),
        ((0.0, 0.0, 0.6, -0.8), (0.0, 0.0, 0.6, -0.8)),
    ],
)
def test_quat_canonical(q: tuple[float, ...], expected: tuple[float, ...]) -> None:
    out = g.quat_canonical(q)
    np.testing.assert_array_equal(out, expected)
    assert not np.any(np.signbit(out[np.asarray(expected) == 0.0]))


@HYP
@given(unit_quats())
def test_canonical_is_sign_invariant(q: np.ndarray) -> None:
    np.testing.assert_array_equal(g.quat_canonical(q), g.quat_canonical(-q))
    np.testing.assert_array_equal(g.quat_canonical(g.quat_canonical(q)), g.quat_canonical(q))


def test_normalize_and_is_unit() -> None:
    q = np.array([[2.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]])
    assert not np.any(g.is_unit_quat(q))
    out = g.quat_normalize(q)
    np.testing.assert_allclose(out, [[1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]])
    assert g.is_unit_quat(out).dtype == np.bool_
    assert np.all(g.is_unit_quat(out))
    assert g.is_unit_quat([1.0 + 1e-7, 0, 0, 0])
    assert not g.is_unit_quat([1.0 + 1e-5, 0, 0, 0])
    with pytest.raises(ValueError):
        g.quat_normalize([0.0, 0.0, 0.0, 0.0])


def test_conjugate_is_inverse(quats: np.ndarray) -> None:
    np.testing.assert_allclose(
        g.quat_multiply(quats, g.quat_conjugate(quats)),
        np.broadcast_to(g.IDENTITY_QUAT, quats.shape),
        atol=1e-12,
    )


def test_relative_recovers_child(rng: np.random.Generator) -> None:
    parent = g.random_quat(rng, N)
    child = g.random_quat(rng, N)
    rel = g.quat_relative(parent, child)
    np.testing.assert_allclose(g.quat_multiply(parent, rel), child, atol=1e-12)
    np.testing.assert_allclose(
        g.quat_to_matrix(rel),
        np.swapaxes(g.quat_to_matrix(parent), -1, -2) @ g.quat_to_matrix(child),
        atol=1e-12,
    )


# Angles ----------------------------------------------------------------------------------


def test_quat_angle_matches_scipy_and_is_sign_invariant(rng: np.random.Generator) -> None:
    a = g.random_quat(rng, N)
    b = g.random_quat(rng, N)
    expected = (to_scipy(a).inv() * to_scipy(b)).magnitude()
    np.testing.assert_allclose(g.quat_angle(a, b), expected, atol=1e-12)
    np.testing.assert_allclose(g.quat_angle(a, -b), expected, atol=1e-12)
    np.testing.assert_allclose(g.quat_angle(a, a), 0.0, atol=1e-15)
    assert np.all((g.quat_angle(a, b) >= 0) & (g.quat_angle(a, b) <= np.pi))


@pytest.mark.parametrize("angle", [1e-12, 1e-9, 1e-6, np.pi - 1e-9, np.pi])
def test_quat_angle_precise_at_extremes(angle: float) -> None:
    q = g.axis_angle_to_quat([1.0, 2.0, 3.0], angle)
    assert g.quat_angle(g.IDENTITY_QUAT, q) == pytest.approx(angle, rel=1e-9, abs=1e-15)


# Broadcasting ----------------------------------------------------------------------------


def test_broadcasting_shapes(rng: np.random.Generator) -> None:
    single = g.random_quat(rng, 1)[0]
    batch = g.random_quat(rng, 5)
    grid = g.random_quat(rng, 5 * 3).reshape(5, 3, 4)
    vecs = rng.normal(size=(5, 3, 3))

    assert g.quat_multiply(single, batch).shape == (5, 4)
    assert g.quat_multiply(batch, single).shape == (5, 4)
    assert g.quat_multiply(grid, single).shape == (5, 3, 4)
    assert g.quat_multiply(batch[:, None, :], grid).shape == (5, 3, 4)
    assert g.quat_multiply(batch[None, :, :], batch[:, None, :]).shape == (5, 5, 4)
    assert g.quat_relative(single, grid).shape == (5, 3, 4)
    assert g.quat_angle(single, grid).shape == (5, 3)
    assert g.quat_rotate(single, vecs).shape == (5, 3, 3)
    assert g.quat_rotate(grid, np.array([1.0, 0.0, 0.0])).shape == (5, 3, 3)
    assert g.quat_to_matrix(grid).shape == (5, 3, 3, 3)
    assert g.matrix_to_quat(g.quat_to_matrix(grid)).shape == (5, 3, 4)
    assert g.quat_to_rpy(grid).shape == (5, 3, 3)
    assert g.rpy_to_quat(vecs).shape == (5, 3, 4)
    assert g.rpy_to_matrix(vecs).shape == (5, 3, 3, 3)
    assert g.quat_canonical(grid).shape == (5, 3, 4)
    assert g.is_unit_quat(grid).shape == (5, 3)
    axis, angle = g.quat_to_axis_angle(grid)
    assert axis.shape == (5, 3, 3) and angle.shape == (5, 3)
    assert g.axis_angle_to_quat([0.0, 0.0, 1.0], np.zeros((5, 3))).shape == (5, 3, 4)
    assert g.axis_angle_to_quat(vecs, 0.5).shape == (5, 3, 4)
    assert g.quat_to_matrix(single).shape == (3, 3)
    assert g.matrix_to_quat(np.eye(3)).shape == (4,)

    # Broadcast results equal the explicit per-element computation.
    np.testing.assert_allclose(
        g.quat_multiply(single, grid),
        g.quat_multiply(np.broadcast_to(single, grid.shape), grid),
    )
    np.testing.assert_allclose(
        g.quat_rotate(grid, vecs).reshape(-1, 3),
        g.quat_rotate(grid.reshape(-1, 4), vecs.reshape(-1, 3)),
    )


def test_outputs_are_float64() -> None:
    assert g.quat_multiply([1, 0, 0, 0], [0, 1, 0, 0]).dtype == np.float64
    assert g.matrix_to_quat(np.eye(3, dtype=np.float32)).dtype == np.float64
    assert g.rpy_to_quat([0, 0, 0]).dtype == np.float64


def test_bad_shapes_raise() -> None:
    with pytest.raises(ValueError):
        g.quat_multiply([1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        g.matrix_to_quat(np.eye(4))
    with pytest.raises(ValueError):
        g.quat_rotate(g.IDENTITY_QUAT, [1.0, 0.0])
    with pytest.raises(ValueError):
        g.random_quat(np.random.default_rng(0), -1)


# Uniformity of random_quat -----------------------------------------------------------------


def test_random_quat_shape_and_determinism() -> None:
    a = g.random_quat(np.random.default_rng(7), 10)
    b = g.random_quat(np.random.default_rng(7), 10)
    assert a.shape == (10, 4) and a.dtype == np.float64
    np.testing.assert_array_equal(a, b)
    assert np.all(g.is_unit_quat(a, tol=1e-12))
    assert g.random_quat(np.random.default_rng(7), 0).shape == (0, 4)


def test_random_quat_is_haar_uniform() -> None:
    q = g.random_quat(np.random.default_rng(2024), 20_000)
    _, theta = g.quat_to_axis_angle(q)
    # Haar measure on SO(3): the angle has density (1 - cos θ)/π on [0, π].
    result = stats.kstest(theta, lambda t: (t - np.sin(t)) / np.pi)
    assert result.pvalue > 0.01

    # E[R] = 0 for the Haar measure; each entry has variance 1/3, so the standard
    # error of the mean is ~0.004.
    mean_R = g.quat_to_matrix(q).mean(axis=0)
    np.testing.assert_allclose(mean_R, np.zeros((3, 3)), atol=0.02)

    # The axis is uniform on the sphere too: its mean is ~0.
    axis, _ = g.quat_to_axis_angle(q)
    np.testing.assert_allclose(axis.mean(axis=0), np.zeros(3), atol=0.03)
