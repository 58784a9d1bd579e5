"""Kinds of node: a type with the nesting depth of every type that has `max_nesting`.

What a node can hold depends on its type and on how deep it already is in each bounded
recursion: a rule into a bounded type is blocked once that type's depth reaches its
`max_nesting` (depths count the node itself, as `ssgc.score.nesting_counts` does).  The
parser's supertree (`ssgc.parse.supertree`), its size counted without building it
(`ssgc.supertree_size`), the mean size of a sampled tree (`ssgc.sample.staged`) and the rules
a fit can observe (`ssgc.fit.observable`) all walk these states; this module is their one
definition of the root's state and of a state's children.
"""

from __future__ import annotations

from collections.abc import Callable

from ssgc.ir import Grammar

State = tuple[int, tuple[int, ...]]  # a type and the nesting depth of every bounded type


def root_state(grammar: Grammar, nesting: bool = True) -> State:
    """The root node's state.  `nesting=False`: states of types alone (every depth tuple
    empty), the type graph, for when there are too many states to follow depths."""
    tb = grammar.tables
    depths = [0] * (tb.nesting_max.shape[0] if nesting else 0)
    slot = int(tb.nesting_slot[grammar.root])
    if nesting and slot >= 0:
        depths[slot] = 1
    return (grammar.root, tuple(depths))


def child_states(grammar: Grammar, state: State) -> list[tuple[int, State]]:
    """(rule id, child state) of each rule of the state's type that can fire there: not one
    of weight or probability 0 (`NodeType.never_fires`), and not blocked by `max_nesting`.
    A state with an empty depth tuple (`root_state(nesting=False)`) ignores the bounds."""
    tb = grammar.tables
    t, depths = state
    node = grammar.types[t]
    out = []
    for rid in node.rules:
        if node.never_fires(int(tb.rule_index[rid])):
            continue
        child = int(tb.rule_child[rid])
        slot = int(tb.nesting_slot[child]) if depths else -1
        if slot < 0:
            out.append((rid, (child, depths)))
        elif depths[slot] < tb.nesting_max[slot]:
            out.append((rid, (child, (*depths[:slot], depths[slot] + 1, *depths[slot + 1 :]))))
    return out


def subtree_total(
    start: State,
    children: Callable[[State], list[tuple[float, State]]],
    max_states: int,
    cap: float = float("inf"),
) -> float | None:
    """total(s) = 1 + Σ weight · total(child) over `children(s)`, for the state `start`:
    each state's total computed once, depth first without recursion (a long chain of types is
    fine; recursion is finite, every cycle being bounded by `max_nesting`).  Totals are
    clipped at `cap` (with integer weights, an exact integer count stops growing there).
    None when more than `max_states` states would be visited."""
    totals: dict[State, float] = {}
    frames = [(start, children(start))]
    running: list[float] = [1]  # int weights keep a count an exact int
    while frames:
        state, kids = frames[-1]
        while kids and kids[-1][1] in totals:
            weight, child = kids.pop()
            running[-1] = min(running[-1] + weight * totals[child], cap)
        if kids:  # the next child has no total yet: compute it first
            if len(totals) + len(frames) > max_states:
                return None
            child = kids[-1][1]
            frames.append((child, children(child)))
            running.append(1)
            continue
        totals[state] = running.pop()
        frames.pop()
    return totals[start]
