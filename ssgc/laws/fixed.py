"""Fixed offsets (`same`, `offset`): point masses in the parent's frame.

A fixed part puts the child exactly at its offset from the parent, so its log-density is 0
there and -inf elsewhere (within `POS_TOL` / `ROT_TOL`: poses of fixed children come out of
frame arithmetic that rounds).  It has nothing to fit.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ssgc.geometry import IDENTITY_QUAT, quat_angle
from ssgc.laws.base import (
    POS_TOL,
    ROT_TOL,
    Columns,
    FloatArray,
    Frame,
    Loc,
    Lowering,
    RotationLaw,
    TranslationLaw,
    frozen,
    register,
)


class _PointMass:
    """A fixed part's mode is its offset, where its log-density is 0."""

    offset: FloatArray

    def mode(self) -> FloatArray:
        return self.offset

    def supremum(self) -> float:
        return 0.0

    @property
    def point(self) -> FloatArray:
        return self.offset


@register
class FixedTranslation(_PointMass, TranslationLaw):
    keys: ClassVar[dict[str, Frame]] = {"same": Frame.PARENT, "offset": Frame.PARENT}
    columns: ClassVar[dict[str, tuple[int, ...]]] = {"offset": (3,)}

    offset: FloatArray

    @classmethod
    def lower(cls, params: Any, key: str, loc: Loc, ctx: Lowering) -> FixedTranslation:
        offset = np.zeros(3) if key == "same" else params
        return cls(key=key, frame=Frame.PARENT, path=loc, offset=frozen(offset))

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        return np.broadcast_to(self.offset, (n, 3)), np.zeros(n)

    def row(self) -> dict[str, Any]:
        return {"offset": self.offset}

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        ok = np.all(np.abs(u - cols["offset"]) <= POS_TOL, axis=1)
        return np.where(ok, 0.0, -np.inf)

    def describe(self) -> str:
        return "same" if not np.any(self.offset) else f"offset {np.round(self.offset, 4).tolist()}"

    def describe_violation(self, u: FloatArray) -> str:
        off = u - self.offset
        a = int(np.argmax(np.abs(off)))
        return f"fixed offset off by {off[a]:+.3g} m"


@register
class FixedRotation(_PointMass, RotationLaw):
    keys: ClassVar[dict[str, Frame]] = {"same": Frame.PARENT, "offset": Frame.PARENT}
    columns: ClassVar[dict[str, tuple[int, ...]]] = {"offset": (4,)}

    offset: FloatArray  # unit quaternion, wxyz

    @classmethod
    def lower(cls, params: Any, key: str, loc: Loc, ctx: Lowering) -> FixedRotation:
        q = IDENTITY_QUAT if key == "same" else ctx.orientation(params, loc)
        return cls(key=key, frame=Frame.PARENT, path=loc, offset=frozen(q))

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        return np.broadcast_to(self.offset, (n, 4)), np.zeros(n)

    def row(self) -> dict[str, Any]:
        return {"offset": self.offset}

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        return np.where(quat_angle(u, cols["offset"]) <= ROT_TOL, 0.0, -np.inf)

    def describe_violation(self, u: FloatArray) -> str:
        angle = float(np.degrees(quat_angle(u, self.offset)))
        return f"fixed rotation off by {angle:.3g}°"

    def describe(self) -> str:
        if self.offset[0] >= 1 - 1e-12:
            return "same"
        return f"offset {np.round(self.offset, 4).tolist()}"
