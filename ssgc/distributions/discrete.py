"""Finite discrete laws: rule choice (Categorical), optional children (Bernoulli) and
child multiplicity (CountLaw).

All three are sampled by inverse-CDF lookup on one batch of uniforms, so sampling n
values costs one ``searchsorted`` regardless of the number of categories.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

from ssgc.distributions.arrays import fit_weights, frozen, sample_count

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = ["Bernoulli", "Categorical", "CountLaw", "fit_geometric_p"]


def _as_int(value: object, name: str) -> int:
    """Accept Python and numpy integers only: a float count is almost always a bug."""
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"{name} must be an integer, got {value!r}") from None


def _non_negative(value: float, name: str) -> float:
    out = float(value)
    if not (np.isfinite(out) and out >= 0):
        raise ValueError(f"{name} must be non-negative and finite, got {value!r}")
    return out


def _index_mask(k: ArrayLike, size: int) -> tuple[IntArray, BoolArray]:
    """Map values to category indices plus a mask of those inside ``0..size-1``.

    Integer-valued floats count as indices (data often round-trips through float
    arrays); anything else -- fractions, NaN, out-of-range -- is simply outside the
    support, which is a density of zero rather than an error.
    """
    arr = np.asarray(k)
    if arr.dtype == np.bool_:
        arr = arr.astype(np.int64)
    if np.issubdtype(arr.dtype, np.integer):
        ok = (arr >= 0) & (arr < size)
    else:
        vals = arr.astype(np.float64)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(vals) & (vals == np.floor(vals)) & (vals >= 0) & (vals < size)
    idx = np.where(ok, arr, 0).astype(np.int64)
    return idx, np.asarray(ok, dtype=np.bool_)


def _frequencies(
    values: ArrayLike,
    weights: ArrayLike | None,
    size: int | None,
    pseudocount: float,
    name: str,
    size_name: str,
) -> FloatArray:
    """Weighted counts per index plus a pseudocount: the shared Categorical/CountLaw M-step.

    Fitting data must lie in the support; silently dropping points would bias EM, so
    out-of-range values raise instead of being scored -inf as in ``log_prob``.
    """
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-d array, got shape {arr.shape}")
    if size is None:
        if arr.size == 0:
            raise ValueError(f"{size_name} must be given when {name} is empty")
        _, ok = _index_mask(arr, np.iinfo(np.int64).max)
        if not np.all(ok):
            bad = arr[~ok][0].item()
            raise ValueError(f"{name} must be non-negative integers, got {bad!r}")
        size = int(arr.max()) + 1
    idx, ok = _index_mask(arr, size)
    if not np.all(ok):
        bad = arr[~ok][0].item()
        raise ValueError(f"{name} must be integers in [0, {size - 1}], got {bad!r}")
    alpha = _non_negative(pseudocount, "pseudocount")
    w = fit_weights(weights, idx.size, positive_total=False)
    counts = np.bincount(idx, weights=w, minlength=size) + alpha
    if not counts.sum() > 0:
        raise ValueError("weights must have a positive total (or pseudocount must be > 0)")
    return counts


@dataclass(frozen=True, eq=False)
class Categorical:
    """Law over ``0..K-1`` given by non-negative weights that are normalised on construction.

    Accepting unnormalised weights lets grammar files state rule weights like
    ``[3, 1]`` directly. Equality is identity (compare ``probs`` with a tolerance).
    """

    probs: FloatArray
    log_probs: FloatArray = field(init=False, repr=False)
    _cdf: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        raw = np.array(self.probs, dtype=np.float64)
        if raw.ndim != 1 or raw.size == 0:
            raise ValueError(f"probs must be a non-empty 1-d array, got shape {raw.shape}")
        if not np.all(np.isfinite(raw)):
            bad = int(np.argmax(~np.isfinite(raw)))
            raise ValueError(f"probs must be finite, got {float(raw[bad])!r} at index {bad}")
        if np.any(raw < 0):
            bad = int(np.argmax(raw < 0))
            raise ValueError(f"probs must be non-negative, got {float(raw[bad])!r} at index {bad}")
        peak = float(raw.max())
        if not peak > 0:
            raise ValueError("probs must have a positive sum, got all zeros")
        # Scaling by the peak first keeps huge weights from overflowing the sum.
        probs = raw / peak
        probs /= probs.sum()
        with np.errstate(divide="ignore"):
            log_probs = np.log(probs)
        cdf = np.cumsum(probs)
        # Rounding can leave the cumulative sum a hair below 1, and a uniform draw in
        # that sliver would index past the end. Pinning everything from the last
        # non-empty bin to exactly 1 closes the sliver without ever handing mass to a
        # trailing zero-probability bin.
        last = int(np.flatnonzero(probs)[-1])
        cdf[last:] = 1.0
        object.__setattr__(self, "probs", frozen(probs))
        object.__setattr__(self, "log_probs", frozen(log_probs))
        object.__setattr__(self, "_cdf", frozen(cdf))

    @property
    def num_categories(self) -> int:
        return int(self.probs.size)

    def sample(self, rng: np.random.Generator, n: int) -> IntArray:
        """Draw ``n`` category indices by inverse-CDF lookup."""
        u = rng.random(sample_count(n))
        # side="right" maps u to the first bin whose CDF exceeds it, so zero-width bins
        # (zero probability) are never chosen, even for u == 0.
        return np.searchsorted(self._cdf, u, side="right").astype(np.int64)

    def log_prob(self, k: ArrayLike) -> FloatArray:
        """Log probability of each index; -inf outside ``0..K-1`` or on zero-probability bins."""
        idx, ok = _index_mask(k, self.num_categories)
        return np.where(ok, self.log_probs[idx], -np.inf)

    @classmethod
    def fit(
        cls,
        k: ArrayLike,
        weights: ArrayLike | None = None,
        num_categories: int | None = None,
        pseudocount: float = 0.0,
    ) -> Categorical:
        """Weighted ML (or, with ``pseudocount`` > 0, Dirichlet-smoothed) category frequencies.

        ``num_categories`` should normally be given: categories that happen not to
        occur in the data must still exist in the fitted law. When omitted it is taken
        as ``max(k) + 1``. ``pseudocount`` is added to every category's weighted count,
        which keeps unseen categories possible in later EM iterations.
        """
        size = None if num_categories is None else _as_int(num_categories, "num_categories")
        if size is not None and size < 1:
            raise ValueError(f"num_categories must be at least 1, got {size}")
        return cls(_frequencies(k, weights, size, pseudocount, "k", "num_categories"))


@dataclass(frozen=True, eq=False)
class Bernoulli:
    """Coin with success probability ``p``; used for optional children."""

    p: float
    _log_p: float = field(init=False, repr=False)
    _log_q: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        try:
            p = float(self.p)
        except (TypeError, ValueError):
            raise ValueError(f"p must be a number in [0, 1], got {self.p!r}") from None
        if not (0.0 <= p <= 1.0):
            raise ValueError(f"p must be in [0, 1], got {self.p!r}")
        object.__setattr__(self, "p", p)
        with np.errstate(divide="ignore"):
            object.__setattr__(self, "_log_p", float(np.log(p)))
            # "+ 0.0" turns log1p(-0.0) == -0.0 into a plain 0.0.
            object.__setattr__(self, "_log_q", float(np.log1p(-p)) + 0.0)

    def sample(self, rng: np.random.Generator, n: int) -> BoolArray:
        """Draw ``n`` booleans; ``u < p`` makes p = 0 and p = 1 exact."""
        return rng.random(sample_count(n)) < self.p

    def log_prob(self, x: ArrayLike) -> FloatArray:
        """Log probability of booleans (or 0/1 numbers); any other value scores -inf."""
        arr = np.asarray(x)
        if arr.dtype == np.bool_:
            ok = np.ones(arr.shape, dtype=np.bool_)
            hit = arr
        else:
            vals = arr.astype(np.float64)
            hit = vals == 1
            ok = hit | (vals == 0)
        return np.where(ok, np.where(hit, self._log_p, self._log_q), -np.inf)

    @classmethod
    def fit(
        cls,
        x: ArrayLike,
        weights: ArrayLike | None = None,
        pseudocount: float = 0.0,
    ) -> Bernoulli:
        """Weighted success frequency, with ``pseudocount`` added to both outcomes."""
        arr = np.asarray(x)
        if arr.ndim != 1:
            raise ValueError(f"x must be a 1-d array, got shape {arr.shape}")
        if arr.dtype != np.bool_:
            vals = arr.astype(np.float64)
            if not np.all((vals == 0) | (vals == 1)):
                raise ValueError("x must contain only booleans or 0/1 values")
            arr = vals == 1
        alpha = _non_negative(pseudocount, "pseudocount")
        w = fit_weights(weights, arr.size, positive_total=False)
        total = float(w.sum()) + 2.0 * alpha
        if not total > 0:
            raise ValueError("weights must have a positive total (or pseudocount must be > 0)")
        return cls((float(w[arr].sum()) + alpha) / total)


@dataclass(frozen=True, eq=False)
class CountLaw:
    """Law over child counts ``0..max_count``; ``probs[n]`` is P(count = n).

    Kept distinct from :class:`Categorical` (which it wraps) because a count has a
    natural order and a maximum the grammar reasons about, and because its fitting
    parameter is ``max_count`` rather than a number of categories.
    """

    probs: FloatArray
    _categorical: Categorical = field(init=False, repr=False)

    def __post_init__(self) -> None:
        cat = Categorical(self.probs)
        object.__setattr__(self, "_categorical", cat)
        object.__setattr__(self, "probs", cat.probs)

    @classmethod
    def geometric(cls, p: float, max_count: int, start: int = 0) -> CountLaw:
        """Geometric law on ``start..max_count``: P(n) proportional to p (1-p)^(n - start).

        Counts above ``max_count`` are impossible in a compiled grammar, so rather than
        losing the geometric tail mass beyond it, the law is truncated at ``max_count``
        and renormalised: the stated probabilities always sum to one, and each P(n) is
        the untruncated one divided by ``1 - (1-p)^(max_count - start + 1)``. Counts
        below ``start`` have probability zero.
        """
        try:
            prob = float(p)
        except (TypeError, ValueError):
            raise ValueError(f"p must be a number in (0, 1], got {p!r}") from None
        if not (0.0 < prob <= 1.0):
            raise ValueError(f"p must be in (0, 1], got {p!r}")
        top = _as_int(max_count, "max_count")
        if top < 0:
            raise ValueError(f"max_count must be non-negative, got {top}")
        first = _as_int(start, "start")
        if not (0 <= first <= top):
            raise ValueError(f"start must satisfy 0 <= start <= max_count ({top}), got {first}")
        steps = np.arange(top - first + 1, dtype=np.float64)
        # The common factor p cancels in the renormalisation; p = 1 gives 0**0 = 1 at
        # ``start`` and zeros elsewhere, i.e. a point mass, as it should.
        weights = np.zeros(top + 1, dtype=np.float64)
        weights[first:] = (1.0 - prob) ** steps
        return cls(weights)

    @property
    def max_count(self) -> int:
        return int(self.probs.size - 1)

    @property
    def largest(self) -> int:
        """The largest count of positive probability: a law written `probs: [0.5, 0.5, 0, 0]`
        (or geometric with p = 1) never makes more, so the supertree holds no more copies."""
        return int(np.flatnonzero(self.probs > 0)[-1])

    @property
    def log_probs(self) -> FloatArray:
        return self._categorical.log_probs

    @property
    def mean(self) -> float:
        """Expected count, handy for sanity checks on fitted grammars."""
        return float(np.arange(self.probs.size) @ self.probs)

    def sample(self, rng: np.random.Generator, n: int) -> IntArray:
        """Draw ``n`` counts."""
        return self._categorical.sample(rng, n)

    def log_prob(self, counts: ArrayLike) -> FloatArray:
        """Log probability of each count; -inf for negative, fractional or too-large counts."""
        return self._categorical.log_prob(counts)

    @classmethod
    def fit(
        cls,
        counts: ArrayLike,
        weights: ArrayLike | None = None,
        max_count: int | None = None,
        pseudocount: float = 0.0,
    ) -> CountLaw:
        """Weighted ML count frequencies on ``0..max_count`` (``pseudocount`` added to each).

        When ``max_count`` is omitted the largest observed count is used.
        """
        size = None
        if max_count is not None:
            top = _as_int(max_count, "max_count")
            if top < 0:
                raise ValueError(f"max_count must be non-negative, got {top}")
            size = top + 1
        return cls(_frequencies(counts, weights, size, pseudocount, "counts", "max_count"))


def fit_geometric_p(histogram: ArrayLike, start: int, p_min: float = 1e-9) -> float | None:
    """Maximum-likelihood ``p`` of a geometric count law truncated to ``start..max``.

    ``histogram[n]`` is the (weighted) number of times count ``n`` was seen, ``n = 0..max``.
    On ``start..max`` the law is ``P(n) ∝ x^(n - start)`` with ``x = 1 - p``: an exponential
    family in ``log x``, so the MLE matches the mean count and is unique.  A mean at or above
    the middle of the range would need ``x >= 1`` (counts growing with n), which a geometric
    law cannot say: ``p`` then stops at ``p_min`` (nearly uniform).  None when the data say
    nothing about ``p`` (no weight, or a single allowed count).
    """
    h = np.asarray(histogram, dtype=np.float64)[start:]
    total = float(h.sum())
    if h.size < 2 or not total > 0:
        return None
    steps = np.arange(h.size, dtype=np.float64)
    target = float(steps @ h) / total
    if target <= 0.0:
        return 1.0  # every count was `start`: a point mass there

    def mean_count(theta: float) -> float:
        w = np.exp(theta * steps - max(theta * (h.size - 1), 0.0))
        return float(steps @ w / w.sum())

    lo, hi = np.log(1e-300), float(np.log1p(-p_min))
    if mean_count(hi) <= target:
        return p_min
    theta = optimize.brentq(lambda t: mean_count(t) - target, lo, hi, xtol=1e-14, rtol=1e-14)
    return float(-np.expm1(theta))
