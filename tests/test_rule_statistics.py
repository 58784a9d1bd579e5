"""Every rule type of Table 2.1: sampled children follow the law the rule states.

Each test compiles a tiny grammar, `P --rule--> C`, whose root P sits at a rotated, translated
pose (so a frame mix-up cannot hide behind the identity), and — where the parent frame matters —
also a chain `P --(uniform box, uniform rotation)--> Q --rule--> C`, so that the parents of the
rule under test vary from scene to scene.  Every law is checked in the coordinates in which it
is simple (world, parent-relative along world axes, or the parent's own frame).

For each rule type the sampler's log-density must also equal the scorer's density
(`translation_log_density + rotation_log_density`), and children moved off the support (off a
pinned axis, a fixed offset, a revolute axis, outside a box) must score -inf.

Statistical checks use fixed seeds and accept at p > 1e-3 (KS / chi-square) or within a few
standard errors (moments), so they are deterministic.  Power: each check was confirmed locally
to fail when the stated law is perturbed (a wrong mean/variance/frame, a missing factor 2 in
the Bingham density, a box or revolute range off by a few percent); several tests also carry
an in-line power check that a *wrong* law is rejected by the same statistic.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pytest
from scipy import stats
from scipy.linalg import solve_triangular
from scipy.spatial.transform import Rotation

from ssgc.compile import compile_text
from ssgc.distributions.bingham import moments
from ssgc.geometry import (
    axis_angle_to_quat,
    quat_angle,
    quat_conjugate,
    quat_multiply,
    quat_to_matrix,
)
from ssgc.ir import Grammar
from ssgc.rules import rotation_log_density, sample_children, translation_log_density
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees
from ssgc.tree import Trees

N = 20_000
P_MIN = 1e-3
LOGP_ATOL = 1e-9
ROOT_XYZ = [1.0, 2.0, 3.0]
ROOT_RPY = [0.3, -0.2, 1.1]
LOG_PI2 = float(np.log(np.pi**2))

# A full, well-conditioned covariance (eigenvalues ~0.08 .. 0.66).
FULL_COV = [[0.5, 0.2, -0.1], [0.2, 0.3, 0.05], [-0.1, 0.05, 0.2]]
DIAG_VAR = [0.1, 0.4, 0.02]
MEAN = [0.5, -1.0, 2.0]


# ------------------------------------------------------------------------------ helpers ---


def _compile(translation: str = "same", rotation: str = "same", chain: bool = False) -> Grammar:
    """`P -> C` under the rule, or `P -> Q -> C` with Q at a random pose (chain=True)."""
    if chain:
        head = (
            "    and:\n"
            "      - child: Q\n"
            "        translation: {world_box: {min: [-1, -1, -1], max: [1, 1, 1]}}\n"
            "        rotation: uniform\n"
            "  Q:\n"
        )
    else:
        head = ""
    text = (
        "grammar: rule_statistics\n"
        f"root: {{type: P, pose: {{xyz: {ROOT_XYZ}, rpy: {ROOT_RPY}}}}}\n"
        "types:\n"
        "  P:\n"
        f"{head}"
        "    and:\n"
        "      - child: C\n"
        f"        translation: {translation}\n"
        f"        rotation: {rotation}\n"
        "  C: {observed: true}\n"
    )
    return compile_text(text)


@dataclass(frozen=True)
class Draw:
    """The C children of `n` sampled trees, with their parents' poses."""

    g: Grammar
    trees: Trees
    logp: np.ndarray  # per tree, from the sampler
    node: np.ndarray  # index of each C node in `trees`
    rule: np.ndarray
    pxyz: np.ndarray
    pquat: np.ndarray
    xyz: np.ndarray
    quat: np.ndarray
    chain: bool

    @property
    def local_quat(self) -> np.ndarray:
        """conj(parent) ⊗ child: the child's rotation in its parent's frame."""
        return quat_multiply(quat_conjugate(self.pquat), self.quat)

    def parent_matrix(self) -> np.ndarray:
        return quat_to_matrix(self.pquat)


def _draw(g: Grammar, seed: int, chain: bool = False, n: int = N) -> Draw:
    trees, logp = sample_trees(g, n, seed)
    node = np.flatnonzero(trees.type == g.type_id("C"))
    assert len(node) == n  # one C per tree
    assert np.array_equal(trees.scene[node], np.arange(n))
    parent = trees.parent[node]
    return Draw(
        g,
        trees,
        logp,
        node,
        trees.rule[node],
        trees.xyz[parent],
        trees.quat[parent],
        trees.xyz[node],
        trees.quat[node],
        chain,
    )


