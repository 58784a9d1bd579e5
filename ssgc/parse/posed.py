"""The pose-instantiated integer program: the supertree unrolled over candidate poses.

For grammars whose every pose is tied to an observation (dependency grammars such as the sink),
a node entered by a non-fixed rule can only sit at one of finitely many candidate poses (those
implied by the scene's objects).  Instead of a supertree node plus a choice of pose (thesis 3.5,
`ssgc.parse.ip`), this formulation gives every (node, candidate pose) its own binary: poses are
constants, every rule's log-density is a constant on one binary, and the copies of a `repeat`
with a free rule are no longer exchangeable variables but distinct candidate children — so
there is no symmetry to break there (top-N cuts give distinct trees).
The model is an assignment problem whose LP relaxation is tight in practice.

Its size is the number of (node, pose) instances, which can grow like K^depth for deep chains
of pose-changing rules (a stack of K steamer trays); `instance_count` measures it first and
the caller falls back to the set formulation when it is too large.

Copies of a `repeat` whose rule is fixed (several `or` nodes at the parent's pose, each
choosing how to place one child) are still exchangeable: their choices are ordered
(`_Model._ordered_choices`).  For a best-tree-only parse, `or` alternatives that lead to the
same rigid subtree at the same pose are dominated by the best of them and dropped
(`_Model.drop_dominated`).  The candidate poses and the unroll are array code
(docs/parsing.md, "The pose-instantiated model: cost and reductions").
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ssgc.errors import Diagnostic
from ssgc.geometry import quat_angle, quat_conjugate, quat_multiply, quat_rotate
from ssgc.io.scene import Scene
from ssgc.ir import Grammar, Kind
from ssgc.parse.clock import check_deadline
from ssgc.parse.ip import UnparseableScene, unplaceable
from ssgc.parse.milp import (
    ColumnBuilder,
    Milp,
    RowBuilder,
    add_correspondences,
    add_count_law,
    add_leq,
)
from ssgc.parse.proposals import Candidates, cross_pairs, earlier_count, pose_groups
from ssgc.parse.reduction import ModelTooLarge, Request
from ssgc.parse.supertree import Supertree, hideable_nodes, or_weight
from ssgc.rules import POS_TOL, ROT_TOL, rotation_log_density, translation_log_density
from ssgc.tree import Trees

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
MAX_INSTANCES = 60_000
# A grammar without latent sets has no proposals to trim, and its instances are counted before
# pruning, where most fall away (a 50-dish sink scene: 63,260 counted, 6,663 kept; parsed in
# 0.7 s): over MAX_INSTANCES it went to the set model, which did not solve that scene in 100 s
# (457,324 variables), so the unrolled model takes such requests up to this many.
MAX_OBSERVED_INSTANCES = 200_000


IMPLIED_ROWS = 8192  # (node, object) poses worked out at once (between deadline checks)
# (node, object) pairs of one scene at most: 10 million poses take 640 MB.  100 nodes of 100
# objects each under 100 others asked for 10^8 (a MemoryError, exit 70), and 3,600 of 3,600
# took 2 GB and half a minute before the model's size was refused.
MAX_IMPLIED = 10_000_000


_CACHE: dict[tuple[int, str], tuple[Supertree, Any]] = {}  # (id(supertree), what) -> table
_CACHE_SIZE = 32


def per_supertree(st: Supertree, what: str, make: Callable[[Supertree], Any]) -> Any:
    """A table that depends on the supertree alone (its edges, its rigid subtrees), made once
    per supertree: a parser's every scene (and an explanation's every re-parse) shares it.
    The entry holds the supertree itself, so its id cannot be reused while cached."""
    key = (id(st), what)
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is st:
        return hit[1]
    if len(_CACHE) >= _CACHE_SIZE:
        _CACHE.pop(next(iter(_CACHE)))  # the oldest
    table = make(st)
    _CACHE[key] = (st, table)
    return table


@dataclass(frozen=True)
class Instances:
    """The unrolled nodes, for callers that rewrite their scores (`reduce_posed(adjust=...)`)."""

    st_node: IntArray  # supertree node of each instance
    parent: IntArray  # parent instance, -1 for the root
    cand_k: IntArray  # index of the instance's pose among its set's candidates
    top: IntArray  # the instance heading each instance's equivalent set
    score: FloatArray  # log-density of the instance's pose given its parent's (writable)


# Per set e: the (member node, rule) child slots and, per candidate pose a of e, the candidate
# index of the child allowed in each slot (the latent-pose assignments of ssgc.parse.bound).
FREE_CHILD = -2  # in a restriction's row: any candidate child (`ssgc.parse.bound.FREE`)
Restriction = dict[int, tuple[tuple[tuple[int, int], ...], IntArray]]


@dataclass(frozen=True)
class PosedProblem:
    milp: Milp
    st_node: IntArray  # (I,) supertree node of each instance
    parent: IntArray  # (I,) parent instance
    xyz: FloatArray
    quat: FloatArray
    col: IntArray  # (I,) column of a[instance], -1 if pruned
    structural: IntArray
    build_s: float
    supertree: Supertree

    def active(self, x: FloatArray) -> IntArray:
        """The instances a solution switches on, parents first (the nodes of `invert`)."""
        on = (self.col >= 0) & (x[np.maximum(self.col, 0)] > 0.5)
        return np.flatnonzero(on | (self.st_node == 0))  # the root is in every tree

    def invert(self, x: FloatArray) -> Trees:
        st = self.supertree
        on = self.active(x)
        new_index = np.full(len(self.col), -1, np.int64)
        new_index[on] = np.arange(len(on))
        parent = self.parent[on]
        return Trees(
            scene=np.zeros(len(on), np.int64),
            type=st.type[self.st_node[on]].copy(),
            parent=np.where(parent >= 0, new_index[np.maximum(parent, 0)], -1),
            rule=st.rule[self.st_node[on]].copy(),
            xyz=self.xyz[on].copy(),
            quat=self.quat[on].copy(),
            n_scenes=1,
        )


def candidate_poses(
    grammar: Grammar, st: Supertree, scene: Scene, deadline: float | None = None
) -> Candidates:
    """Per equivalent set, the distinct poses of its top node that put one of its observed
    nodes exactly on an object of the scene (latent sets get none here: see proposals).

    The poses are worked out for all observed nodes of one type and all objects of that type
    at once; a set keeps them in node, then object order, each unless it is within the pose
    tolerances of an earlier one.  Sets of the same shape (`_alike_sets`: the copies of a
    `repeat`) get the same poses, worked out once and shared: a 1,000-disc scene has a
    thousand sets of a thousand poses each, and working out each took 94% of its parse.
    Past the deadline it raises OutOfTime."""
    cand = Candidates(
        [np.zeros((0, 3)) for _ in range(st.n_sets)], [np.zeros((0, 4)) for _ in range(st.n_sets)]
    )
    observed = np.flatnonzero(grammar.tables.type_observed[st.type])
    mandatory = _mandatory(grammar, st)
    first = _alike_sets(st, observed, mandatory)
    leaders = observed[first[st.set_of[observed]] == st.set_of[observed]]
    node, obj, xyz, quat = _implied_poses(grammar, st, scene, leaders, deadline)
    check_deadline(deadline)
    e = st.set_of[node]
    order = np.argsort(e, kind="stable")  # per set, in node then object order
    check_deadline(deadline)
    e, node, obj, xyz, quat = e[order], node[order], obj[order], xyz[order], quat[order]
    held = np.zeros(st.n_sets, bool)  # sets where every instance holds an observed node
    held[st.set_of[observed[mandatory[observed]]]] = True
    sets, starts = np.unique(e, return_index=True)
    ends = np.r_[starts[1:], len(e)][: len(starts)]
    for s, lo, hi in zip(sets.tolist(), starts.tolist(), ends.tolist(), strict=True):
        who = node[lo:hi] if held[s] else None
        keep = _first_distinct(xyz[lo:hi], quat[lo:hi], obj[lo:hi], who, deadline)
        cand.xyz[s], cand.quat[s] = xyz[lo:hi][keep], quat[lo:hi][keep]
    for s in np.flatnonzero(first != np.arange(st.n_sets)).tolist():
        cand.xyz[s], cand.quat[s] = cand.xyz[first[s]], cand.quat[first[s]]
    root_set = int(st.set_of[0])  # the root's set has exactly one pose
    cand.xyz[root_set] = grammar.root_xyz.reshape(1, 3).copy()
    cand.quat[root_set] = grammar.root_quat.reshape(1, 4).copy()
    return cand


def _mandatory(grammar: Grammar, st: Supertree) -> NDArray[np.bool_]:
    """Supertree nodes present in every instance of their equivalent set: its top, and the
    children of mandatory `and` nodes in the same set."""
    out = np.zeros(len(st), bool)
    out[st.set_top] = True
    is_and = grammar.tables.type_kind[st.type] == Kind.AND
    parent = np.maximum(st.parent, 0)
    done = st.parent < 0  # the root
    while not np.all(done):  # generation by generation: each node once its parent is done
        lvl = np.flatnonzero(~done & done[parent])
        par = parent[lvl]
        out[lvl] |= out[par] & is_and[par] & (st.set_of[par] == st.set_of[lvl])
        done[lvl] = True
    return out


def _alike_sets(st: Supertree, observed: IntArray, mandatory: NDArray[np.bool_]) -> IntArray:
    """For each equivalent set, the first set of its shape: the same observed node types at
    the same offsets from the set's top, each mandatory or not alike, in the same order.  Two
    such sets have the same implied poses and keep the same candidates (the copies of a
    `repeat`, and the sets below them).  A set with no observed node is its own first."""
    first = np.arange(st.n_sets)
    e = st.set_of[observed]
    order = np.argsort(e, kind="stable")
    rows = np.column_stack(
        [st.type[observed], mandatory[observed], st.offset_xyz[observed], st.offset_quat[observed]]
    )
    rows, e = rows[order], e[order]
    sets, starts = np.unique(e, return_index=True)
    ends = np.r_[starts[1:], len(e)][: len(starts)]
    shapes: dict[bytes, int] = {}
    for s, lo, hi in zip(sets.tolist(), starts.tolist(), ends.tolist(), strict=True):
        first[s] = shapes.setdefault(rows[lo:hi].tobytes(), s)
    return first


def _implied_poses(
    grammar: Grammar,
    st: Supertree,
    scene: Scene,
    observed: IntArray,
    deadline: float | None = None,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """(observed supertree node, object, set-top xyz, set-top quat) of every (node, object of its
    type) pair of the given `observed` nodes, in node order, then object order: the pose of
    the node's set top that puts the node on the object.  Worked out about IMPLIED_ROWS
    pairs at a time, each written straight to its place, with a deadline check between (a
    thousand nodes of a thousand objects each are a million poses).  Also returns each pair's
    object."""
    n_objs = np.bincount(scene.types, minlength=len(grammar.types))[st.type[observed]]
    start = np.cumsum(n_objs) - n_objs  # each node's first row
    total = int(n_objs.sum())
    if total > MAX_IMPLIED:
        raise ModelTooLarge.single(
            f"scene '{scene.name}': {total:,} (node, object) pairs to place, over the limit of "
            f"{MAX_IMPLIED:,} ({len(scene)} objects, {len(observed):,} observed nodes in the "
            "grammar's supertree); parse fewer objects at a time"
        )
    node = np.repeat(observed, n_objs)
    obj = np.empty(total, np.int64)
    xyz, quat = np.empty((total, 3)), np.empty((total, 4))
    for t in np.unique(st.type[observed][n_objs > 0]).tolist():
        objs = np.flatnonzero(scene.types == t)
        mine = np.flatnonzero(st.type[observed] == t)
        step = max(1, IMPLIED_ROWS // len(objs))
        for lo in range(0, len(mine), step):
            check_deadline(deadline)
            m = mine[lo : lo + step]
            n = observed[m]
            q = quat_multiply(
                scene.quat[objs][None, :, :], quat_conjugate(st.offset_quat[n])[:, None, :]
            )
            x = scene.xyz[objs][None, :, :] - quat_rotate(q, st.offset_xyz[n][:, None, :])
            rows = (start[m][:, None] + np.arange(len(objs))[None, :]).reshape(-1)
            xyz[rows], quat[rows] = x.reshape(-1, 3), q.reshape(-1, 4)
            obj[rows] = np.tile(objs, len(m))
    return node, obj, xyz, quat


def _first_distinct(
    xyz: FloatArray,
    quat: FloatArray,
    obj: IntArray,
    node: IntArray | None,
    deadline: float | None,
) -> IntArray:
    """Indices of the poses a set keeps as its candidates: as many at one pose as the
    instances a tree can have there.

    Where every instance holds some observed node (`node` given: the set's top or an `and`
    below it is observed), each instance there holds its one object, so a pose is the r-th
    of its node there (its rank: how many earlier poses of its node are within the
    tolerances), and is dropped when an earlier pose of another node has the same rank: one
    instance explains both.  (Two mugs at the same pose were one candidate, and the scene
    was proven infeasible.)  Where the observed nodes are optional (`node` None: below an
    `or`, an `independent` or a `repeat`), each object there may be its own instance, so a
    pose is dropped only when an earlier one is the same object's: a cup and a plate at one
    pose, each a choice of an `or`, were one candidate, and the scene was proven
    infeasible.  The near pairs come from the sorted sweep of `Candidates.add`: a wide
    `repeat` of a 1,000-object scene has a thousand sets of a thousand poses each, and
    comparing every pair of each set took 25 s of CPU; a chain of 10,000 objects at one
    pose made 50 million pairs, so poses at one place are taken as a group
    (`proposals.PoseGroups`) and only distinct nearby poses are compared pairwise."""
    check_deadline(deadline)
    groups = pose_groups(xyz, quat)
    i, j = cross_pairs(groups)
    if node is None:
        taken = earlier_count(groups.of, obj) > 0
        taken[j[obj[i] == obj[j]]] = True
    else:
        one_node = node[i] == node[j]
        rank = earlier_count(groups.of, node) + np.bincount(j[one_node], minlength=len(xyz))
        # within a group the ranks of one node increase, so equal ranks are other nodes'
        taken = earlier_count(groups.of, rank) > 0
        taken[j[~one_node & (rank[i] == rank[j])]] = True
    return np.flatnonzero(~taken)


@dataclass(frozen=True)
class Unrolled:
    """The instances in breadth-first order (parents first; a parent's children by rule
    slot, then by copy or candidate index): the order the model's columns follow."""

    node: IntArray  # supertree node
    parent: IntArray  # parent instance, -1 for the root
    slot: IntArray  # index of the producing rule slot in the parent's children
    cand_k: IntArray  # index of the instance's pose among its set's candidates
    top: IntArray  # the instance heading each instance's set
    xyz: FloatArray
    quat: FloatArray


