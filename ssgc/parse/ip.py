"""The equivalent-set integer program for MAP parsing (thesis 3.5), as a reduction.

`reduce_scene(grammar, supertree, scene)` lowers a parse problem to a `Milp` plus the data to
map a solution back (`ParseProblem.invert(x) -> Trees`); the tree read back is re-scored with
the grammar's own scorer, so a parse score and a tree score can never disagree.

Variables (all derived from the supertree, after pruning nodes that cannot be active):
  a[n]      node n is in the tree (binary; the root is fixed to 1)
  s[E, k]   equivalent set E takes its k-th candidate pose (binary)
  b[n, o]   observed node n explains scene object o (binary)
  z[n, c]   `repeat` node n has c children (binary, one per possible count)
  e[p→c,i,j] the edge p→c joins parent pose i and child pose j (continuous in [0, 1]: it is
            integral whenever the s are)
Objective: the tree's log-probability (Eq. 2.1), exactly — discrete terms on a and z, every
rule's log-density precomputed per candidate pose pair on e.

Candidate poses of a set come from the observed objects its observed nodes could explain, so
this model is for grammars without latent poses (`SetReduction.accepts`); the parser takes it
when the pose-instantiated model (`ssgc.parse.posed`) would be too large.  Grammars with latent
poses go through `ssgc.parse.posed` and `ssgc.parse.bound`, over proposed poses.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import Diagnostic, SsgError
from ssgc.geometry import quat_angle, quat_conjugate, quat_multiply, quat_rotate
from ssgc.io.scene import Scene
from ssgc.ir import Grammar, Kind
from ssgc.parse.milp import (
    ColumnBuilder,
    Milp,
    RowBuilder,
    add_correspondences,
    add_count_law,
    add_leq,
)
from ssgc.parse.proposals import Candidates
from ssgc.parse.reduction import Request
from ssgc.parse.supertree import Supertree, or_weight
from ssgc.rules import POS_TOL, ROT_TOL, rotation_log_density, translation_log_density
from ssgc.tree import Trees

MAX_SET_COLUMNS = 1_000_000  # the set model's variables: HiGHS needs ~2.5 kB each

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


class UnparseableScene(SsgError):
    """The grammar cannot produce this scene (exit code 2)."""


def implied_set_poses(grammar: Grammar, st: Supertree, scene: Scene):  # type: ignore[no-untyped-def]
    """For each observed supertree node n with objects of its type: (n, objects, t, q), the
    poses of n's set top that put n exactly on each of those objects."""
    for n in np.flatnonzero(grammar.tables.type_observed[st.type]):
        objs = np.flatnonzero(scene.types == st.type[n])
        if len(objs):
            q = quat_multiply(scene.quat[objs], quat_conjugate(st.offset_quat[n]))
            yield int(n), objs, scene.xyz[objs] - quat_rotate(q, st.offset_xyz[n]), q


def unplaceable(grammar: Grammar, scene: Scene, placeable: set[int]) -> Diagnostic:
    """The message for a scene no tree can explain, naming the objects no node can take."""
    lost = [
        f"{o} ({grammar.types[scene.types[o]].name})"
        for o in range(len(scene))
        if o not in placeable
    ]
    text = (
        ("objects the grammar cannot place: " + ", ".join(lost))
        if lost
        else ("no tree of the grammar contains this scene's objects")
    )
    return Diagnostic(f"scene '{scene.name}': {text}")


@dataclass(frozen=True)
class ParseProblem:
    milp: Milp
    supertree: Supertree
    node_col: IntArray  # (S,) column of a[n], -1 for pruned nodes
    set_cols: tuple[IntArray, ...]  # per set: columns of s[E, :]
    set_xyz: tuple[FloatArray, ...]  # per set: candidate poses of its top node
    set_quat: tuple[FloatArray, ...]
    structural: IntArray  # binaries that determine the tree (no-good cuts use these)
    build_s: float

    def invert(self, x: FloatArray) -> Trees:
        """The tree a solution encodes: active nodes, parents first, posed from their sets."""
        st = self.supertree
        on = (self.node_col >= 0) & (x[np.maximum(self.node_col, 0)] > 0.5)
        on[0] = True  # the root is in every tree, also when the model needs no column for it
        active = np.flatnonzero(on)
        pose_k = np.full(st.n_sets, -1, np.int64)
        for e, cols in enumerate(self.set_cols):
            if len(cols):
                pose_k[e] = int(np.argmax(x[cols]))
        sets = st.set_of[active]
        base_xyz = np.stack([self.set_xyz[e][pose_k[e]] for e in sets]).reshape(-1, 3)
        base_quat = np.stack([self.set_quat[e][pose_k[e]] for e in sets]).reshape(-1, 4)
        xyz = base_xyz + quat_rotate(base_quat, st.offset_xyz[active])
        quat = quat_multiply(base_quat, st.offset_quat[active])
        new_index = np.full(len(st), -1, np.int64)
        new_index[active] = np.arange(len(active))
        parent = st.parent[active]
        return Trees(
            scene=np.zeros(len(active), np.int64),
            type=st.type[active].copy(),
            parent=np.where(parent >= 0, new_index[np.maximum(parent, 0)], -1),
            rule=st.rule[active].copy(),
            xyz=xyz,
            quat=quat,
            n_scenes=1,
        )