def _edge_density(g: Grammar, rule, pxyz, pquat, xyz, quat) -> np.ndarray:  # type: ignore[no-untyped-def]
    rule = np.broadcast_to(np.asarray(rule, np.int64), (len(xyz),)).copy()
    return translation_log_density(g, rule, pxyz, pquat, xyz) + rotation_log_density(
        g, rule, pquat, quat
    )


def _check_logp(d: Draw, seed: int) -> None:
    """Sampler log-density == scorer density, on trees and on direct rule draws."""
    g = d.g
    score = score_trees(g, d.trees)
    assert np.all(np.isfinite(d.logp))
    np.testing.assert_allclose(score, d.logp, rtol=0, atol=LOGP_ATOL)
    edge = _edge_density(g, d.rule, d.pxyz, d.pquat, d.xyz, d.quat)
    assert np.all(np.isfinite(edge))
    if not d.chain:  # the root's `and` has probability 1: the tree's logp is the edge's
        np.testing.assert_allclose(d.logp, edge, rtol=0, atol=LOGP_ATOL)
    # sample_children directly, on the sampled parents (a second, independent draw).
    rid = int(d.rule[0])
    k = min(2000, len(d.rule))
    xyz, quat, lp = sample_children(g, rid, d.pxyz[:k], d.pquat[:k], np.random.default_rng(seed))
    assert xyz.shape == (k, 3) and quat.shape == (k, 4) and lp.shape == (k,)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(
        lp, _edge_density(g, rid, d.pxyz[:k], d.pquat[:k], xyz, quat), rtol=0, atol=LOGP_ATOL
    )


def _rescore(
    d: Draw, xyz: np.ndarray | None = None, quat: np.ndarray | None = None, count: int = 50
) -> np.ndarray:
    """Scores of the first `count` trees after replacing their C poses."""
    new_xyz, new_quat = d.trees.xyz.copy(), d.trees.quat.copy()
    sel = d.node[:count]
    if xyz is not None:
        new_xyz[sel] = xyz[:count]
    if quat is not None:
        new_quat[sel] = quat[:count]
    trees = dataclasses.replace(d.trees, xyz=new_xyz, quat=new_quat)
    return score_trees(d.g, trees)[:count]


def _root_matrix() -> np.ndarray:
    """R_root from its rpy, computed independently of ssgc (extrinsic x-y-z = Rz Ry Rx)."""
    return Rotation.from_euler("xyz", ROOT_RPY).as_matrix()


def _same_rotation(a: np.ndarray, b: np.ndarray, atol: float = 1e-10) -> None:
    np.testing.assert_allclose(quat_to_matrix(a), quat_to_matrix(b), rtol=0, atol=atol)


def _assert_normal(x: np.ndarray, mean, cov, n_se: float = 4.5) -> None:  # type: ignore[no-untyped-def]
    """x (n, d) ~ N(mean, cov): mean and covariance within `n_se` standard errors, every
    whitened coordinate N(0, 1) (KS) and the squared Mahalanobis distance chi2(d) (KS)."""
    mean, cov = np.asarray(mean, float), np.asarray(cov, float)
    n, dim = x.shape
    se_mean = np.sqrt(np.diag(cov) / n)
    assert np.all(np.abs(x.mean(axis=0) - mean) <= n_se * se_mean), (x.mean(axis=0), mean)
    s = np.cov(x.T).reshape(dim, dim)
    var = np.diag(cov)
    se_cov = np.sqrt((np.outer(var, var) + cov**2) / n)  # sd of a Gaussian sample covariance
    assert np.all(np.abs(s - cov) <= n_se * se_cov), (s, cov)
    chol = np.linalg.cholesky(cov)
    white = solve_triangular(chol, (x - mean).T, lower=True).T
    for k in range(dim):
        assert stats.kstest(white[:, k], "norm").pvalue > P_MIN, k
    maha = np.sum(white**2, axis=1)
    assert stats.kstest(maha, stats.chi2(dim).cdf).pvalue > P_MIN


def _normal_rejected(x: np.ndarray, mean, cov) -> bool:  # type: ignore[no-untyped-def]
    """Power check: True if `_assert_normal` rejects this (wrong) law."""
    try:
        _assert_normal(x, mean, cov)
    except AssertionError:
        return True
    return False


