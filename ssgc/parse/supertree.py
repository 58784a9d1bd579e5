"""The supertree and its equivalent sets (thesis 3.3).

The supertree holds every node any tree of the grammar could contain: each node expands all of
its rules (a `repeat` into as many copies as its largest count), down to the `max_nesting`
bounds — rules blocked by a bound are simply absent, exactly as in the sampler and the scorer.
So are rules that can never fire: an `or` rule of weight 0 and an `independent` rule of
probability 0.  An `or` whose every rule of positive weight is blocked therefore makes nothing,
with probability 1, as one whose every rule is blocked (docs/grammar.md 3.4).  Any parse tree
is a subtree of it.

Equivalent sets are the connected groups of supertree nodes joined by rules whose translation
and rotation are both fixed: their poses follow from one pose (the set's top node) and a fixed
offset per node.  `always_observed` marks the sets that cannot be active without an observed
node — their poses can only come from observations (thesis 3.4.3 / 3.5, "observability").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import SsgError
from ssgc.geometry import quat_multiply, quat_rotate
from ssgc.ir import Grammar, Kind
from ssgc.node_states import child_states, root_state

IntArray = NDArray[np.int64]
MAX_SUPERTREE_NODES = 200_000


@dataclass(frozen=True)
class Supertree:
    type: IntArray  # (S,) node type
    parent: IntArray  # (S,) parent node, -1 for the root; parents come before children
    rule: IntArray  # (S,) producing rule id, -1 for the root
    copy: IntArray  # (S,) index among the copies of a `repeat` rule (0 otherwise)
    children: tuple[tuple[int, ...], ...]  # per node, its children in rule order
    set_of: IntArray  # (S,) equivalent set of each node
    set_top: IntArray  # (E,) top node of each set (the only node entered from outside)
    offset_xyz: NDArray[np.float64]  # (S, 3) node position in its set top's frame
    offset_quat: NDArray[np.float64]  # (S, 4) node rotation relative to its set top
    always_observed: NDArray[np.bool_]  # (E,)

    def __len__(self) -> int:
        return int(self.type.shape[0])

    @property
    def n_sets(self) -> int:
        return int(self.set_top.shape[0])


def build_supertree(grammar: Grammar) -> Supertree:
    types, parents, rules, copies = [grammar.root], [-1], [-1], [0]
    states = [root_state(grammar)]
    children: list[list[int]] = [[]]
    i = 0
    while i < len(types):  # breadth first, so parents precede children
        node = grammar.types[types[i]]
        n_copies = node.count.largest if node.kind == Kind.REPEAT and node.count else 1
        for rid, state in child_states(grammar, states[i]):
            for k in range(n_copies):
                children[i].append(len(types))
                types.append(state[0])
                parents.append(i)
                rules.append(rid)
                copies.append(k)
                states.append(state)
                children.append([])
        if len(types) > MAX_SUPERTREE_NODES:
            raise SsgError.single(
                f"the grammar's supertree (every node a tree of it can hold) has more than "
                f"{MAX_SUPERTREE_NODES:,} nodes, more than the parser builds; lower the `max` "
                "of its count laws or its `max_nesting` (ssg inspect counts the supertree)",
                grammar.file or None,
            )
        i += 1
    type_a = np.asarray(types, np.int64)
    parent_a = np.asarray(parents, np.int64)
    rule_a = np.asarray(rules, np.int64)
    set_of, set_top, off_xyz, off_quat = _equivalent_sets(grammar, parent_a, rule_a)
    observed = _always_observed(grammar, type_a, rule_a, children, set_of, set_top)
    return Supertree(
        type=type_a,
        parent=parent_a,
        rule=rule_a,
        copy=np.asarray(copies, np.int64),
        children=tuple(tuple(c) for c in children),
        set_of=set_of,
        set_top=set_top,
        offset_xyz=off_xyz,
        offset_quat=off_quat,
        always_observed=observed,
    )


def is_fixed_rule(grammar: Grammar, rule_id: int) -> bool:
    """A rule that places its child at a fixed offset from the parent (pose fully determined)."""
    return bool(grammar.tables.point[rule_id])


def _equivalent_sets(grammar: Grammar, parent: IntArray, rule: IntArray):  # type: ignore[no-untyped-def]
    """Sets joined by fixed rules, and each node's pose offset from its set's top node."""
    n = len(parent)
    set_of = np.full(n, -1, np.int64)
    off_xyz = np.zeros((n, 3))
    off_quat = np.tile([1.0, 0, 0, 0], (n, 1))
    tops: list[int] = []
    tb = grammar.tables
    for i in range(n):  # parents first: a fixed child joins its parent's set
        p = parent[i]
        if p >= 0 and is_fixed_rule(grammar, int(rule[i])):
            set_of[i] = set_of[p]
            off_xyz[i] = off_xyz[p] + quat_rotate(off_quat[p], tb.point_xyz[rule[i]])
            off_quat[i] = quat_multiply(off_quat[p], tb.point_quat[rule[i]])
        else:
            set_of[i] = len(tops)
            tops.append(i)
    return set_of, np.asarray(tops, np.int64), off_xyz, off_quat


def _always_observed(
    grammar: Grammar,
    types: IntArray,
    rule: IntArray,
    children: list[list[int]],
    set_of: IntArray,
    set_top: IntArray,
) -> NDArray[np.bool_]:
    """Whether every way of activating a set includes one of its observed nodes.

    must(n): an active n forces an observed node of n's set to be active: n cannot hold
    nothing (`NodeType.can_hold_nothing`) when its children outside the set count as holding
    nothing.  Observed: yes.  AND: some in-set child must.  OR: every child is in the set and
    must.  A `repeat` whose count cannot be 0, or an `independent` rule with p = 1, behaves
    like an AND child.  Anything else may stop without an observed node.
    """
    must = np.zeros(len(types), bool)
    for i in range(len(types) - 1, -1, -1):  # children before parents
        # a child outside the set, or one that need not hold an observed node, may hold none
        kids = [
            (grammar.rules[rule[c]].index, not (set_of[c] == set_of[i] and must[c]))
            for c in children[i]
        ]
        must[i] = not grammar.types[types[i]].can_hold_nothing(kids)
    return must[set_top]


def hideable_nodes(grammar: Grammar, st: Supertree) -> NDArray[np.bool_]:
    """Per supertree node, whether it can be in a tree with no observed node at or below it.

    Such a node is unseen there: its pose is integrated out of the parse score
    (`ssgc.score`), so the parser lets it go unplaced (`ssgc.parse.posed`) and the bound never
    counts its terms inside its parent's (`ssgc.parse.bound`).  The supertree holds only the
    rules that can fire at each node (max_nesting, weights of 0), so this is exact where the
    scorer's per-type `_maybe_unseen` may say yes too often (`NodeType.can_hold_nothing`).
    """
    hide = np.zeros(len(st), bool)
    for i in range(len(st) - 1, -1, -1):  # children before parents
        kids = [(grammar.rules[st.rule[c]].index, bool(hide[c])) for c in st.children[i]]
        hide[i] = grammar.types[st.type[i]].can_hold_nothing(kids)
    return hide


def or_weight(weight: float, present: float) -> float:
    """An `or` rule's probability at a node: its weight over the weights of the rules present
    there (max_nesting leaves the blocked ones out, and the supertree the rules of weight 0).
    A rule of weight 0 gets 0, never a division by zero (which stopped `ssg parse`)."""
    return weight / present if present > 0 else 0.0


def max_observed(grammar: Grammar, st: Supertree) -> NDArray[np.int64]:
    """The most nodes of each type one tree can hold (0 for unobserved types).

    A node holds itself plus, for `and`, `independent` and `repeat` nodes, everything its
    supertree children can hold (every rule, every copy), and for `or` nodes the most any one
    child can.  A scene with more objects of a type than this, or more objects in all than the
    most the root can hold, has no parse: `ssg parse` says so before building any model.
    """
    n_types = len(grammar.types)
    observed = grammar.tables.type_observed
    hold = np.zeros((len(st), n_types), np.int64)
    total = np.zeros(len(st), np.int64)
    for i in range(len(st) - 1, -1, -1):  # children before parents
        kids = list(st.children[i])
        if kids:
            if grammar.types[st.type[i]].kind == Kind.OR:
                best = max(kids, key=lambda c: total[c])
                hold[i] = hold[kids].max(axis=0)
                total[i] = total[best]
            else:
                hold[i] = hold[kids].sum(axis=0)
                total[i] = total[kids].sum()
        if observed[st.type[i]]:
            hold[i, st.type[i]] += 1
            total[i] += 1
    return np.append(hold[0], total[0])