@dataclass(frozen=True)
class _Edges:
    """Child edges of the supertree as arrays, grouped by parent node: those of node n are
    rows start[n]:start[n + 1], in slot order, then copy order."""

    start: IntArray
    slot: IntArray  # the rule slot (one per rule, its first copy for a free rule)
    sub: IntArray  # the copy's index among the rule's copies (fixed rules)
    child: IntArray  # the supertree child
    rule: IntArray
    target: IntArray  # the child's set

    @staticmethod
    def of(st: Supertree, fixed: bool) -> _Edges:
        """The fixed edges (every copy) or the free ones (the first copy of each rule)."""
        rows: list[tuple[int, int, int, int, int]] = []
        start = np.zeros(len(st) + 1, np.int64)
        for n in range(len(st)):
            copies: dict[int, int] = {}  # rule -> copies seen so far (dicts keep slot order)
            for c in st.children[n]:
                r = int(st.rule[c])
                sub = copies.setdefault(r, 0)
                copies[r] += 1
                if (st.set_of[c] == st.set_of[n]) == fixed and (fixed or sub == 0):
                    rows.append((list(copies).index(r), sub, c, r, int(st.set_of[c])))
            start[n + 1] = len(rows)
        cols = np.array(rows, np.int64).reshape(-1, 5).T
        return _Edges(start, *cols)

    def expand(self, inst: IntArray, node: IntArray) -> tuple[IntArray, IntArray]:
        """(parent instance, edge row) of every edge of every instance, instance by instance."""
        count = self.start[node + 1] - self.start[node]
        parent = np.repeat(inst, count)
        return parent, np.repeat(self.start[node], count) + _within(count)