def _uniform_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    """Haar-uniform rotations, independently of ssgc: normalised 4-D standard normals."""
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _haar_angle_cdf(theta: np.ndarray) -> np.ndarray:
    return (theta - np.sin(theta)) / np.pi


# ------------------------------------------------------------------- fixed translations ---


def test_root_frame_is_the_stated_pose() -> None:
    g = _compile()
    np.testing.assert_allclose(g.root_xyz, ROOT_XYZ)
    np.testing.assert_allclose(quat_to_matrix(g.root_quat), _root_matrix(), atol=1e-12)


@pytest.mark.parametrize("chain", [False, True])
def test_same_translation_and_rotation(chain: bool) -> None:
    g = _compile("same", "same", chain)
    d = _draw(g, 11, chain)
    np.testing.assert_allclose(d.xyz, d.pxyz, rtol=0, atol=1e-12)
    _same_rotation(d.quat, d.pquat)
    if not chain:
        assert np.all(d.logp == 0.0)
    np.testing.assert_allclose(
        _edge_density(g, d.rule, d.pxyz, d.pquat, d.xyz, d.quat), 0.0, atol=LOGP_ATOL
    )
    _check_logp(d, 12)
    # Moved or turned by 1e-3: impossible.
    assert np.all(_rescore(d, xyz=d.xyz + np.array([0.0, 1e-3, 0.0])) == -np.inf)
    turned = quat_multiply(d.quat, axis_angle_to_quat([0.0, 0.0, 1.0], 1e-3))
    assert np.all(_rescore(d, quat=turned) == -np.inf)


@pytest.mark.parametrize("chain", [False, True])
def test_offset_translation_is_in_the_parent_frame(chain: bool) -> None:
    offset = [0.5, -1.0, 2.0]
    g = _compile(f"{{offset: {offset}}}", "same", chain)
    d = _draw(g, 21, chain)
    expected = d.pxyz + np.einsum("nij,j->ni", d.parent_matrix(), offset)
    np.testing.assert_allclose(d.xyz, expected, rtol=0, atol=1e-12)
    if not chain:  # against an independently computed root frame
        expected = np.add(ROOT_XYZ, _root_matrix() @ offset)
        np.testing.assert_allclose(d.xyz, np.broadcast_to(expected, d.xyz.shape), atol=1e-12)
    _check_logp(d, 22)
    # The offset applied along world axes is a different point, which is impossible.
    world = d.pxyz + offset
    assert np.all(_rescore(d, xyz=world) == -np.inf)
    for axis in range(3):
        moved = d.xyz.copy()
        moved[:, axis] += 1e-3
        assert np.all(_rescore(d, xyz=moved) == -np.inf)


# ---------------------------------------------------------------------- fixed rotations ---


@pytest.mark.parametrize("chain", [False, True])
def test_offset_rotation_composes_on_the_right(chain: bool) -> None:
    off_rpy = [0.1, 0.7, -0.4]
    g = _compile("same", f"{{offset: {{rpy: {off_rpy}}}}}", chain)
    d = _draw(g, 31, chain)
    r_off = Rotation.from_euler("xyz", off_rpy).as_matrix()
    np.testing.assert_allclose(quat_to_matrix(d.quat), d.parent_matrix() @ r_off, atol=1e-10)
    if not chain:
        expected = np.broadcast_to(_root_matrix() @ r_off, (N, 3, 3))
        np.testing.assert_allclose(quat_to_matrix(d.quat), expected, atol=1e-10)
    _check_logp(d, 32)
    # offset ⊗ parent (the wrong order) is another rotation: impossible.
    q_off = Rotation.from_euler("xyz", off_rpy).as_quat()[[3, 0, 1, 2]]
    wrong = quat_multiply(q_off, d.pquat)
    assert np.all(quat_angle(wrong, d.quat)[:50] > 1e-3)
    assert np.all(_rescore(d, quat=wrong) == -np.inf)
    turned = quat_multiply(d.quat, axis_angle_to_quat([1.0, 0.0, 0.0], 1e-3))
    assert np.all(_rescore(d, quat=turned) == -np.inf)


# ----------------------------------------------------------------------- normal offsets ---


@pytest.mark.parametrize("spread", ["variance", "covariance"])
def test_world_normal(spread: str) -> None:
    cov = FULL_COV if spread == "covariance" else np.diag(DIAG_VAR).tolist()
    law = f"covariance: {FULL_COV}" if spread == "covariance" else f"variance: {DIAG_VAR}"
    g = _compile(f"{{world_normal: {{mean: {MEAN}, {law}}}}}", "same")
    d = _draw(g, 41)
    _assert_normal(d.xyz, MEAN, cov)
    # Power: the same draws are not N(mean + 0.05, cov) nor N(mean, 1.1 cov).
    assert _normal_rejected(d.xyz, np.add(MEAN, 0.05), cov)
    assert _normal_rejected(d.xyz, MEAN, 1.1 * np.asarray(cov))
    _check_logp(d, 42)


