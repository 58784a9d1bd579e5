"""Convergence diagnostics for many chains run in lockstep: rank-normalised split-R̂ and the
bulk effective sample size (Vehtari, Gelman, Simpson, Carpenter and Bürkner 2021, "Rank-
normalization, folding, and localization: an improved R̂"), for a statistic recorded at every
sweep of every chain, e.g. the number of nodes of each type.

RJMCMC (`ssgc.sample.rjmcmc`) uses them to decide when its burn-in is over instead of a
fixed number of sweeps: while the chains still drift from where they started (towards fewer
objects, say), the first and second halves of each chain's window disagree: split-R̂ is
above 1 and the chains' mean moves (`drift`).  RJMCMC runs many short chains and reports
one state of each, so the drift of the ensemble decides, and R̂ and ESS are recorded.
Counts are discrete (ties), so values are replaced by their average ranks over all draws
before R̂ is computed, which also makes R̂ blind to the scale of the statistic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import special

FloatArray = NDArray[np.float64]


def _split(x: FloatArray) -> FloatArray:
    """(draws, chains) -> (draws // 2, 2 chains): each chain's first and second half."""
    half = x.shape[0] // 2
    return np.concatenate([x[:half], x[x.shape[0] - half :]], axis=1)


def _rank_normal(x: FloatArray) -> FloatArray:
    """Average ranks over all draws mapped through the normal quantile (fractional offset
    3/8, as in the paper); constant input stays constant."""
    from scipy.stats import rankdata  # here, not at the top: it costs `ssg` 0.4 s to start

    r = rankdata(x, method="average").reshape(x.shape)
    return special.ndtri((r - 0.375) / (x.size + 0.25))


def _rhat(x: FloatArray) -> float:
    n = x.shape[0]
    within = float(np.mean(np.var(x, axis=0, ddof=1)))
    between = float(n * np.var(np.mean(x, axis=0), ddof=1))
    if within <= 0.0:
        return 1.0 if between <= 0.0 else float("inf")
    var_plus = (n - 1) / n * within + between / n
    return float(np.sqrt(var_plus / within))


def split_rhat(x: FloatArray) -> float:
    """Rank-normalised split-R̂ of one statistic, x of shape (draws, chains), draws ≥ 4.
    1 for a statistic that never varies."""
    s = _split(np.asarray(x, float))
    if np.ptp(s) == 0.0:
        return 1.0
    return _rhat(_rank_normal(s))


def _autocovariance(x: FloatArray) -> FloatArray:
    """Per chain (columns), the biased autocovariance at every lag, by FFT."""
    n = x.shape[0]
    centred = x - x.mean(axis=0)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(centred, n=size, axis=0)
    return np.fft.irfft(f * np.conj(f), n=size, axis=0)[:n] / n


def ess_bulk(x: FloatArray) -> float:
    """Bulk effective sample size of one statistic over all chains, x of shape (draws,
    chains): the rank-normalised split chains' autocorrelations summed with Geyer's initial
    monotone sequence.  The number of draws for a statistic that never varies."""
    s = _split(np.asarray(x, float))
    n, m = s.shape
    if np.ptp(s) == 0.0 or n < 4:
        return float(s.size)
    z = _rank_normal(s)
    acov = _autocovariance(z)
    within = float(np.mean(acov[0]) * n / (n - 1))
    var_plus = within * (n - 1) / n + float(np.var(np.mean(z, axis=0), ddof=1))
    rho = 1.0 - (within - np.mean(acov, axis=1)) / var_plus
    rho[0] = 1.0
    pairs = rho[: 2 * (n // 2)].reshape(-1, 2).sum(axis=1)
    positive = np.flatnonzero(pairs <= 0.0)
    pairs = pairs[: positive[0]] if len(positive) else pairs
    pairs = np.minimum.accumulate(pairs)  # initial monotone sequence
    tau = max(-1.0 + 2.0 * float(pairs.sum()), 1.0 / np.log10(n * m))
    return float(n * m / tau)


def drift(x: FloatArray) -> float:
    """How far the chains' mean moved between the first and the second half of the draws, in
    standard errors: each chain's second-half mean minus its first-half mean is one
    independent difference per chain (the chains are independent), and z is their mean over
    its standard error.  Many short chains that still forget their starting law drift
    together, which this sees even when each chain is too short for R̂ to be near 1
    (R̂² ≈ 1 + τ / n for a chain of n draws with autocorrelation time τ).  0 for a statistic
    that does not change."""
    s = _split(np.asarray(x, float))
    m = s.shape[1] // 2
    d = s[:, m:].mean(axis=0) - s[:, :m].mean(axis=0)
    spread = float(np.std(d, ddof=1)) if len(d) > 1 else 0.0
    if spread == 0.0:
        return 0.0 if float(np.mean(d)) == 0.0 else float("inf")
    return float(abs(np.mean(d)) / (spread / np.sqrt(len(d))))


@dataclass(frozen=True)
class Summary:
    """Worst values over the statistics: largest split-R̂, smallest bulk ESS, largest
    drift (in standard errors)."""

    rhat: float
    ess: float
    drift: float


def summary(history: FloatArray) -> Summary:
    """`Summary` of `history`, shaped (draws, chains, statistics)."""
    k = history.shape[2]
    cols = [history[:, :, j] for j in range(k)]
    return Summary(
        rhat=max((split_rhat(c) for c in cols), default=1.0),
        ess=min((ess_bulk(c) for c in cols), default=float(history.shape[0])),
        drift=max((drift(c) for c in cols), default=0.0),
    )
