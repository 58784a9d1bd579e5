"""The argument checks every distribution shares: frozen parameter arrays, sample counts,
EM weights.  One definition, so every law words the same mistake the same way."""

from __future__ import annotations

import operator

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def frozen(values: ArrayLike) -> FloatArray:
    """Copy to float64 and lock, so a distribution can never be mutated behind our back."""
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


def sample_count(n: int) -> int:
    """`n` as a number of draws: Python and numpy integers >= 0 only."""
    try:
        count = operator.index(n)
    except TypeError:
        raise ValueError(f"n must be a non-negative integer, got {n!r}") from None
    if count < 0:
        raise ValueError(f"n must be a non-negative integer, got {count}")
    return count


def fit_weights(weights: ArrayLike | None, n: int, positive_total: bool = True) -> FloatArray:
    """Validate EM responsibilities; None means every sample counts once.  Laws with a
    pseudocount check the total themselves (`positive_total=False`)."""
    if weights is None:
        return np.ones(n, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,):
        raise ValueError(f"weights must have shape ({n},) to match the samples, got {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError("weights must be finite")
    if np.any(w < 0):
        raise ValueError(f"weights must be non-negative, got {float(w.min())!r}")
    if positive_total and not w.sum() > 0:
        raise ValueError("weights must have a positive total")
    return w
