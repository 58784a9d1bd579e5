"""The uniform (Haar) rotation (`uniform`): every rotation equally likely, whatever the parent.

Its density w.r.t. the SO(3) volume measure (total volume π²) is 1/π² everywhere, so it has no
mode, its supremum is its value, and there is nothing to fit.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ssgc.distributions.uniform import UNIFORM_SO3_LOG_DENSITY
from ssgc.geometry import random_quat
from ssgc.laws.base import (
    Columns,
    Context,
    Deviation,
    FloatArray,
    Frame,
    Loc,
    Lowering,
    RotationLaw,
    register,
)


@register
class UniformRotation(RotationLaw):
    keys: ClassVar[dict[str, Frame]] = {"uniform": Frame.WORLD}

    @classmethod
    def lower(cls, params: Any, key: str, loc: Loc, ctx: Lowering) -> UniformRotation:
        return cls(key=key, frame=Frame.WORLD, path=loc)

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        return random_quat(rng, n), np.full(n, UNIFORM_SO3_LOG_DENSITY)

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        return np.full(len(u), UNIFORM_SO3_LOG_DENSITY)

    def supremum(self) -> float:
        return UNIFORM_SO3_LOG_DENSITY

    def describe_deviation(self, u: FloatArray, log_prob: float, ctx: Context) -> Deviation:
        return Deviation("rotation: any rotation is equally likely")
