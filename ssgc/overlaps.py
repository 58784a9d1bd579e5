"""Which objects of a scene take part in violations of the grammar's `non_penetration`
constraints, and by how much: a reason for `ssg explain` (docs/explain.md, "Overlaps").

The grammar's probabilities do not see contact: a dish slid 15 cm along the bin floor keeps
its height and its way up, and the floor's horizontal law is wide.  Real scenes are physically
settled, so such a dish often ends up inside another one.  The grammar says so itself when it
declares `non_penetration` on its objects; this module evaluates that constraint per pair.

Geometries overlap in real scenes too: a solid cylinder standing for a bowl overlaps what lies
in it (a hollow `revolve` does not), and any shape guessed for a real model is a few
millimetres off.  `ssg explain` measures a pair's overlap as how far one must move to free it
(`NonPenetration.pair_distances(separation=True)`: thin walls that cross count fully).
Pairs the parse tree relates — one object's block is an ancestor of the other (carrier and
carried, at any depth) — are where the grammar itself puts things close: they are left out.
What remains is an overlap the tree does not account for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.penetration import NonPenetration
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Overlap:
    """Objects `a` and `b` (scene indices) overlap by `depth` metres (FCL penetration depth of
    the constraint's geometries), and neither carries the other in the parse tree."""

    constraint: str
    a: int
    b: int
    depth: float


class _Objects:
    """One scene's objects as a batch of one tree (what a constraint evaluates)."""

    def __init__(self, scene: Scene) -> None:
        n = len(scene)
        self.xyz, self.quat, self.type = scene.xyz, scene.quat, scene.types
        self.scene = np.zeros(n, np.int64)
        self.parent = np.full(n, -1, np.int64)
        self.n_scenes = 1


def related(tree: Trees, top: IntArray, obj_of: IntArray, n_objects: int) -> NDArray[np.bool_]:
    """(objects, objects): whether the parse relates the pair — one object's block top is an
    ancestor (or the block) of the other's node: carrier and carried, at any depth."""
    node = np.full(n_objects, -1, np.int64)
    has = np.flatnonzero(obj_of >= 0)
    node[obj_of[has]] = has
    # above[o, k]: tree node k is a block top on the path from object o's node to the root
    above = np.zeros((n_objects, len(tree)), bool)
    for o in np.flatnonzero(node >= 0):
        k = int(top[node[o]])
        while k >= 0:
            above[o, k] = True
            parent = int(tree.parent[k])
            k = int(top[parent]) if parent >= 0 else -1
    own = np.zeros((n_objects, len(tree)), bool)
    seen = node >= 0
    own[np.flatnonzero(seen), top[node[seen]]] = True
    under = (own.astype(np.int64) @ above.T.astype(np.int64)) > 0  # [a, b]: a's block above b
    out = under | under.T
    np.fill_diagonal(out, False)
    return out


def overlaps(
    grammar: Grammar, scene: Scene, tree: Trees, top: IntArray, obj_of: IntArray
) -> list[Overlap]:
    """Every pair of objects that overlaps under one of the grammar's `non_penetration`
    constraints while the parse relates neither to the other, deepest first."""
    out: list[Overlap] = []
    checks = [c for c in grammar.constraints if isinstance(c, NonPenetration)]
    if not checks or len(scene) < 2:
        return out
    rel = related(tree, top, obj_of, len(scene))
    batch = _Objects(scene)
    for c in checks:
        i, j, dist = c.pair_distances(batch, separation=True)
        keep = (dist < 0) & ~rel[i, j]
        out += [
            Overlap(c.name, int(a), int(b), float(-d))
            for a, b, d in zip(i[keep], j[keep], dist[keep], strict=True)
        ]
    return sorted(out, key=lambda v: -v.depth)