def _within(count: IntArray) -> IntArray:
    """0, 1, ..., count[0] - 1, 0, 1, ..., count[1] - 1, ...: each row's place in its group."""
    total = int(count.sum())
    return np.arange(total) - np.repeat(np.cumsum(count) - count, count)


class _Unroll:
    """Builds the instances (supertree node, pose) top-down, one generation at a time, each in
    a few array operations: the fixed rules' children of every instance of the generation are
    one batched quaternion product, the free rules' children the cross product of the
    instances with their sets' candidate poses (`_Edges`)."""

    def __init__(
        self,
        grammar: Grammar,
        st: Supertree,
        scene: Scene,
        cand: Candidates,
        restrict: Restriction | None = None,
    ) -> None:
        self.g, self.st, self.scene = grammar, st, scene
        self.cand_xyz, self.cand_quat = cand.xyz, cand.quat
        self.n_cand = np.array([len(x) for x in cand.xyz], np.int64)
        self.cand_start = np.cumsum(self.n_cand) - self.n_cand
        self.all_xyz = np.concatenate([x.reshape(-1, 3) for x in cand.xyz])
        self.all_quat = np.concatenate([q.reshape(-1, 4) for q in cand.quat])
        self.restrict = restrict or {}
        self.restricted = np.isin(st.set_of, np.array(list(self.restrict), np.int64))
        self.fixed = per_supertree(st, "fixed edges", lambda s: _Edges.of(s, True))
        self.free = per_supertree(st, "free edges", lambda s: _Edges.of(s, False))
        self.deadline: float | None = None

    def unroll(self) -> Unrolled:
        g = self.g
        cols: dict[str, list[Any]] = {
            "node": [np.zeros(1, np.int64)],
            "parent": [np.full(1, -1, np.int64)],
            "slot": [np.full(1, -1, np.int64)],
            "cand_k": [np.zeros(1, np.int64)],
            "top": [np.zeros(1, np.int64)],
            "xyz": [np.asarray(g.root_xyz, float).reshape(1, 3)],
            "quat": [np.asarray(g.root_quat, float).reshape(1, 4)],
        }
        lo, n_total = 0, 1
        cand_k_all, top_all = cols["cand_k"][0], cols["top"][0]
        while True:  # generation [lo, n_total) gives the next one
            check_deadline(self.deadline)
            gen = (cols["node"][-1], cols["xyz"][-1], cols["quat"][-1])
            kid = self._children(lo, *gen, cand_k_all, top_all)
            if not len(kid["node"]):
                break
            order = np.lexsort((kid["sub"], kid["slot"], kid["parent"]))  # breadth first
            kid = {k: v[order] for k, v in kid.items()}
            own = np.arange(n_total, n_total + len(order))
            kid["top"] = np.where(kid.pop("fixed"), top_all[kid["parent"]], own)
            for k, v in cols.items():
                v.append(kid[k])
            cand_k_all = np.concatenate([cand_k_all, kid["cand_k"]])
            top_all = np.concatenate([top_all, kid["top"]])
            lo, n_total = n_total, n_total + len(order)
        return Unrolled(
            *(np.concatenate(cols[k]) for k in ("node", "parent", "slot", "cand_k", "top")),
            np.concatenate(cols["xyz"]).reshape(-1, 3),
            np.concatenate(cols["quat"]).reshape(-1, 4),
        )

    def _children(
        self,
        lo: int,
        node: IntArray,
        xyz: FloatArray,
        quat: FloatArray,
        cand_k: IntArray,
        top: IntArray,
    ) -> dict[str, Any]:
        """The children of the generation starting at instance `lo` (unordered), with the
        keys (parent, slot, sub) that order them."""
        tb = self.g.tables
        inst = lo + np.arange(len(node))
        parent, e = self.fixed.expand(inst, node)  # fixed rules: the rule's offset
        r, local = self.fixed.rule[e], parent - lo
        fixed = {
            "node": self.fixed.child[e],
            "parent": parent,
            "slot": self.fixed.slot[e],
            "sub": self.fixed.sub[e],
            "cand_k": cand_k[parent],
            "fixed": np.ones(len(e), bool),
            "xyz": xyz[local] + quat_rotate(quat[local], tb.point_xyz[r]),
            "quat": quat_multiply(quat[local], tb.point_quat[r]),
        }
        free_mask = ~self.restricted[node]
        parent, e = self.free.expand(inst[free_mask], node[free_mask])
        count = self.n_cand[self.free.target[e]]  # one child per candidate pose of its set
        parent, e, k = np.repeat(parent, count), np.repeat(e, count), _within(count)
        parts = [fixed, self._free(parent, e, k)]
        if np.any(~free_mask):
            parts.append(self._restricted(inst[~free_mask], node[~free_mask], cand_k, top))
        return {key: np.concatenate([p[key] for p in parts]) for key in fixed}

    def _free(self, parent: IntArray, e: IntArray, k: IntArray) -> dict[str, Any]:
        """Free-rule children: edge rows e of parents `parent`, at candidates k."""
        at = self.cand_start[self.free.target[e]] + k
        return {
            "node": self.free.child[e],
            "parent": parent,
            "slot": self.free.slot[e],
            "sub": k,
            "cand_k": k,
            "fixed": np.zeros(len(e), bool),
            "xyz": self.all_xyz[at],
            "quat": self.all_quat[at],
        }

    def _restricted(
        self, inst: IntArray, node: IntArray, cand_k: IntArray, top: IntArray
    ) -> dict[str, Any]:
        """Free-rule children of instances in `restrict`ed sets: per slot, the candidates
        their set top's assignment names (`_allowed`)."""
        parents: list[IntArray] = [np.zeros(0, np.int64)]
        rows: list[IntArray] = [np.zeros(0, np.int64)]
        ks: list[IntArray] = [np.zeros(0, np.int64)]
        for n in np.unique(node).tolist():
            mine = inst[node == n]
            for e in range(self.free.start[n], self.free.start[n + 1]):
                rule, target = int(self.free.rule[e]), int(self.free.target[e])
                p, k = self._allowed(mine, n, rule, target, cand_k[top[mine]])
                parents.append(p)
                rows.append(np.full(len(p), e, np.int64))
                ks.append(k)
        return self._free(np.concatenate(parents), np.concatenate(rows), np.concatenate(ks))

    def _allowed(
        self, inst: IntArray, n: int, rule: int, e: int, top_k: IntArray
    ) -> tuple[IntArray, IntArray]:
        """(parent instance, candidate index) of every child the instances `inst` (of node
        n, their set tops at candidates `top_k`) may have through `rule` in set e."""
        n_cand = len(self.cand_xyz[e])
        everything = (np.repeat(inst, n_cand), np.tile(np.arange(n_cand), len(inst)))
        slots, assignment = self.restrict[int(self.st.set_of[n])]
        cols = [j for j, s in enumerate(slots) if s == (n, rule)]
        if not cols:  # a rule the assignment does not name (an independent latent child)
            return everything
        named = assignment[:, cols]  # per assignment row; -1: this column has no child
        rows, row_of = np.unique(top_k, return_inverse=True)  # instances sharing a row share
        k_start, k_count, k = _row_children(named[rows], n_cand)  # their children
        count = k_count[row_of]
        parents = np.repeat(inst, count)
        at = np.repeat(k_start[row_of], count) + _within(count)
        return parents, k[at]


