"""Normal translations (`world_normal`, `world_normal_offset`, `parent_normal_offset`).

A Normal over the free axes, with the pinned axes (`pin`) held at the mean: a point mass
there.  Its spread is written one of three ways, and the fit keeps the way it was written: an
isotropic `variance` (one number), a per-axis `variance` (three) or a full `covariance`.
"""

from __future__ import annotations

from enum import Enum
from typing import Any, ClassVar

import numpy as np
from scipy.special import chdtrc

from ssgc import dsl
from ssgc.distributions.normal import Normal
from ssgc.laws.base import (
    POS_TOL,
    Columns,
    Context,
    Deviation,
    FitSettings,
    FloatArray,
    Frame,
    Loc,
    Lowering,
    TranslationLaw,
    frozen,
    percent,
    register,
)

AXES = {"x": 0, "y": 1, "z": 2}


class Spread(Enum):
    """How the spread was written, which is the form it is fitted in."""

    ISOTROPIC = "variance: number"
    AXES = "variance: [x, y, z]"
    FULL = "covariance"


@register
class NormalTranslation(TranslationLaw):
    keys: ClassVar[dict[str, Frame]] = {
        "world_normal": Frame.WORLD,
        "world_normal_offset": Frame.WORLD_OFFSET,
        "parent_normal_offset": Frame.PARENT,
    }
    columns: ClassVar[dict[str, tuple[int, ...]]] = {
        "offset": (3,),
        "free": (3,),
        "whiten": (3, 3),
        "lognorm": (),
    }

    offset: FloatArray  # the full 3-D mean (pinned axes included)
    free: FloatArray  # bool (3,): the axes with a density
    normal: Normal  # over the free axes only
    spread: Spread

    @classmethod
    def lower(
        cls, p: dsl.NormalParams, key: str, loc: Loc, ctx: Lowering
    ) -> NormalTranslation | None:
        free = np.ones(3, bool)
        for axis in p.pin:
            free[AXES[axis]] = False
        if not free.any():
            ctx.error((*loc, "pin"), "all three axes are pinned; use `offset` for a fixed offset")
            return None
        sub = _covariance(p, free, loc, ctx) if p.covariance is not None else None
        sub = _variance(p, free, loc, ctx) if p.covariance is None else sub
        if sub is None:
            return None
        try:
            normal = Normal(np.asarray(p.mean, float)[free], sub)
        except ValueError as exc:  # numerically singular despite the checks above
            spread = "covariance" if p.covariance is not None else "variance"
            ctx.error((*loc, spread), f"invalid {spread} (too large or nearly singular): {exc}")
            return None
        if p.covariance is not None:
            form = Spread.FULL
        else:
            form = Spread.AXES if isinstance(p.variance, list) else Spread.ISOTROPIC
        return cls(
            key=key,
            frame=cls.keys[key],
            path=loc,
            fixed=p.fixed,
            offset=frozen(p.mean),
            free=frozen(free),
            normal=normal,
            spread=form,
        )

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        z = rng.standard_normal((n, int(self.free.sum())))
        local = np.broadcast_to(self.offset, (n, 3)).copy()
        local[:, self.free] = self.normal.mean + z @ self.normal.chol.T
        return local, self.normal.log_prob_from_standard(z)

    def row(self) -> dict[str, Any]:
        free = np.flatnonzero(self.free)
        whiten = np.zeros((3, 3))
        whiten[np.ix_(free, free)] = np.linalg.inv(self.normal.chol)
        # Normal stores the log density at its mean
        return {
            "offset": self.offset,
            "free": self.free,
            "whiten": whiten,
            "lognorm": -self.normal.log_normalizer,
        }

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        free, delta = cols["free"], u - cols["offset"]
        pinned_ok = np.all(free | (np.abs(delta) <= POS_TOL), axis=1)
        white = np.einsum("nij,nj->ni", cols["whiten"], np.where(free, delta, 0))
        out = -0.5 * np.sum(white**2, axis=1) - cols["lognorm"]
        return np.where(pinned_ok, out, -np.inf)

    def mode(self) -> FloatArray:
        return self.offset

    def supremum(self) -> float:
        return float(self.normal.log_normalizer)

    def concave_form(self) -> tuple[FloatArray, FloatArray, float]:
        """The precision is zero on pinned axes (their point mass is not relaxed)."""
        w = np.asarray(self.row()["whiten"])
        return self.offset, w.T @ w, self.supremum()

    def fit(self, u: FloatArray, w: FloatArray, settings: FitSettings) -> dict[str, object] | None:
        """Weighted MLE of the mean and spread on the free axes; what is written for a pinned
        axis stays as it is (None)."""
        free = np.flatnonzero(self.free)
        full = self.spread == Spread.FULL
        fit = Normal.fit(u[:, free], w, diagonal=not full, min_variance=settings.min_variance)
        mean: list[float | None] = [None, None, None]
        for i, a in enumerate(free):
            mean[a] = float(fit.mean[i])
        values: dict[str, object] = {"mean": mean}
        if full:
            cov: list[list[float | None]] = [[None] * 3 for _ in range(3)]
            for i, a in enumerate(free):
                for j, b in enumerate(free):
                    cov[a][b] = float(fit.cov[i, j])
            values["covariance"] = cov
        elif self.spread == Spread.ISOTROPIC:
            values["variance"] = float(max(np.diag(fit.cov).mean(), settings.min_variance))
        else:
            var: list[float | None] = [None, None, None]
            for i, a in enumerate(free):
                var[a] = float(fit.cov[i, i])
            values["variance"] = var
        return values

    def describe(self) -> str:
        pinned = "".join("xyz"[i] for i in range(3) if not self.free[i])
        pin = f", pin {pinned}" if pinned else ""
        return (
            f"{self.key} mean {np.round(self.offset, 4).tolist()} "
            f"var {np.round(self.normal.variance, 5).tolist()}{pin}"
        )

    def describe_deviation(self, u: FloatArray, log_prob: float, ctx: Context) -> Deviation:
        """Distance from the mean over the free axes, and how many draws land farther (χ²)."""
        d = float(np.linalg.norm(np.where(self.free, u - self.offset, 0.0)))
        m2 = max(0.0, -2.0 * (log_prob - self.supremum()))
        sigma, farther = float(np.sqrt(m2)), float(chdtrc(int(self.free.sum()), m2))
        return Deviation(
            f"position {d:.2f} m from where its parent {ctx.parent} places it ({sigma:.1f}σ, "
            f"{percent(farther)} of placements are farther)",
            sigma,
            farther,
        )

    def describe_violation(self, u: FloatArray) -> str:
        off = np.where(self.free, 0.0, u - self.offset)
        a = int(np.argmax(np.abs(off)))
        return f"pinned axis {'xyz'[a]} off by {off[a]:+.3g} m"


