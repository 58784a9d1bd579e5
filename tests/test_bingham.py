"""Tests for ssgc.distributions.bingham.

Independent Monte Carlo references use an angular central Gaussian (ACG)
proposal.  If ``y ~ N(0, Σ)`` in R⁴ and ``x = y/|y|``, the density of ``x`` with
respect to the surface measure on S³ is obtained by integrating out the radius::

    g(x) = ∫₀^∞ N(r x; 0, Σ) r³ dr
         = (2π)^(-2) |Σ|^(-1/2) ∫₀^∞ r³ exp(-r² a / 2) dr,     a = xᵀ Σ⁻¹ x
         = (2π)^(-2) |Σ|^(-1/2) · 2 / a²
         = |Σ|^(-1/2) (xᵀ Σ⁻¹ x)^(-2) / (2π²).

(Check: Σ = I gives 1/(2π²), the uniform density.)  Hence
``F(Z) = E_g[exp(xᵀ M diag(Z) Mᵀ x) / g(x)]``; with ``Σ⁻¹ = M diag(1 + k c) Mᵀ``
the weights are bounded on the sphere, so the estimator has finite variance and
its standard error can be estimated reliably from the sample.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, special, stats

from ssgc.distributions.bingham import (
    Bingham,
    fit_bingham,
    log_normalizer,
    moments,
)

TWO_PI2 = 2.0 * math.pi**2


# ---------------------------------------------------------------------------
# Independent helpers
# ---------------------------------------------------------------------------


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A random 4x4 orthogonal matrix (Haar, via QR with sign fix)."""
    q, r = np.linalg.qr(rng.standard_normal((4, 4)))
    return q * np.sign(np.diag(r))


def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions, written via the left-multiplication matrix."""
    w, x, y, z = p
    left = np.array(
        [
            [w, -x, -y, -z],
            [x, w, -z, y],
            [y, z, w, -x],
            [z, -y, x, w],
        ]
    )
    return left @ q


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def acg_sample(rng: np.random.Generator, cov: np.ndarray, n: int) -> np.ndarray:
    chol = np.linalg.cholesky(cov)
    y = rng.standard_normal((n, 4)) @ chol.T
    return y / np.linalg.norm(y, axis=1, keepdims=True)


def acg_logpdf(x: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Exact ACG log density w.r.t. the surface measure on S³ (see module docstring)."""
    prec = np.linalg.inv(cov)
    a = np.einsum("ni,ij,nj->n", x, prec, x)
    return -0.5 * np.linalg.slogdet(cov)[1] - 2.0 * np.log(a) - math.log(TWO_PI2)


def proposal_cov(M: np.ndarray, Z: np.ndarray, k: float) -> np.ndarray:
    """ACG covariance Σ = M diag(1 / (1 + k c)) Mᵀ with c = max(Z) - Z."""
    c = np.max(Z) - np.asarray(Z, dtype=float)
    return (M / (1.0 + k * c)) @ M.T


def choose_k(Z, rng: np.random.Generator, n_pilot: int = 100_000) -> float:
    """Pick the ACG scale k with the smallest importance-weight variance on a pilot run.

    Only the proposal is tuned; the pilot draws are discarded, so the estimates
    made afterwards with fresh draws stay unbiased.
    """
    c = np.max(Z) - np.asarray(Z, dtype=float)
    best_k, best_rv = 1.0, np.inf
    for k in (0.5, 1.0, 2.0, 3.0):
        omega = 1.0 + k * c
        y2 = rng.standard_normal((n_pilot, 4)) ** 2 / omega
        x2 = y2 / y2.sum(axis=1, keepdims=True)
        w = np.exp(-(x2 @ c)) * (x2 @ omega) ** 2
        rv = w.var() / w.mean() ** 2
        if rv < best_rv:
            best_k, best_rv = k, rv
    return best_k


