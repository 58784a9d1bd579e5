"""A brute-force parser, for tests only: every tree of a grammar that explains a scene.

`enumerate_parses` walks the grammar top-down and tries every structure and every way of
assigning the scene's objects to observed nodes.  It is meant to be slow and obviously right, so
that real parsers can be checked against it on scenes of a handful of objects.

Poses.  A rule whose translation and rotation are both fixed (`same` or `offset`) places its
child exactly; the nodes linked by such rules form a *group* (thesis: an equivalent set) whose
poses all follow from the pose of its head, the node at its top.  The root's group hangs from the
root pose.  Every other group's head comes from a rule with a density, and its pose must be
read off an observed node of its group: the search tries every unused scene object that some
chain of fixed rules below the head could reach, back-computes the head pose from it, expands
the head, and keeps the result only if the group really contains an observed node.  Observed
nodes whose pose is known must land exactly (within the scorer's tolerances) on an unused scene
object of their type.  Grammars in which a group could contain no observed node (its pose would
be a free latent variable) are out of scope: `enumerate_parses` raises NotImplementedError.

Identity of trees.  The copies produced by a `repeat` are exchangeable: trees that differ only
in the order of a repeat node's children are the same tree, returned once.  Identical scene
objects (same type and pose) are interchangeable too.  Each tree is put in a canonical form
(children of repeat nodes sorted by a key of their subtree) and deduplicated on that form.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import quat_angle, quat_conjugate, quat_multiply, quat_rotate
from ssgc.io.scene import Scene
from ssgc.ir import Grammar, Kind, Rule
from ssgc.rules import POS_TOL, ROT_TOL, rotation_log_density, translation_log_density
from ssgc.score import score_trees
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]
Nest = tuple[int, ...]  # per type id: nodes of that type on the path to the root (inclusive)
Key = tuple  # canonical key of a subtree (nested tuples of ints)

CANDIDATE_TOL = 1e-9  # candidate head poses closer than this are the same candidate


@dataclass(frozen=True)
class _Node:
    type: int
    rule: int  # -1 for the root
    xyz: FloatArray
    quat: FloatArray
    obj: int  # scene object explained by this node, -1 for latent nodes (and an implicit root)
    children: tuple[_Node, ...]


def enumerate_parses(
    grammar: Grammar, scene: Scene, max_nodes: int = 40
) -> list[tuple[float, Trees]]:
    """Every tree T of the grammar whose observed nodes are exactly the scene's objects
    (same multiset of (type, pose)), with its score, best first. Only for grammars in which every
    latent node's pose is determined by observed nodes or the root (dependency grammars):
    others raise NotImplementedError.

    The root is the grammar's root type at the root pose.  If the root type is observed and the
    scene holds objects of that type, one of them must be the root; if it holds none, the root
    counts as implicitly observed.  Scores are `ssgc.score.score_trees`; trees scoring -inf are
    dropped.  `max_nodes` bounds the size of the trees searched (larger ones are not returned).
    """
    return _Search(grammar, scene, max_nodes).run()


def is_fixed(rule: Rule) -> bool:
    """True if the rule places its child exactly (fixed translation and fixed rotation)."""
    return rule.translation.point is not None and rule.rotation.point is not None


def guaranteed_observed(grammar: Grammar) -> list[bool]:
    """Per type: does every expansion of a node of this type put an observed node in its group?

    Conservative (a least fixed point): a rule to a type with `max_nesting` might be blocked, so
    it never guarantees anything.
    """
    types = grammar.types
    count_logp = grammar.tables.count_logp
    must = [t.observed for t in types]
    changed = True
    while changed:
        changed = False
        for t in types:
            if must[t.id]:
                continue
            ok = [
                is_fixed(grammar.rules[r])
                and must[grammar.rules[r].child]
                and types[grammar.rules[r].child].max_nesting is None
                for r in t.rules
            ]
            if t.kind == Kind.AND:
                value = any(ok)
            elif t.kind == Kind.OR:
                live = [k for k, p in zip(ok, t.probs, strict=True) if p > 0]
                value = bool(live) and all(live)
            elif t.kind == Kind.INDEPENDENT:
                value = any(k and p >= 1 for k, p in zip(ok, t.probs, strict=True))
            elif t.kind == Kind.REPEAT:
                value = bool(ok) and ok[0] and bool(np.isneginf(count_logp[t.id, 0]))
            else:
                value = False
            if value:
                must[t.id] = True
                changed = True
    return must


def _compose(
    xyz: FloatArray, quat: FloatArray, t: FloatArray, q: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The pose (t, q), given in the frame of (xyz, quat), in world coordinates."""
    return xyz + quat_rotate(quat, t), quat_multiply(quat, q)


