"""What every constraint kind shares, and the array helpers they are built from.

A batch of trees is anything with the flat node arrays of `ssgc.tree.Trees` (`scene`, `type`,
`parent`, `n_scenes`; pose constraints also `xyz`, `quat`).  Parents must come before their
children, but nodes need not be grouped by tree: the structure sampler evaluates structural
constraints on level-major arrays without reordering them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from itertools import pairwise
from typing import Any, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
Loc = tuple[str | int, ...]
# Pairs formed at once by `pair_chunks` (a chunk may exceed it by one node's partners): each
# array over them is 8 MB.  A batch of 1,024 trees of 700 objects has 250 million pairs.
MAX_PAIRS = 1 << 20


class NodeBatch(Protocol):
    scene: IntArray
    type: IntArray
    parent: IntArray
    n_scenes: int


@dataclass(frozen=True)
class Constraint:
    """A named constraint; subclasses set `kind` and implement `margin`."""

    name: str
    path: Loc
    kind: ClassVar[str] = ""  # "structure" or "pose"
    word: ClassVar[str] = ""  # its key in the grammar file
    rank: ClassVar[int] = 1  # evaluation order among pose constraints: likely rejecters first
    # A pose constraint cheap enough to judge partial trees after every depth of poses
    # (`ssgc.sample.staged.pose_stage`); costly ones are judged once per candidate.
    progressive: ClassVar[bool] = True

    def reads(self, n_types: int) -> NDArray[np.bool_]:
        """Per type: whether a node of that type can change this constraint's margin (the
        pose sampler re-judges a partial tree only when such a node got its pose)."""
        types = getattr(self, "types", None)
        return types if types is not None and len(types) == n_types else np.ones(n_types, bool)

    def margin(self, batch: Any) -> FloatArray:  # pragma: no cover - abstract
        """(n_scenes,) margins: >= 0 holds; +inf when there is nothing to check."""
        raise NotImplementedError


# ------------------------------------------------------------------ kinds ---

# A kind's builder: (the builder context of `ssgc.constraints.build`, the constraint's name,
# its validated `{word: ...}` body, its location) -> the constraint, or None after reporting
# an error through the context.
Builder = Callable[[Any, str, Any, Loc], "Constraint | None"]
_KINDS: dict[str, Builder] = {}
_ADDED: set[str] = set()


def register(word: str, spec: Any = None) -> Callable[[Builder], Builder]:
    """Decorator on a builder function: make the constraint kind `word` known, as
    `ssgc.laws.base.register` does for laws.  `spec` is the pydantic model of the whole
    entry `{word: {...}}` for a kind the grammar language does not have yet: it joins the
    `constraints:` section's union (`ssgc.dsl.add_choice`).  Adding a kind is one module: its
    model, its `Constraint` subclass and its registered builder."""

    def add(build: Builder) -> Builder:
        if word in _KINDS:
            raise ValueError(f"the constraint word '{word}' already names a kind")
        if spec is not None:
            from ssgc import dsl

            dsl.add_choice("constraint", spec, word)
            _ADDED.add(word)
        _KINDS[word] = build
        return build

    return add


def unregister(word: str) -> None:
    """Forget a registered kind and the document shape it added (for tests)."""
    _KINDS.pop(word, None)
    if word in _ADDED:
        from ssgc import dsl

        _ADDED.discard(word)
        dsl.remove_choice("constraint", word)


def builder_for(word: str) -> Builder:
    return _KINDS[word]


def satisfied(margins: FloatArray) -> NDArray[np.bool_]:
    return margins >= 0


def per_scene_min(scene: IntArray, values: FloatArray, n_scenes: int) -> FloatArray:
    """Minimum of `values` per tree; +inf for a tree with none."""
    out = np.full(n_scenes, np.inf)
    if len(values):
        np.minimum.at(out, scene, values)
    return out


def per_scene_argmin(scene: IntArray, values: FloatArray, n_scenes: int) -> IntArray:
    """Per tree, the index (into `values`) of its smallest value; -1 for a tree with none."""
    out = np.full(n_scenes, -1, np.int64)
    if len(values):
        order = np.lexsort((values, scene))
        first = np.r_[True, scene[order][1:] != scene[order][:-1]]
        out[scene[order][first]] = order[first]
    return out


def range_margin(value: NDArray[Any], lo: float, hi: float | None) -> FloatArray:
    """How far an integer statistic is inside [lo, hi] (negative: outside)."""
    v = value.astype(np.float64)
    low = v - lo
    return low if hi is None else np.minimum(low, hi - v)


def nearest_ancestor(
    parent: IntArray, type_: IntArray, of_type: int, nodes: IntArray | None = None
) -> IntArray:
    """For each of `nodes` (default all), its nearest proper ancestor of type `of_type`; -1
    if there is none.  One vectorised step per tree level."""
    nodes = np.arange(len(parent)) if nodes is None else nodes
    out = np.full(len(nodes), -1, np.int64)
    anc = parent[nodes]
    idx = np.flatnonzero(anc >= 0)
    while len(idx):
        hit = type_[anc[idx]] == of_type
        out[idx[hit]] = anc[idx[hit]]
        idx = idx[~hit]
        anc[idx] = parent[anc[idx]]
        idx = idx[anc[idx] >= 0]
    return out


def depths(parent: IntArray) -> IntArray:
    """Depth of every node (roots 0), one vectorised step per level."""
    depth = np.zeros(len(parent), np.int64)
    anc = parent.copy()
    live = np.flatnonzero(anc >= 0)
    while len(live):
        depth[live] += 1
        anc[live] = parent[anc[live]]
        live = live[anc[live] >= 0]
    return depth


def ancestor_table(parent: IntArray) -> tuple[IntArray, IntArray]:
    """(depth, table): table[n, d] is node n's ancestor at depth d (itself at its own depth,
    -1 below it).  Parents must come before children."""
    depth = depths(parent)
    top = int(depth.max(initial=0)) + 1
    table = np.full((len(parent), top), -1, np.int64)
    for d in range(top):
        at = np.flatnonzero(depth == d)
        if d:
            table[at, :d] = table[parent[at], :d]
        table[at, d] = at
    return depth, table


def lineal(a: IntArray, b: IntArray, parent: IntArray) -> NDArray[np.bool_]:
    """Pairwise: is one of nodes a[k], b[k] an ancestor of the other?"""
    if not len(a):
        return np.zeros(0, bool)
    depth, table = ancestor_table(parent)
    da, db = depth[a], depth[b]
    hi = np.where(da < db, a, b)  # the shallower node
    lo = np.where(da < db, b, a)
    return (da != db) & (table[lo, np.minimum(da, db)] == hi)


def lineal_few(
    a: IntArray, b: IntArray, parent: IntArray, depth: IntArray | None = None
) -> NDArray[np.bool_]:
    """`lineal` for a few pairs: walks up from both nodes (one step per level), without the
    whole batch's ancestor table.  With the nodes' depths, only from the deeper node of a
    pair and only up to the other's depth (nodes at one depth are never lineal)."""
    if depth is not None:
        da, db = depth[a], depth[b]
        low, high = np.where(da > db, a, b), np.where(da > db, b, a)
        steps = np.abs(da - db)
        out = np.zeros(len(a), bool)
        live = np.flatnonzero(steps > 0)
        cur, steps = low[live], steps[live]
        while len(live):
            cur = parent[cur]
            steps = steps - 1
            done = steps == 0
            out[live[done]] = cur[done] == high[live[done]]
            live, cur, steps = live[~done], cur[~done], steps[~done]
        return out
    out = np.zeros(len(a), bool)
    for x, y in ((a, b), (b, a)):
        cur = parent[y]
        live = np.flatnonzero(cur >= 0)
        while len(live):
            out[live[cur[live] == x[live]]] = True
            cur[live] = parent[cur[live]]
            live = live[cur[live] >= 0]
    return out