def _covariance(
    p: dsl.NormalParams, free: FloatArray, loc: Loc, ctx: Lowering
) -> FloatArray | None:
    """The free axes' block of the covariance; None after reporting every independent
    mistake (asymmetry, a negative pinned variance, no positive definiteness)."""
    cov = np.asarray(p.covariance, float)
    symmetric = np.allclose(cov, cov.T, rtol=0, atol=1e-12 * max(1.0, np.abs(cov).max()))
    if not symmetric:
        ctx.error((*loc, "covariance"), "covariance must be symmetric")
    # a pinned axis's row and column are dropped, but its variance may be 0, not negative,
    # as in the `variance` form (docs/grammar.md 4.2)
    negative = np.flatnonzero(~free & (np.diag(cov) < 0))
    for i in negative:
        ctx.error(
            (*loc, "covariance", int(i), int(i)),
            f"the variance of a pinned axis may be 0 but not negative, got {cov[i, i]:g} "
            f"({'xyz'[i]} axis)",
        )
    if not symmetric:
        # Which triangle was meant is unknown, so positive definiteness is judged only where
        # every symmetric reading agrees: a free axis's variance <= 0 fails it in all of them.
        if np.any(free & ~(np.diag(cov) > 0)):
            ctx.error((*loc, "covariance"), "covariance must be positive definite")
        return None
    if negative.size:
        return None
    # the rows and columns of pinned axes are dropped, not conditioned on: a coupling written
    # there has no effect, which the user should hear about
    coupled = np.argwhere(~free[:, None] & (cov != 0) & ~np.eye(3, dtype=bool))
    for i, j in coupled[:1]:
        ctx.warn(
            (*loc, "covariance", int(i), int(j)),
            f"the covariance couples the pinned {'xyz'[i]} axis with {'xyz'[j]} "
            f"({cov[i, j]:g}); a pinned axis's row and column are dropped, so this has no effect",
        )
    sub = cov[np.ix_(free, free)]
    try:
        with np.errstate(all="ignore"):  # huge entries overflow: NaN fails below
            eig = np.linalg.eigvalsh(sub)
    except np.linalg.LinAlgError:
        eig = np.array([np.nan])
    if not np.all(eig > 0):
        ctx.error((*loc, "covariance"), "covariance must be positive definite")
        return None
    return sub


def _variance(p: dsl.NormalParams, free: FloatArray, loc: Loc, ctx: Lowering) -> FloatArray | None:
    var = np.broadcast_to(np.asarray(p.variance, float), (3,))
    bad = (var < 0) | (free & (var == 0))  # zero is fine only on a pinned axis
    for i in np.flatnonzero(bad):
        where = (*loc, "variance", int(i)) if isinstance(p.variance, list) else (*loc, "variance")
        # a pinned axis is told what the `covariance` form tells it: 0 is allowed there
        if free[i]:
            message = f"variance must be positive, got {var[i]:g} ({'xyz'[i]} axis)"
        else:
            message = (
                f"the variance of a pinned axis may be 0 but not negative, got {var[i]:g} "
                f"({'xyz'[i]} axis)"
            )
        ctx.error(where, message)
    return None if np.any(bad) else np.diag(var[free])