def _row_children(named: IntArray, n_cand: int) -> tuple[IntArray, IntArray, IntArray]:
    """Per assignment row: the distinct candidates it names (every candidate where a column
    is FREE_CHILD), as (start, count) into one flat array of candidate indices."""
    free = np.any(named == FREE_CHILD, axis=1)
    ordered = np.sort(named, axis=1)
    first = np.ones_like(ordered, bool)
    first[:, 1:] = ordered[:, 1:] != ordered[:, :-1]
    keep = first & (ordered >= 0) & ~free[:, None]
    count = np.where(free, n_cand, keep.sum(axis=1))
    width = np.maximum(count, 0)
    flat = np.zeros(int(width.sum()), np.int64)
    start = np.cumsum(width) - width
    rows, cols = np.nonzero(keep)
    place = np.cumsum(keep, axis=1) - 1  # a kept entry's place among its row's kept ones
    flat[start[rows] + place[rows, cols]] = ordered[rows, cols]
    f = np.flatnonzero(free)
    flat[np.repeat(start[f], n_cand) + np.tile(np.arange(n_cand), len(f))] = np.tile(
        np.arange(n_cand), len(f)
    )
    return start, count, flat


def instance_count(
    st: Supertree,
    cand: Candidates,
    restricted: frozenset[int] = frozenset(),
    limit: int = MAX_INSTANCES,
) -> int:
    """How many instances `reduce_posed` would unroll (counting stops past `limit`):
    a fixed child has one per instance of its parent, the first copy of every other rule one
    per candidate pose of its set (one, under a `restrict`ed parent set), other copies none."""
    n_cand = [len(x) for x in cand.xyz]
    count = [0] * len(st)
    count[0] = total = 1
    for n in range(len(st)):
        if not count[n]:
            continue
        own = int(st.set_of[n])
        seen: set[int] = set()
        for c in st.children[n]:
            r = int(st.rule[c])
            if st.set_of[c] == own:
                count[c] = count[n]
            elif r not in seen:
                copies = sum(1 for c2 in st.children[n] if st.rule[c2] == r)
                per = copies if own in restricted else n_cand[st.set_of[c]]
                count[c] = count[n] * per
            seen.add(r)
            total += count[c]
        if total > limit:
            break
    return total