class SetReduction:
    """The equivalent-set model (`reduce_scene`), for grammars without latent poses whose edge
    variables stay within MAX_SET_COLUMNS."""

    def accepts(self, request: Request) -> bool:
        return not request.latent and self._size(request) <= MAX_SET_COLUMNS

    def refusal(self, request: Request) -> str | None:
        size = 0 if request.latent else self._size(request)
        if size <= MAX_SET_COLUMNS:
            return None
        scene = request.scene
        return (
            f"scene '{scene.name}': the parse model would have about {size:,} "
            f"variables (limit {MAX_SET_COLUMNS:,}) for {len(scene)} objects; parse "
            "fewer objects at a time"
        )

    def apply(self, request: Request) -> tuple[Milp, ParseProblem]:
        problem = reduce_scene(request.grammar, request.supertree, request.scene)
        return problem.milp, problem

    def invert(self, problem: ParseProblem, x: FloatArray) -> Trees:
        return problem.invert(x)

    @staticmethod
    def _size(request: Request) -> int:
        return set_model_size(request.supertree, request.cand)


def set_model_size(st: Supertree, cand: Candidates) -> int:
    """The equivalent-set model's edge variables (its bulk): one per pair of candidate poses
    of every non-fixed parent-child link, counted before any model is built."""
    n_cand = np.array([len(x) for x in cand.xyz], np.int64)
    child = np.flatnonzero(st.parent >= 0)
    link = st.set_of[child] != st.set_of[st.parent[child]]
    c = child[link]
    return int(np.sum(n_cand[st.set_of[st.parent[c]]] * n_cand[st.set_of[c]]))


def reduce_scene(grammar: Grammar, st: Supertree, scene: Scene) -> ParseProblem:
    t0 = time.perf_counter()
    builder = _Reduction(grammar, st, scene)
    problem = builder.build()
    return ParseProblem(
        milp=problem,
        supertree=st,
        node_col=builder.node_col,
        set_cols=tuple(builder.set_cols),
        set_xyz=tuple(builder.cand_xyz),
        set_quat=tuple(builder.cand_quat),
        structural=np.concatenate(builder.structural).astype(np.int64),
        build_s=time.perf_counter() - t0,
    )


