"""Per-object-type MMD² of poses (thesis §4.3.1): the estimator, and its use on scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import GRAMMARS
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from ssgc.compile import compile_text, load_grammar
from ssgc.fit.metrics import DEFAULT_ALPHAS, mmd2, mmd_by_type
from ssgc.geometry import axis_angle_to_quat, quat_multiply
from ssgc.io.scene import Scene, scene_from_tree
from ssgc.ir import Grammar
from ssgc.sample.forward import sample_trees

Poses = tuple[NDArray[np.float64], NDArray[np.float64]]


def _poses(rng: np.random.Generator, n: int) -> Poses:
    """Positions ~ N(0, 0.3² I) and rotations scattered ~0.3 rad about the identity.

    The rotations must be concentrated: a rotation shift of a uniform SO(3) sample is the
    same distribution again, and the MMD rightly could not see it.
    """
    xyz = rng.normal(0.0, 0.3, size=(n, 3))
    quat = axis_angle_to_quat(rng.normal(size=(n, 3)), rng.normal(0.0, 0.3, size=n))
    return xyz, quat


def _rotated(quat: NDArray[np.float64], degrees: float) -> NDArray[np.float64]:
    """Every rotation turned further by `degrees` about world z."""
    return quat_multiply(axis_angle_to_quat([0.0, 0.0, 1.0], math.radians(degrees)), quat)


def _reference_mmd2(
    xa: NDArray[np.float64],
    qa: NDArray[np.float64],
    xb: NDArray[np.float64],
    qb: NDArray[np.float64],
    alphas: tuple[float, ...] = DEFAULT_ALPHAS,
    beta: float = 0.1,
) -> float:
    """The unbiased estimator written out pair by pair, with the angle taken from R1ᵀ R2."""

    def matrix(q: NDArray[np.float64]) -> NDArray[np.float64]:
        return Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()

    def k(
        t1: NDArray[np.float64],
        q1: NDArray[np.float64],
        t2: NDArray[np.float64],
        q2: NDArray[np.float64],
    ) -> float:
        rel = matrix(q1).T @ matrix(q2)
        angle = math.acos(min(1.0, max(-1.0, (np.trace(rel) - 1.0) / 2.0)))
        d = math.sqrt(sum((t1[i] - t2[i]) ** 2 for i in range(3))) + beta * angle
        return sum(math.exp(-a * d * d) for a in alphas)

    m, n = len(xa), len(xb)
    aa = sum(k(xa[i], qa[i], xa[j], qa[j]) for i in range(m) for j in range(m) if i != j)
    bb = sum(k(xb[i], qb[i], xb[j], qb[j]) for i in range(n) for j in range(n) if i != j)
    ab = sum(k(xa[i], qa[i], xb[j], qb[j]) for i in range(m) for j in range(n))
    return aa / (m * (m - 1)) + bb / (n * (n - 1)) - 2.0 * ab / (m * n)


# ------------------------------------------------------------------------------ mmd2 ---


def test_matches_a_double_loop_reference() -> None:
    rng = np.random.default_rng(7)
    xa, _ = _poses(rng, 7)
    xb, _ = _poses(rng, 9)
    # Spread rotations widely so that angles near 0 and π both occur.
    qa = Rotation.random(7, random_state=1).as_quat()[:, [3, 0, 1, 2]]
    qb = Rotation.random(9, random_state=2).as_quat()[:, [3, 0, 1, 2]]
    for alphas, beta in [(DEFAULT_ALPHAS, 0.1), ((0.5, 3.0), 1.0), ((2.0,), 0.0)]:
        expected = _reference_mmd2(xa, qa, xb, qb, alphas, beta)
        assert mmd2(xa, qa, xb, qb, alphas, beta) == pytest.approx(expected, abs=1e-12)


def test_same_distribution_is_near_zero_and_shifts_are_clearly_positive() -> None:
    rng = np.random.default_rng(0)
    xa, qa = _poses(rng, 400)
    xb, qb = _poses(rng, 400)
    same = mmd2(xa, qa, xb, qb)
    moved = [mmd2(xa, qa, xb + np.array([d, 0.0, 0.0]), qb) for d in (0.1, 0.5, 1.0)]
    turned = [mmd2(xa, qa, xb, _rotated(qb, deg)) for deg in (30.0, 90.0, 180.0)]
    assert abs(same) < 0.05 * moved[1]
    assert abs(same) < 0.05 * turned[1]
    assert moved[1] > 0.2 and turned[1] > 0.05
    assert moved == sorted(moved) and turned == sorted(turned)


def test_symmetric_and_blind_to_quaternion_sign() -> None:
    rng = np.random.default_rng(3)
    xa, qa = _poses(rng, 50)
    xb, qb = _poses(rng, 60)
    xb += 0.2
    value = mmd2(xa, qa, xb, qb)
    assert mmd2(xb, qb, xa, qa) == pytest.approx(value, rel=1e-12)
    flip_a = np.where(rng.random((50, 1)) < 0.5, -1.0, 1.0)
    flip_b = np.where(rng.random((60, 1)) < 0.5, -1.0, 1.0)
    assert mmd2(xa, qa * flip_a, xb, qb * flip_b) == pytest.approx(value, rel=1e-12)


def test_identical_poses_and_bad_input() -> None:
    xyz = np.zeros((3, 3))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    # Every kernel value is exactly 1 per scale, so all three averages cancel.
    assert mmd2(xyz, quat, xyz, -quat) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="at least 2"):
        mmd2(xyz[:1], quat[:1], xyz, quat)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        mmd2(quat, quat, xyz, quat)
    with pytest.raises(ValueError, match="alphas"):
        mmd2(xyz, quat, xyz, quat, alphas=(1.0, -1.0))
    with pytest.raises(ValueError, match="zero quaternion"):
        mmd2(xyz, quat * 0.0, xyz, quat)


# ----------------------------------------------------------------------- mmd_by_type ---


def _scenes(grammar: Grammar, n: int, seed: int) -> list[Scene]:
    trees, logp = sample_trees(grammar, n, seed)
    return [scene_from_tree(grammar, trees.tree(i), f"s{i}", float(logp[i])) for i in range(n)]


def test_by_type_small_for_the_same_grammar() -> None:
    grammar = load_grammar(GRAMMARS / "dimsum_table.yaml")
    values = mmd_by_type(grammar, _scenes(grammar, 150, 1), _scenes(grammar, 150, 2))
    assert len(values) >= 3
    assert grammar.types[grammar.root].name not in values
    assert all(abs(v) < 0.03 for v in values.values()), values


def test_by_type_sees_a_moved_mixture_mode() -> None:
    text = (GRAMMARS / "gmm.yaml").read_text()
    moved_text = text.replace("mean: [0.5, -1.0, 0.5]", "mean: [0.5, -1.0, 1.5]")
    assert moved_text != text
    gmm = load_grammar(GRAMMARS / "gmm.yaml")
    moved = compile_text(moved_text)
    data = _scenes(gmm, 400, 1)
    same = mmd_by_type(gmm, data, _scenes(gmm, 400, 2))
    other = mmd_by_type(gmm, data, _scenes(moved, 400, 2))
    # The observed root sits at the origin in every scene: skipped, not reported as 0.
    assert set(same) == set(other) == {"Point"}
    assert abs(same["Point"]) < 0.02
    assert other["Point"] > 0.1
    assert other["Point"] > 10 * abs(same["Point"])


def test_by_type_omits_rare_types_and_subsamples_reproducibly() -> None:
    gmm = load_grammar(GRAMMARS / "gmm.yaml")
    data = _scenes(gmm, 60, 5)
    # One Point on a side is too few for the unbiased estimate: the type is left out.
    assert mmd_by_type(gmm, data[:1], data) == {}
    assert mmd_by_type(gmm, [], data) == {}
    first = mmd_by_type(gmm, data, _scenes(gmm, 60, 6), max_objects=20, seed=3)
    again = mmd_by_type(gmm, data, _scenes(gmm, 60, 6), max_objects=20, seed=3)
    full = mmd_by_type(gmm, data, _scenes(gmm, 60, 6))
    assert first == again
    assert first["Point"] != full["Point"]