FIT_STEP = 0.8  # each try keeps this share of the previous try's proposals per latent set


def fit_instances(st: Supertree, cand: Candidates, latent: NDArray[np.bool_]) -> bool:
    """Drop proposed poses of the latent sets until the unrolled model stays within
    MAX_INSTANCES; whether anything was dropped.  Each latent set keeps the same share of its
    poses, half from the front of its list (the poses its children imply, first proposed) and
    half from the back (the bound's assignment poses, the chain's and the hard laws' poses,
    added last).

    Why: the model over proposals unrolls a latent set once per pose of its latent parent, so
    a chain of two latent sets with 150 and 70 proposals each passes the limit (issue 11:
    `no_parse`, phase `instance_limit`).  The model over proposals is not complete anyway:
    fewer proposals never make a false answer (its trees are real and re-scored, and the
    certificate comes from the assignment bound, which does not use them)."""
    if instance_count(st, cand) <= MAX_INSTANCES:
        return False
    sets = np.flatnonzero(latent)
    full = {int(e): (cand.xyz[e], cand.quat[e]) for e in sets}
    share = 1.0
    while share > 1e-3:
        share *= FIT_STEP
        for e, (xyz, quat) in full.items():
            keep = _front_and_back(len(xyz), max(1, int(share * len(xyz))))
            cand.xyz[e], cand.quat[e] = xyz[keep], quat[keep]
        if instance_count(st, cand) <= MAX_INSTANCES:
            return True
    return True


def _front_and_back(n: int, k: int) -> IntArray:
    """k of n indices: the first ⌈k/2⌉ and the last ⌊k/2⌋."""
    front = (k + 1) // 2
    return np.r_[np.arange(front), np.arange(n - (k - front), n)].astype(np.int64)


def reduce_posed(
    grammar: Grammar,
    st: Supertree,
    scene: Scene,
    cand: Candidates | None = None,
    adjust: Callable[[Instances], None] | None = None,
    restrict: Restriction | None = None,
    deadline: float | None = None,
    best_only: bool = False,
) -> PosedProblem:
    """The unrolled MILP over the given candidate poses (by default, the observed ones).

    `best_only` drops the `or` alternatives no best tree needs (`_Model.drop_dominated`):
    the model then keeps the MAP score, its certificate and its infeasibility proofs, but
    not every tree, so it is for a parse of the best tree alone (`--top 1`).

    `restrict` limits the children of some sets' instances to one candidate per slot, and
    `adjust` may rewrite the instances' edge scores before the model is built (-inf removes an
    instance): `ssgc.parse.bound` uses both for latent-pose assignments and their bounds.
    """
    t0 = time.perf_counter()
    if cand is None:
        cand = candidate_poses(grammar, st, scene)
    u = _Unroll(grammar, st, scene, cand, restrict)
    u.deadline = deadline
    inst = u.unroll()
    node, parent, xyz, quat = inst.node, inst.parent, inst.xyz, inst.quat
    model = _Model(grammar, st, scene, node, parent, inst.slot, xyz, quat)
    model.cand_k = inst.cand_k
    model.order_copies = adjust is None and restrict is None  # copies stay exchangeable
    model.deadline = deadline
    check_deadline(deadline)
    model.edge_scores()
    model.rule_probs()
    if best_only:
        model.drop_dominated()
    if adjust is not None:
        adjust(Instances(node, parent, inst.cand_k, inst.top, model.score))
    milp = model.build()
    return PosedProblem(
        milp,
        node,
        parent,
        xyz,
        quat,
        model.col,
        np.concatenate(model.structural).astype(np.int64),
        time.perf_counter() - t0,
        st,
    )


class PosedReduction:
    """The unrolled model over candidate poses (`reduce_posed`), for requests without the
    bound's assignments whose unrolled instances stay within MAX_INSTANCES."""

    def accepts(self, request: Request) -> bool:
        return _unbound(request) and self._count(request) <= _limit(request)

    def refusal(self, request: Request) -> str | None:
        if not _unbound(request) or self._count(request) <= _limit(request):
            return None
        return too_many_instances(request.scene, _limit(request))

    def apply(self, request: Request) -> tuple[Milp, PosedProblem]:
        r = request
        problem = reduce_posed(
            r.grammar, r.supertree, r.scene, r.cand, deadline=r.deadline, best_only=r.best_only
        )
        return problem.milp, problem

    def invert(self, problem: PosedProblem, x: FloatArray) -> Trees:
        return problem.invert(x)

    @staticmethod
    def _count(request: Request) -> int:
        return instance_count(request.supertree, request.cand, limit=_limit(request))


def _limit(request: Request) -> int:
    return MAX_INSTANCES if request.latent else MAX_OBSERVED_INSTANCES


def _unbound(request: Request) -> bool:
    """No assignments to build on: none, or bounds that only certify (`certify_only`)."""
    return request.bounds is None or any(b.decoupled for b in request.bounds.values())


def too_many_instances(scene: Scene, limit: int = MAX_INSTANCES) -> str:
    return (
        f"scene '{scene.name}': the parse model would have more than {limit:,} node "
        f"instances ({len(scene)} objects); parse fewer objects at a time"
    )


def _rule_copies(st: Supertree) -> IntArray:
    """Per supertree node, how many children its parent has by the node's rule (a
    `repeat`'s copies; 1 otherwise)."""
    out = np.ones(len(st), np.int64)
    for kids in st.children:
        rules = st.rule[np.asarray(kids, np.int64)]
        if len(rules):
            _, inverse, counts = np.unique(rules, return_inverse=True, return_counts=True)
            out[np.asarray(kids, np.int64)] = counts[inverse]
    return out