@pytest.mark.parametrize("chain", [False, True])
def test_world_normal_ignores_the_parent(chain: bool) -> None:
    g = _compile(f"{{world_normal: {{mean: {MEAN}, covariance: {FULL_COV}}}}}", "same", chain)
    d = _draw(g, 43, chain)
    _assert_normal(d.xyz, MEAN, FULL_COV)
    _check_logp(d, 44)


@pytest.mark.parametrize("chain", [False, True])
def test_world_normal_offset(chain: bool) -> None:
    g = _compile(
        f"{{world_normal_offset: {{mean: {MEAN}, covariance: {FULL_COV}}}}}", "same", chain
    )
    d = _draw(g, 51, chain)
    _assert_normal(d.xyz - d.pxyz, MEAN, FULL_COV)
    # Power: in the parent's frame the offset is not this law.
    local = np.einsum("nji,nj->ni", d.parent_matrix(), d.xyz - d.pxyz)
    assert _normal_rejected(local, MEAN, FULL_COV)
    _check_logp(d, 52)


@pytest.mark.parametrize("chain", [False, True])
@pytest.mark.parametrize("spread", ["variance", "covariance"])
def test_parent_normal_offset(chain: bool, spread: str) -> None:
    cov = FULL_COV if spread == "covariance" else np.diag(DIAG_VAR).tolist()
    law = f"covariance: {FULL_COV}" if spread == "covariance" else f"variance: {DIAG_VAR}"
    g = _compile(f"{{parent_normal_offset: {{mean: {MEAN}, {law}}}}}", "same", chain)
    d = _draw(g, 61 + chain, chain)
    # R_pᵀ (child - parent) ~ N(mean, cov).
    local = np.einsum("nji,nj->ni", d.parent_matrix(), d.xyz - d.pxyz)
    _assert_normal(local, MEAN, cov)
    if not chain:
        local_ref = (d.xyz - ROOT_XYZ) @ _root_matrix()
        np.testing.assert_allclose(local, local_ref, atol=1e-12)
    # Power: along world axes, or rotated the wrong way, it is not this law.
    assert _normal_rejected(d.xyz - d.pxyz, MEAN, cov)
    wrong_way = np.einsum("nij,nj->ni", d.parent_matrix(), d.xyz - d.pxyz)
    assert _normal_rejected(wrong_way, MEAN, cov)
    _check_logp(d, 63)


PIN_CASES = [
    ("world_normal", ["z"]),
    ("world_normal_offset", ["z"]),
    ("parent_normal_offset", ["z"]),
    ("parent_normal_offset", ["x", "z"]),
    ("world_normal", ["y"]),
]


def _law_coordinates(d: Draw, kind: str) -> np.ndarray:
    """The child's position in the coordinates its translation law is written in."""
    if kind in ("world_normal", "world_box"):
        return d.xyz
    if kind == "parent_normal_offset":
        return np.einsum("nji,nj->ni", d.parent_matrix(), d.xyz - d.pxyz)
    return d.xyz - d.pxyz


@pytest.mark.parametrize(("kind", "pin"), PIN_CASES)
def test_pinned_axes(kind: str, pin: list[str]) -> None:
    g = _compile(
        f"{{{kind}: {{mean: {MEAN}, variance: {DIAG_VAR}, pin: [{', '.join(pin)}]}}}}",
        "same",
        chain=True,
    )
    d = _draw(g, 71, chain=True)
    u = _law_coordinates(d, kind)
    pinned = np.isin(["x", "y", "z"], pin)
    np.testing.assert_allclose(
        u[:, pinned], np.broadcast_to(np.asarray(MEAN)[pinned], (N, pinned.sum())), atol=1e-12
    )
    free = ~pinned
    _assert_normal(u[:, free], np.asarray(MEAN)[free], np.diag(np.asarray(DIAG_VAR)[free]))
    _check_logp(d, 72)
    # The density is over the free axes only: compare with scipy's Normal on those.
    expected = stats.multivariate_normal(
        np.asarray(MEAN)[free], np.diag(np.asarray(DIAG_VAR)[free])
    ).logpdf(u[:, free])
    edge = _edge_density(g, d.rule, d.pxyz, d.pquat, d.xyz, d.quat)
    np.testing.assert_allclose(edge, np.atleast_1d(expected), rtol=0, atol=1e-9)
    # Off the pinned axis (in the law's coordinates) by 1e-3: impossible.
    axis = int(np.flatnonzero(pinned)[0])
    step = np.zeros(3)
    step[axis] = 1e-3
    if kind == "parent_normal_offset":
        step = np.einsum("nij,j->ni", d.parent_matrix(), step)
    assert np.all(_rescore(d, xyz=d.xyz + step) == -np.inf)
    # ...while a move along a free axis keeps the tree possible.
    free_step = np.zeros(3)
    free_step[int(np.flatnonzero(free)[0])] = 1e-3
    if kind == "parent_normal_offset":
        free_step = np.einsum("nij,j->ni", d.parent_matrix(), free_step)
    assert np.all(np.isfinite(_rescore(d, xyz=d.xyz + free_step)))


