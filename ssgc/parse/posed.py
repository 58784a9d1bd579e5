"""The pose-instantiated integer program: the supertree unrolled over candidate poses.

For grammars whose every pose is tied to an observation (dependency grammars such as the sink),
a node entered by a non-fixed rule can only sit at one of finitely many candidate poses (those
implied by the scene's objects).  Instead of a supertree node plus a choice of pose (thesis 3.5,
`ssgc.parse.ip`), this formulation gives every (node, candidate pose) its own binary: poses are
constants, every rule's log-density is a constant on one binary, and the copies of a `repeat`
are no longer exchangeable variables but distinct candidate children — so there is no
symmetry to break and each tree has exactly one encoding (top-N cuts give distinct trees).
The model is an assignment problem whose LP relaxation is tight in practice.

Its size is the number of (node, pose) instances, which can grow like K^depth for deep chains
of pose-changing rules (a stack of K steamer trays); `count_instances` measures it first and
the caller falls back to the set formulation when it is too large.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import Diagnostic
from ssgc.geometry import quat_angle, quat_multiply, quat_rotate
from ssgc.io.scene import Scene
from ssgc.ir import Grammar, Kind
from ssgc.parse.clock import check_deadline
from ssgc.parse.ip import UnparseableScene, implied_set_poses, unplaceable
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
from ssgc.parse.supertree import Supertree
from ssgc.rules import POS_TOL, ROT_TOL, rotation_log_density, translation_log_density
from ssgc.tree import Trees

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
MAX_INSTANCES = 60_000


ADD_CHUNK = 1024  # implied poses deduplicated at once (candidate_poses, between deadline checks)
UNROLL_CHECK = 32  # instances unrolled between deadline checks (each costs ~0.1-1 ms)


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

    Past the deadline it raises OutOfTime: a wide `repeat` of a large scene has a thousand
    sets of a thousand poses each, whose deduplication alone takes a minute."""
    cand = Candidates(
        [np.zeros((0, 3)) for _ in range(st.n_sets)], [np.zeros((0, 4)) for _ in range(st.n_sets)]
    )
    for n, _, t, q in implied_set_poses(grammar, st, scene):
        t, q = t.reshape(-1, 3), q.reshape(-1, 4)
        for i in range(0, len(t), ADD_CHUNK):  # bounded work between deadline checks
            check_deadline(deadline)
            cand.add(int(st.set_of[n]), t[i : i + ADD_CHUNK], q[i : i + ADD_CHUNK])
    root_set = int(st.set_of[0])  # the root's set has exactly one pose
    cand.xyz[root_set] = grammar.root_xyz.reshape(1, 3).copy()
    cand.quat[root_set] = grammar.root_quat.reshape(1, 4).copy()
    return cand


class _Unroll:
    """Builds the instances (supertree node, pose) top-down, then the MILP over them."""

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
        self.restrict = restrict or {}
        self.deadline: float | None = None
        self.top: list[int] = []  # instance heading each instance's set
        self.node: list[int] = []
        self.parent: list[int] = []
        self.slot: list[int] = []  # index of the producing rule slot in the parent's children
        self.cand_k: list[int] = []  # index of the instance's pose among its set's candidates
        self.xyz: list[FloatArray] = []
        self.quat: list[FloatArray] = []

    def unroll(self) -> None:
        st, g = self.st, self.g
        tb = g.tables
        self._add(0, -1, -1, g.root_xyz, g.root_quat, 0)
        i = 0
        while i < len(self.node):
            n = self.node[i]
            for slot, c in enumerate(self._slots(n)):
                if st.set_of[c] == st.set_of[n]:  # fixed rule: the rule's offset from i
                    r = st.rule[c]
                    xyz = self.xyz[i] + quat_rotate(self.quat[i], tb.point_xyz[r])
                    quat = quat_multiply(self.quat[i], tb.point_quat[r])
                    for c2 in (c2 for c2 in st.children[n] if st.rule[c2] == r):
                        self._add(c2, i, slot, xyz, quat, self.cand_k[i])
                else:  # one child per candidate pose of the child's set
                    e = st.set_of[c]
                    for k in self._allowed(i, n, int(st.rule[c]), e):
                        self._add(c, i, slot, self.cand_xyz[e][k], self.cand_quat[e][k], k)
            if i % UNROLL_CHECK == 0:
                check_deadline(self.deadline)
            i += 1

    def _allowed(self, i: int, n: int, rule: int, e: int) -> range | list[int]:
        """Candidate indices a child of instance i (node n) through `rule` may take."""
        own = int(self.st.set_of[n])
        if own in self.restrict:
            slots, assignment = self.restrict[own]
            a = self.cand_k[self.top[i]]
            cols = [j for j, s in enumerate(slots) if s == (n, rule)]
            if not cols:  # a rule the assignment does not name (an independent latent child)
                return range(len(self.cand_xyz[e]))
            named = assignment[a, cols]  # -1: this column has no child
            if np.any(named == FREE_CHILD):  # a row whose children are free (bound.FREE)
                return range(len(self.cand_xyz[e]))
            return sorted({int(k) for k in named if k >= 0})
        return range(len(self.cand_xyz[e]))

    def _slots(self, n: int) -> list[int]:
        """One representative supertree child per rule (the first copy of a `repeat`)."""
        seen, out = set(), []
        for c in self.st.children[n]:
            r = int(self.st.rule[c])
            if r not in seen:
                seen.add(r)
                out.append(c)
        return out

    def _add(
        self, n: int, parent: int, slot: int, xyz: FloatArray, quat: FloatArray, k: int
    ) -> None:
        if len(self.node) % 2048 == 0:  # one node can have thousands of candidate children
            check_deadline(self.deadline)
        self.cand_k.append(k)
        fixed = parent >= 0 and self.st.set_of[n] == self.st.set_of[self.node[parent]]
        self.top.append(self.top[parent] if fixed else len(self.node))
        self.node.append(n)
        self.parent.append(parent)
        self.slot.append(slot)
        self.xyz.append(np.asarray(xyz, float))
        self.quat.append(np.asarray(quat, float))


