"""Tests for the primitive distributions in ``ssgc.distributions``.

Statistical tests use fixed seeds and a p > 0.01 acceptance level, so they are
deterministic: a failure means the sampler or the density changed, not bad luck.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from ssgc.distributions.discrete import Bernoulli, Categorical, CountLaw
from ssgc.distributions.normal import Normal
from ssgc.distributions.uniform import UNIFORM_SO3_LOG_DENSITY, UniformBox, UniformRevolute

P_MIN = 0.01


def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


def _random_spd(rng: np.random.Generator, d: int) -> np.ndarray:
    a = rng.normal(size=(d, d))
    return a @ a.T + 0.5 * np.eye(d)


class _ConstantRng:
    """Stand-in generator with fixed uniforms, to hit the edges of a CDF lookup exactly."""

    def __init__(self, u: float) -> None:
        self.u = u

    def random(self, n: int) -> np.ndarray:
        return np.full(n, self.u)


_NEAR_ONE = _ConstantRng(np.nextafter(1.0, 0.0))


# --------------------------------------------------------------------------- Normal


@pytest.mark.parametrize("d", [1, 2, 3])
def test_normal_log_prob_matches_scipy(d: int) -> None:
    rng = _rng(10 + d)
    mean = rng.normal(size=d)
    cov = _random_spd(rng, d)
    law = Normal(mean, cov)
    x = rng.normal(size=(4, 5, d)) * 2.0
    expected = stats.multivariate_normal(mean, cov).logpdf(x.reshape(-1, d)).reshape(4, 5)
    got = law.log_prob(x)
    assert got.shape == (4, 5)
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10)
    # A single point gives a scalar-shaped answer.
    assert np.shape(law.log_prob(x[0, 0])) == ()
    np.testing.assert_allclose(law.log_prob(mean), law.log_normalizer)


def test_normal_sample_shapes_and_finite_log_prob() -> None:
    law = Normal([1.0, -2.0], [[2.0, 0.3], [0.3, 0.5]])
    x = law.sample(_rng(1), 1000)
    assert x.shape == (1000, 2)
    assert np.all(np.isfinite(law.log_prob(x)))
    assert law.sample(_rng(1), 0).shape == (0, 2)
    assert law.log_prob(np.zeros((0, 2))).shape == (0,)


def test_normal_log_prob_from_standard_matches_log_prob_of_sample() -> None:
    rng_law = _rng(2)
    law = Normal(rng_law.normal(size=3), _random_spd(rng_law, 3))
    x = law.sample(_rng(7), 500)
    # The sampler draws its standard normals as one (n, d) block, so replaying the seed
    # recovers the z behind every sampled point.
    z = _rng(7).standard_normal((500, 3))
    np.testing.assert_allclose(law.mean + z @ law.chol.T, x)
    np.testing.assert_allclose(law.log_prob_from_standard(z), law.log_prob(x), rtol=1e-10)


def test_normal_sample_moments_and_ks() -> None:
    mean = np.array([0.5, -1.0, 2.0])
    cov = np.array([[1.0, 0.4, 0.1], [0.4, 2.0, -0.3], [0.1, -0.3, 0.7]])
    law = Normal(mean, cov)
    x = law.sample(_rng(3), 20000)
    np.testing.assert_allclose(x.mean(axis=0), mean, atol=0.05)
    np.testing.assert_allclose(np.cov(x.T), cov, atol=0.06)
    for axis in range(3):
        standardised = (x[:, axis] - mean[axis]) / np.sqrt(cov[axis, axis])
        assert stats.kstest(standardised, "norm").pvalue > P_MIN
    # Squared Mahalanobis distances are chi-square with d degrees of freedom.
    maha = -2.0 * (law.log_prob(x) - law.log_normalizer)
    assert stats.kstest(maha, "chi2", args=(3,)).pvalue > P_MIN


def test_normal_non_finite_points_score_minus_inf_and_bad_shape_raises() -> None:
    law = Normal.diagonal([0.0, 0.0], [1.0, 1.0])
    got = law.log_prob([[np.nan, 0.0], [np.inf, 0.0], [0.0, 0.0]])
    assert got[0] == -np.inf and got[1] == -np.inf and np.isfinite(got[2])
    with pytest.raises(ValueError, match="x must have shape"):
        law.log_prob([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="z must have shape"):
        law.log_prob_from_standard([1.0])


def test_normal_diagonal_and_scalar_variance() -> None:
    law = Normal.diagonal([1.0, 2.0], [0.5, 3.0])
    np.testing.assert_array_equal(law.cov, np.diag([0.5, 3.0]))
    np.testing.assert_array_equal(law.variance, [0.5, 3.0])
    shared = Normal.diagonal([0.0, 0.0, 0.0], 2.0)
    np.testing.assert_array_equal(shared.cov, 2.0 * np.eye(3))
    one_d = Normal.diagonal(0.0, 4.0)
    assert one_d.dim == 1
    np.testing.assert_allclose(one_d.log_prob([[1.0]]), stats.norm(0.0, 2.0).logpdf([1.0]))


def test_normal_is_immutable_and_copies_inputs() -> None:
    mean = np.array([0.0, 1.0])
    cov = np.eye(2)
    law = Normal(mean, cov)
    mean[0] = 99.0
    cov[0, 0] = 99.0
    assert law.mean[0] == 0.0 and law.cov[0, 0] == 1.0
    for arr in (law.mean, law.cov, law.chol):
        assert arr.dtype == np.float64 and not arr.flags.writeable
    with pytest.raises(AttributeError):
        law.mean = np.zeros(2)  # type: ignore[misc]


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: Normal.diagonal([0.0], [-0.01]), r"variance must be positive, got -0\.01"),
        (lambda: Normal.diagonal([0.0, 0.0], [1.0, 0.0]), "variance must be positive.*axis 1"),
        (lambda: Normal.diagonal([0.0], [np.nan]), "variance must be finite"),
        (lambda: Normal.diagonal([0.0, 0.0], [1.0, 1.0, 1.0]), "variance must be a scalar"),
        (lambda: Normal([0.0, 0.0], [[1.0, 0.5], [0.0, 1.0]]), "cov must be symmetric"),
        (lambda: Normal([0.0, 0.0], [[1.0, 2.0], [2.0, 1.0]]), "cov must be positive definite"),
        (lambda: Normal([0.0, 0.0], np.zeros((2, 2))), "cov must be positive definite"),
        (lambda: Normal([0.0, 0.0], np.eye(3)), r"cov must have shape \(2, 2\)"),
        (lambda: Normal([0.0, 0.0], [[np.inf, 0], [0, 1]]), "cov must be finite"),
        (lambda: Normal([np.nan, 0.0], np.eye(2)), "mean must be finite"),
        (lambda: Normal(np.zeros((2, 2)), np.eye(2)), "mean must be a non-empty 1-d array"),
        (lambda: Normal.fit([[0.0], [1.0]], min_variance=0.0), "min_variance must be positive"),
        (lambda: Normal.fit([[0.0], [1.0]], weights=[1.0, -1.0]), "weights must be non-negative"),
        (lambda: Normal.fit([[0.0], [1.0]], weights=[0.0, 0.0]), "weights must have a positive"),
        (lambda: Normal.fit([[0.0], [1.0]], weights=[1.0]), r"weights must have shape \(2,\)"),
        (lambda: Normal.fit([[0.0], [np.nan]]), "x must be finite"),
        (lambda: Normal.fit(np.zeros((0, 2))), "x must have shape"),
    ],
)
def test_normal_invalid_parameters_raise(build, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build()


def test_normal_invalid_sample_count() -> None:
    law = Normal.diagonal([0.0], [1.0])
    with pytest.raises(ValueError, match="n must be a non-negative integer"):
        law.sample(_rng(0), -1)
    with pytest.raises(ValueError, match="n must be a non-negative integer"):
        law.sample(_rng(0), 2.5)  # type: ignore[arg-type]


def test_normal_fit_recovers_parameters() -> None:
    mean = np.array([1.0, -0.5])
    cov = np.array([[0.8, -0.3], [-0.3, 0.4]])
    x = Normal(mean, cov).sample(_rng(4), 40000)
    fitted = Normal.fit(x)
    np.testing.assert_allclose(fitted.mean, mean, atol=0.02)
    np.testing.assert_allclose(fitted.cov, cov, atol=0.02)
    diag = Normal.fit(x, diagonal=True)
    np.testing.assert_allclose(diag.cov, np.diag(np.diag(fitted.cov)), atol=1e-12)


def test_normal_fit_is_the_biased_ml_estimate() -> None:
    x = np.array([[0.0, 0.0], [2.0, 1.0], [4.0, 5.0]])
    fitted = Normal.fit(x)
    np.testing.assert_allclose(fitted.mean, x.mean(axis=0))
    np.testing.assert_allclose(fitted.cov, np.cov(x.T, bias=True))
    # A 1-d x is n scalar samples.
    scalar = Normal.fit([1.0, 2.0, 3.0, 6.0])
    assert scalar.dim == 1
    np.testing.assert_allclose(scalar.cov, [[np.var([1.0, 2.0, 3.0, 6.0])]])


def test_normal_fit_weights_act_like_repeated_samples() -> None:
    x = _rng(5).normal(size=(30, 2))
    reps = _rng(6).integers(0, 4, size=30)
    reps[0] = 1
    for diagonal in (False, True):
        weighted = Normal.fit(x, weights=reps, diagonal=diagonal)
        repeated = Normal.fit(np.repeat(x, reps, axis=0), diagonal=diagonal)
        np.testing.assert_allclose(weighted.mean, repeated.mean, atol=1e-12)
        np.testing.assert_allclose(weighted.cov, repeated.cov, atol=1e-12)
    # Only the relative size of the weights matters.
    scaled = Normal.fit(x, weights=reps * 0.125)
    np.testing.assert_allclose(scaled.cov, Normal.fit(x, weights=reps).cov, atol=1e-12)


def test_normal_fit_floors_variance_on_degenerate_data() -> None:
    single = Normal.fit([[1.0, 2.0]], min_variance=1e-6)
    np.testing.assert_allclose(single.cov, 1e-6 * np.eye(2))
    diag = Normal.fit([[1.0, 2.0], [1.0, 4.0]], diagonal=True, min_variance=1e-6)
    np.testing.assert_allclose(diag.variance, [1e-6, 1.0])
    # Perfectly collinear points: the covariance is singular until floored.
    t = np.linspace(0.0, 1.0, 11)
    collinear = Normal.fit(np.stack([t, 2.0 * t], axis=1), min_variance=1e-8)
    eig = np.linalg.eigvalsh(collinear.cov)
    assert eig.min() == pytest.approx(1e-8, rel=1e-3)
    assert np.all(np.isfinite(collinear.log_prob(np.stack([t, 2.0 * t], axis=1))))


# --------------------------------------------------------------------------- Categorical


def test_categorical_normalises_and_samples_match_chisquare() -> None:
    law = Categorical([2.0, 0.0, 5.0, 3.0, 0.0])
    np.testing.assert_allclose(law.probs, [0.2, 0.0, 0.5, 0.3, 0.0])
    k = law.sample(_rng(8), 20000)
    assert k.dtype == np.int64 and k.shape == (20000,)
    counts = np.bincount(k, minlength=5)
    assert counts[1] == 0 and counts[4] == 0
    support = law.probs > 0
    assert stats.chisquare(counts[support], 20000 * law.probs[support]).pvalue > P_MIN
    assert np.all(np.isfinite(law.log_prob(k)))


def test_categorical_normalises_extreme_weights() -> None:
    np.testing.assert_allclose(Categorical([1e308, 1e308, 0.0]).probs, [0.5, 0.5, 0.0])
    np.testing.assert_allclose(Categorical([5e-324, 0.0]).probs, [1.0, 0.0])


def test_categorical_last_bin_guard() -> None:
    # Ten bins of 0.1 sum to 0.9999999999999999 in floating point.
    law = Categorical([0.1] * 10)
    assert np.all(law.sample(_NEAR_ONE, 5) == 9)  # type: ignore[arg-type]
    # A trailing zero-probability bin must not absorb the rounding sliver either.
    trailing = Categorical([0.1] * 10 + [0.0])
    assert np.all(trailing.sample(_NEAR_ONE, 5) == 9)  # type: ignore[arg-type]


def test_categorical_never_samples_leading_zero_bins() -> None:
    law = Categorical([0.0, 0.0, 1.0, 1.0])
    assert np.all(law.sample(_ConstantRng(0.0), 5) == 2)  # type: ignore[arg-type]
    assert np.all(law.sample(_ConstantRng(0.5), 5) == 3)  # type: ignore[arg-type]


def test_categorical_log_prob_out_of_support() -> None:
    law = Categorical([0.25, 0.75, 0.0])
    got = law.log_prob(np.array([0, 1, 2, 3, -1]))
    np.testing.assert_allclose(got[:2], np.log([0.25, 0.75]))
    assert np.all(got[2:] == -np.inf)
    floats = law.log_prob([1.0, 1.5, np.nan, np.inf, -0.0])
    np.testing.assert_allclose(floats[[0, 4]], np.log([0.75, 0.25]))
    assert np.all(floats[1:4] == -np.inf)
    assert law.log_prob(np.zeros((2, 3), dtype=int)).shape == (2, 3)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    weights=st.lists(st.floats(0.0, 1e6, allow_nan=False), min_size=1, max_size=12).filter(
        lambda w: sum(w) > 0
    ),
    seed=st.integers(0, 2**32 - 1),
)
def test_categorical_samples_have_finite_log_prob_of_normalised_weight(
    weights: list[float], seed: int
) -> None:
    law = Categorical(weights)
    k = law.sample(_rng(seed), 50)
    lp = law.log_prob(k)
    assert np.all(np.isfinite(lp))
    w = np.asarray(weights)
    # log p near 0 for a dominant weight: compare absolutely there (rounding is ~1e-16).
    np.testing.assert_allclose(lp, np.log(w[k] / w.sum()), rtol=1e-12, atol=1e-12)
    assert law.probs.sum() == pytest.approx(1.0)


def test_categorical_fit() -> None:
    truth = Categorical([0.1, 0.6, 0.3])
    fitted = Categorical.fit(truth.sample(_rng(9), 30000), num_categories=3)
    np.testing.assert_allclose(fitted.probs, truth.probs, atol=0.01)
    # Unseen categories exist only when num_categories says so.
    assert Categorical.fit([0, 0, 2]).num_categories == 3
    np.testing.assert_allclose(Categorical.fit([0, 0, 2], num_categories=5).probs[3:], 0.0)
    smoothed = Categorical.fit([0, 0, 2], num_categories=4, pseudocount=1.0)
    np.testing.assert_allclose(smoothed.probs, np.array([3.0, 1.0, 2.0, 1.0]) / 7.0)


def test_categorical_fit_weights_act_like_repeated_samples() -> None:
    k = _rng(10).integers(0, 4, size=40)
    reps = _rng(11).integers(0, 5, size=40)
    weighted = Categorical.fit(k, reps, 4)
    repeated = Categorical.fit(np.repeat(k, reps), num_categories=4)
    np.testing.assert_allclose(weighted.probs, repeated.probs, atol=1e-14)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: Categorical([0.5, -0.1]), r"probs must be non-negative, got -0\.1 at index 1"),
        (lambda: Categorical([0.5, np.nan]), "probs must be finite"),
        (lambda: Categorical([0.0, 0.0]), "probs must have a positive sum"),
        (lambda: Categorical([]), "probs must be a non-empty 1-d array"),
        (lambda: Categorical([[0.5, 0.5]]), "probs must be a non-empty 1-d array"),
        (lambda: Categorical.fit([0, 3], num_categories=3), r"k must be integers in \[0, 2\]"),
        (lambda: Categorical.fit([0, 1.5]), "k must be non-negative integers"),
        (lambda: Categorical.fit([0, 1], num_categories=0), "num_categories must be at least 1"),
        (lambda: Categorical.fit([0, 1], num_categories=2.0), "num_categories must be an integer"),
        (lambda: Categorical.fit([0], pseudocount=-1.0), "pseudocount must be non-negative"),
        (lambda: Categorical.fit([0], [0.0], 2), "weights must have a positive total"),
        (lambda: Categorical.fit([], num_categories=None), "num_categories must be given"),
    ],
)
def test_categorical_invalid_parameters_raise(build, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build()


# --------------------------------------------------------------------------- Bernoulli


def test_bernoulli_sample_and_log_prob() -> None:
    law = Bernoulli(0.3)
    x = law.sample(_rng(12), 10000)
    assert x.dtype == np.bool_
    assert stats.binomtest(int(x.sum()), x.size, 0.3).pvalue > P_MIN
    np.testing.assert_allclose(law.log_prob(x), stats.bernoulli(0.3).logpmf(x))
    got = law.log_prob([True, False, 1, 0, 2, 0.5, np.nan])
    np.testing.assert_allclose(got[:4], np.log([0.3, 0.7, 0.3, 0.7]))
    assert np.all(got[4:] == -np.inf)


def test_bernoulli_extremes_are_exact() -> None:
    assert not Bernoulli(0.0).sample(_rng(0), 1000).any()
    assert Bernoulli(1.0).sample(_rng(0), 1000).all()
    np.testing.assert_array_equal(Bernoulli(0.0).log_prob([True, False]), [-np.inf, 0.0])
    np.testing.assert_array_equal(Bernoulli(1.0).log_prob([True, False]), [0.0, -np.inf])


def test_bernoulli_fit() -> None:
    x = Bernoulli(0.8).sample(_rng(13), 20000)
    assert Bernoulli.fit(x).p == pytest.approx(0.8, abs=0.01)
    data = np.array([True, False, True, True])
    reps = np.array([2, 5, 0, 1])
    assert Bernoulli.fit(data, reps).p == pytest.approx(Bernoulli.fit(np.repeat(data, reps)).p)
    assert Bernoulli.fit([1, 1], pseudocount=1.0).p == pytest.approx(0.75)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: Bernoulli(1.5), r"p must be in \[0, 1\], got 1\.5"),
        (lambda: Bernoulli(-0.1), "p must be in"),
        (lambda: Bernoulli(float("nan")), "p must be in"),
        (lambda: Bernoulli.fit([0, 2]), "x must contain only booleans"),
        (lambda: Bernoulli.fit([True], [-1.0]), "weights must be non-negative"),
    ],
)
def test_bernoulli_invalid_parameters_raise(build, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build()


# --------------------------------------------------------------------------- CountLaw


@pytest.mark.parametrize("start", [0, 1])
@pytest.mark.parametrize("p", [0.2, 0.5, 0.9])
def test_geometric_count_law_matches_formula(start: int, p: float) -> None:
    max_count = 6
    law = CountLaw.geometric(p, max_count, start)
    assert law.max_count == max_count
    n = np.arange(max_count + 1)
    unnormalised = np.where(n >= start, p * (1.0 - p) ** (n - start), 0.0)
    np.testing.assert_allclose(law.probs, unnormalised / unnormalised.sum(), rtol=1e-12)
    assert law.probs.sum() == pytest.approx(1.0, abs=1e-12)
    # Independently: scipy's geometric law lives on 1, 2, ...; shift and truncate it.
    shifted = stats.geom(p, loc=start - 1)
    truncated = shifted.pmf(n) / shifted.cdf(max_count)
    np.testing.assert_allclose(law.probs, truncated, rtol=1e-12, atol=1e-15)
    assert np.all(law.log_prob(np.arange(start)) == -np.inf)
    assert law.log_prob(max_count + 1) == -np.inf


def test_geometric_point_mass_and_mean() -> None:
    law = CountLaw.geometric(1.0, 4, 2)
    np.testing.assert_array_equal(law.probs, [0.0, 0.0, 1.0, 0.0, 0.0])
    assert law.mean == 2.0
    assert np.all(law.sample(_rng(0), 50) == 2)
    with np.errstate(divide="ignore"):
        np.testing.assert_array_equal(law.log_probs, np.log(law.probs))


@settings(max_examples=80, deadline=None, derandomize=True)
@given(
    p=st.floats(1e-6, 1.0, exclude_min=False),
    max_count=st.integers(0, 60),
    data=st.data(),
)
def test_geometric_count_law_sums_to_one(p: float, max_count: int, data: st.DataObject) -> None:
    start = data.draw(st.integers(0, max_count))
    law = CountLaw.geometric(p, max_count, start)
    assert law.probs.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.all(law.probs[:start] == 0.0)
    assert law.probs[start] >= law.probs.max()
    # Successive probabilities fall by the factor 1 - p (checked away from underflow,
    # which p close to 1 reaches within a few dozen steps).
    prev, succ = law.probs[start:-1], law.probs[start + 1 :]
    normal_range = succ > 1e-250
    np.testing.assert_allclose(succ[normal_range], prev[normal_range] * (1.0 - p), rtol=1e-9)


def test_count_law_samples_match_chisquare() -> None:
    law = CountLaw([0.1, 0.2, 0.4, 0.3])
    k = law.sample(_rng(14), 20000)
    counts = np.bincount(k, minlength=4)
    assert stats.chisquare(counts, 20000 * law.probs).pvalue > P_MIN
    assert law.mean == pytest.approx(1.9)


def test_count_law_fit() -> None:
    truth = CountLaw.geometric(0.4, 5, 1)
    counts = truth.sample(_rng(15), 30000)
    fitted = CountLaw.fit(counts, max_count=5)
    assert fitted.max_count == 5
    np.testing.assert_allclose(fitted.probs, truth.probs, atol=0.01)
    reps = _rng(16).integers(0, 3, size=50)
    weighted = CountLaw.fit(counts[:50], reps, 5)
    repeated = CountLaw.fit(np.repeat(counts[:50], reps), max_count=5)
    np.testing.assert_allclose(weighted.probs, repeated.probs, atol=1e-14)
    assert CountLaw.fit([0, 3]).max_count == 3
    smoothed = CountLaw.fit([1], max_count=2, pseudocount=0.5)
    np.testing.assert_allclose(smoothed.probs, [0.5 / 2.5, 1.5 / 2.5, 0.5 / 2.5])


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: CountLaw.geometric(0.0, 3), r"p must be in \(0, 1\], got 0\.0"),
        (lambda: CountLaw.geometric(1.2, 3), r"p must be in \(0, 1\]"),
        (lambda: CountLaw.geometric(0.5, -1), "max_count must be non-negative"),
        (lambda: CountLaw.geometric(0.5, 3, 4), "start must satisfy 0 <= start <= max_count"),
        (lambda: CountLaw.geometric(0.5, 3, -1), "start must satisfy"),
        (lambda: CountLaw.geometric(0.5, 3.0), "max_count must be an integer"),
        (lambda: CountLaw([0.5, -0.5]), "probs must be non-negative"),
        (lambda: CountLaw.fit([0, 4], max_count=3), r"counts must be integers in \[0, 3\]"),
        (lambda: CountLaw.fit([-1]), "counts must be non-negative integers"),
        (lambda: CountLaw.fit([1], max_count=-2), "max_count must be non-negative"),
    ],
)
def test_count_law_invalid_parameters_raise(build, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build()


# --------------------------------------------------------------------------- UniformBox


def test_uniform_box_matches_scipy_and_ks() -> None:
    lo = np.array([-1.0, 0.0, 2.0])
    hi = np.array([1.0, 0.5, 5.0])
    box = UniformBox(lo, hi)
    assert box.free_axes.tolist() == [True, True, True]
    x = box.sample(_rng(17), 5000)
    assert x.shape == (5000, 3)
    expected = stats.uniform(lo, hi - lo).logpdf(x).sum(axis=-1)
    np.testing.assert_allclose(box.log_prob(x), expected)
    for axis in range(3):
        law = stats.uniform(lo[axis], hi[axis] - lo[axis])
        assert stats.kstest(x[:, axis], law.cdf).pvalue > P_MIN
    outside = np.array([[0.0, 0.25, 5.5], [-1.5, 0.25, 3.0], [np.nan, 0.25, 3.0]])
    assert np.all(box.log_prob(outside) == -np.inf)


def test_uniform_box_boundary_slack() -> None:
    box = UniformBox([0.0, 10.0], [1.0, 20.0])
    assert np.isfinite(box.log_prob([1.0 + 1e-13, 20.0 + 1e-11]))
    assert np.isfinite(box.log_prob([-1e-13, 10.0 - 1e-11]))
    assert box.log_prob([1.0 + 1e-9, 15.0]) == -np.inf
    assert box.log_prob([0.5, 20.0 + 1e-9]) == -np.inf


def test_uniform_box_pinned_axes() -> None:
    box = UniformBox([0.0, 1000.0, -2.0], [2.0, 1000.0, 3.0])
    assert box.free_axes.tolist() == [True, False, True]
    assert box.log_density == pytest.approx(-np.log(2.0 * 5.0))
    x = box.sample(_rng(18), 1000)
    assert np.all(x[:, 1] == 1000.0)
    np.testing.assert_allclose(box.log_prob(x), -np.log(10.0))
    # Pinned tolerance is 1e-9 * max(1, |lo|) = 1e-6 here.
    assert np.isfinite(box.log_prob([1.0, 1000.0 + 5e-7, 0.0]))
    assert box.log_prob([1.0, 1000.0 + 5e-6, 0.0]) == -np.inf
    small = UniformBox([0.0, 0.5], [0.0, 1.5])
    assert np.isfinite(small.log_prob([5e-10, 1.0]))
    assert small.log_prob([5e-9, 1.0]) == -np.inf
    all_pinned = UniformBox([1.0, 2.0], [1.0, 2.0])
    assert all_pinned.log_prob([1.0, 2.0]) == 0.0


def test_uniform_box_fit() -> None:
    x = UniformBox([0.0, -1.0], [2.0, 3.0]).sample(_rng(19), 5000)
    fitted = UniformBox.fit(x)
    np.testing.assert_allclose(fitted.lo, [0.0, -1.0], atol=0.01)
    np.testing.assert_allclose(fitted.hi, [2.0, 3.0], atol=0.01)
    assert np.all(np.isfinite(fitted.log_prob(x)))
    pts = np.array([[0.0, 5.0], [1.0, 5.0], [100.0, -100.0], [0.5, 5.0]])
    w = np.array([1.0, 2.0, 0.0, 0.5])
    from_weights = UniformBox.fit(pts, w)
    np.testing.assert_array_equal(from_weights.lo, [0.0, 5.0])
    np.testing.assert_array_equal(from_weights.hi, [1.0, 5.0])
    assert from_weights.free_axes.tolist() == [True, False]
    repeated = UniformBox.fit(np.repeat(pts, [1, 2, 0, 1], axis=0))
    np.testing.assert_array_equal(repeated.lo, from_weights.lo)
    np.testing.assert_array_equal(repeated.hi, from_weights.hi)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: UniformBox([0.0, 1.0], [1.0, 0.5]), r"hi must be >= lo.*hi\[1\]"),
        (lambda: UniformBox([0.0, np.nan], [1.0, 1.0]), "lo must be finite"),
        (lambda: UniformBox([0.0], [np.inf]), "hi must be finite"),
        (lambda: UniformBox([0.0, 0.0], [1.0]), "hi must have shape"),
        (lambda: UniformBox.fit([[0.0], [1.0]], [0.0, 0.0]), "at least one sample"),
        (lambda: UniformBox.fit([[0.0], [1.0]], [1.0, -1.0]), "weights must be non-negative"),
    ],
)
def test_uniform_box_invalid_parameters_raise(build, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build()


# --------------------------------------------------------------------------- UniformRevolute


def test_revolute_matches_scipy_and_ks() -> None:
    arc = UniformRevolute(-0.5, 1.5)
    theta = arc.sample(_rng(20), 5000)
    assert np.all((theta >= -0.5) & (theta < 1.5))
    np.testing.assert_allclose(arc.log_prob(theta), stats.uniform(-0.5, 2.0).logpdf(theta))
    assert stats.kstest(theta, stats.uniform(-0.5, 2.0).cdf).pvalue > P_MIN


def test_revolute_membership_is_modulo_two_pi() -> None:
    arc = UniformRevolute(3.0, 3.5)
    inside = 3.2 + 2.0 * np.pi * np.arange(-3, 4)
    np.testing.assert_allclose(arc.log_prob(inside), -np.log(0.5))
    # -3.0 is 3.283... once wrapped, so it is on the arc.
    assert arc.log_prob(-3.0) == pytest.approx(-np.log(0.5))
    assert np.all(arc.log_prob([0.0, 2.9, 3.6, -2.7, np.nan, np.inf]) == -np.inf)
    # Arc across the seam at +/- pi.
    seam = UniformRevolute(np.pi - 0.2, np.pi + 0.2)
    assert np.isfinite(seam.log_prob([-np.pi + 0.1, np.pi - 0.1, np.pi, -np.pi])).all()
    assert seam.log_prob(-np.pi + 0.3) == -np.inf
    # Angles a rounding error below lo still count.
    assert np.isfinite(UniformRevolute(0.0, 1.0).log_prob(-1e-14))


def test_revolute_wrap() -> None:
    arc = UniformRevolute(-np.pi, 0.0)
    theta = np.array([-np.pi, np.pi, 0.0, 3 * np.pi, -7.0, 10.0, -1e-18])
    wrapped = arc.wrap(theta)
    assert np.all((wrapped >= -np.pi) & (wrapped < np.pi))
    np.testing.assert_allclose(np.cos(wrapped), np.cos(theta), atol=1e-12)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(theta), atol=1e-12)
    assert wrapped[0] == -np.pi and wrapped[1] == pytest.approx(-np.pi)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    lo=st.floats(-10.0, 10.0),
    width=st.floats(1e-3, 2 * np.pi),
    theta=st.floats(-100.0, 100.0),
)
def test_revolute_wrap_lands_in_range_and_agrees_with_log_prob(
    lo: float, width: float, theta: float
) -> None:
    arc = UniformRevolute(lo, lo + width)
    w = float(arc.wrap(theta))
    assert lo <= w < lo + 2 * np.pi
    assert np.cos(w) == pytest.approx(np.cos(theta), abs=1e-9)
    assert np.sin(w) == pytest.approx(np.sin(theta), abs=1e-9)
    if w - lo < arc.width - 1e-9 or arc.is_full_circle:
        assert np.isfinite(arc.log_prob(theta))


def test_revolute_full_circle() -> None:
    for lo in (-np.pi, 0.3, 5.0):
        arc = UniformRevolute(lo, lo + 2.0 * np.pi)
        assert arc.is_full_circle and arc.width == 2.0 * np.pi
        got = arc.log_prob([0.0, 100.0, -3.0, lo - 1.0, np.nan])
        np.testing.assert_allclose(got[:4], -np.log(2.0 * np.pi))
        assert got[4] == -np.inf
    theta = UniformRevolute(-np.pi, np.pi).sample(_rng(21), 4000)
    assert stats.kstest(theta, stats.uniform(-np.pi, 2 * np.pi).cdf).pvalue > P_MIN


def test_revolute_fit_across_the_seam() -> None:
    truth = UniformRevolute(np.pi - 0.3, np.pi + 0.3)
    theta = truth.sample(_rng(22), 5000)
    # Present the data as a robot would report it: in (-pi, pi], split across the seam.
    reported = np.angle(np.exp(1j * theta))
    assert reported.min() < -2.5 and reported.max() > 2.5
    fitted = UniformRevolute.fit(reported)
    assert fitted.width == pytest.approx(0.6, abs=0.005)
    assert np.cos(fitted.lo) == pytest.approx(np.cos(np.pi - 0.3), abs=0.005)
    assert -np.pi <= fitted.lo < np.pi
    assert np.all(np.isfinite(fitted.log_prob(reported)))
    # Points on both sides of 0 do not wrap.
    simple = UniformRevolute.fit([-0.1, 0.2, 0.05])
    assert (simple.lo, simple.hi) == pytest.approx((-0.1, 0.2))


def test_revolute_fit_weights_and_single_point() -> None:
    theta = np.array([3.0, -3.0, 0.0, 3.1])
    fitted = UniformRevolute.fit(theta, [1.0, 2.0, 0.0, 1.0])
    assert fitted.width == pytest.approx(2 * np.pi - 6.0)
    assert np.all(np.isfinite(fitted.log_prob(theta[[0, 1, 3]])))
    assert fitted.log_prob(0.0) == -np.inf
    repeated = UniformRevolute.fit(np.repeat(theta, [1, 2, 0, 1]))
    assert (repeated.lo, repeated.hi) == pytest.approx((fitted.lo, fitted.hi))
    pinned = UniformRevolute.fit([1.25, 1.25 + 2 * np.pi])
    assert pinned.is_pinned
    assert pinned.log_prob(1.25) == 0.0
    assert pinned.log_prob(1.3) == -np.inf
    assert np.all(pinned.sample(_rng(0), 3) == pinned.lo)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: UniformRevolute(0.0, 7.0), r"hi - lo must be at most 2\*pi"),
        (lambda: UniformRevolute(1.0, 0.5), "hi must be >= lo"),
        (lambda: UniformRevolute(np.nan, 0.5), "lo must be finite"),
        (lambda: UniformRevolute(0.0, "x"), "hi must be a finite number"),
        (lambda: UniformRevolute.fit([]), "theta must be a non-empty 1-d array"),
        (lambda: UniformRevolute.fit([0.0, np.inf]), "theta must be finite"),
        (lambda: UniformRevolute.fit([0.0], [0.0]), "at least one sample"),
    ],
)
def test_revolute_invalid_parameters_raise(build, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build()


# --------------------------------------------------------------------------- SO(3)


def test_uniform_so3_log_density() -> None:
    assert pytest.approx(-2.0 * np.log(np.pi)) == UNIFORM_SO3_LOG_DENSITY