def test_normal_density_is_normalised() -> None:
    """∫ exp(translation density) = 1, by importance sampling from a wider Normal."""
    g = _compile(f"{{parent_normal_offset: {{mean: {MEAN}, covariance: {FULL_COV}}}}}", "same")
    rng = np.random.default_rng(81)
    n = 100_000
    root = np.asarray(ROOT_XYZ)
    proposal = stats.multivariate_normal(
        root + _root_matrix() @ MEAN, 4.0 * _root_matrix() @ np.asarray(FULL_COV) @ _root_matrix().T
    )
    x = proposal.rvs(size=n, random_state=rng)
    px = np.broadcast_to(g.root_xyz, (n, 3))
    pq = np.broadcast_to(g.root_quat, (n, 4))
    w = np.exp(translation_log_density(g, np.zeros(n, np.int64), px, pq, x) - proposal.logpdf(x))
    assert abs(w.mean() - 1.0) <= 5 * w.std() / np.sqrt(n)
    assert abs(w.mean() - 1.0) < 0.01


# --------------------------------------------------------------------------------- boxes ---


BOX_LO = [-0.3, 0.2, 0.7]
BOX_HI = [0.5, 0.2, 1.9]  # y has zero width: pinned


@pytest.mark.parametrize("kind", ["world_box", "world_box_offset"])
@pytest.mark.parametrize("chain", [False, True])
def test_box(kind: str, chain: bool) -> None:
    g = _compile(f"{{{kind}: {{min: {BOX_LO}, max: {BOX_HI}}}}}", "same", chain)
    d = _draw(g, 91 + chain, chain)
    u = _law_coordinates(d, kind)
    lo, hi = np.asarray(BOX_LO), np.asarray(BOX_HI)
    free = hi > lo
    np.testing.assert_allclose(u[:, ~free], np.broadcast_to(lo[~free], (N, 1)), atol=1e-12)
    for axis in np.flatnonzero(free):
        width = hi[axis] - lo[axis]
        assert stats.kstest(u[:, axis], "uniform", args=(lo[axis], width)).pvalue > P_MIN
        # Power: a box 3% narrower on this axis is rejected.
        assert stats.kstest(u[:, axis], "uniform", args=(lo[axis], 0.97 * width)).pvalue < P_MIN
    # Independent axes: the 5x5 table of the two free axes' quintiles.
    a, b = np.flatnonzero(free)
    qa = np.minimum(((u[:, a] - lo[a]) / (hi[a] - lo[a]) * 5).astype(int), 4)
    qb = np.minimum(((u[:, b] - lo[b]) / (hi[b] - lo[b]) * 5).astype(int), 4)
    table = np.bincount(qa * 5 + qb, minlength=25)
    assert stats.chisquare(table).pvalue > P_MIN
    _check_logp(d, 93)
    # exp(density) × volume of the free axes = 1.
    edge = _edge_density(g, d.rule, d.pxyz, d.pquat, d.xyz, d.quat)
    np.testing.assert_allclose(np.exp(edge) * np.prod((hi - lo)[free]), 1.0, rtol=1e-12)
    # Outside the box on a free axis, or off the pinned axis: impossible.
    for axis, step in ((0, hi[0] - lo[0]), (2, -(hi[2] - lo[2])), (1, 1e-3)):
        moved = d.xyz.copy()
        moved[:, axis] += step
        assert np.all(_rescore(d, xyz=moved) == -np.inf), axis
    # On the box's faces: still possible.
    edge_pt = d.xyz.copy()
    edge_pt[:, 0] += hi[0] - u[:, 0]
    assert np.all(np.isfinite(_rescore(d, xyz=edge_pt)))