def rigid_signatures(st: Supertree) -> IntArray:
    """Per supertree node, an id shared by nodes heading identical rigid subtrees (the same
    types and rules below, every rule fixed, so the same instances at the same pose), -1 for
    a node with a free rule below it."""
    sig = np.full(len(st), -1, np.int64)
    ids: dict[tuple[Any, ...], int] = {}
    for n in range(len(st) - 1, -1, -1):  # children come after their parents
        kids = st.children[n]
        if any(st.set_of[c] != st.set_of[n] or sig[c] < 0 for c in kids):
            continue
        key = (int(st.type[n]), tuple(sorted((int(st.rule[c]), int(sig[c])) for c in kids)))
        sig[n] = ids.setdefault(key, len(ids))
    return sig


NEAR_K = 8  # neighbours asked of the k-d tree per instance; more only where all 8 are near


def _near_pairs(points: FloatArray, objects: FloatArray) -> tuple[IntArray, IntArray]:
    """(point, object) index pairs within POS_TOL of each other.  A k-d tree over the
    objects instead of the (points × objects) distance array: an 85-object scene has ~10⁵
    instance poses, whose dense array took 0.2–0.3 s without a deadline check."""
    k = min(NEAR_K, len(objects))
    d, j = cKDTree(objects).query(points, k=k, distance_upper_bound=2 * POS_TOL)
    d, j = d.reshape(len(points), k), j.reshape(len(points), k)
    pi, col = np.nonzero(np.isfinite(d))
    oi = j[pi, col]
    crowded = np.flatnonzero(np.isfinite(d[:, -1])) if k < len(objects) else np.zeros(0, int)
    if len(crowded):  # k neighbours all near: the rest may be too (degenerate scenes)
        full = np.linalg.norm(points[crowded][:, None] - objects[None], axis=2) <= POS_TOL
        ci, co = np.nonzero(full)
        drop = np.isin(pi, crowded)
        pi, oi = np.concatenate([pi[~drop], crowded[ci]]), np.concatenate([oi[~drop], co])
    exact = np.linalg.norm(points[pi] - objects[oi], axis=1) <= POS_TOL
    return pi[exact], oi[exact]


