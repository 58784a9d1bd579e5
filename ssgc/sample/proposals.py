"""The staged sampler's exact structure proposals (ssgc/sample/staged.py).

Rejection sampling under a structural constraint wastes most candidates when the constraint is
rarely met by chance ("at least 3 stacks", "a stack at least 4 high").  Each proposal here
draws part of the structure from a law other than the grammar's, chosen so that it multiplies
the probability of every tree the constraints accept by one constant: the kept candidates are
still exactly P(T | constraints) (docs/constraints.md, "Rejection, in stages (exact)").

- `count_proposals`: a `repeat` count drawn from its law restricted to a `children` range;
- `forced_rules`: the `independent` rules on the only path to a required node always fire;
- `chain_proposal`: one chain forced to a `longest_chain` bound, kept with probability 1/K.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint
from ssgc.constraints.structural import Children, LongestChain
from ssgc.ir import Grammar, Kind

IntArray = NDArray[np.int64]


def reachers(grammar: Grammar) -> NDArray[np.bool_]:
    """reach[a, b]: a type-b node can descend from a type-a node (through >= 1 rule)."""
    n = len(grammar.types)
    reach = np.zeros((n, n), bool)
    for r in grammar.rules:
        reach[r.parent, r.child] = True
    for k in range(n):  # transitive closure (Warshall), n is small
        reach |= reach[:, [k]] & reach[[k], :]
    return reach


def count_proposals(
    grammar: Grammar, constraints: list[Constraint]
) -> dict[int, tuple[int, int | None]]:
    """`repeat` types whose count can be drawn from its law restricted to a constraint's
    range, without changing which trees the sampler returns or their law.

    A `children` constraint on the one `of` node a tree can have (`single`), with `min` >= 1,
    rejects every tree without that node; if the node is a `repeat` of the counted child
    type, its number of children is its count.  So every accepted tree has the node with a
    count in [min, max], and drawing the count from P(count | min <= count <= max) instead of
    P(count) multiplies the probability of each such tree by the same constant
    1 / P(min <= count <= max): the accepted trees keep the law P(T | constraints), and the
    candidates the count alone would reject are never drawn (docs/constraints.md)."""
    out: dict[int, tuple[int, int | None]] = {}
    for c in constraints:
        if not isinstance(c, Children) or not c.single or c.lo < 1:
            continue
        node = grammar.types[c.of]
        if node.kind != Kind.REPEAT or node.count is None:
            continue
        if c.child is not None and grammar.rules[node.rules[0]].child != c.child:
            continue
        lo, hi = out.get(c.of, (0, None))
        lo = max(lo, c.lo)
        hi = c.hi if hi is None else (hi if c.hi is None else min(hi, c.hi))
        out[c.of] = (lo, hi)
    return out


def forced_rules(grammar: Grammar, constraints: list[Constraint]) -> frozenset[int]:
    """`independent` rules that can be made to fire without changing the law of the trees
    the sampler returns.

    A `children` constraint with `min` >= 1 on a type X of which no tree has two nodes
    (`single`) rejects every tree without an X node.  If X is produced by one rule only, whose
    parent is an `and` (always fires) or an `independent` (fires with probability p), and so on
    up to the root, every accepted tree fires each `independent` rule of that chain exactly
    once: making them fire always multiplies the probability of every accepted tree by the
    same constant 1 / prod(p) (docs/constraints.md)."""
    producers: dict[int, list[int]] = {}
    for rid, r in enumerate(grammar.rules):
        producers.setdefault(r.child, []).append(rid)
    out: set[int] = set()
    for c in constraints:
        if not isinstance(c, Children) or not c.single or c.lo < 1:
            continue
        t = c.of
        while t != grammar.root and len(producers.get(t, [])) == 1:
            rid = producers[t][0]
            parent = grammar.types[grammar.rules[rid].parent]
            if parent.kind == Kind.INDEPENDENT:
                if not parent.probs[list(parent.rules).index(rid)] > 0:
                    break
                out.add(rid)
            elif parent.kind != Kind.AND:
                break
            t = grammar.rules[rid].parent
    return frozenset(out)


@dataclass(frozen=True)
class ChainProposal:
    """Draw the structure with one chain of `chain_type` nodes at least `length` long.

    Under the `repeat` node (type `repeat`, rule `root_rule` makes the chain roots), the
    count n is drawn size-biased (weight n, on top of its restriction by `count_proposals`),
    one of the n roots J is picked uniformly, and J and the next `length` - 2 nodes of its
    chain choose the self rule `self_rule` (index `self_index` among the `or` type's rules);
    everything else is drawn from the grammar.  A candidate is then kept with probability
    1/K, K the number of its chains at least `length` long (`chain_proposal` says when and
    docs/constraints.md why the kept candidates follow the grammar's law given the
    constraint)."""

    constraint: str
    repeat: int
    root_rule: int
    chain_type: int
    self_rule: int
    self_index: int
    length: int

    def must(self, force: IntArray) -> tuple[NDArray[np.bool_], int, int]:
        return force > 0, self.chain_type, self.self_index

    def child_force(
        self, force: IntArray, at: IntArray, rid: IntArray, rng: np.random.Generator
    ) -> IntArray:
        """The forced links left to each child: one less than its parent's along the self
        rule, `length` - 1 for the one chain root picked among each `repeat` node's roots."""
        out = np.where(rid == self.self_rule, np.maximum(force[at] - 1, 0), 0)
        new = np.flatnonzero(rid == self.root_rule)
        if len(new):
            par = at[new]  # sorted: a repeat node's children are consecutive
            starts = np.flatnonzero(np.r_[True, par[1:] != par[:-1]])
            sizes = np.diff(np.r_[starts, len(par)])
            picked = starts + (rng.random(len(starts)) * sizes).astype(np.int64)
            out[new[picked]] = self.length - 1
        return out


def chain_proposal(
    grammar: Grammar,
    constraints: list[Constraint],
    counts: dict[int, tuple[int, int | None]],
) -> ChainProposal | None:
    """The chain proposal for the first `longest_chain` constraint where it is exact.

    It needs: `min` = m >= 2 on a chain type X of kind `or` with one self rule X -> X of
    probability p > 0; X produced otherwise only by a `repeat` node R whose count is drawn
    from a restricted law (`count_proposals`: every accepted tree has exactly one R node,
    n >= 1 roots); no other rule of X leads back to X (so chains are paths from R's
    children, one per root) and none has a nesting-bounded child; and m <= X's
    `max_nesting` (so the m - 1 forced choices are never blocked: each has probability p).
    Then the proposal's probability of a tree ω is P(ω) K(ω) / (Z p^(m-1)) with Z the
    size-biased count law's normaliser, and keeping ω with probability 1/K makes it a
    constant times P(ω) on every tree with K >= 1 (docs/constraints.md)."""
    tb = grammar.tables
    reach = reachers(grammar)
    for c in constraints:
        if not isinstance(c, LongestChain) or c.lo < 2:
            continue
        x = c.type_id
        node = grammar.types[x]
        if node.kind != Kind.OR:
            continue
        own = [k for k, r in enumerate(node.rules) if grammar.rules[r].child == x]
        producers = [rid for rid, r in enumerate(grammar.rules) if r.child == x and r.parent != x]
        if len(own) != 1 or len(producers) != 1 or not node.probs[own[0]] > 0:
            continue
        repeat = grammar.rules[producers[0]].parent
        if repeat not in counts or grammar.types[repeat].kind != Kind.REPEAT:
            continue
        others = [grammar.rules[r].child for k, r in enumerate(node.rules) if k != own[0]]
        if any(reach[o, x] or o == x or tb.nesting_slot[o] >= 0 for o in others):
            continue
        slot = tb.nesting_slot[x]
        if slot >= 0 and c.lo > tb.nesting_max[slot]:
            continue
        return ChainProposal(
            c.name, repeat, producers[0], x, int(node.rules[own[0]]), own[0], int(c.lo)
        )
    return None