def importance_estimate(
    Z,
    seed: int,
    *,
    target_rel_se: float = 2.5e-4,
    chunk: int = 1_000_000,
    max_n: int = 16_000_000,
) -> dict:
    """IS estimates of F(Z) and of E[x_i²] (M = I), with standard errors.

    Chunks of ``chunk`` ACG draws are added until the relative standard error of
    ``F`` is below ``target_rel_se`` (or ``max_n`` draws were used).  Deterministic.
    """
    Z = np.asarray(Z, dtype=float)
    rng = np.random.default_rng(seed)
    k = choose_k(Z, rng)
    c = np.max(Z) - Z
    omega = 1.0 + k * c  # diagonal of Σ⁻¹ (M = I)
    log_det_cov = -float(np.sum(np.log(omega)))
    n = 0
    s_w = s_w2 = 0.0
    s_wx = np.zeros(4)
    s_w2x = np.zeros(4)
    s_w2x2 = np.zeros(4)
    while True:
        u2 = rng.standard_normal((chunk, 4)) ** 2
        y2 = u2 / omega  # y = Σ^(1/2) u componentwise, squared
        r2 = y2.sum(axis=1)
        x2 = y2 / r2[:, None]  # x_i² of the projected direction x = y / |y|
        quad_prec = u2.sum(axis=1) / r2  # xᵀ Σ⁻¹ x
        # w = f(x) / g(x) = exp(Σ z x²) · 2π² |Σ|^(1/2) (xᵀΣ⁻¹x)².  Z is shifted by its
        # max (multiplied back below) so nothing overflows.
        w = np.exp(x2 @ (Z - np.max(Z))) * quad_prec**2
        w *= TWO_PI2 * math.exp(0.5 * log_det_cov)
        w2 = w * w
        n += chunk
        s_w += float(w.sum())
        s_w2 += float(w2.sum())
        s_wx += w @ x2
        s_w2x += w2 @ x2
        s_w2x2 += w2 @ (x2 * x2)
        mean = s_w / n
        var = max(s_w2 / n - mean * mean, 0.0)
        rel_se = math.sqrt(var / n) / mean
        if rel_se < target_rel_se or n >= max_n:
            break
    m_hat = s_wx / s_w
    # Delta-method standard error of the self-normalised ratio estimator.
    resid2 = s_w2x2 - 2.0 * m_hat * s_w2x + m_hat**2 * s_w2
    m_se = np.sqrt(np.maximum(resid2, 0.0)) / s_w
    return {
        "F": mean * math.exp(float(np.max(Z))),
        "rel_se": rel_se,
        "moments": m_hat,
        "moments_se": m_se,
        "n": n,
    }


def uniform_sphere(rng: np.random.Generator, n: int) -> np.ndarray:
    y = rng.standard_normal((n, 4))
    return y / np.linalg.norm(y, axis=1, keepdims=True)


# ---------------------------------------------------------------------------
# Normalising constant
# ---------------------------------------------------------------------------


def test_normalizer_at_zero_is_sphere_area():
    assert log_normalizer([0.0, 0.0, 0.0, 0.0]) == pytest.approx(math.log(TWO_PI2), abs=1e-15)
    assert math.exp(log_normalizer(np.zeros(4))) == pytest.approx(TWO_PI2, rel=1e-14)


@pytest.mark.parametrize(
    "z",
    [
        [-1.0, -2.0, -3.0, 0.0],
        [-100.0, -50.0, -20.0, 0.0],
        [-1e4, -3.0, -0.5, 0.0],
        [2.0, -7.0, 0.25, 1.0],
    ],
)
@pytest.mark.parametrize("shift", [-1234.5, -3.0, 0.7, 42.0])
def test_shift_identity(z, shift):
    z = np.asarray(z)
    assert log_normalizer(z + shift) == pytest.approx(log_normalizer(z) + shift, abs=1e-9)