class _Reduction:
    """Builds the MILP of one scene; each method adds one family of variables or rows."""

    def __init__(self, grammar: Grammar, st: Supertree, scene: Scene) -> None:
        self.g, self.st, self.scene = grammar, st, scene
        self.cols, self.rows = ColumnBuilder(), RowBuilder()
        self.structural: list[IntArray] = []
        self.observed_node = grammar.tables.type_observed[st.type]
        self.implicit_root = bool(self.observed_node[0] and not np.any(scene.types == st.type[0]))

    # ------------------------------------------------------------------ build ---

    def build(self) -> Milp:
        self.candidates()
        self.prune()
        self.node_columns()
        self.set_columns()
        self.correspondences()
        self.node_logic()
        self.edges()
        self.symmetry()
        return Milp.build(self.cols, self.rows)

    def candidates(self) -> None:
        """Candidate poses per set, from the objects its observed nodes could explain."""
        st, scene = self.st, self.scene
        n_sets = st.n_sets
        self.cand_xyz: list[FloatArray] = [np.zeros((0, 3)) for _ in range(n_sets)]
        self.cand_quat: list[FloatArray] = [np.zeros((0, 4)) for _ in range(n_sets)]
        self.pairs: list[tuple[int, int, int]] = []  # (node, object, candidate)
        latent = ~st.always_observed
        latent[st.set_of[0]] = False  # the root's set has its one known pose
        self.root_set = int(st.set_of[0])
        self.cand_xyz[self.root_set] = self.g.root_xyz.reshape(1, 3).copy()
        self.cand_quat[self.root_set] = self.g.root_quat.reshape(1, 4).copy()
        self.latent_sets = np.flatnonzero(latent)
        self.cand_nodes: list[list[set[int]]] = [[] for _ in range(n_sets)]
        self.cand_nodes[self.root_set] = [set()]
        for n, objs, t, q in implied_set_poses(self.g, st, scene):
            e = int(st.set_of[n])
            for o, ti, qi in zip(objs, t, q, strict=True):
                k = self._candidate_index(e, n, ti, qi, add=(e != self.root_set))
                if k >= 0:
                    self.pairs.append((n, int(o), k))

    def _candidate_index(self, e: int, n: int, t: FloatArray, q: FloatArray, add: bool) -> int:
        """The candidate pose of set `e` that puts node `n` on an object at (t, q).

        Objects of different nodes at one set pose share the candidate (one instance of the
        set explains them all), but two objects that put the same node at the same pose need a
        candidate each: two mugs at one pose are two copies, not one (the scene was called
        infeasible)."""
        xyz, quat = self.cand_xyz[e], self.cand_quat[e]
        if len(xyz):
            same = (np.linalg.norm(xyz - t, axis=1) <= POS_TOL) & (quat_angle(quat, q) <= ROT_TOL)
            free = [k for k in np.flatnonzero(same).tolist() if n not in self.cand_nodes[e][k]]
            if free:
                self.cand_nodes[e][free[0]].add(n)
                return free[0]
            if np.any(same) and not add:
                return int(np.argmax(same))
        if not add:
            return -1
        self.cand_xyz[e] = np.vstack([xyz, t])
        self.cand_quat[e] = np.vstack([quat, q])
        self.cand_nodes[e].append({n})
        return len(xyz)

    def prune(self) -> None:
        """can[n]: n could be in a tree explaining this scene (cheap necessary conditions)."""
        st, g = self.st, self.g
        has_cand = np.array([len(x) > 0 for x in self.cand_xyz])
        can = has_cand[st.set_of].copy()  # (rules that never fire are not in the supertree)
        explains = np.zeros(len(st), bool)
        explains[[n for n, _, _ in self.pairs]] = True
        if self.implicit_root:
            explains[0] = True
        can &= ~self.observed_node | explains
        for n in range(len(st) - 1, -1, -1):  # children first
            if not can[n]:
                continue
            node, kids = g.types[st.type[n]], st.children[n]
            if node.kind == Kind.AND:
                can[n] = all(can[c] for c in kids)
            elif node.kind == Kind.OR and kids:
                can[n] = any(can[c] for c in kids)
            elif node.kind == Kind.INDEPENDENT:
                can[n] = all(can[c] for c in kids if self._p(c) >= 1.0)
            elif node.kind == Kind.REPEAT and kids and node.count is not None:
                can[n] = node.count.probs[0] > 0 or bool(can[kids[0]])
        for n in range(1, len(st)):  # parents first
            can[n] &= can[st.parent[n]]
        if latent_live := [e for e in self.latent_sets if can[st.set_top[e]]]:
            names = sorted({g.types[st.type[st.set_top[e]]].name for e in latent_live})
            raise SsgError.single(
                "this grammar has latent poses (types " + ", ".join(names) + " are never "
                "observed and not tied to an observed node); the IP parser does not yet "
                "propose poses for them",
                g.file,
            )
        if not can[0]:
            raise UnparseableScene([self._explain_infeasible()], exit_code=2)
        self.can = can

    def _explain_infeasible(self) -> Diagnostic:
        return unplaceable(self.g, self.scene, {o for _, o, _ in self.pairs})

    def _p(self, c: int) -> float:
        parent = self.st.parent[c]
        node = self.g.types[self.st.type[parent]]
        return float(node.probs[self.g.tables.rule_index[self.st.rule[c]]])

    def _or_weight(self, p: int, c: int) -> float:
        """Renormalised over the rules present at this node (blocked rules are absent)."""
        node = self.g.types[self.st.type[p]]
        idx = self.g.tables.rule_index[self.st.rule[list(self.st.children[p])]]
        weight = node.probs[self.g.tables.rule_index[self.st.rule[c]]]
        return or_weight(float(weight), float(node.probs[idx].sum()))

    # -------------------------------------------------------------- variables ---

    def node_columns(self) -> None:
        live = np.flatnonzero(self.can)
        self.node_col = np.full(len(self.st), -1, np.int64)
        cols = self.cols.add(len(live), integer=True)
        self.node_col[live] = cols
        self.cols.lo[-1] = np.where(live == 0, 1.0, 0.0)  # the root is always there
        self.structural.append(cols[live != 0])
        parents = self.st.parent[live[1:]]
        child_cols, parent_cols = cols[1:], self.node_col[parents]
        add_leq(self.rows, child_cols, parent_cols)  # child <= parent

    def set_columns(self) -> None:
        st = self.st
        self.set_cols: list[IntArray] = []
        for e in range(st.n_sets):
            top = st.set_top[e]
            if not self.can[top]:
                self.set_cols.append(np.zeros(0, np.int64))
                continue
            cols = self.cols.add(len(self.cand_xyz[e]), integer=True)
            self.set_cols.append(cols)
            k = len(cols)  # one pose iff the set is active: sum_k s[E,k] = a[top]
            self.rows.add(
                np.zeros(k + 1, np.int64),
                np.r_[cols, self.node_col[top]],
                np.r_[np.ones(k), -1.0],
                1,
                0.0,
                0.0,
            )

    def correspondences(self) -> None:
        live = [(n, o, k) for n, o, k in self.pairs if self.can[n]]
        n_obj = len(self.scene)
        by_obj = np.zeros(n_obj, np.int64)
        cols = self.cols.add(len(live), integer=True)
        self.structural.append(cols)
        node = np.array([n for n, _, _ in live], np.int64)
        obj = np.array([o for _, o, _ in live], np.int64)
        np.add.at(by_obj, obj, 1)
        if np.any(by_obj == 0):
            raise UnparseableScene([self._explain_infeasible()], exit_code=2)
        obs_nodes = np.flatnonzero(self.can & self.observed_node)
        if self.implicit_root:
            obs_nodes = obs_nodes[obs_nodes != 0]
        add_correspondences(self.rows, cols, node, obj, n_obj, self.node_col, obs_nodes)
        # ... at its set's chosen pose
        set_pose = np.array([self.set_cols[self.st.set_of[n]][k] for n, _, k in live], np.int64)
        add_leq(self.rows, cols, set_pose)

    def node_logic(self) -> None:
        """Which rules fire, and their discrete log-probabilities (thesis 3.4.3)."""
        st, g, col = self.st, self.g, self.node_col
        eq_r, eq_c, eq_v, n_eq = [], [], [], 0
        cost_col: list[int] = []
        cost_val: list[float] = []
        for p in np.flatnonzero(self.can):
            node, kids = g.types[st.type[p]], st.children[p]
            live = [c for c in kids if self.can[c]]
            if node.kind == Kind.AND:
                for c in live:  # every child present: a[c] = a[p]
                    eq_r += [n_eq, n_eq]
                    eq_c += [col[c], col[p]]
                    eq_v += [1.0, -1.0]
                    n_eq += 1
            elif node.kind == Kind.OR and kids:
                for c in live:
                    cost_col.append(col[c])
                    cost_val.append(float(np.log(self._or_weight(p, c))))
                eq_r += [n_eq] * (len(live) + 1)
                eq_c += [col[c] for c in live] + [col[p]]
                eq_v += [1.0] * len(live) + [-1.0]
                n_eq += 1
            elif node.kind == Kind.INDEPENDENT:
                for c in kids:
                    prob = self._p(c)
                    if prob >= 1.0:
                        eq_r += [n_eq, n_eq]
                        eq_c += [col[c], col[p]]
                        eq_v += [1.0, -1.0]
                        n_eq += 1
                    else:  # (rules of p = 0 are not in the supertree)
                        cost_col.append(col[p])
                        cost_val.append(float(np.log1p(-prob)))
                        if self.can[c]:
                            cost_col.append(col[c])
                            cost_val.append(float(np.log(prob) - np.log1p(-prob)))
            elif node.kind == Kind.REPEAT and node.count is not None and kids:
                self._repeat(p, live, node.count.probs)
        self.rows.add(
            np.asarray(eq_r, np.int64),
            np.asarray(eq_c, np.int64),
            np.asarray(eq_v, float),
            n_eq,
            0.0,
            0.0,
        )
        self.cols.add_cost(np.asarray(cost_col, np.int64), np.asarray(cost_val, float))

    def _repeat(self, p: int, live: list[int], probs: FloatArray) -> None:
        """The count law of a `repeat` node with supertree children.  A node without any (its
        rule blocked by `max_nesting`, or a largest count of 0) makes nothing with probability
        1 and gets no count law: charging log P(0) there was wrong, and -inf when P(0) = 0."""
        col = self.node_col
        add_count_law(self.cols, self.rows, int(col[p]), col[live], probs)
        if len(live) > 1:  # copies fill up in order: a[c_k+1] <= a[c_k]
            add_leq(self.rows, col[live[1:]], col[live[:-1]])

    def edges(self) -> None:
        """Every rule log-density between candidate poses of a parent set and a child set."""
        st = self.st
        cross = [
            c for c in range(1, len(st)) if self.can[c] and st.set_of[c] != st.set_of[st.parent[c]]
        ]
        rule_l, pxyz_l, pquat_l, cxyz_l, cquat_l, meta = [], [], [], [], [], []
        for c in cross:
            p = st.parent[c]
            ep, ec = st.set_of[p], st.set_of[c]
            bq = self.cand_quat[ep]
            px = self.cand_xyz[ep] + quat_rotate(bq, st.offset_xyz[p])
            pq = quat_multiply(bq, st.offset_quat[p])
            ni, nj = len(px), len(self.cand_xyz[ec])
            ii, jj = np.repeat(np.arange(ni), nj), np.tile(np.arange(nj), ni)
            rule_l.append(np.full(ni * nj, st.rule[c]))
            pxyz_l.append(px[ii])
            pquat_l.append(pq[ii])
            cxyz_l.append(self.cand_xyz[ec][jj])
            cquat_l.append(self.cand_quat[ec][jj])
            meta.append((c, ii, jj))
        if not cross:
            return
        rules = np.concatenate(rule_l)
        pq_all = np.concatenate(pquat_l)
        score = translation_log_density(
            self.g, rules, np.concatenate(pxyz_l), pq_all, np.concatenate(cxyz_l)
        )
        score += rotation_log_density(self.g, rules, pq_all, np.concatenate(cquat_l))
        start = 0
        for c, ii, jj in meta:
            s = score[start : start + len(ii)]
            start += len(ii)
            self._edge_block(c, ii, jj, s)

    def _edge_block(self, c: int, ii: IntArray, jj: IntArray, score: FloatArray) -> None:
        st = self.st
        ok = np.isfinite(score)
        ii, jj, score = ii[ok], jj[ok], score[ok]
        a_c = self.node_col[c]
        if len(score) == 0:
            self.rows.add(np.zeros(1, np.int64), np.array([a_c]), 1.0, 1, 0.0, 0.0)
            return
        e = self.cols.add(len(score), integer=False, cost=score)
        m = len(e)
        self.rows.add(
            np.zeros(m + 1, np.int64), np.r_[e, a_c], np.r_[np.ones(m), -1.0], 1, 0.0, 0.0
        )
        sp_cols = self.set_cols[st.set_of[st.parent[c]]]
        sc_cols = self.set_cols[st.set_of[c]]
        for idx, cols in ((ii, sp_cols), (jj, sc_cols)):  # the parent's side, the child's side
            u, r = np.unique(idx, return_inverse=True)
            self.rows.add(
                np.r_[r, np.arange(len(u))],
                np.r_[e, cols[u]],
                np.r_[np.ones(m), -np.ones(len(u))],
                len(u),
                -np.inf,
                0.0,
            )

    def symmetry(self) -> None:
        """Copies of a `repeat` child are exchangeable: take their candidate poses in order."""
        st = self.st
        for p in np.flatnonzero(self.can):
            kids = [c for c in st.children[p] if self.can[c]]
            if len(kids) < 2 or self.g.types[st.type[p]].kind != Kind.REPEAT:
                continue
            if st.set_of[kids[0]] == st.set_of[p]:
                continue  # copies share the parent's pose: only the prefix order applies
            strict = all(st.always_observed[st.set_of[c]] for c in kids)
            for c0, c1 in itertools.pairwise(kids):
                s0, s1 = self.set_cols[st.set_of[c0]], self.set_cols[st.set_of[c1]]
                k = len(s0)
                idx = np.arange(1, k + 1, dtype=float)
                big = float(k + 1)
                # idx(c1) >= idx(c0) + 1 when c1 is active (idx = 1-based chosen pose, 0 if off)
                # strict: idx1 - idx0 - big*a1 >= -k; non-strict (latent poses may repeat):
                # idx1 - idx0 - big*a1 >= -big.  Both are void when c1 is inactive.
                self.rows.add(
                    np.zeros(2 * k + 1, np.int64),
                    np.r_[s1, s0, self.node_col[c1]],
                    np.r_[idx, -idx, -big],
                    1,
                    -k if strict else -big,
                    np.inf,
                )