# ------------------------------------------------------------------- uniform rotations ---


@pytest.mark.parametrize("chain", [False, True])
def test_uniform_rotation_is_haar(chain: bool) -> None:
    g = _compile("same", "uniform", chain)
    d = _draw(g, 101, chain)
    fixed = Rotation.from_euler("xyz", [1.0, -0.5, 2.0]).as_quat()[[3, 0, 1, 2]]
    theta = quat_angle(np.broadcast_to(fixed, d.quat.shape), d.quat)
    assert stats.kstest(theta, _haar_angle_cdf).pvalue > P_MIN
    # Power: the angle of a rotation uniform in a 0.95-scaled ball of rotation vectors is not Haar.
    assert stats.kstest(0.95 * theta, _haar_angle_cdf).pvalue < P_MIN
    # Uniform on S³ up to sign: E[q qᵀ] = I/4.
    second = np.einsum("ni,nj->ij", d.quat, d.quat) / N
    se = np.std(d.quat[:, :, None] * d.quat[:, None, :], axis=0) / np.sqrt(N)
    assert np.all(np.abs(second - np.eye(4) / 4) <= 5 * se)
    _check_logp(d, 102)
    edge = rotation_log_density(g, d.rule, d.pquat, d.quat)
    np.testing.assert_allclose(edge, -LOG_PI2, rtol=0, atol=1e-12)


# -------------------------------------------------------------------------------- Bingham ---


BINGHAM_MODE = [0.4, 0.5, -0.6]
BINGHAM_CONC = [5, 20, 80]


def _bingham_rel(d: Draw, kind: str) -> np.ndarray:
    return d.quat if kind == "world_bingham" else d.local_quat


def _raw_m() -> np.ndarray:
    """A fixed, generic 4x4 orthogonal matrix."""
    q, r = np.linalg.qr(np.random.default_rng(7).standard_normal((4, 4)))
    return q * np.sign(np.diag(r))


RAW_Z = [-3.0, -30.0, 2.0, -1.0]  # not shifted: the mode is M's third column


@pytest.mark.parametrize("kind", ["world_bingham", "parent_bingham"])
@pytest.mark.parametrize("chain", [False, True])
@pytest.mark.parametrize("form", ["mode", "raw"])
def test_bingham_second_moment(kind: str, chain: bool, form: str) -> None:
    if form == "mode":
        law = f"mode: {{rpy: {BINGHAM_MODE}}}, concentration: {BINGHAM_CONC}"
    else:
        law = f"M: {_raw_m().tolist()}, Z: {RAW_Z}"
    g = _compile("same", f"{{{kind}: {{{law}}}}}", chain)
    rule = next(r for r in g.rules if r.child == g.type_id("C"))
    bingham = rule.rotation.bingham
    # The mode is the stated rotation.
    if form == "mode":
        mode = Rotation.from_euler("xyz", BINGHAM_MODE).as_quat()[[3, 0, 1, 2]]
    else:
        mode = _raw_m()[:, 2]
    assert quat_angle(bingham.mode, mode) < 1e-9
    d = _draw(g, 111 + chain + 2 * (form == "raw"), chain)
    q = _bingham_rel(d, kind)
    expected = bingham.M @ np.diag(moments(bingham.Z)) @ bingham.M.T
    outer = q[:, :, None] * q[:, None, :]
    got = outer.mean(axis=0)
    se = outer.std(axis=0) / np.sqrt(N)
    assert np.all(np.abs(got - expected) <= 5 * se + 1e-12), (got, expected)
    # Power: the second moment of the other kind's relative rotation does not match.
    other = d.local_quat if kind == "world_bingham" else d.quat
    outer_o = other[:, :, None] * other[:, None, :]
    assert np.any(np.abs(outer_o.mean(axis=0) - expected) > 5 * outer_o.std(axis=0) / np.sqrt(N))
    _check_logp(d, 113)


