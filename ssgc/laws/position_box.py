"""Uniform translations on an axis-aligned box (`world_box`, `world_box_offset`).

An axis with min == max is pinned (a point mass).  A box is a support, not a shape: its
maximum-likelihood value is the hull of the data, which would make every scene slightly
outside it impossible, so `ssg fit` keeps it as written (docs/fitting.md).

The density holds up to `POS_TOL` outside each face, as a pin does: frame arithmetic and
rounded data put an object lying on a face a round-off outside it.  A free axis w wide then
carries mass (w + 2 POS_TOL) / w, so one narrower than `MIN_WIDTH` (2% too much) is refused
(docs/grammar.md 4.2).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ssgc import dsl
from ssgc.distributions.uniform import UniformBox
from ssgc.laws.base import (
    MIN_WIDTH,
    POS_TOL,
    Columns,
    Context,
    Deviation,
    FloatArray,
    Frame,
    Loc,
    Lowering,
    TranslationLaw,
    register,
)


def narrow_box(width: float, axis: str) -> str:
    """Why a free box axis `width` wide is refused (`MIN_WIDTH`)."""
    return (
        f"box is {width:g} m wide on {axis}, narrower than {MIN_WIDTH:g} m: positions within "
        f"{POS_TOL:g} m outside a face count as inside, which would give it a mass of "
        f"{(width + 2 * POS_TOL) / width:.3g}, not 1; pin the axis (min == max) or widen it"
    )


@register
class BoxTranslation(TranslationLaw):
    keys: ClassVar[dict[str, Frame]] = {
        "world_box": Frame.WORLD,
        "world_box_offset": Frame.WORLD_OFFSET,
    }
    columns: ClassVar[dict[str, tuple[int, ...]]] = {"lo": (3,), "hi": (3,), "lognorm": ()}

    box: UniformBox

    @classmethod
    def lower(cls, p: dsl.BoxParams, key: str, loc: Loc, ctx: Lowering) -> BoxTranslation | None:
        """Each axis is checked on its own, so one run names every bad axis."""
        lo, hi = np.asarray(p.min, float), np.asarray(p.max, float)
        inverted = np.flatnonzero(hi < lo)
        for i in inverted:
            ctx.error((*loc, "max", int(i)), f"box max must be >= min, got {hi[i]:g} < {lo[i]:g}")
        with np.errstate(over="ignore"):
            too_wide = not np.all(np.isfinite(hi - lo))
        if too_wide:  # the density 1/volume would be 0
            ctx.error((*loc, "max"), "box is too large (its width overflows)")
        narrow = np.flatnonzero((hi > lo) & (hi - lo < MIN_WIDTH))
        for i in narrow:  # `density` would give it more than 1.02 of mass on that axis
            ctx.error((*loc, "max", int(i)), narrow_box(float(hi[i] - lo[i]), "xyz"[i]))
        if inverted.size or too_wide or narrow.size:
            return None
        return cls(key=key, frame=cls.keys[key], path=loc, fixed=p.fixed, box=UniformBox(lo, hi))

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        local = self.box.sample(rng, n)
        return local, self.box.log_prob(local)

    def row(self) -> dict[str, Any]:
        return {"lo": self.box.lo, "hi": self.box.hi, "lognorm": -self.box.log_density}

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        inside = (u >= cols["lo"] - POS_TOL) & (u <= cols["hi"] + POS_TOL)
        return np.where(np.all(inside, axis=1), -cols["lognorm"], -np.inf)

    def mode(self) -> FloatArray:
        return 0.5 * (self.box.lo + self.box.hi)

    def supremum(self) -> float:
        return self.box.log_density

    def describe_deviation(self, u: FloatArray, log_prob: float, ctx: Context) -> Deviation:
        return Deviation(
            f"position inside the box where {ctx.parent} places it (every point equally likely)"
        )

    def describe_violation(self, u: FloatArray) -> str:
        out = np.maximum(self.box.lo - u, u - self.box.hi)
        a = int(np.argmax(out))
        return f"outside its box on {'xyz'[a]} by {out[a]:.3g} m"

    def describe(self) -> str:
        lo, hi = np.round(self.box.lo, 4).tolist(), np.round(self.box.hi, 4).tolist()
        return f"{self.key} [{lo}, {hi}]"