@pytest.mark.parametrize(
    "z", [[-1.0, -2.0, -3.0, 0.0], [-500.0, -1.0, -0.1, 0.0], [-1e4, -2e3, -7.0, -0.3]]
)
def test_permutation_invariance(z):
    ref = log_normalizer(z)
    for perm in itertools.permutations(range(4)):
        assert log_normalizer(np.asarray(z)[list(perm)]) == pytest.approx(ref, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(min_value=-1e4, max_value=0.0), min_size=4, max_size=4),
    st.permutations(range(4)),
    st.floats(min_value=-50.0, max_value=50.0),
)
def test_normalizer_properties(z, perm, shift):
    z = np.asarray(z)
    base = log_normalizer(z)
    assert np.isfinite(base)
    assert log_normalizer(z[list(perm)] + shift) == pytest.approx(base + shift, abs=1e-9)
    # F is increasing in every z_i and bounded by exp(max z) · 2π².
    assert base <= np.max(z) + math.log(TWO_PI2) + 1e-12
    m = moments(z)
    assert np.all(m >= 0) and m.sum() == pytest.approx(1.0, abs=1e-13)
    np.testing.assert_allclose(moments(z[list(perm)]), m[list(perm)], rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("c", [0.5, 3.0, 40.0, 700.0, 1e4, 1e5, 1e8])
def test_normalizer_closed_forms(c):
    """Exact special cases, up to the largest concentrations."""
    # Two equal pairs: F = 2π² (e^a - e^b) / (a - b).
    a, b = -0.25 * c, -c
    expected = math.log(TWO_PI2) + a + math.log(-math.expm1(b - a)) - math.log(a - b)
    assert log_normalizer([a, b, a, b]) == pytest.approx(expected, rel=1e-10, abs=1e-10)
    # Three equal: x4² ~ Beta(1/2, 3/2) under the uniform law, so
    # F(-c,-c,-c,0) = 2π² 1F1(3/2; 2; -c) and F(-c,0,0,0) = 2π² 1F1(1/2; 2; -c).
    expected = math.log(TWO_PI2 * special.hyp1f1(1.5, 2.0, -c))
    assert log_normalizer([-c, -c, 0.0, -c]) == pytest.approx(expected, rel=1e-10, abs=1e-10)
    expected = math.log(TWO_PI2 * special.hyp1f1(0.5, 2.0, -c))
    assert log_normalizer([0.0, 0.0, -c, 0.0]) == pytest.approx(expected, rel=1e-10, abs=1e-10)


def test_normalizer_laplace_limit():
    """For large concentrations F → 2 π^{3/2} / sqrt(c1 c2 c3) (two antipodal Gaussians)."""
    c = np.array([1e4, 3e4, 8e4])
    laplace = math.log(2 * math.pi**1.5) - 0.5 * float(np.sum(np.log(c)))
    value = log_normalizer(np.append(-c, 0.0))
    assert abs(value - laplace) < 3.0 / c.min()  # O(1/c) correction


MC_CASES = [
    [0.0, 0.0, 0.0, 0.0],
    [-1.0, -1.0, -1.0, 0.0],
    [-10.0, -5.0, -1.0, 0.0],
    [-100.0, -50.0, -20.0, 0.0],
    [-500.0, -500.0, -500.0, 0.0],
    [-500.0, -1.0, -0.1, 0.0],
    [-0.5, -200.0, 3.0, -30.0],  # unsorted, non-canonical (max Z = 3)
]


@pytest.fixture(scope="module")
def mc_results():
    return {tuple(z): importance_estimate(z, seed=1000 + i) for i, z in enumerate(MC_CASES)}


@pytest.mark.parametrize("z", MC_CASES)
def test_normalizer_matches_importance_sampling(z, mc_results):
    res = mc_results[tuple(z)]
    assert res["rel_se"] < 3e-4, res
    ratio = math.exp(log_normalizer(z)) / res["F"]
    assert abs(ratio - 1.0) < 1e-3, (ratio, res["rel_se"])
    assert abs(ratio - 1.0) < 5.0 * res["rel_se"] + 1e-12, (ratio, res["rel_se"])


@pytest.mark.parametrize("z", MC_CASES)
def test_moments_match_importance_sampling(z, mc_results):
    res = mc_results[tuple(z)]
    m = moments(z)
    err = np.abs(m - res["moments"])
    assert np.all(err <= 5.0 * res["moments_se"] + 1e-12), (m, res["moments"], res["moments_se"])
    assert np.all(res["moments_se"] < 5e-4)  # so a real discrepancy would be visible


@pytest.mark.parametrize(
    "z", [[-1.0, -0.5, -0.2, 0.0], [-1.5, -1.0, -0.5, 0.0], [-0.3, -2.0, 0.0, -1.0]]
)
def test_normalizer_matches_uniform_sphere_mc(z):
    """Plain Monte Carlo with uniform points, for small concentrations."""
    rng = np.random.default_rng(7)
    n = 4_000_000
    x = uniform_sphere(rng, n)
    f = np.exp((x * x) @ np.asarray(z))
    est = TWO_PI2 * f.mean()
    rel_se = f.std() / f.mean() / math.sqrt(n)
    assert rel_se < 3e-4
    ratio = math.exp(log_normalizer(z)) / est
    assert abs(ratio - 1.0) < min(1e-3, 5 * rel_se)


# ---------------------------------------------------------------------------
# Moments
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "z",
    [
        [0.0, 0.0, 0.0, 0.0],
        [-1.0, -2.0, -3.0, 0.0],
        [-10.0, -5.0, -1.0, 0.0],
        [-500.0, -1.0, -0.1, 0.0],
        [-1e4, -5e3, -1.0, 0.0],
        [-3.0, 0.0, -3.0, -1.0],
    ],
)
def test_moments_are_gradient_of_log_normalizer(z):
    z = np.asarray(z, dtype=float)
    m = moments(z)
    assert m.shape == (4,)
    assert m.sum() == pytest.approx(1.0, abs=1e-14)
    for i in range(4):
        h = 1e-4 * max(1.0, abs(z[i]))
        zp, zm = z.copy(), z.copy()
        zp[i] += h
        zm[i] -= h
        fd = (log_normalizer(zp) - log_normalizer(zm)) / (2 * h)
        assert fd == pytest.approx(m[i], rel=1e-6, abs=1e-9)


