"""The supertree: every node any tree of the grammar could contain (thesis 3.3).

Each node expands all of its rules (a `repeat` as many times as its largest count), down to
the recursion bounds.  The parser will work on this tree; for now its size tells a user how
big a parse problem a grammar makes.
"""

from __future__ import annotations

from functools import cache

from ssgc.ir import Grammar, Kind


def supertree_size(grammar: Grammar) -> int:
    """Number of nodes of the supertree rooted at the grammar's root (an exact integer)."""
    tb = grammar.tables
    bounded = [int(t) for t in (tb.nesting_slot >= 0).nonzero()[0]]
    limit = {t: int(tb.nesting_max[tb.nesting_slot[t]]) for t in bounded}

    @cache
    def size(type_id: int, nesting: tuple[int, ...]) -> int:
        node = grammar.types[type_id]
        total = 1
        for rid in node.rules:
            child = grammar.rules[rid].child
            depth = dict(zip(bounded, nesting, strict=True))
            if child in limit and depth[child] >= limit[child]:
                continue  # blocked by max_nesting
            if child in limit:
                depth[child] += 1
            copies = node.count.max_count if node.kind == Kind.REPEAT and node.count else 1
            total += copies * size(child, tuple(depth[t] for t in bounded))
        return total

    start = tuple(1 if t == grammar.root else 0 for t in bounded)
    return size(grammar.root, start)
