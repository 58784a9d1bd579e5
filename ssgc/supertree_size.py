"""The supertree's size, counted without building it (for `ssg inspect`).

The supertree (thesis 3.3; built by `ssgc.parse.supertree`) holds every node any tree of the
grammar could contain: each node expands all of its rules (a `repeat` as many times as its
largest count), down to the recursion bounds; rules that can never fire (weight or probability
0) are left out.  Its size tells a user how big a parse problem a
grammar makes, even for grammars whose supertree is far too large to build.
"""

from __future__ import annotations

from ssgc.ir import Grammar, Kind

MAX_COUNT = 10**18  # larger sizes are reported as "too large to count"
MAX_STATE_VALUES = 10_000_000  # bounds the memory of the count: states x bounded types

State = tuple[int, tuple[int, ...]]  # a type and the nesting depth of every bounded type


def supertree_size(grammar: Grammar) -> int | None:
    """Number of nodes of the supertree rooted at the grammar's root (an exact integer).

    None when it is too large to count: over `MAX_COUNT` nodes, or so many distinct kinds of
    node (a type with the nesting depths that got it there, each at least one node) that
    counting them would not fit in memory.  Iterative, so a long chain of types cannot
    exhaust Python's recursion limit.
    """
    tb = grammar.tables
    bounded = [int(t) for t in (tb.nesting_slot >= 0).nonzero()[0]]
    slot = {t: i for i, t in enumerate(bounded)}
    limit = [int(tb.nesting_max[tb.nesting_slot[t]]) for t in bounded]
    max_states = max(1000, MAX_STATE_VALUES // max(1, len(bounded)))

    def expand(state: State) -> list[tuple[int, State]]:
        """(copies, child state) of every rule not blocked by `max_nesting`."""
        type_id, nesting = state
        node = grammar.types[type_id]
        copies = node.count.largest if node.kind == Kind.REPEAT and node.count else 1
        out = []
        for rid in node.rules:
            child = grammar.rules[rid].child
            if node.never_fires(grammar.rules[rid].index):
                continue  # left out of the supertree too
            depth = nesting
            if child in slot:
                i = slot[child]
                if nesting[i] >= limit[i]:
                    continue  # blocked by max_nesting
                depth = (*nesting[:i], nesting[i] + 1, *nesting[i + 1 :])
            out.append((copies, (child, depth)))
        return out

    start: State = (grammar.root, tuple(1 if t == grammar.root else 0 for t in bounded))
    sizes: dict[State, int] = {}
    frames: list[tuple[State, list[tuple[int, State]]]] = [(start, expand(start))]
    totals = [1]
    while frames:
        state, kids = frames[-1]
        while kids and kids[-1][1] in sizes:
            copies, child = kids.pop()
            totals[-1] = min(totals[-1] + copies * sizes[child], MAX_COUNT + 1)
        if kids:  # the next child is not counted yet: count it first
            if len(sizes) + len(frames) > max_states:
                return None
            child = kids[-1][1]
            frames.append((child, expand(child)))
            totals.append(1)
            continue
        sizes[state] = totals.pop()
        frames.pop()
    size = sizes[start]
    return size if size <= MAX_COUNT else None