def test_moments_uniform_and_limits():
    np.testing.assert_allclose(moments(np.zeros(4)), 0.25, atol=1e-15)
    # Large concentration: E[x_i²] ≈ 1/(2 c_i).
    c = np.array([2e4, 5e4, 1e5])
    m = moments(np.append(-c, 0.0))
    np.testing.assert_allclose(m[:3], 0.5 / c, rtol=5e-4)


def test_invalid_z():
    with pytest.raises(ValueError):
        log_normalizer([0.0, 1.0, 2.0])
    with pytest.raises(ValueError):
        log_normalizer([0.0, np.nan, 0.0, 0.0])
    with pytest.raises(ValueError):
        moments([0.0, np.inf, 0.0, 0.0])


# ---------------------------------------------------------------------------
# Construction, properties, density
# ---------------------------------------------------------------------------


def test_constructor_validation_and_canonicalisation():
    rng = np.random.default_rng(3)
    M = random_rotation(rng)
    b = Bingham(M, [1.0, -2.0, 3.0, -5.0])
    np.testing.assert_allclose(b.Z, [-2.0, -5.0, 0.0, -8.0])
    np.testing.assert_allclose(b.concentration, [2.0, 5.0, 0.0, 8.0])
    mode = b.mode
    assert abs(abs(mode @ M[:, 2]) - 1.0) < 1e-12
    assert mode[0] >= 0
    assert b.log_normalizer == pytest.approx(log_normalizer([-2.0, -5.0, 0.0, -8.0]))
    with pytest.raises(ValueError):
        b.M[0, 0] = 1.0  # read-only
    with pytest.raises(ValueError):
        b.Z[0] = 1.0
    with pytest.raises(ValueError, match="orthogonal"):
        Bingham(M * 1.01, [0, 0, 0, 0])
    with pytest.raises(ValueError, match="orthogonal"):
        Bingham(np.ones((4, 4)), [0, 0, 0, 0])
    with pytest.raises(ValueError):
        Bingham(np.eye(3), [0, 0, 0, 0])
    with pytest.raises(ValueError):
        Bingham(np.eye(4), [0, 0, np.inf, 0])
    with pytest.raises(ValueError):
        Bingham(np.eye(4), [0, 0, 0])
    # Tiny non-orthogonality is accepted and repaired.
    b2 = Bingham(M + 1e-8, [0, -1, -2, -3])
    np.testing.assert_allclose(b2.M.T @ b2.M, np.eye(4), atol=1e-14)


def test_from_mode_body_frame_convention():
    rng = np.random.default_rng(11)
    q_mode = rng.standard_normal(4)
    q_mode /= np.linalg.norm(q_mode)
    c = np.array([4.0, 90.0, 700.0])
    b = Bingham.from_mode(q_mode, c)
    assert abs(abs(b.mode @ q_mode) - 1.0) < 1e-12
    np.testing.assert_allclose(b.concentration, [4.0, 90.0, 700.0, 0.0])
    base = float(b.log_prob(q_mode))
    assert float(b.log_prob(-q_mode)) == pytest.approx(base, abs=1e-12)
    r_mode = quat_to_matrix(q_mode)
    for i in range(3):
        axis = np.eye(3)[i]
        for delta in (1e-3, 0.1, 1.0, 2.5):
            q = qmul(q_mode, axis_angle(axis, delta))
            # Hamilton convention: q_mode ⊗ dq ↔ R_mode · R(axis, δ), a body-frame rotation.
            np.testing.assert_allclose(
                quat_to_matrix(q), r_mode @ quat_to_matrix(axis_angle(axis, delta)), atol=1e-12
            )
            drop = base - float(b.log_prob(q))
            assert drop == pytest.approx(c[i] * math.sin(delta / 2) ** 2, rel=1e-10, abs=1e-12)
    # Scalar concentration = isotropic.
    iso = Bingham.from_mode(q_mode, 25.0)
    np.testing.assert_allclose(iso.concentration, [25.0, 25.0, 25.0, 0.0])
    with pytest.raises(ValueError):
        Bingham.from_mode(q_mode, [-1.0, 2.0, 3.0])
    with pytest.raises(ValueError):
        Bingham.from_mode(q_mode, [1.0, 2.0])
    with pytest.raises(ValueError):
        Bingham.from_mode(np.zeros(4), 1.0)


