"""Structural constraints: functions of a tree's types and parent links only (thesis 2.4).

They never read poses, so the structure sampler evaluates them on trees whose poses have not
been drawn yet.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ssgc.constraints.base import Constraint, FloatArray, IntArray, NodeBatch, range_margin


@dataclass(frozen=True)
class Count(Constraint):
    """Number of nodes of `type_id` in the tree, within [lo, hi]."""

    type_id: int = 0
    lo: int = 0
    hi: int | None = None
    kind: ClassVar[str] = "structure"
    word: ClassVar[str] = "count"

    def margin(self, batch: NodeBatch) -> FloatArray:
        c = np.bincount(batch.scene[batch.type == self.type_id], minlength=batch.n_scenes)
        return range_margin(c, self.lo, self.hi)


@dataclass(frozen=True)
class LongestChain(Constraint):
    """Longest parent-to-child run of nodes of `type_id` (a stack's height), within [lo, hi]."""

    type_id: int = 0
    lo: int = 0
    hi: int | None = None
    kind: ClassVar[str] = "structure"
    word: ClassVar[str] = "longest_chain"

    def margin(self, batch: NodeBatch) -> FloatArray:
        run = chain_runs(batch.type, batch.parent, self.type_id)
        longest = np.zeros(batch.n_scenes, np.int64)
        np.maximum.at(longest, batch.scene, run)
        return range_margin(longest, self.lo, self.hi)


def chain_runs(type_: IntArray, parent: IntArray, type_id: int) -> IntArray:
    """Per node: length of the run of `type_id` nodes ending at it (0 for other types).

    Each pass lengthens every run by one link, so the loop runs as often as the longest run.
    """
    is_t = type_ == type_id
    idx = np.flatnonzero(is_t & (parent >= 0))
    idx = idx[is_t[parent[idx]]]  # nodes whose parent continues the run
    par = parent[idx]
    run = is_t.astype(np.int64)
    while len(idx):
        new = run[par] + 1
        if np.array_equal(new, run[idx]):
            break
        run[idx] = new
    return run


@dataclass(frozen=True)
class Children(Constraint):
    """Children produced by the nodes of type `of` (optionally only of type `child`), summed
    over the tree, within [lo, hi]: with one `of` node, its number of children; none, zero."""

    of: int = 0
    child: int | None = None
    lo: int = 0
    hi: int | None = None
    single: bool = False  # no tree of the grammar has two `of` nodes
    kind: ClassVar[str] = "structure"
    word: ClassVar[str] = "children"

    def margin(self, batch: NodeBatch) -> FloatArray:
        has = batch.parent >= 0
        sel = has & (batch.type[np.maximum(batch.parent, 0)] == self.of)
        if self.child is not None:
            sel &= batch.type == self.child
        c = np.bincount(batch.scene[sel], minlength=batch.n_scenes)
        return range_margin(c, self.lo, self.hi)