@pytest.mark.parametrize("kind", ["world_bingham", "parent_bingham"])
def test_bingham_concentration_is_angular_precision(kind: str) -> None:
    """Concentration c about a body axis: the small rotation about it has variance ≈ 2/c."""
    conc = np.array([400.0, 200.0, 1000.0])
    g = _compile(
        "same",
        f"{{{kind}: {{mode: {{rpy: {BINGHAM_MODE}}}, concentration: {conc.tolist()}}}}}",
        chain=True,
    )
    d = _draw(g, 121, chain=True)
    mode = Rotation.from_euler("xyz", BINGHAM_MODE).as_quat()[[3, 0, 1, 2]]
    r = quat_multiply(quat_conjugate(mode), _bingham_rel(d, kind))  # in the mode's body frame
    r = r * np.where(r[:, :1] < 0, -1.0, 1.0)
    vec = np.linalg.norm(r[:, 1:], axis=1, keepdims=True)
    rotvec = 2.0 * np.arctan2(vec, r[:, :1]) * r[:, 1:] / vec
    var = rotvec.var(axis=0)
    np.testing.assert_allclose(var, 2.0 / conc, rtol=0.06)
    assert np.all(np.abs(rotvec.mean(axis=0)) <= 5 * np.sqrt(2.0 / conc / N))
    # Each small angle is close to Normal(0, 2/c).
    for k in range(3):
        assert stats.kstest(rotvec[:, k] / np.sqrt(2.0 / conc[k]), "norm").pvalue > P_MIN, k
    _check_logp(d, 122)


@pytest.mark.parametrize("kind", ["world_bingham", "parent_bingham"])
def test_bingham_with_zero_concentration_is_uniform(kind: str) -> None:
    """Z = 0: exactly the uniform density -log π², and Haar-distributed draws."""
    g = _compile(
        "same", f"{{{kind}: {{mode: {{rpy: {BINGHAM_MODE}}}, concentration: 0}}}}", chain=True
    )
    d = _draw(g, 125, chain=True)
    edge = rotation_log_density(g, d.rule, d.pquat, d.quat)
    np.testing.assert_allclose(edge, -LOG_PI2, rtol=0, atol=1e-9)
    fixed = Rotation.from_euler("xyz", [1.0, -0.5, 2.0]).as_quat()[[3, 0, 1, 2]]
    theta = quat_angle(np.broadcast_to(fixed, d.quat.shape), d.quat)
    assert stats.kstest(theta, _haar_angle_cdf).pvalue > P_MIN
    _check_logp(d, 126)


@pytest.mark.parametrize("kind", ["world_bingham", "parent_bingham"])
@pytest.mark.parametrize("conc", [[5, 20, 80], [0.5, 1, 2]])
def test_bingham_density_is_normalised_on_so3(kind: str, conc: list[float]) -> None:
    """π² · E_uniform[exp(rotation density)] = 1: the SO(3) density integrates to one."""
    g = _compile("same", f"{{{kind}: {{mode: {{rpy: {BINGHAM_MODE}}}, concentration: {conc}}}}}")
    rng = np.random.default_rng(131)
    n = 400_000
    child = _uniform_quats(rng, n)
    parent = np.broadcast_to(g.root_quat, (n, 4))
    f = np.exp(rotation_log_density(g, np.zeros(n, np.int64), parent, child)) * np.pi**2
    se = f.std() / np.sqrt(n)
    assert abs(f.mean() - 1.0) <= 5 * se, (f.mean(), se)
    assert se < 0.05  # precise enough to see a missing factor 2
    # The density does not depend on the quaternion's sign.
    np.testing.assert_array_equal(
        rotation_log_density(g, np.zeros(100, np.int64), parent[:100], child[:100]),
        rotation_log_density(g, np.zeros(100, np.int64), parent[:100], -child[:100]),
    )


# ------------------------------------------------------------------------------- revolute ---


AXIS = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)