def instance_count(
    st: Supertree, cand: Candidates, restricted: frozenset[int] = frozenset()
) -> int:
    """How many instances `reduce_posed` would unroll (counting stops past MAX_INSTANCES):
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
        if total > MAX_INSTANCES:
            break
    return total


def reduce_posed(
    grammar: Grammar,
    st: Supertree,
    scene: Scene,
    cand: Candidates | None = None,
    adjust: Callable[[Instances], None] | None = None,
    restrict: Restriction | None = None,
    deadline: float | None = None,
) -> PosedProblem:
    """The unrolled MILP over the given candidate poses (by default, the observed ones).

    `restrict` limits the children of some sets' instances to one candidate per slot, and
    `adjust` may rewrite the instances' edge scores before the model is built (-inf removes an
    instance): `ssgc.parse.bound` uses both for latent-pose assignments and their bounds.
    """
    t0 = time.perf_counter()
    if cand is None:
        cand = candidate_poses(grammar, st, scene)
    u = _Unroll(grammar, st, scene, cand, restrict)
    u.deadline = deadline
    u.unroll()
    node = np.asarray(u.node, np.int64)
    parent = np.asarray(u.parent, np.int64)
    slot = np.asarray(u.slot, np.int64)
    xyz, quat = np.asarray(u.xyz).reshape(-1, 3), np.asarray(u.quat).reshape(-1, 4)
    model = _Model(grammar, st, scene, node, parent, slot, xyz, quat)
    model.deadline = deadline
    check_deadline(deadline)
    model.edge_scores()
    if adjust is not None:
        cand_k, top = np.asarray(u.cand_k, np.int64), np.asarray(u.top, np.int64)
        adjust(Instances(node, parent, cand_k, top, model.score))
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
        return _unbound(request) and self._count(request) <= MAX_INSTANCES

    def refusal(self, request: Request) -> str | None:
        if not _unbound(request) or self._count(request) <= MAX_INSTANCES:
            return None
        return too_many_instances(request.scene)

    def apply(self, request: Request) -> tuple[Milp, PosedProblem]:
        r = request
        problem = reduce_posed(r.grammar, r.supertree, r.scene, r.cand, deadline=r.deadline)
        return problem.milp, problem

    def invert(self, problem: PosedProblem, x: FloatArray) -> Trees:
        return problem.invert(x)

    @staticmethod
    def _count(request: Request) -> int:
        return instance_count(request.supertree, request.cand)


def _unbound(request: Request) -> bool:
    """No assignments to build on: none, or bounds that only certify (`certify_only`)."""
    return request.bounds is None or any(b.decoupled for b in request.bounds.values())


def too_many_instances(scene: Scene) -> str:
    return (
        f"scene '{scene.name}': the parse model would have more than {MAX_INSTANCES} node "
        f"instances ({len(scene)} objects); parse fewer objects at a time"
    )


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
        n = len(node)
        self.children: list[list[int]] = [[] for _ in range(n)]
        for i in range(1, n):
            self.children[parent[i]].append(i)

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
            d = np.linalg.norm(self.xyz[ii][:, None, :] - scene.xyz[oo][None, :, :], axis=2)
            a = quat_angle(self.quat[ii][:, None, :], scene.quat[oo][None, :, :])
            hit_i, hit_o = np.nonzero((d <= POS_TOL) & (a <= ROT_TOL))
            inst.append(ii[hit_i])
            obj.append(oo[hit_o])
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
        for i in range(1, n):  # rules that can never fire
            kind = g.types[self.type[self.parent[i]]].kind
            if kind in (Kind.OR, Kind.INDEPENDENT) and self._prob(i) <= 0:
                can[i] = False
        for i in range(n - 1, -1, -1):
            if i % UNROLL_CHECK == 0:
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
            elif node.kind == Kind.REPEAT and node.count is not None:
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

    def _prob(self, c: int) -> float:
        """`or`: weight renormalised over the rules present; `independent`: p."""
        p = self.parent[c]
        probs = self._slot_probs(p)
        node = self.g.types[self.type[p]]
        w = probs[int(self.rule[c])]
        return w / sum(probs.values()) if node.kind == Kind.OR else w

    def columns(self) -> None:
        live = np.flatnonzero(self.can)
        self.col = np.full(len(self.node), -1, np.int64)
        self.col[live] = self.cols.add(len(live), integer=True, cost=self.score[live])
        self.cols.lo[-1] = np.where(live == 0, 1.0, 0.0)
        self.structural.append(self.col[live[live != 0]])
        ch = live[live != 0]
        add_leq(self.rows, self.col[ch], self.col[self.parent[ch]])  # child <= parent

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
                cost_v += [float(np.log(self._prob(c))) for c in kids]
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
            elif node.kind == Kind.REPEAT and node.count is not None:
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
        add_count_law(self.cols, self.rows, a, self.col[kids], probs)
        # copies at one pose (a fixed `repeat` rule) fill up in order
        st = self.st
        same = [c for c in kids if st.set_of[self.node[c]] == st.set_of[self.node[self.parent[c]]]]
        if len(same) > 1:
            add_leq(self.rows, self.col[same[1:]], self.col[same[:-1]])
