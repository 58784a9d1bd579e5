"""What the MCMC and projection methods share: their outcome (with per-scene chain
statistics), the exact final check, and the tally of what each constraint rejected."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint
from ssgc.ir import Grammar
from ssgc.sample.staged import Outcome
from ssgc.score import score_trees
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]


@dataclass
class ChainOutcome(Outcome):
    """An `Outcome` whose kept scenes also carry their chain's statistics (acceptance rates,
    step sizes, ...), one array per statistic, in scene order."""

    chain: dict[str, FloatArray] = field(default_factory=dict)


class Judge:
    """Counts, per constraint, the candidates it judged and rejected, and the closest miss."""

    def __init__(self, constraints: list[Constraint]) -> None:
        self.constraints = constraints
        self.evaluated = {c.name: 0 for c in constraints}
        self.rejected = {c.name: 0 for c in constraints}
        self.best = {c.name: -np.inf for c in constraints}

    def margins(
        self, trees: Trees, kinds: tuple[str, ...] = ("structure", "pose")
    ) -> dict[str, FloatArray]:
        return {c.name: c.margin(trees) for c in self.constraints if c.kind in kinds}

    def judge(self, margins: dict[str, FloatArray], alive: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Which of the `alive` trees satisfy every constraint in `margins`; counted."""
        ok = alive.copy()
        for name, m in margins.items():
            bad = alive & ~(m >= 0)
            self.evaluated[name] += int(alive.sum())
            self.rejected[name] += int(bad.sum())
            if bad.any():
                self.best[name] = max(self.best[name], float(np.max(m[bad])))
            ok &= m >= 0
        return ok

    def outcome(
        self,
        grammar: Grammar,
        trees: Trees,
        keep: NDArray[np.bool_],
        drawn: int,
        chain: dict[str, FloatArray],
    ) -> ChainOutcome:
        """The kept trees, with every constraint's margin evaluated on them afresh."""
        kept = trees.select(keep)
        margins = {c.name: c.margin(kept) for c in self.constraints}
        return ChainOutcome(
            trees=kept,
            logp=score_trees(grammar, kept),
            margins=margins,
            evaluated=self.evaluated,
            rejected=self.rejected,
            best=self.best,
            drawn=drawn,
            chain={k: np.asarray(v, float)[keep] for k, v in chain.items()},
        )
