"""The supertree's size, counted without building it (for `ssg inspect`).

The supertree (thesis 3.3; built by `ssgc.parse.supertree`) holds every node any tree of the
grammar could contain: each node expands all of its rules (a `repeat` as many times as its
largest count), down to the recursion bounds; rules that can never fire (weight or probability
0) are left out.  Its size tells a user how big a parse problem a
grammar makes, even for grammars whose supertree is far too large to build.
"""

from __future__ import annotations

from ssgc.ir import Grammar, Kind
from ssgc.node_states import State, child_states, root_state, subtree_total

MAX_COUNT = 10**18  # larger sizes are reported as "too large to count"
MAX_STATE_VALUES = 10_000_000  # bounds the memory of the count: states x bounded types


def supertree_size(grammar: Grammar) -> int | None:
    """Number of nodes of the supertree rooted at the grammar's root (an exact integer).

    None when it is too large to count: over `MAX_COUNT` nodes, or so many distinct kinds of
    node (a type with the nesting depths that got it there, each at least one node) that
    counting them would not fit in memory (`ssgc.node_states.subtree_total`).
    """

    def copies(state: State) -> list[tuple[float, State]]:
        node = grammar.types[state[0]]
        n = node.count.largest if node.kind == Kind.REPEAT and node.count else 1
        return [(n, child) for _, child in child_states(grammar, state)]

    bounded = int(grammar.tables.nesting_max.shape[0])
    max_states = max(1000, MAX_STATE_VALUES // max(1, bounded))
    size = subtree_total(root_state(grammar), copies, max_states, MAX_COUNT + 1)
    return None if size is None or size > MAX_COUNT else int(size)