def test_log_prob_shapes_and_sign_invariance():
    rng = np.random.default_rng(5)
    b = Bingham(random_rotation(rng), [-3.0, -30.0, -0.5, 0.0])
    q = uniform_sphere(rng, 60).reshape(3, 4, 5, 4)
    lp = b.log_prob(q)
    assert lp.shape == (3, 4, 5)
    np.testing.assert_allclose(b.log_prob(-q), lp, atol=1e-12)
    np.testing.assert_allclose(b.log_prob(2.5 * q), lp, atol=1e-12)  # normalised first
    np.testing.assert_allclose(b.prob(q), np.exp(lp))
    # Maximum at the mode.
    assert float(b.log_prob(b.mode)) == pytest.approx(-b.log_normalizer)
    assert np.all(lp <= -b.log_normalizer + 1e-12)


def test_log_prob_integrates_to_one_uniform():
    rng = np.random.default_rng(21)
    b = Bingham(random_rotation(rng), [-2.0, -0.3, -5.0, 0.0])
    x = uniform_sphere(rng, 1_000_000)
    p = np.exp(b.log_prob(x))
    est = TWO_PI2 * p.mean()
    se = TWO_PI2 * p.std() / math.sqrt(len(p))
    assert abs(est - 1.0) < max(5 * se, 1e-4) and se < 1e-3


@pytest.mark.parametrize("conc", [[5.0, 50.0, 200.0], [800.0, 800.0, 800.0], [0.0, 3.0, 300.0]])
def test_log_prob_integrates_to_one_importance(conc):
    rng = np.random.default_rng(22)
    q_mode = axis_angle([1.0, -2.0, 0.5], 2.1)
    b = Bingham.from_mode(q_mode, conc)
    # Proposal built from the construction parameters, not from the object.
    pure = [np.array([0.0, 1.0, 0.0, 0.0]), np.array([0, 0, 1.0, 0]), np.array([0, 0, 0, 1.0])]
    M = np.column_stack([qmul(q_mode, e) for e in pure] + [q_mode])
    z = -np.append(conc, 0.0)
    cov = proposal_cov(M, z, choose_k(z, rng))
    x = acg_sample(rng, cov, 1_000_000)
    w = np.exp(b.log_prob(x) - acg_logpdf(x, cov))
    est, se = w.mean(), w.std() / math.sqrt(len(w))
    assert se < 1e-3
    assert abs(est - 1.0) < 5 * se


# ---------------------------------------------------------------------------
# Sampler
# ---------------------------------------------------------------------------


def _sampler_cases():
    rng = np.random.default_rng(2024)
    q_mode = axis_angle([0.3, -1.0, 2.0], 2.7)
    return {
        "uniform-rotated": Bingham(random_rotation(rng), [0.0, 0.0, 0.0, 0.0]),
        "c1-rotated": Bingham(random_rotation(rng), [-1.0, -1.0, -1.0, 0.0]),
        "from_mode-50": Bingham.from_mode(q_mode, 50.0),
        "from_mode-500": Bingham.from_mode(q_mode, [500.0, 500.0, 500.0]),
        "mixed-rotated": Bingham(random_rotation(rng), [-500.0, -50.0, 0.0, -1.0]),
        "from_mode-mixed-0": Bingham.from_mode(q_mode, [0.0, 1.0, 500.0]),
    }


SAMPLER_CASES = _sampler_cases()


@pytest.mark.parametrize("name", list(SAMPLER_CASES))
def test_sampler_second_moments(name):
    b = SAMPLER_CASES[name]
    n = 60_000
    x = b.sample(np.random.default_rng(99), n)
    assert x.shape == (n, 4)
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, atol=1e-12)
    outer = x[:, :, None] * x[:, None, :]
    emp = outer.mean(axis=0)
    se = outer.std(axis=0) / math.sqrt(n)
    expected = (b.M * moments(b.Z)) @ b.M.T
    np.testing.assert_allclose(b.second_moment(), expected, atol=1e-15)
    z_scores = np.abs(emp - expected) / (se + 1e-15)
    assert np.max(z_scores) < 5.0, (name, np.max(z_scores))