@pytest.mark.parametrize(
    ("lo", "hi"),
    [(-0.5, 1.2), (2.5, 4.0), (10.0, 11.0), (-np.pi, np.pi), (None, None)],
    ids=["range", "across-pi", "beyond-2pi", "full-explicit", "full-default"],
)
@pytest.mark.parametrize("chain", [False, True])
def test_revolute(lo: float | None, hi: float | None, chain: bool) -> None:
    bounds = "" if lo is None else f", min: {lo!r}, max: {hi!r}"
    g = _compile("same", f"{{revolute: {{axis: [1, 1, 0]{bounds}}}}}", chain)
    lo = -np.pi if lo is None else lo
    hi = np.pi if hi is None else hi
    width = hi - lo
    d = _draw(g, 141 + chain, chain)
    rel = d.local_quat
    along = rel[:, 1:] @ AXIS
    off_axis = np.linalg.norm(rel[:, 1:] - along[:, None] * AXIS, axis=1)
    assert off_axis.max() < 1e-12  # exactly about the axis, in the parent's frame
    theta = lo + np.mod(2.0 * np.arctan2(along, rel[:, 0]) - lo, 2.0 * np.pi)
    assert theta.min() >= lo - 1e-12 and theta.max() <= hi + 1e-12
    assert stats.kstest(theta, "uniform", args=(lo, width)).pvalue > P_MIN
    assert stats.kstest(theta, "uniform", args=(lo, 0.97 * width)).pvalue < P_MIN  # power
    _check_logp(d, 143)
    edge = rotation_log_density(g, d.rule, d.pquat, d.quat)
    np.testing.assert_allclose(np.exp(edge) * width, 1.0, rtol=1e-12)
    # Off the axis by 1e-3 rad (about a perpendicular axis): impossible.
    perp = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    tilted = quat_multiply(d.quat, axis_angle_to_quat(perp, 1e-3))
    assert np.all(_rescore(d, quat=tilted) == -np.inf)
    # The end points are possible; outside the range is not.
    at = {"lo": lo, "hi": hi, "mid": lo + 0.5 * width}
    for name, angle in at.items():
        q = quat_multiply(d.pquat[:50], axis_angle_to_quat(AXIS, np.full(50, angle)))
        assert np.all(np.isfinite(_rescore(d, quat=q))), name
    if width < 2 * np.pi - 1e-9:
        for angle in (lo - 0.05, hi + 0.05):
            q = quat_multiply(d.pquat[:50], axis_angle_to_quat(AXIS, np.full(50, angle)))
            assert np.all(_rescore(d, quat=q) == -np.inf), angle
            assert np.all(_rescore(d, quat=-q) == -np.inf), angle  # sign does not matter


# ------------------------------------------------------------ all kinds, sampler vs scorer ---


TRANSLATIONS = [
    "same",
    "{offset: [0.3, -0.2, 0.9]}",
    f"{{world_normal: {{mean: {MEAN}, covariance: {FULL_COV}}}}}",
    f"{{world_normal_offset: {{mean: {MEAN}, variance: 0.3, pin: [x]}}}}",
    f"{{parent_normal_offset: {{mean: {MEAN}, covariance: {FULL_COV}}}}}",
    f"{{world_box: {{min: {BOX_LO}, max: {BOX_HI}}}}}",
    "{world_box_offset: {min: [-1, -2, -3], max: [1, 2, 3]}}",
]
ROTATIONS = [
    "same",
    "{offset: {rpy_deg: [10, 20, 30]}}",
    "uniform",
    f"{{world_bingham: {{mode: {{rpy: {BINGHAM_MODE}}}, concentration: {BINGHAM_CONC}}}}}",
    "{parent_bingham: {mode: {quat_wxyz: [0.5, 0.5, 0.5, 0.5]}, concentration: 3.0}}",
    "{revolute: {axis: [0, 2, 1], min: -2.0, max: 0.25}}",
]


@pytest.mark.parametrize("translation", TRANSLATIONS)
@pytest.mark.parametrize("rotation", ROTATIONS)
def test_sampler_logp_equals_scorer_density(translation: str, rotation: str) -> None:
    g = _compile(translation, rotation, chain=True)
    d = _draw(g, 151, chain=True, n=600)
    _check_logp(d, 152)


def test_support_tolerances() -> None:
    """A pinned axis / fixed rotation matches within 1e-6 (m / rad), not beyond."""
    g = _compile(
        f"{{parent_normal_offset: {{mean: {MEAN}, variance: 0.1, pin: [z]}}}}",
        "{offset: {rpy: [0.1, 0.2, 0.3]}}",
    )
    d = _draw(g, 161, n=50)
    z_world = d.parent_matrix()[:, :, 2]  # the parent's z axis, in world coordinates
    spin = axis_angle_to_quat([0.0, 1.0, 0.0], 1.0)
    for eps, ok in ((0.5e-6, True), (2e-6, False)):
        assert np.all(np.isfinite(_rescore(d, xyz=d.xyz + eps * z_world)) == ok), eps
        turned = quat_multiply(d.quat, axis_angle_to_quat([0.0, 1.0, 0.0], eps))
        assert np.all(np.isfinite(_rescore(d, quat=turned)) == ok), eps
    assert np.all(_rescore(d, quat=quat_multiply(d.quat, spin)) == -np.inf)
    # A move within the pinned tolerance does not change the density of the free axes.
    np.testing.assert_allclose(
        _rescore(d, xyz=d.xyz + 0.5e-6 * z_world), d.logp[:50], rtol=0, atol=1e-12
    )