class _Model:
    """The MILP over instances: activations, correspondences, node logic, costs."""

    def __init__(
        self,
        g: Grammar,
        st: Supertree,
        scene: Scene,
        node: IntArray,
        parent: IntArray,
        slot: IntArray,
        xyz: FloatArray,
        quat: FloatArray,
    ) -> None:
        self.g, self.st, self.scene = g, st, scene
        self.node, self.parent, self.slot, self.xyz, self.quat = node, parent, slot, xyz, quat
        self.type = st.type[node]
        self.rule = st.rule[node]
        self.cols, self.rows = ColumnBuilder(), RowBuilder()
        self.structural: list[IntArray] = []
        self.deadline: float | None = None
        self.cand_k = np.zeros(len(node), np.int64)  # candidate index (`Unrolled.cand_k`)
        self.order_copies = False  # order exchangeable `or` copies (`_ordered_choices`)
        n = len(node)
        order = np.argsort(parent[1:], kind="stable") + 1  # children in instance order
        ends = np.cumsum(np.bincount(parent[1:], minlength=n))[:-1] if n else []
        self.children: list[list[int]] = [c.tolist() for c in np.split(order, ends)]

    def build(self) -> Milp:
        for step in (
            self.matches,
            self.prune,
            self.columns,
            self.correspondence_rows,
            self.logic_rows,
        ):
            check_deadline(self.deadline)
            step()
        check_deadline(self.deadline)
        return Milp.build(self.cols, self.rows)

    def edge_scores(self) -> None:
        """log p(pose | parent pose) of every instance; 0 for the root."""
        p = np.maximum(self.parent, 0)
        score = np.zeros(len(self.node))
        child = np.flatnonzero(self.parent >= 0)
        if len(child):
            r, pp = self.rule[child], p[child]
            score[child] = translation_log_density(
                self.g, r, self.xyz[pp], self.quat[pp], self.xyz[child]
            ) + rotation_log_density(self.g, r, self.quat[pp], self.quat[child])
        self.score = score

    def matches(self) -> None:
        """(instance, object) pairs: an observed instance exactly on an object of its type."""
        observed = self.g.tables.type_observed[self.type]
        inst, obj = [], []
        scene = self.scene
        for t in np.unique(self.type[observed]):
            ii = np.flatnonzero(observed & (self.type == t))
            oo = np.flatnonzero(scene.types == t)
            if len(oo) == 0:
                continue
            hit_i, hit_o = _near_pairs(self.xyz[ii], scene.xyz[oo])
            a = quat_angle(self.quat[ii[hit_i]], scene.quat[oo[hit_o]])
            keep = a <= ROT_TOL
            inst.append(ii[hit_i[keep]])
            obj.append(oo[hit_o[keep]])
        self.match_inst = np.concatenate(inst) if inst else np.zeros(0, np.int64)
        self.match_obj = np.concatenate(obj) if obj else np.zeros(0, np.int64)
        self.observed = observed
        self.implicit_root = bool(observed[0] and not np.any(scene.types == self.type[0]))

    def prune(self) -> None:
        g = self.g
        n = len(self.node)
        can = np.isfinite(self.score)
        explains = np.zeros(n, bool)
        explains[self.match_inst] = True
        explains[0] |= self.implicit_root
        can &= ~self.observed | explains
        check_deadline(self.deadline)
        can[1:] &= self.prob[1:] > 0  # rules that can never fire
        for i in range(n - 1, -1, -1):
            if i % 512 == 0:
                check_deadline(self.deadline)
            if not can[i]:
                continue
            node = g.types[self.type[i]]
            slots = self._slot_groups(i, can)
            n_slots = len(self._slot_rules(i))
            if node.kind == Kind.AND:
                can[i] = len(slots) == n_slots and all(slots.values())
            elif node.kind == Kind.OR and n_slots:
                can[i] = any(slots.values())
            elif node.kind == Kind.INDEPENDENT:
                can[i] = all(slots.get(k) for k, p in self._slot_probs(i).items() if p >= 1)
            elif node.kind == Kind.REPEAT and node.count is not None and n_slots:
                live = sum(len(v) for v in slots.values())
                can[i] = bool(np.any(node.count.probs[: live + 1] > 0))
        for i in range(1, n):
            can[i] &= can[self.parent[i]]
        if not can[0]:
            raise UnparseableScene([self._unexplained()], exit_code=2)
        self.can = can

    def _unexplained(self) -> Diagnostic:
        return unplaceable(self.g, self.scene, set(self.match_obj.tolist()))

    def _slot_rules(self, i: int) -> list[int]:
        return sorted({int(self.st.rule[c]) for c in self.st.children[self.node[i]]})

    def _slot_groups(self, i: int, can: NDArray[np.bool_]) -> dict[int, list[int]]:
        """Live children of instance i grouped by producing rule."""
        out: dict[int, list[int]] = {}
        for c in self.children[i]:
            if can[c]:
                out.setdefault(int(self.rule[c]), []).append(c)
        return out

    def _slot_probs(self, i: int) -> dict[int, float]:
        node = self.g.types[self.type[i]]
        return {r: float(node.probs[self.g.tables.rule_index[r]]) for r in self._slot_rules(i)}

    def rule_probs(self) -> None:
        """Per instance, the probability of the rule that made it: under an `or`, its weight
        renormalised over the rules present; under `independent`, its p; else 1.  It depends
        on the supertree node alone, so it is worked out once per node."""
        st, g = self.st, self.g
        per_node = np.ones(len(st))
        for c in np.unique(self.node[1:]).tolist():
            p = int(st.parent[c])
            node = g.types[st.type[p]]
            if node.kind not in (Kind.OR, Kind.INDEPENDENT):
                continue
            rules = sorted({int(st.rule[k]) for k in st.children[p]})
            probs = {r: float(node.probs[g.tables.rule_index[r]]) for r in rules}
            w = probs[int(st.rule[c])]
            per_node[c] = or_weight(w, sum(probs.values())) if node.kind == Kind.OR else w
        self.prob = per_node[self.node]
        self.prob[0] = 1.0

    def drop_dominated(self) -> None:
        """Remove the `or` alternatives no best parse uses (their score becomes -inf).

        Children of one `or` instance that are the same rigid subtree (every rule below
        fixed, the same types and rules) at the same pose differ only in the rule that placed
        them — a plate upside down or on its side, where it lies — so a tree choosing any of
        them scores at most what it scores with the best of them (its placement log-density
        plus its choice's log-probability; the subtree's terms are equal).  Keeping only the
        best is exact for the MAP tree (and its certificate), not for the N-th best."""
        sig = per_supertree(self.st, "rigid signatures", rigid_signatures)
        par = self.parent
        kids = np.flatnonzero(par >= 0)
        is_or = np.array([t.kind == Kind.OR for t in self.g.types])
        hide = per_supertree(self.st, "hideable", lambda st: hideable_nodes(self.g, st))
        # an unseen subtree scores its choice alone, a seen one its edge too: not comparable
        kids = kids[is_or[self.type[par[kids]]] & (sig[self.node[kids]] >= 0)]
        kids = kids[~hide[self.node[kids]]]
        if len(kids) < 2:
            return
        key = np.column_stack([par[kids], sig[self.node[kids]], self.xyz[kids], self.quat[kids]])
        _, group = np.unique(key, axis=0, return_inverse=True)
        group = group.reshape(-1)
        with np.errstate(divide="ignore"):
            value = self.score[kids] + np.log(self.prob[kids])
        order = np.lexsort((kids, -value, group))  # best first in each group, ties: first
        first = np.r_[True, group[order][1:] != group[order][:-1]]
        self.score[kids[order[~first]]] = -np.inf

    def columns(self) -> None:
        live = np.flatnonzero(self.can)
        # a latent node that cannot be unseen (every way of making it shows an object) is
        # seen whenever it is there: its edge stays on its a, with no column or row more
        latent = live[self._needs_seen_column(live)]
        self.col = np.full(len(self.node), -1, np.int64)
        cost = np.where(np.isin(live, latent), 0.0, self.score[live])
        self.col[live] = self.cols.add(len(live), integer=True, cost=cost)
        self.cols.lo[-1] = np.where(live == 0, 1.0, 0.0)
        self.structural.append(self.col[live[live != 0]])
        ch = live[live != 0]
        add_leq(self.rows, self.col[ch], self.col[self.parent[ch]])  # child <= parent
        self.seen_rows(live, latent)

    def _needs_seen_column(self, live: IntArray) -> NDArray[np.bool_]:
        """Which live instances get a column v: latent ones that can be unseen and either
        have an edge to count or a parent that has v (its OR needs theirs).  The sink's
        empty `repeat`s at their parent's pose need none: their edges are 0."""
        hide = per_supertree(self.st, "hideable", lambda st: hideable_nodes(self.g, st))
        can_hide = np.zeros(len(self.node), bool)
        can_hide[live] = ~self.observed[live] & hide[self.node[live]]
        can_hide[0] = False
        need = can_hide & (self.score != 0.0)
        parent = np.maximum(self.parent, 0)
        while True:  # one generation per round: a v parent's hideable children need v
            more = need | (can_hide & need[parent] & (self.parent >= 0))
            if np.array_equal(more, need):
                return need[live]
            need = more

    def seen_rows(self, live: IntArray, latent: IntArray) -> None:
        """A latent instance's edge counts only where something observed lies at or below it
        (`ssgc.score`, marginal): v[i] = a[i] and OR(v of its children), v = a for an
        observed instance and for one that cannot be unseen (`latent` holds the others).
        v ≤ a, v ≤ the children's sum and v ≥ each child's make v exactly
        that OR, so v needs no integrality (it is integral whenever the a are)."""
        v = self.col.copy()
        v[latent] = self.cols.add(len(latent), integer=False, cost=self.score[latent])
        add_leq(self.rows, v[latent], self.col[latent])
        kids = live[live != 0]
        kids = kids[np.isin(self.parent[kids], latent)]
        add_leq(self.rows, v[kids], v[self.parent[kids]])  # something seen below: seen
        row = np.searchsorted(latent, self.parent[kids])  # v[p] <= sum of its children's v
        self.rows.add(
            np.r_[np.arange(len(latent)), row],
            np.r_[v[latent], v[kids]],
            np.r_[np.ones(len(latent)), -np.ones(len(kids))],
            len(latent),
            -np.inf,
            0.0,
        )
        if self.order_copies:
            self._unseen_first(latent, v)

    def _unseen_first(self, latent: IntArray, v: IntArray) -> None:
        """An unseen instance's pose is integrated out, so the same tree has it at any of its
        candidates; each solve of `--top N` found one more of them, a copy to refine and
        drop (60 solves for 2 trees).  Only the first m candidates of each (parent, node)
        may hold an unseen instance, m the copies of its rule (1 but for a `repeat`): enough
        for every unseen copy wherever the seen ones sit.  For the model over proposals
        only: a candidate whose children a pose law rules out may then be the one kept, so
        the bound's models (`adjust`, `restrict`) keep every candidate."""
        copies = per_supertree(self.st, "rule copies", _rule_copies)
        order = np.lexsort((self.cand_k[latent], self.node[latent], self.parent[latent]))
        inst = latent[order]
        key = np.column_stack([self.parent[inst], self.node[inst]])
        start = np.r_[True, np.any(key[1:] != key[:-1], axis=1)]
        first = np.maximum.accumulate(np.where(start, np.arange(len(inst)), 0))
        late = inst[np.arange(len(inst)) - first >= copies[self.node[inst]]]
        add_leq(self.rows, self.col[late], v[late])  # a <= v: seen where it is at all

    def correspondence_rows(self) -> None:
        keep = self.can[self.match_inst]
        inst, obj = self.match_inst[keep], self.match_obj[keep]
        n_obj = len(self.scene)
        if np.any(np.bincount(obj, minlength=n_obj) == 0):
            raise UnparseableScene([self._unexplained()], exit_code=2)
        b = self.cols.add(len(inst), integer=True)
        self.structural.append(b)
        obs = np.flatnonzero(self.can & self.observed)
        if self.implicit_root:
            obs = obs[obs != 0]
        add_correspondences(self.rows, b, inst, obj, n_obj, self.col, obs)

    def logic_rows(self) -> None:
        g = self.g
        eq_r: list[int] = []
        eq_c: list[int] = []
        eq_v: list[float] = []
        n_eq = 0
        cost_c: list[int] = []
        cost_v: list[float] = []
        for count, i in enumerate(np.flatnonzero(self.can)):
            if count % 512 == 0:
                check_deadline(self.deadline)
            node = g.types[self.type[i]]
            if node.kind == Kind.TERMINAL:
                continue
            groups = self._slot_groups(i, self.can)
            a = int(self.col[i])
            if node.kind == Kind.AND:
                for kids in groups.values():  # each rule fires once: sum over its poses = a
                    eq_r += [n_eq] * (len(kids) + 1)
                    eq_c += [int(self.col[c]) for c in kids] + [a]
                    eq_v += [1.0] * len(kids) + [-1.0]
                    n_eq += 1
            elif node.kind == Kind.OR and groups:
                kids = [c for v in groups.values() for c in v]
                eq_r += [n_eq] * (len(kids) + 1)
                eq_c += [int(self.col[c]) for c in kids] + [a]
                eq_v += [1.0] * len(kids) + [-1.0]
                n_eq += 1
                cost_c += [int(self.col[c]) for c in kids]
                cost_v += np.log(self.prob[kids]).tolist()
            elif node.kind == Kind.INDEPENDENT:
                for r, p in self._slot_probs(i).items():
                    kids = groups.get(r, [])
                    if p >= 1:
                        eq_r += [n_eq] * (len(kids) + 1)
                        eq_c += [int(self.col[c]) for c in kids] + [a]
                        eq_v += [1.0] * len(kids) + [-1.0]
                        n_eq += 1
                    elif p > 0:
                        cost_c.append(a)
                        cost_v.append(float(np.log1p(-p)))
                        cost_c += [int(self.col[c]) for c in kids]
                        cost_v += [float(np.log(p) - np.log1p(-p))] * len(kids)
                        if len(kids) > 1:  # at most one pose for the one child
                            self.rows.add(
                                np.zeros(len(kids) + 1, np.int64),
                                np.r_[self.col[kids], a],
                                np.r_[np.ones(len(kids)), -1.0],
                                1,
                                -np.inf,
                                0.0,
                            )
            elif node.kind == Kind.REPEAT and node.count is not None and self._slot_rules(i):
                kids = [c for v in groups.values() for c in v]
                self._repeat(a, kids, node.count.probs)
        self.rows.add(
            np.asarray(eq_r, np.int64),
            np.asarray(eq_c, np.int64),
            np.asarray(eq_v, float),
            n_eq,
            0.0,
            0.0,
        )
        self.cols.add_cost(np.asarray(cost_c, np.int64), np.asarray(cost_v, float))

    def _repeat(self, a: int, kids: list[int], probs: FloatArray) -> None:
        """The count law of a `repeat` whose rule is there in the supertree: one blocked by
        `max_nesting` makes nothing with probability 1 (no law, docs/grammar.md 3.4)."""
        add_count_law(self.cols, self.rows, a, self.col[kids], probs)
        # copies at one pose (a fixed `repeat` rule) fill up in order
        st = self.st
        same = [c for c in kids if st.set_of[self.node[c]] == st.set_of[self.node[self.parent[c]]]]
        if len(same) > 1:
            add_leq(self.rows, self.col[same[1:]], self.col[same[:-1]])
            if self.order_copies and self.g.types[self.type[same[0]]].kind == Kind.OR:
                for first, second in itertools.pairwise(same):
                    self._ordered_choices(first, second)

    def _ordered_choices(self, first: int, second: int) -> None:
        """Two copies of one `or` at one pose (a fixed `repeat` rule) are exchangeable: any
        tree can swap them so that the second's choice (its live child's place in the copy's
        list, the same list for both) comes no earlier than the first's.  Prefix sums say it:
        for every m, sum(second's children up to m) <= sum(first's up to m)."""
        a = [c for c in self.children[first] if self.can[c]]
        b = [c for c in self.children[second] if self.can[c]]
        key = np.column_stack([self.slot, self.cand_k])
        if len(a) != len(b) or len(a) < 2 or not np.array_equal(key[a], key[b]):
            return  # not the same list of choices: no ordering to add
        m = len(a)
        row, pos = np.tril_indices(m)  # row m holds positions 0..m
        self.rows.add(
            np.r_[row, row],
            np.r_[self.col[b][pos], self.col[a][pos]],
            np.r_[np.ones(len(row)), -np.ones(len(row))],
            m,
            -np.inf,
            0.0,
        )