def _close(
    xyz_a: FloatArray,
    quat_a: FloatArray,
    xyz_b: FloatArray,
    quat_b: FloatArray,
    pos_tol: float = POS_TOL,
    rot_tol: float = ROT_TOL,
) -> bool:
    return bool(
        np.linalg.norm(xyz_a - xyz_b) <= pos_tol and float(quat_angle(quat_a, quat_b)) <= rot_tol
    )


class _Search:
    def __init__(self, grammar: Grammar, scene: Scene, max_nodes: int) -> None:
        self.g = grammar
        self.types = grammar.types
        self.scene_types = np.asarray(scene.types, np.int64)
        self.scene_xyz = np.asarray(scene.xyz, float).reshape(-1, 3)
        self.scene_quat = np.asarray(scene.quat, float).reshape(-1, 4)
        self.n_objects = len(self.scene_types)
        self.max_nodes = max_nodes
        self.must = guaranteed_observed(grammar)
        for rule in grammar.rules:
            if not is_fixed(rule) and not self.must[rule.child]:
                raise NotImplementedError(
                    f"rule {grammar.rule_name(rule.id)} can produce a group of latent nodes "
                    "with no observed node, whose pose is not determined by the scene"
                )
        # alias[i]: the first object identical to object i (same type and pose)
        self.alias = []
        for i in range(self.n_objects):
            same = [
                j
                for j in range(i + 1)
                if self.scene_types[j] == self.scene_types[i]
                and _close(
                    self.scene_xyz[j], self.scene_quat[j], self.scene_xyz[i], self.scene_quat[i]
                )
            ]
            self.alias.append(same[0])

    # ------------------------------------------------------------------------- driver ---

    def run(self) -> list[tuple[float, Trees]]:
        g = self.g
        root = g.root
        root_xyz = np.array(g.root_xyz, float)
        root_quat = np.array(g.root_quat, float)
        objs = [-1]
        if self.types[root].observed and np.any(self.scene_types == root):
            # One of the root-type objects is the root; it must sit at the root pose.
            objs = self._matches(root, root_xyz, root_quat, frozenset())
        nest = self._child_nest(tuple(0 for _ in self.types), root)
        everything = frozenset(range(self.n_objects))
        found: dict[Key, _Node] = {}
        for obj in objs:
            for node, used, _ in self._expand_with(
                root, -1, root_xyz, root_quat, nest, frozenset(), self.max_nodes, obj
            ):
                if used != everything:
                    continue
                canonical = self._canonical(node)
                found.setdefault(self._key(canonical), canonical)
        trees = [_to_trees(node) for node in found.values()]
        if not trees:
            return []
        scores = score_trees(g, Trees.concatenate(trees))
        out = [(float(s), t) for s, t in zip(scores, trees, strict=True) if np.isfinite(s)]
        out.sort(key=lambda pair: -pair[0])
        return out

    # ---------------------------------------------------------------------- structure ---

    def _expand(
        self,
        tid: int,
        rule: int,
        xyz: FloatArray,
        quat: FloatArray,
        nest: Nest,
        used: frozenset[int],
        budget: int,
    ) -> Iterator[tuple[_Node, frozenset[int], int]]:
        """Every subtree rooted at a node of type `tid` at this (known) pose.

        Yields (subtree, objects used so far, number of nodes in the subtree).
        """
        if self.types[tid].observed:
            objs = self._matches(tid, xyz, quat, used)
        else:
            objs = [-1]
        for obj in objs:
            yield from self._expand_with(tid, rule, xyz, quat, nest, used, budget, obj)

    def _expand_with(
        self,
        tid: int,
        rule: int,
        xyz: FloatArray,
        quat: FloatArray,
        nest: Nest,
        used: frozenset[int],
        budget: int,
        obj: int,
    ) -> Iterator[tuple[_Node, frozenset[int], int]]:
        if budget < 1:
            return
        if obj >= 0:
            used = used | {obj}
        for fired in self._choices(tid, nest, budget - 1, self.n_objects - len(used)):
            for children, used_after, size in self._expand_all(
                fired, xyz, quat, nest, used, budget - 1
            ):
                yield _Node(tid, rule, xyz, quat, obj, children), used_after, 1 + size

    def _choices(self, tid: int, nest: Nest, budget: int, free: int) -> list[tuple[int, ...]]:
        """Every possible list of fired rules at a node (a rule repeats for `repeat` copies)."""
        node = self.types[tid]
        live = [r for r in node.rules if not self._blocked(r, nest)]
        if node.kind == Kind.TERMINAL:
            return [()]
        if node.kind == Kind.AND:
            return [tuple(live)]
        if node.kind == Kind.OR:
            return [(r,) for r in live] if live else [()]
        if node.kind == Kind.INDEPENDENT:
            return [c for k in range(len(live) + 1) for c in itertools.combinations(live, k)]
        # REPEAT
        if not live:
            return [()]
        rule = live[0]
        most = min(int(self.g.tables.count_max[tid]), budget)
        if self.must[self.g.rules[rule].child]:
            most = min(most, free)  # every copy explains at least one more object
        return [(rule,) * k for k in range(most + 1)]

    def _expand_all(
        self,
        fired: tuple[int, ...],
        xyz: FloatArray,
        quat: FloatArray,
        nest: Nest,
        used: frozenset[int],
        budget: int,
    ) -> Iterator[tuple[tuple[_Node, ...], frozenset[int], int]]:
        """Every sequence of children for the fired rules, threading the used objects."""
        if not fired:
            yield (), used, 0
            return
        for child, used1, size1 in self._expand_child(fired[0], xyz, quat, nest, used, budget):
            for rest, used2, size2 in self._expand_all(
                fired[1:], xyz, quat, nest, used1, budget - size1
            ):
                yield (child, *rest), used2, size1 + size2

    def _expand_child(
        self,
        rid: int,
        xyz: FloatArray,
        quat: FloatArray,
        nest: Nest,
        used: frozenset[int],
        budget: int,
    ) -> Iterator[tuple[_Node, frozenset[int], int]]:
        rule = self.g.rules[rid]
        child = rule.child
        child_nest = self._child_nest(nest, child)
        if is_fixed(rule):
            c_xyz, c_quat = _compose(xyz, quat, rule.translation.offset, rule.rotation.offset)
            yield from self._expand(child, rid, c_xyz, c_quat, child_nest, used, budget)
            return
        for c_xyz, c_quat in self._candidates(child, child_nest, used):
            if not self._edge_possible(rid, xyz, quat, c_xyz, c_quat):
                continue
            for node, used1, size in self._expand(
                child, rid, c_xyz, c_quat, child_nest, used, budget
            ):
                if self._group_observed(node):
                    yield node, used1, size

    # -------------------------------------------------------------------------- poses ---

    def _fixed_paths(self, tid: int, nest: Nest) -> list[tuple[int, FloatArray, FloatArray]]:
        """(observed type, offset t, offset q) for every chain of fixed rules from `tid`
        (including the empty chain) that ends at an observed type."""
        out: list[tuple[int, FloatArray, FloatArray]] = []

        def walk(t: int, nest: Nest, off_t: FloatArray, off_q: FloatArray, depth: int) -> None:
            if self.types[t].observed:
                out.append((t, off_t, off_q))
            if depth >= self.max_nodes:
                return
            for rid in self.types[t].rules:
                rule = self.g.rules[rid]
                if not is_fixed(rule) or self._blocked(rid, nest):
                    continue
                new_t, new_q = _compose(off_t, off_q, rule.translation.offset, rule.rotation.offset)
                walk(rule.child, self._child_nest(nest, rule.child), new_t, new_q, depth + 1)

        walk(tid, nest, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), 0)
        return out

    def _candidates(
        self, tid: int, nest: Nest, used: frozenset[int]
    ) -> list[tuple[FloatArray, FloatArray]]:
        """Poses for a group head of type `tid`: each puts some fixed-chain descendant of the
        head exactly on an unused scene object."""
        out: list[tuple[FloatArray, FloatArray]] = []
        for obs_type, off_t, off_q in self._fixed_paths(tid, nest):
            for i in range(self.n_objects):
                if i in used or self.scene_types[i] != obs_type:
                    continue
                # object = head ⊕ offset  =>  head = object ⊕ offset⁻¹
                quat = quat_multiply(self.scene_quat[i], quat_conjugate(off_q))
                xyz = self.scene_xyz[i] - quat_rotate(quat, off_t)
                if not any(_close(xyz, quat, x, q, CANDIDATE_TOL, CANDIDATE_TOL) for x, q in out):
                    out.append((xyz, quat))
        return out

    def _matches(
        self, tid: int, xyz: FloatArray, quat: FloatArray, used: frozenset[int]
    ) -> list[int]:
        """Unused scene objects of this type at this pose (one per class of identical ones)."""
        out = []
        seen = set()
        for i in range(self.n_objects):
            if i in used or self.scene_types[i] != tid:
                continue
            if not _close(self.scene_xyz[i], self.scene_quat[i], xyz, quat):
                continue
            if self.alias[i] not in seen:
                seen.add(self.alias[i])
                out.append(i)
        return out

    def _edge_possible(
        self,
        rid: int,
        p_xyz: FloatArray,
        p_quat: FloatArray,
        c_xyz: FloatArray,
        c_quat: FloatArray,
    ) -> bool:
        """Pruning only (the final score decides): can the rule put the child at this pose?"""
        r = np.array([rid], np.int64)
        t = translation_log_density(self.g, r, p_xyz[None], p_quat[None], c_xyz[None])
        q = rotation_log_density(self.g, r, p_quat[None], c_quat[None])
        return bool(np.isfinite(t[0] + q[0]))

    def _group_observed(self, node: _Node) -> bool:
        if self.types[node.type].observed:
            return True
        return any(
            is_fixed(self.g.rules[c.rule]) and self._group_observed(c) for c in node.children
        )

    # ------------------------------------------------------------------------ nesting ---

    def _child_nest(self, nest: Nest, child: int) -> Nest:
        if self.types[child].max_nesting is None:
            return nest
        return tuple(n + 1 if t == child else n for t, n in enumerate(nest))

    def _blocked(self, rid: int, nest: Nest) -> bool:
        child = self.g.rules[rid].child
        limit = self.types[child].max_nesting
        return limit is not None and nest[child] >= limit

    # --------------------------------------------------------------------- canonical ---

    def _canonical(self, node: _Node) -> _Node:
        """The same tree with the children of repeat nodes in a canonical order."""
        children = tuple(self._canonical(c) for c in node.children)
        if self.types[node.type].kind == Kind.REPEAT:
            children = tuple(sorted(children, key=self._key))
        return _Node(node.type, node.rule, node.xyz, node.quat, node.obj, children)

    def _key(self, node: _Node) -> Key:
        """Structure plus the objects explained: this determines every pose of the tree."""
        obj = self.alias[node.obj] if node.obj >= 0 else -1
        return (node.type, node.rule, obj, tuple(self._key(c) for c in node.children))


def _to_trees(root: _Node) -> Trees:
    """A single tree as flat arrays, parents first (preorder)."""
    nodes: list[tuple[_Node, int]] = []

    def visit(node: _Node, parent: int) -> None:
        index = len(nodes)
        nodes.append((node, parent))
        for c in node.children:
            visit(c, index)

    visit(root, -1)
    n = len(nodes)
    return Trees(
        scene=np.zeros(n, np.int64),
        type=np.array([node.type for node, _ in nodes], np.int64),
        parent=np.array([p for _, p in nodes], np.int64),
        rule=np.array([node.rule for node, _ in nodes], np.int64),
        xyz=np.array([node.xyz for node, _ in nodes], float).reshape(n, 3),
        quat=np.array([node.quat for node, _ in nodes], float).reshape(n, 4),
        n_scenes=1,
    )