def test_sampler_deterministic_and_edge_cases():
    b = SAMPLER_CASES["mixed-rotated"]
    a1 = b.sample(np.random.default_rng(5), 1000)
    a2 = b.sample(np.random.default_rng(5), 1000)
    np.testing.assert_array_equal(a1, a2)
    assert b.sample(np.random.default_rng(5), 0).shape == (0, 4)
    assert b.sample(np.random.default_rng(5), 1).shape == (1, 4)
    with pytest.raises(ValueError):
        b.sample(np.random.default_rng(5), -1)


def test_sampler_uniform_exact_marginals():
    """Z = 0: x4² ~ Beta(1/2, 3/2) and x1² + x2² ~ U(0, 1) under the uniform law."""
    b = Bingham(np.eye(4), np.zeros(4))
    x = b.sample(np.random.default_rng(8), 20_000)
    assert stats.kstest(x[:, 3] ** 2, stats.beta(0.5, 1.5).cdf).pvalue > 1e-3
    assert stats.kstest(x[:, 0] ** 2 + x[:, 1] ** 2, "uniform").pvalue > 1e-3


def _isotropic_cdf(c: float):
    """CDF of v = 1 - (qᵀ mode)² for Z = (-c, -c, -c, 0), by 1-D quadrature.

    Under the uniform law u = x4² ~ Beta(1/2, 3/2), so under the Bingham v = 1 - u
    has density ∝ v^{1/2} (1 - v)^{-1/2} exp(-c v) on [0, 1].  With v = sin²θ this
    becomes ∝ 2 sin²θ exp(-c sin²θ) dθ on [0, π/2], which is smooth.
    """
    theta = np.linspace(0.0, math.pi / 2, 4001)

    def dens(t: float) -> float:
        s2 = math.sin(t) ** 2
        return 2.0 * s2 * math.exp(-c * s2)

    pieces = [
        integrate.quad(dens, lo, hi, epsabs=0, epsrel=1e-12)[0]
        for lo, hi in itertools.pairwise(theta)
    ]
    cdf = np.concatenate([[0.0], np.cumsum(pieces)])
    cdf /= cdf[-1]
    return lambda v: np.interp(np.arcsin(np.sqrt(np.clip(v, 0.0, 1.0))), theta, cdf)


@pytest.mark.parametrize("c", [2.0, 30.0])
def test_sampler_isotropic_exact_distribution(c):
    rng = np.random.default_rng(31)
    q_mode = axis_angle([1.0, 1.0, 0.0], 0.7)
    b = Bingham.from_mode(q_mode, c)
    x = b.sample(rng, 20_000)
    v = 1.0 - (x @ q_mode) ** 2
    assert stats.kstest(v, _isotropic_cdf(c)).pvalue > 1e-3


def _weighted_reference_cdf(M, Z, seed, n=1_000_000):
    """Weighted ECDF of s = xᵀAx (A = -M diag(Z) Mᵀ) by importance sampling."""
    rng = np.random.default_rng(seed)
    Z = np.asarray(Z, dtype=float) - np.max(Z)
    cov = proposal_cov(M, Z, choose_k(Z, rng))
    x = acg_sample(rng, cov, n)
    proj = x @ M
    s = (proj * proj) @ (-Z)
    logw = -s - acg_logpdf(x, cov)
    w = np.exp(logw - logw.max())
    order = np.argsort(s)
    s_sorted = s[order]
    cdf = np.cumsum(w[order])
    cdf /= cdf[-1]
    return lambda v: np.interp(v, s_sorted, cdf, left=0.0, right=1.0)


@pytest.mark.parametrize(
    "name", ["c1-rotated", "from_mode-50", "mixed-rotated", "from_mode-mixed-0"]
)
def test_sampler_goodness_of_fit(name):
    """KS test of s = qᵀAq of the sampler against an IS reference of the true density.

    s weighs every axis by its concentration, so an error in the acceptance ratio
    (e.g. the ACG exponent q/2, the envelope bound, or the Ω used) shows up in it.
    """
    b = SAMPLER_CASES[name]
    ref = _weighted_reference_cdf(np.array(b.M), np.array(b.Z), seed=77)
    x = b.sample(np.random.default_rng(123), 20_000)
    proj = x @ b.M
    s = (proj * proj) @ (-b.Z)
    assert stats.kstest(s, ref).pvalue > 1e-3


