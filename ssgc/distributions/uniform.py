"""Uniform laws for positions (axis-aligned boxes), joint angles and rotations.

Boxes may be degenerate along some axes: a grammar that places objects "on the table"
pins the height while leaving x and y free. Rather than forcing such axes into a
separate constant, a pinned axis is treated as a point mass, and densities are taken
with respect to Lebesgue measure on the free axes times counting measure on the pinned
ones. That makes pinned axes contribute a factor of one, so densities of boxes with the
same free axes remain comparable.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ssgc.distributions.arrays import fit_weights, frozen, sample_count

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["UNIFORM_SO3_LOG_DENSITY", "UniformBox", "UniformRevolute"]

TWO_PI = 2.0 * np.pi

UNIFORM_SO3_LOG_DENSITY: float = -float(np.log(np.pi**2))
"""Log density of the Haar-uniform rotation w.r.t. the SO(3) volume measure (total volume pi^2)."""

# Tolerances, relative to max(1, |value|): pinned coordinates are usually produced by
# arithmetic (frame transforms) and need a loose match; free-axis bounds only need to
# forgive the last few ulps.
_PINNED_RTOL = 1e-9
_BOUND_RTOL = 1e-12


def _support_mask(weights: ArrayLike | None, n: int) -> BoolArray:
    """Points that carry weight; zero-weight points must not widen a fitted support."""
    keep = fit_weights(weights, n, positive_total=False) > 0
    if not np.any(keep):
        raise ValueError("weights must give at least one sample positive weight")
    return keep


def _real(value: float, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite number, got {value!r}") from None
    if not np.isfinite(out):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return out


@dataclass(frozen=True, eq=False)
class UniformBox:
    """Uniform law on the axis-aligned box ``[lo, hi]``; axes with ``hi == lo`` are pinned."""

    lo: FloatArray
    hi: FloatArray
    free_axes: BoolArray = field(init=False, repr=False)
    _log_density: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        lo = np.atleast_1d(np.array(self.lo, dtype=np.float64))
        hi = np.atleast_1d(np.array(self.hi, dtype=np.float64))
        if lo.ndim != 1 or lo.size == 0:
            raise ValueError(f"lo must be a non-empty 1-d array, got shape {lo.shape}")
        if hi.shape != lo.shape:
            raise ValueError(f"hi must have shape {lo.shape} to match lo, got {hi.shape}")
        for name, arr in (("lo", lo), ("hi", hi)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} must be finite, got {arr.tolist()}")
        if np.any(hi < lo):
            axis = int(np.argmax(hi < lo))
            raise ValueError(
                f"hi must be >= lo on every axis, got hi[{axis}] = {float(hi[axis])!r} "
                f"< lo[{axis}] = {float(lo[axis])!r}"
            )
        free = hi > lo
        free.flags.writeable = False
        object.__setattr__(self, "lo", frozen(lo))
        object.__setattr__(self, "hi", frozen(hi))
        object.__setattr__(self, "free_axes", free)
        log_density = -float(np.sum(np.log(hi[free] - lo[free])))
        object.__setattr__(self, "_log_density", log_density)

    @property
    def dim(self) -> int:
        return int(self.lo.size)

    @property
    def width(self) -> FloatArray:
        return frozen(self.hi - self.lo)

    @property
    def log_density(self) -> float:
        """Log density inside the box: ``-sum(log width)`` over the free axes only."""
        return self._log_density

    def sample(self, rng: np.random.Generator, n: int) -> FloatArray:
        """Draw ``n`` points, shape (n, d); pinned axes come out exactly equal to ``lo``."""
        u = rng.random((sample_count(n), self.dim))
        return self.lo + u * (self.hi - self.lo)

    def log_prob(self, x: ArrayLike) -> FloatArray:
        """Log density at points ``x`` of shape (..., d); -inf outside the box.

        Free axes accept ``x`` within ``[lo, hi]`` widened by 1e-12 * max(1, |lo|, |hi|)
        so that points produced by transforms that round do not fall off the boundary.
        Pinned axes accept ``|x - lo| <= 1e-9 * max(1, |lo|)``.
        """
        pts = np.asarray(x, dtype=np.float64)
        if pts.ndim == 0 or pts.shape[-1] != self.dim:
            raise ValueError(f"x must have shape (..., {self.dim}), got {pts.shape}")
        lo, hi = self.lo, self.hi
        scale = np.maximum(1.0, np.maximum(np.abs(lo), np.abs(hi)))
        slack = np.where(self.free_axes, _BOUND_RTOL, _PINNED_RTOL) * scale
        # NaN compares False, so it lands outside without a special case.
        inside = np.all((pts >= lo - slack) & (pts <= hi + slack), axis=-1)
        return np.where(inside, self._log_density, -np.inf)

    @classmethod
    def fit(cls, x: ArrayLike, weights: ArrayLike | None = None) -> UniformBox:
        """Bounding box of the points with positive weight: the ML uniform box.

        Any smaller box would give some weighted point zero density, and any larger
        one lowers the density everywhere. The weight values beyond being positive do
        not matter. Axes on which all points agree come out pinned. A 1-d ``x`` is read
        as n scalar samples.
        """
        pts = np.asarray(x, dtype=np.float64)
        if pts.ndim == 1:
            pts = pts[:, None]
        if pts.ndim != 2 or pts.shape[0] == 0 or pts.shape[1] == 0:
            raise ValueError(f"x must have shape (n, d) with n, d >= 1, got {pts.shape}")
        keep = _support_mask(weights, pts.shape[0])
        support = pts[keep]
        if not np.all(np.isfinite(support)):
            raise ValueError("x must be finite")
        return cls(support.min(axis=0), support.max(axis=0))


@dataclass(frozen=True, eq=False)
class UniformRevolute:
    """Angle uniform on the arc ``[lo, hi]`` radians, with angles identified modulo 2 pi.

    ``hi - lo`` may not exceed 2 pi; exactly 2 pi (up to rounding) is the full circle.
    ``hi == lo`` is a pinned angle (a point mass with log density 0, matching pinned
    axes of :class:`UniformBox`), which is what fitting a single observation yields.
    """

    lo: float
    hi: float
    _width: float = field(init=False, repr=False)
    _full: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        lo = _real(self.lo, "lo")
        hi = _real(self.hi, "hi")
        if hi < lo:
            raise ValueError(f"hi must be >= lo, got hi = {hi!r} < lo = {lo!r}")
        width = hi - lo
        tol = _BOUND_RTOL * max(1.0, abs(lo), abs(hi))
        if width > TWO_PI + tol:
            raise ValueError(f"hi - lo must be at most 2*pi (the full circle), got {width!r}")
        full = width >= TWO_PI - tol
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)
        object.__setattr__(self, "_width", TWO_PI if full else width)
        object.__setattr__(self, "_full", full)

    @property
    def width(self) -> float:
        return self._width

    @property
    def is_full_circle(self) -> bool:
        return self._full

    @property
    def is_pinned(self) -> bool:
        return self._width == 0.0

    @property
    def log_density(self) -> float:
        """``-log(hi - lo)`` on the arc, 0 for a pinned angle."""
        return 0.0 if self.is_pinned else -float(np.log(self._width))

    def wrap(self, theta: ArrayLike) -> FloatArray:
        """Representative of ``theta`` in ``[lo, lo + 2 pi)``; non-finite input gives NaN."""
        t = np.asarray(theta, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            off = np.mod(t - self.lo, TWO_PI)
        # mod can round a tiny negative offset up to exactly 2 pi.
        off = np.where(off >= TWO_PI, 0.0, off)
        return self.lo + off

    def sample(self, rng: np.random.Generator, n: int) -> FloatArray:
        """Draw ``n`` angles in ``[lo, hi)``."""
        return self.lo + rng.random(sample_count(n)) * self._width

    def log_prob(self, theta: ArrayLike) -> FloatArray:
        """Log density of angles, testing arc membership modulo 2 pi; -inf off the arc."""
        t = np.asarray(theta, dtype=np.float64)
        finite = np.isfinite(t)
        if self._full:
            return np.where(finite, self.log_density, -np.inf)
        with np.errstate(invalid="ignore"):
            off = np.mod(t - self.lo, TWO_PI)
        rtol = _PINNED_RTOL if self.is_pinned else _BOUND_RTOL
        # |theta| joins the scale because reducing a large angle modulo 2 pi loses
        # absolute precision in proportion to its size.
        scale = np.maximum(max(1.0, abs(self.lo), abs(self.hi)), np.abs(np.where(finite, t, 0)))
        tol = rtol * scale
        # Offsets just below 2 pi are angles a hair below lo, so they count as on the arc.
        on_arc = finite & ((off <= self._width + tol) | (off >= TWO_PI - tol))
        return np.where(on_arc, self.log_density, -np.inf)

    @classmethod
    def fit(cls, theta: ArrayLike, weights: ArrayLike | None = None) -> UniformRevolute:
        """Smallest arc containing every positively weighted angle: the ML arc.

        On the circle the smallest covering arc is the complement of the largest gap
        between neighbouring angles, so data straddling the +/- pi seam gives a short
        arc across it rather than one spanning almost the whole circle. The result has
        ``lo`` in ``[-pi, pi)`` and ``hi = lo + width`` (which may exceed pi).
        """
        t = np.asarray(theta, dtype=np.float64)
        if t.ndim != 1 or t.size == 0:
            raise ValueError(f"theta must be a non-empty 1-d array, got shape {t.shape}")
        keep = _support_mask(weights, t.size)
        t = t[keep]
        if not np.all(np.isfinite(t)):
            raise ValueError("theta must be finite")
        phi = np.mod(t, TWO_PI)
        phi = np.sort(np.where(phi >= TWO_PI, 0.0, phi))
        # gaps[i] is the empty stretch after phi[i]; the last one wraps to phi[0].
        gaps = np.append(np.diff(phi), phi[0] + TWO_PI - phi[-1])
        i = int(np.argmax(gaps))
        if i == phi.size - 1:
            start, width = phi[0], phi[-1] - phi[0]
        else:
            start, width = phi[i + 1], phi[i] + TWO_PI - phi[i + 1]
        lo = float(np.mod(start + np.pi, TWO_PI) - np.pi)
        if lo >= np.pi:
            lo -= TWO_PI
        return cls(lo, lo + float(width))
