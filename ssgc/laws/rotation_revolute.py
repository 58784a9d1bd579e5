"""Revolute rotations (`revolute`): the parent's rotation times a turn about a fixed axis by an
angle uniform on [min, max] (radians, modulo 2π), a density w.r.t. the angle.

Like a box, the range is a support, so `ssg fit` keeps it as written, and like a box's faces
its ends hold to `ROT_TOL` beyond: a range narrower than `MIN_WIDTH` would carry more than 2%
too much mass, and is refused (docs/grammar.md 4.6).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ssgc import dsl
from ssgc.distributions.uniform import UniformRevolute
from ssgc.geometry import axis_angle_to_quat
from ssgc.laws.base import (
    MIN_WIDTH,
    ROT_TOL,
    Columns,
    Context,
    Deviation,
    FloatArray,
    Frame,
    Loc,
    Lowering,
    RotationLaw,
    frozen,
    register,
)


@register
class RevoluteRotation(RotationLaw):
    keys: ClassVar[dict[str, Frame]] = {"revolute": Frame.PARENT}
    columns: ClassVar[dict[str, tuple[int, ...]]] = {
        "axis": (3,),
        "lo": (),
        "hi": (),
        "lognorm": (),
    }

    axis: FloatArray  # unit
    revolute: UniformRevolute

    @classmethod
    def lower(
        cls, p: dsl.RevoluteParams, key: str, loc: Loc, ctx: Lowering
    ) -> RevoluteRotation | None:
        """The axis and the range are independent: both are checked before giving up."""
        axis = np.asarray(p.axis, float)
        scale = np.abs(axis).max()
        if scale == 0:  # the whole vector is wrong: at its key, as every list is (SourceMap)
            ctx.error((*loc, "axis"), "revolute axis must be nonzero")
        ranged = _range_ok(p, loc, ctx)
        if scale == 0 or not ranged:
            return None
        axis = axis / scale  # so that the norm neither overflows nor underflows
        return cls(
            key=key,
            frame=Frame.PARENT,
            path=loc,
            fixed=p.fixed,
            axis=frozen(axis / np.linalg.norm(axis)),
            revolute=UniformRevolute(p.min, min(p.max, p.min + 2 * np.pi)),
        )

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        theta = self.revolute.sample(rng, n)
        return axis_angle_to_quat(self.axis, theta), self.revolute.log_prob(theta)

    def row(self) -> dict[str, Any]:
        lo, hi = self.revolute.lo, self.revolute.hi
        return {"axis": self.axis, "lo": lo, "hi": hi, "lognorm": float(np.log(hi - lo))}

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        """A rotation about `axis` by an angle in [lo, hi] (mod 2π) has density 1/(hi - lo)."""
        axis, lo = cols["axis"], cols["lo"]
        along = np.sum(u[:, 1:] * axis, axis=1)
        off_axis = np.linalg.norm(u[:, 1:] - along[:, None] * axis, axis=1)
        theta = 2.0 * np.arctan2(along, u[:, 0])
        on_axis = 2.0 * np.arcsin(np.minimum(off_axis, 1.0)) <= ROT_TOL
        rel_angle = np.mod(theta - lo, 2.0 * np.pi)
        width = cols["hi"] - lo
        in_range = (rel_angle <= width + ROT_TOL) | (rel_angle >= 2.0 * np.pi - ROT_TOL)
        return np.where(on_axis & in_range, -cols["lognorm"], -np.inf)

    def mode(self) -> FloatArray:
        return axis_angle_to_quat(self.axis, 0.5 * (self.revolute.lo + self.revolute.hi))

    def supremum(self) -> float:
        return -float(np.log(self.revolute.hi - self.revolute.lo))

    def describe_deviation(self, u: FloatArray, log_prob: float, ctx: Context) -> Deviation:
        return Deviation("rotation about its rule's axis, every allowed angle equally likely")

    def describe_violation(self, u: FloatArray) -> str:
        return "rotation outside the rule's revolute range or axis"

    def describe(self) -> str:
        return (
            f"revolute axis {np.round(self.axis, 3).tolist()} "
            f"[{self.revolute.lo:.3g}, {self.revolute.hi:.3g}]"
        )


def _range_ok(p: dsl.RevoluteParams, loc: Loc, ctx: Lowering) -> bool:
    """Whether [min, max] is a range the density can hold: ordered, at most 2π, and not
    narrower than `MIN_WIDTH` (each failure reported)."""
    width = p.max - p.min
    if not p.max > p.min:
        ctx.error((*loc, "max"), f"revolute max must be > min, got [{p.min:g}, {p.max:g}]")
        return False
    if width > 2 * np.pi + 1e-9:
        ctx.error((*loc, "max"), f"revolute range exceeds 2π ({width:g} rad)")
        return False
    if width < MIN_WIDTH:  # `density` would give it more than 1.02 of mass
        ctx.error(
            (*loc, "max"),
            f"revolute range is {width:g} rad wide, narrower than {MIN_WIDTH:g} rad: angles "
            f"within {ROT_TOL:g} rad beyond its ends count as inside, which would give it a "
            f"mass of {(width + 2 * ROT_TOL) / width:.3g}, not 1; use a fixed rotation "
            "`offset`, or widen it",
        )
        return False
    return True
