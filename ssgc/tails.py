"""How rare a physical finding is among the objects of real scenes: the exponential tails
`ssg explain` turns overlaps, floating and going through a container into nats with
(docs/explain.md, "Overlaps" and "Support, floor and walls").

A tail belongs to the constraint whose findings it calibrates: a `non_penetration` constraint's
`tail:`, an `inside_box` (with `geometry: true`) constraint's `floating:` and `outside:`
(docs/constraints.md).  `ssg fit` measures them on the dataset (`ssgc.fit.tails`).  A grammar
that gives none gets the defaults below, measured once on the real sink scenes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TOLERANCE = 0.01  # m: closer than this to the floor or to a dish below counts as resting


@dataclass(frozen=True)
class Tail:
    """P(D >= d) = rate * exp(-excess / mean): `rate` is the share of a real scene's objects
    with such a finding, `mean` (m) the mean excess of their findings (for overlaps, the
    summed depth; for floating and going outside, the distance beyond TOLERANCE)."""

    rate: float
    mean: float  # m

    def nats(self, excess: float | np.ndarray) -> float | np.ndarray:
        """-log P(D >= d) for a finding `excess` metres beyond where the tail starts."""
        return -np.log(self.rate) + np.asarray(excess) / self.mean


# The defaults, measured on the real sink scenes 0-39 (169 dishes), each scene's best parse
# under the fitted sink_detailed grammar with its dishes as hollow solids of revolution
# (`revolve`); docs/explain.md ("Overlaps", "Support, floor and walls") and docs/perturbation.md
# ("With hollow dishes"):
# - overlaps: 34 of 169 dishes overlap a dish the tree does not relate to them, by 1.13 cm on
#   average (summed per dish);
# - floating: 15 dishes float by more than 1 cm (mean excess 4.1 mm, floored at 1 cm);
# - outside: none goes through the floor or a wall (counted as one in 169, mean floored at 1 cm).
OVERLAP = Tail(rate=34 / 169, mean=0.0113)
FLOATING = Tail(rate=15 / 169, mean=TOLERANCE)
OUTSIDE = Tail(rate=1 / 169, mean=TOLERANCE)
