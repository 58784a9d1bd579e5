"""Multivariate normal law used for continuous offsets in scene grammars.

Grammars mostly place children relative to a parent with small (1-3 dimensional)
Gaussian offsets, so the class favours clarity and exact bookkeeping over speed for
large dimensions: the Cholesky factor and the log-normaliser are computed once at
construction, and every density evaluation is a triangular solve against that factor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import solve_triangular

from ssgc.distributions.arrays import fit_weights, frozen, sample_count

FloatArray = NDArray[np.float64]

__all__ = ["Normal"]

_LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True, eq=False)
class Normal:
    """Gaussian with mean ``mean`` (d,) and covariance ``cov`` (d, d).

    Equality is identity: comparing float arrays for equality is rarely what a caller
    means, so tests and EM code should compare parameters with a tolerance instead.
    """

    mean: FloatArray
    cov: FloatArray
    _chol: FloatArray = field(init=False, repr=False)
    _log_norm: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        mean = np.array(self.mean, dtype=np.float64)
        if mean.ndim == 0:
            mean = mean.reshape(1)
        if mean.ndim != 1 or mean.size == 0:
            raise ValueError(f"mean must be a non-empty 1-d array, got shape {mean.shape}")
        if not np.all(np.isfinite(mean)):
            raise ValueError(f"mean must be finite, got {mean.tolist()}")
        d = mean.size

        cov = np.array(self.cov, dtype=np.float64)
        if cov.ndim == 0:
            cov = cov.reshape(1, 1)
        if cov.shape != (d, d):
            raise ValueError(f"cov must have shape ({d}, {d}) to match mean, got {cov.shape}")
        if not np.all(np.isfinite(cov)):
            raise ValueError("cov must be finite")
        asym = float(np.max(np.abs(cov - cov.T)))
        if asym > 1e-10 * float(np.max(np.abs(cov))):
            raise ValueError(f"cov must be symmetric, got max |cov - cov.T| = {asym!r}")
        # Symmetrise so round-off in a caller's matrix cannot leak into the factor.
        cov = 0.5 * (cov + cov.T)
        try:
            chol = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            chol = np.full_like(cov, np.nan)
        diag = np.diag(chol)
        if not (np.all(np.isfinite(chol)) and np.all(diag > 0)):
            raise ValueError("cov must be positive definite (Cholesky factorisation failed)")

        object.__setattr__(self, "mean", frozen(mean))
        object.__setattr__(self, "cov", frozen(cov))
        object.__setattr__(self, "_chol", frozen(chol))
        log_norm = -0.5 * d * _LOG_2PI - float(np.sum(np.log(diag)))
        object.__setattr__(self, "_log_norm", log_norm)

    @classmethod
    def diagonal(cls, mean: ArrayLike, variance: ArrayLike) -> Normal:
        """Axis-aligned Gaussian; a scalar ``variance`` is shared by every axis.

        Validated here rather than by the generic Cholesky check so that the error
        names the offending variance, which is what a grammar author wrote.
        """
        mean_arr = np.atleast_1d(np.asarray(mean, dtype=np.float64))
        var = np.asarray(variance, dtype=np.float64)
        if var.ndim == 0:
            var = np.full(mean_arr.shape, float(var))
        if var.shape != mean_arr.shape:
            raise ValueError(
                f"variance must be a scalar or have shape {mean_arr.shape} to match mean, "
                f"got {var.shape}"
            )
        for problem, bad in (("finite", ~np.isfinite(var)), ("positive", ~(var > 0))):
            if np.any(bad):
                axis = int(np.argmax(bad))
                where = f" on axis {axis}" if var.size > 1 else ""
                raise ValueError(f"variance must be {problem}, got {float(var[axis])!r}{where}")
        return cls(mean_arr, np.diag(var))

    @property
    def dim(self) -> int:
        return int(self.mean.size)

    @property
    def variance(self) -> FloatArray:
        """Marginal variances, i.e. the diagonal of ``cov``."""
        return frozen(np.diag(self.cov))

    @property
    def chol(self) -> FloatArray:
        """Lower Cholesky factor L with ``cov = L @ L.T``."""
        return self._chol

    @property
    def log_normalizer(self) -> float:
        """``-d/2 log(2 pi) - log|L|``: the log density at the mean."""
        return self._log_norm

    def _check_last_axis(self, x: FloatArray, name: str) -> None:
        if x.ndim == 0 or x.shape[-1] != self.dim:
            raise ValueError(f"{name} must have shape (..., {self.dim}), got {x.shape}")

    def sample(self, rng: np.random.Generator, n: int) -> FloatArray:
        """Draw ``n`` points, shape (n, d)."""
        z = rng.standard_normal((sample_count(n), self.dim))
        return self.mean + z @ self._chol.T

    def log_prob(self, x: ArrayLike) -> FloatArray:
        """Log density at points ``x`` of shape (..., d); non-finite points score -inf."""
        pts = np.asarray(x, dtype=np.float64)
        self._check_last_axis(pts, "x")
        batch = pts.shape[:-1]
        flat = pts.reshape(-1, self.dim)
        with np.errstate(invalid="ignore", over="ignore"):
            # Solve L z = (x - mean) for all points at once: columns are independent.
            z = solve_triangular(self._chol, (flat - self.mean).T, lower=True, check_finite=False)
            lp = self._log_norm - 0.5 * np.sum(z * z, axis=0)
        lp = np.where(np.all(np.isfinite(flat), axis=-1), lp, -np.inf)
        return lp.reshape(batch)

    def log_prob_from_standard(self, z: ArrayLike) -> FloatArray:
        """Log density of ``mean + L z`` computed from the standard-normal draw ``z``.

        The change of variables gives ``log N(z; 0, I) - log|L|`` without touching the
        sampled point, so a sampler that reports this value is checked independently
        by :meth:`log_prob` rather than sharing its arithmetic (and its bugs).
        """
        std = np.asarray(z, dtype=np.float64)
        self._check_last_axis(std, "z")
        with np.errstate(invalid="ignore", over="ignore"):
            lp = self._log_norm - 0.5 * np.sum(std * std, axis=-1)
        return np.where(np.all(np.isfinite(std), axis=-1), lp, -np.inf)

    @classmethod
    def fit(
        cls,
        x: ArrayLike,
        weights: ArrayLike | None = None,
        diagonal: bool = False,
        min_variance: float = 1e-12,
    ) -> Normal:
        """Weighted maximum-likelihood Gaussian (the biased, divide-by-total-weight covariance).

        ``x`` has shape (n, d); a 1-d ``x`` is read as n scalar samples. Weights act like
        repetition counts, which is what the EM M-step needs for responsibilities.

        Variances are floored at ``min_variance`` so that degenerate data (a single
        sample, repeated points, collinear points) still yields a valid distribution
        instead of a singular covariance; EM would otherwise crash or collapse onto a
        point with infinite likelihood. For a full covariance the floor is applied to
        the eigenvalues, i.e. to the variance along every direction, which is what keeps
        the matrix positive definite; for a diagonal fit this is the same as flooring
        each axis variance. The floor is absolute, so choose it in the data's units.
        """
        pts = np.asarray(x, dtype=np.float64)
        if pts.ndim == 1:
            pts = pts[:, None]
        if pts.ndim != 2 or pts.shape[0] == 0 or pts.shape[1] == 0:
            raise ValueError(f"x must have shape (n, d) with n, d >= 1, got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError("x must be finite")
        floor = float(min_variance)
        if not (np.isfinite(floor) and floor > 0):
            raise ValueError(f"min_variance must be positive and finite, got {min_variance!r}")
        w = fit_weights(weights, pts.shape[0])
        total = float(w.sum())

        mean = (w @ pts) / total
        centred = pts - mean
        if diagonal:
            var = (w @ (centred * centred)) / total
            return cls(mean, np.diag(np.maximum(var, floor)))
        cov = (centred * w[:, None]).T @ centred / total
        cov = 0.5 * (cov + cov.T)
        eigval, eigvec = np.linalg.eigh(cov)
        if eigval.min() < floor:
            cov = (eigvec * np.maximum(eigval, floor)) @ eigvec.T
            cov = 0.5 * (cov + cov.T)
        return cls(mean, cov)