# ---------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "z_true",
    [
        [-0.5, -2.0, -3.0, 0.0],
        [-10.0, -5.0, -1.0, 0.0],
        [-500.0, -500.0, -500.0, 0.0],
        [-5000.0, -40.0, -0.2, 0.0],
        [-9000.0, -9000.0, -1.0, 0.0],
    ],
)
def test_fit_recovers_z_from_exact_moments(z_true):
    """Samples = the axes of M with weights = exact moments ⇒ scatter = M diag(m) Mᵀ."""
    rng = np.random.default_rng(17)
    M = random_rotation(rng)
    m = moments(z_true)
    fitted = Bingham.fit(M.T, weights=m)
    order = np.argsort(fitted.Z)
    np.testing.assert_allclose(np.sort(fitted.Z), np.sort(z_true), rtol=1e-8, atol=1e-9)
    # Axes recovered up to sign (distinct Z only).
    for j, i in zip(order, np.argsort(z_true), strict=True):
        if np.sum(np.isclose(z_true, z_true[i])) == 1:
            assert abs(fitted.M[:, j] @ M[:, i]) == pytest.approx(1.0, abs=1e-8)


def test_fit_recovers_known_bingham_from_samples():
    q_mode = axis_angle([-0.4, 0.8, 0.2], 1.9)
    conc = np.array([10.0, 60.0, 400.0])
    truth = Bingham.from_mode(q_mode, conc)
    x = truth.sample(np.random.default_rng(4), 20_000)
    # Random signs must not matter.
    x *= np.where(np.random.default_rng(5).random(len(x)) < 0.5, -1.0, 1.0)[:, None]
    fitted = fit_bingham(x)
    assert abs(fitted.mode @ q_mode) == pytest.approx(1.0, abs=1e-4)
    order = np.argsort(fitted.concentration)[::-1][:3]  # decreasing concentration
    got = fitted.concentration[order]
    np.testing.assert_allclose(got, conc[::-1], rtol=0.05)
    for j, i in zip(order, [2, 1, 0], strict=True):
        assert abs(fitted.M[:, j] @ truth.M[:, i]) > 0.99
    # The fitted parameters beat the truth in likelihood (it is the MLE).
    assert fitted.log_prob(x).sum() >= truth.log_prob(x).sum()


def test_fit_weights_equal_duplication():
    rng = np.random.default_rng(9)
    truth = Bingham(random_rotation(rng), [-30.0, -8.0, -2.0, 0.0])
    x = truth.sample(rng, 600)
    counts = rng.integers(0, 4, size=len(x))
    weighted = Bingham.fit(x, weights=counts)
    duplicated = Bingham.fit(np.repeat(x, counts, axis=0))
    np.testing.assert_allclose(weighted.Z, duplicated.Z, rtol=1e-9, atol=1e-9)
    for j in range(4):
        assert abs(weighted.M[:, j] @ duplicated.M[:, j]) == pytest.approx(1.0, abs=1e-9)
    # Rescaling the weights changes nothing; dropping/adding weight does.
    scaled = Bingham.fit(x, weights=2.5 * counts)
    np.testing.assert_allclose(scaled.Z, weighted.Z, rtol=1e-9, atol=1e-9)
    unweighted = Bingham.fit(x)
    assert np.max(np.abs(unweighted.Z - weighted.Z)) > 1e-3


def test_fit_degenerate_inputs():
    q = axis_angle([0.0, 0.0, 1.0], 0.8)
    single = Bingham.fit(q[None, :], max_concentration=5e3)
    assert abs(single.mode @ q) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(np.sort(single.concentration), [0.0, 5e3, 5e3, 5e3])
    # Two distinct samples: two concentrations hit the bound, one is finite.
    q2 = axis_angle([1.0, 0.0, 0.0], 0.3)
    two = Bingham.fit(np.stack([q, q2]))
    assert np.sum(np.isclose(two.concentration, 1e4)) == 2
    with pytest.raises(ValueError, match="total weight"):
        Bingham.fit(np.stack([q, q2]), weights=[0.0, 0.0])
    with pytest.raises(ValueError):
        Bingham.fit(np.stack([q, q2]), weights=[1.0, -1.0])
    with pytest.raises(ValueError):
        Bingham.fit(np.stack([q, q2]), weights=[1.0])
    with pytest.raises(ValueError):
        Bingham.fit(np.zeros((0, 4)))
    with pytest.raises(ValueError):
        Bingham.fit(np.zeros((3, 4)))
    with pytest.raises(ValueError):
        Bingham.fit(np.ones((3, 3)))


