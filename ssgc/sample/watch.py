"""Structural margins followed level by level while the staged sampler grows structure.

The structure stage of ssgc/sample/staged.py grows only the part of each candidate that a
structural constraint depends on (`relevant_types`), and `Watch` keeps every `count`,
`children` and `longest_chain` statistic up to date as levels are added, so a candidate is
rejected as soon as its fate is sealed instead of once its whole tree is drawn.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint, range_margin
from ssgc.constraints.structural import Children, Count, LongestChain
from ssgc.ir import Grammar
from ssgc.sample.proposals import ChainProposal, reachers

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


class Tally(Protocol):
    """Where the watch reports the margins it decides (the sampler's per-constraint counts)."""

    def count(self, name: str, margin: FloatArray) -> None: ...


def relevant_types(grammar: Grammar, constraints: list[Constraint]) -> NDArray[np.bool_]:
    """Types whose expansion can change a structural margin: the types a structural
    constraint names, and every type from which one of them can descend."""
    reach = reachers(grammar)
    out = np.zeros(len(grammar.types), bool)
    for c in constraints:
        if c.kind == "structure":
            named = _named(c) if is_watched(c) else np.flatnonzero(c.reads(len(grammar.types)))
            for t in named:
                out[t] = True
                out |= reach[:, t]
    return out


def is_watched(c: Constraint) -> bool:
    """Structural kinds whose statistic `Watch` keeps level by level; other (registered)
    structural kinds are judged once the structure stage is over."""
    return isinstance(c, Count | LongestChain | Children)


def _named(c: Constraint) -> list[int]:
    return [
        int(v) for v in (getattr(c, a, None) for a in ("type_id", "of", "child")) if v is not None
    ]


class Watch:
    """Structural margins kept up to date level by level during the structure stage, so a
    candidate is rejected as soon as its fate is sealed: a bound `max` is exceeded (counts
    only grow), or no node that could still change the statistic is left to expand."""

    def __init__(
        self,
        grammar: Grammar,
        constraints: list[Constraint],
        n: int,
        stats: Tally,
        chain: ChainProposal | None = None,
    ):
        reach = reachers(grammar)
        self.stats = stats
        self.chain = chain
        self.tall = np.zeros(n, np.int64)  # chains reaching the proposal's length (K)
        self.alive = np.ones(n, bool)
        self.items = []
        for c in constraints:
            if not is_watched(c):
                continue
            if isinstance(c, Children):
                opens = reach[:, c.of].copy()
                opens[c.of] = True
            else:
                opens = reach[:, c.type_id].copy()
            self.items.append(
                {
                    "c": c,
                    "opens": opens,
                    "stat": np.zeros(n, np.int64),
                    "undecided": np.arange(n),
                }
            )
        self.f_type = np.zeros(0, np.int64)
        self.runs: dict[int, IntArray] = {}

    def start(self, f_type: IntArray, f_scene: IntArray) -> None:
        self.f_type = f_type
        for it in self.items:
            c = it["c"]
            if isinstance(c, Count | LongestChain):
                hit = f_type == c.type_id
                np.add.at(it["stat"], f_scene[hit], 1)
                if isinstance(c, LongestChain):
                    self.runs[id(c)] = hit.astype(np.int64)
        self.check(f_type, f_scene)

    def select(self, live: NDArray[np.bool_]) -> None:
        self.f_type = self.f_type[live]
        for key in self.runs:
            self.runs[key] = self.runs[key][live]

    def step(self, at: IntArray, c_type: IntArray, c_scene: IntArray, next_type: IntArray) -> None:
        p_type = self.f_type[at]
        for it in self.items:
            c = it["c"]
            if isinstance(c, Count):
                it["stat"] += np.bincount(c_scene[c_type == c.type_id], minlength=len(self.alive))
            elif isinstance(c, Children):
                hit = p_type == c.of
                if c.child is not None:
                    hit &= c_type == c.child
                it["stat"] += np.bincount(c_scene[hit], minlength=len(self.alive))
            else:
                is_t = c_type == c.type_id
                run = np.where(is_t, np.where(p_type == c.type_id, self.runs[id(c)][at] + 1, 1), 0)
                self.runs[id(c)] = run
                np.maximum.at(it["stat"], c_scene[is_t], run[is_t])
                if self.chain is not None and self.chain.constraint == c.name:
                    self.tall += np.bincount(
                        c_scene[is_t & (run == self.chain.length)], minlength=len(self.alive)
                    )
        self.f_type = c_type
        self.check(next_type, c_scene)

    def check(self, f_type: IntArray, f_scene: IntArray) -> None:
        """Decide the candidates whose statistic is sealed; only undecided ones are looked at,
        so a level costs what its frontier and the open candidates cost."""
        n = len(self.alive)
        for it in self.items:
            idx = it["undecided"]
            idx = idx[self.alive[idx]]
            if not len(idx):
                it["undecided"] = idx
                continue
            c, stat = it["c"], it["stat"][idx]
            still_open = (np.bincount(f_scene[it["opens"][f_type]], minlength=n) > 0)[idx]
            ready = ~still_open
            if c.hi is not None:
                ready |= stat > c.hi
            self.decide(it, idx[ready], range_margin(stat[ready], c.lo, c.hi))
            it["undecided"] = idx[~ready]

    def finish(self) -> None:
        for it in self.items:
            idx = it["undecided"]
            idx = idx[self.alive[idx]]
            c = it["c"]
            self.decide(it, idx, range_margin(it["stat"][idx], c.lo, c.hi))
            it["undecided"] = idx[:0]

    def decide(self, it: dict, idx: IntArray, margin: FloatArray) -> None:  # type: ignore[type-arg]
        """Candidates `idx` are decided by `it`'s constraint, with these margins."""
        self.alive[idx[margin < 0]] = False
        self.stats.count(it["c"].name, margin)