def tree_pairs(nodes: IntArray, scene: IntArray) -> tuple[IntArray, IntArray]:
    """Every unordered pair (i, j) of `nodes` that lie in the same tree, as two index arrays."""
    return _pairs_at(*_pair_plan(nodes, scene, None))


def fresh_pairs(
    nodes: IntArray, scene: IntArray, fresh: NDArray[np.bool_]
) -> tuple[IntArray, IntArray]:
    """The pairs of `tree_pairs` with at least one fresh node, each once, without
    enumerating the others: within a tree the old nodes come first, and each fresh node is
    paired with the nodes before it (trees with no fresh node are left out)."""
    return _pairs_at(*_pair_plan(nodes, scene, fresh))


def pair_chunks(
    nodes: IntArray,
    scene: IntArray,
    fresh: NDArray[np.bool_] | None = None,
    limit: int | None = None,
) -> Iterator[tuple[IntArray, IntArray]]:
    """The pairs of `tree_pairs` (with `fresh`, of `fresh_pairs`), in the same order, in
    chunks of about `limit` pairs (default `MAX_PAIRS`; a chunk ends after the node that
    reaches it).  A pair constraint's memory is then bounded by the chunk, not by the batch
    (candidates × objects² / 2 pairs), and its per-tree minimum is the minimum over chunks."""
    limit = MAX_PAIRS if limit is None else limit
    order, partners, base = _pair_plan(nodes, scene, fresh)
    ends = np.cumsum(partners)
    total = int(ends[-1]) if len(ends) else 0
    cuts = np.searchsorted(ends, limit * np.arange(1, -(-total // limit)), side="left") + 1
    bounds = np.unique(np.r_[0, cuts, len(order)])
    for lo, hi in pairwise(bounds.tolist()):
        yield _pairs_at(order, partners, base, lo, hi)


def _pair_plan(
    nodes: IntArray, scene: IntArray, fresh: NDArray[np.bool_] | None
) -> tuple[IntArray, IntArray, IntArray]:
    """(order, partners, base): the nodes grouped by tree, and the pairs of the node at
    position a, (order[a], order[base[a] + m]) for m < partners[a].  Without `fresh`, each
    node is paired with the later nodes of its tree; with it, within a tree the old nodes
    come first and each fresh node is paired with the nodes before it (trees with no fresh
    node are left out)."""
    if fresh is not None:
        has = np.zeros(int(scene.max(initial=-1)) + 1, bool)
        has[scene[nodes[fresh[nodes]]]] = True
        nodes = nodes[has[scene[nodes]]]
    if len(nodes) < 2:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty
    if fresh is None:
        order = nodes[np.argsort(scene[nodes], kind="stable")]
    else:
        order = nodes[np.lexsort((fresh[nodes], scene[nodes]))]
    s = scene[order]
    start = np.flatnonzero(np.r_[True, s[1:] != s[:-1]])
    size = np.diff(np.r_[start, len(order)])
    first_of = np.repeat(start, size)
    pos = np.arange(len(order)) - first_of  # position within its tree
    if fresh is None:
        partners = np.repeat(size, size) - 1 - pos  # the later nodes of its tree
        return order, partners, np.arange(1, len(order) + 1)
    return order, np.where(fresh[order], pos, 0), first_of  # the nodes before it


def _pairs_at(
    order: IntArray, partners: IntArray, base: IntArray, lo: int = 0, hi: int | None = None
) -> tuple[IntArray, IntArray]:
    """The pairs of the nodes at positions lo..hi of a `_pair_plan`."""
    hi = len(order) if hi is None else hi
    p = partners[lo:hi]
    at = np.repeat(np.arange(lo, hi), p)
    offset = np.arange(len(at)) - np.repeat(np.cumsum(p) - p, p)
    return order[at], order[base[at] + offset]


def type_mask(type_ids: list[int], n_types: int) -> NDArray[np.bool_]:
    mask = np.zeros(n_types, bool)
    mask[type_ids] = True
    return mask


def pair_table(pairs: list[tuple[int, int]], n_types: int) -> NDArray[np.bool_]:
    """Symmetric (type, type) table of exempt pairs."""
    table = np.zeros((n_types, n_types), bool)
    for a, b in pairs:
        table[a, b] = table[b, a] = True
    return table