def test_report_largest_mc_error(mc_results):
    """Not a check of its own: records the largest MC relative error (visible with -s)."""
    worst = max(
        abs(math.exp(log_normalizer(z)) / mc_results[tuple(z)]["F"] - 1.0) for z in MC_CASES
    )
    print(f"\nlargest |F_quad / F_mc - 1| = {worst:.2e}")
    assert worst < 1e-3


@pytest.mark.parametrize("spread", [0.0, 0.1])
def test_fit_about_a_mode_a_half_turn_from_the_data_finds_them(spread: float) -> None:
    """Rotations about a half turn (about body x) from the start mode: the alternation from
    that start stalled at a free turn about x (concentration 0, the data on its circle of
    modes); the fit now also starts from the scatter's top eigenvector and gives the data's
    mode and three concentrations, the same as from a start at the data.  With no mass on the
    start mode at all (spread 0: λ = 0 there), without a NumPy warning either."""
    import warnings

    rng = np.random.default_rng(0)
    q = np.tile([0.0, 1.0, 0.0, 0.0], (50, 1)) + rng.normal(0.0, 0.01, (50, 4))
    q[:, 0] = spread * rng.normal(size=50)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mode, conc = Bingham.fit_about_mode(q, np.ones(50), [1.0, 0.0, 0.0, 0.0], False)
    near, near_conc = Bingham.fit_about_mode(q, np.ones(50), [0.0, 1.0, 0.0, 0.0], False)
    assert abs(mode @ near) > 1 - 1e-9
    np.testing.assert_allclose(conc, near_conc, rtol=1e-6)
    assert np.all(conc > 10)  # the stall left 0 on x


# log F and the moments E[x_i²] (in the order of z sorted decreasing) of the module docstring's
# one-dimensional integral, evaluated with mpmath at 30 digits (Bessel functions and adaptive
# quadrature in arbitrary precision, break points at 2^-k from both ends): an independent check
# of the Gauss–Legendre panels, from a uniform law to concentrations of 1e10.
HIGH_PRECISION = [
    (
        (0.0, -1.0, -2.0, -3.0),
        1.6866096368596349584,
        (0.390247414014864872, 0.267401322327849898, 0.194147415054253818, 0.148203848603031412),
    ),
    (
        (0.0, -0.5, -40.0, -400.0),
        -2.0889741387652403608,
        (0.553436388165282583, 0.432743737593171211, 0.0125691879576977741, 0.00125068628384843132),
    ),
    (
        (0.0, -400.0, -400.0, -400.0),
        -6.57507272976688475,
        (
            0.996245276965134845,
            0.00125157434495505155,
            0.00125157434495505155,
            0.00125157434495505155,
        ),
    ),
    (
        (0.0, -10000.0, -2000.0, -7.0),
        -6.9243173602901542165,
        (
            0.920248236582132659,
            0.0794516910351967071,
            0.000250069600551327302,
            0.0000500027821193065153,
        ),
    ),
    ((0.0, 0.0, -10000.0, -10000.0), -6.2277334197174370784, (0.49995, 0.49995, 0.00005, 0.00005)),
    (
        (0.0, -300.0, -300.0, 0.0),
        -2.7211755223974554017,
        (
            0.498333333333333333,
            0.498333333333333333,
            0.00166666666666666667,
            0.00166666666666666667,
        ),
    ),
    (
        (0.0, -1000000.0, -100000000.0, -10000000000.0),
        -25.220778854069251349,
        (
            0.999999494949749974,
            5.00000250000501298e-7,
            5.00000002500002669e-9,
            5.00000000025000047e-11,
        ),
    ),
    (
        (-5.0, 0.0, -10000000000.0, -2.5),
        -10.157760036347032431,
        (0.661110786876134602, 0.225158380183712571, 0.113730832890152827, 5.00000000031577506e-11),
    ),
]


@pytest.mark.parametrize("z, log_f, second_moments", HIGH_PRECISION)
def test_normaliser_and_moments_match_high_precision_values(z, log_f, second_moments):
    z = np.array(z)
    assert log_normalizer(z) == pytest.approx(log_f, abs=1e-14)
    found = moments(z)[np.argsort(-z, kind="stable")]
    # relative to each moment where every concentration is at most 1e4 (what fits reach);
    # beyond, E[x2²] = (i0e - i1e) / ... loses digits to cancellation, so 1e-6 of it and 1e-16
    fit_range = np.max(-z + np.max(z)) <= 1e4
    rel = 1e-13 if fit_range else 1e-6
    assert np.allclose(found, second_moments, rtol=rel, atol=0.0 if fit_range else 1e-16)
