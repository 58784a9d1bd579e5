"""An upper bound on the MAP score for grammars with latent poses (the certificate of 3.4).

The proposal parser's trees are feasible, so their scores are lower bounds on the MAP score;
this module gives the matching upper bound, so that a parse can report its gap honestly.

The bound keeps the tree structure discrete and relaxes the latent poses.  For a latent set
whose parent pose is known (or irrelevant) and whose children are observed objects, the score
terms that move with its pose depend only on *which* candidate child fills each of its rule
slots (an *assignment*).  Writing the set's rotation as X = q qᵀ (a 4x4 matrix; the rotation
matrix is linear in X and so is every Bingham log-density), and relaxing X to the convex hull
{X ⪰ 0, tr X = 1}, every such term is a concave function of (t, X): isotropic parent-frame
Normal offsets and world-frame Normal offsets are concave quadratics of a linear function of
(t, X), and every other term is replaced by its supremum.  The maximum over t is taken in
closed form; the maximum over X is approached by Frank–Wolfe, whose duality gap gives a valid
upper bound at every iterate.  The MILP over structures, with each latent node's edge terms
replaced by the bound of its assignment, then bounds the MAP score from above (solved to
optimality by HiGHS).

Scope: latent sets of `and` nodes whose child slots are single rules (no `repeat` copies),
whose children's poses are observed, and whose own parent pose is known or irrelevant.
Grammars outside it get no bound (gap unknown), never a wrong one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import quat_conjugate, quat_multiply, quat_rotate, quat_to_matrix
from ssgc.io.scene import Scene
from ssgc.ir import Grammar, Kind
from ssgc.laws.base import Frame
from ssgc.parse.milp import Milp
from ssgc.parse.posed import (
    MAX_INSTANCES,
    Instances,
    PosedProblem,
    instance_count,
    reduce_posed,
    too_many_instances,
)
from ssgc.parse.poses import PoseEdges, maximize_independent
from ssgc.parse.proposals import Candidates, known_parent, latent_sets
from ssgc.parse.reduction import Request
from ssgc.parse.supertree import Supertree
from ssgc.rules import rotation_log_density, translation_log_density
from ssgc.tree import Trees

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
FW_ITERATIONS = 150
MAX_ASSIGNMENTS = 20_000
IDENTITY = np.array([1.0, 0, 0, 0])


def _rotation_forms() -> FloatArray:
    """K[i, j]: the 4x4 symmetric matrix with qᵀ K[i, j] q = R(q)[i, j] for unit q."""

    def homogeneous(q: FloatArray) -> FloatArray:
        n2 = float(q @ q)
        return n2 * quat_to_matrix(q / np.sqrt(n2))

    k = np.zeros((3, 3, 4, 4))
    eye = np.eye(4)
    for a in range(4):
        k[:, :, a, a] = homogeneous(eye[a])
    for a in range(4):
        for b in range(a + 1, 4):
            both = homogeneous(eye[a] + eye[b])
            k[:, :, a, b] = k[:, :, b, a] = 0.5 * (both - k[:, :, a, a] - k[:, :, b, b])
    return k


K_ROT = _rotation_forms()


def _left_linear(f, n: int) -> FloatArray:  # type: ignore[no-untyped-def]
    """The (n, 4, 4) matrices G with f(q)[k] = G[k] q, for a map f linear in q."""
    eye = np.eye(4)
    return np.stack([f(np.tile(eye[a], (n, 1))) for a in range(4)], axis=-1)


@dataclass
class _Terms:
    """g(t, X) = -½ Σ_k (c_k - t - R(X) m_k)ᵀ P_k (…) + tr(B X) + const, per assignment."""

    c: FloatArray  # (A, K, 3)
    m: FloatArray  # (K, 3)
    P: FloatArray  # (K, 3, 3)
    B: FloatArray  # (A, 4, 4)
    const: FloatArray  # (A,)


def _isotropic(precision: FloatArray) -> bool:
    """Whether a Normal's precision is a multiple of the identity (no axis pinned)."""
    return bool(precision[0, 0] > 0 and np.allclose(precision, precision[0, 0] * np.eye(3)))


class _LocalBounds:
    """Upper bounds on the latent-pose-dependent score of one set, for many assignments.

    A law whose log-density is a quadratic form (`concave_form`: a Normal translation is
    concave in the set's position, a Bingham rotation linear in X = q qᵀ) enters the relaxation
    exactly where its frame keeps it so; every other law contributes its supremum, or its exact
    value when it does not depend on the set's pose.
    """

    def __init__(self, grammar: Grammar, n: int) -> None:
        self.g, self.n = grammar, n
        self.c: list[FloatArray] = []
        self.m: list[FloatArray] = []
        self.P: list[FloatArray] = []
        self.B = np.zeros((n, 4, 4))
        self.const = np.zeros(n)

    def quadratic(self, c: FloatArray, m: FloatArray, P: FloatArray) -> None:
        self.c.append(np.broadcast_to(c, (self.n, 3)))
        self.m.append(m)
        self.P.append(P)

    def prior(self, r: int, parent: tuple[FloatArray, FloatArray] | None) -> None:
        """The set's own rule, at its known parent pose (None: the rule ignores the parent)."""
        rule = self.g.rules[r]
        px, pq = parent if parent is not None else (np.zeros(3), IDENTITY)
        law, form = rule.translation, rule.translation.concave_form()
        if form is not None:
            mean, P, c = form
            if law.frame == Frame.WORLD_OFFSET:
                mean = px + mean
            elif law.frame == Frame.PARENT:
                Rp = quat_to_matrix(pq)
                mean, P = px + Rp @ mean, Rp @ P @ Rp.T
            self.quadratic(mean, np.zeros(3), P)
            self.const += c
        else:
            self.const += law.supremum()
        rot, rform = rule.rotation, rule.rotation.concave_form()
        if rform is not None:
            A, c = rform
            G = np.eye(4)
            if rot.frame == Frame.PARENT:
                G = _left_linear(lambda q: quat_multiply(quat_conjugate(pq), q), 1)[0]
            self.B += G.T @ A @ G
            self.const += c
        else:
            self.const += rot.supremum()

    def child(self, r: int, off_t: FloatArray, off_q: FloatArray, cx: FloatArray, cq: FloatArray):  # type: ignore[no-untyped-def]
        """A child at poses (cx, cq) (one per assignment) of the member at offset (off_t, off_q).

        Terms that do not move with the set (world-frame laws) are exact; a parent-frame
        quadratic is kept only when isotropic (else rotating it is not concave in X)."""
        g, rule = self.g, self.g.rules[r]
        rules = np.full(self.n, r)
        law, form = rule.translation, rule.translation.concave_form()
        if law.frame == Frame.WORLD:
            zeros, ident = np.zeros((self.n, 3)), np.tile(IDENTITY, (self.n, 1))
            self.const += translation_log_density(g, rules, zeros, ident, cx)
        elif form is not None and law.frame == Frame.PARENT and _isotropic(form[1]):
            mean, P, c = form
            self.quadratic(cx, off_t + quat_rotate(off_q, mean), P)
            self.const += c
        elif form is not None and law.frame == Frame.WORLD_OFFSET:
            mean, P, c = form
            self.quadratic(cx - mean, off_t, P)
            self.const += c
        else:
            self.const += law.supremum()
        rot, rform = rule.rotation, rule.rotation.concave_form()
        if rot.frame == Frame.WORLD:
            self.const += rotation_log_density(g, rules, np.tile(IDENTITY, (self.n, 1)), cq)
        elif rform is not None and rot.frame == Frame.PARENT:
            A, c = rform
            inv_off = quat_conjugate(off_q)
            G = _left_linear(
                lambda q: quat_multiply(quat_multiply(inv_off, quat_conjugate(q)), cq), self.n
            )
            self.B += np.einsum("nki,kl,nlj->nij", G, A, G)
            self.const += c
        else:
            self.const += rot.supremum()

    def terms(self) -> _Terms:
        if not self.c:
            return _Terms(
                np.zeros((self.n, 0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), self.B, self.const
            )
        return _Terms(
            np.stack(self.c, axis=1), np.stack(self.m), np.stack(self.P), self.B, self.const
        )


def _h_and_gradient(terms: _Terms, X: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """max over t of g(t, X), its gradient in X (Danskin: the gradient at t*), and t*."""
    R = np.einsum("ijab,nab->nij", K_ROT, X)  # (A, 3, 3)
    Rm = np.einsum("nij,kj->nki", R, terms.m)  # (A, K, 3)
    e = terms.c - Rm  # d_k = e_k - t
    P_tot = terms.P.sum(axis=0)
    rhs = np.einsum("kij,nkj->ni", terms.P, e)
    t = rhs @ np.linalg.pinv(P_tot).T
    d = e - t[:, None, :]
    Pd = np.einsum("kij,nkj->nki", terms.P, d)
    h = -0.5 * np.einsum("nki,nki->n", d, Pd) + np.einsum("nab,nab->n", terms.B, X) + terms.const
    grad_R = np.einsum("nki,kj->nij", Pd, terms.m)  # d g / d R
    grad_X = np.einsum("nij,ijab->nab", grad_R, K_ROT) + terms.B
    return h, grad_X, t


def relaxed_upper_bound(
    terms: _Terms, iterations: int = FW_ITERATIONS, deadline: float | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Frank–Wolfe over {X ⪰ 0, tr X = 1}: the best duality-gap bound per assignment, and the
    pose (t, q) read off the last iterate (q: X's leading eigenvector), a starting point for
    the exact local optimisation.

    For concave h, h(Y) <= h(X) + <∇h(X), Y - X> <= h(X) + λmax(∇h(X)) - <∇h(X), X> for every
    feasible Y, so every iterate yields a valid upper bound on the relaxation, hence on the
    true maximum over rotations.  Stopping early (at the deadline) leaves a looser, still
    valid bound.
    """
    w, v = np.linalg.eigh(terms.B)
    top = v[..., -1]
    X = np.einsum("na,nb->nab", top, top)
    best = np.full(len(X), np.inf)
    for _ in range(iterations):
        if deadline is not None and time.perf_counter() >= deadline and np.all(best < np.inf):
            break
        h, G, _ = _h_and_gradient(terms, X)
        w, v = np.linalg.eigh(0.5 * (G + np.swapaxes(G, 1, 2)))
        bound = h + w[:, -1] - np.einsum("nab,nab->n", G, X)
        best = np.minimum(best, bound)
        S = np.einsum("na,nb->nab", v[..., -1], v[..., -1])
        h_half = _h_and_gradient(terms, 0.5 * (X + S))[0]
        h_one = _h_and_gradient(terms, S)[0]
        # h(X + γ(S - X)) is a concave parabola in γ through these three values.
        curv = 2 * (h_one - 2 * h_half + h)
        slope = 4 * h_half - 3 * h - h_one
        gamma = np.where(curv < -1e-15, np.clip(-slope / np.minimum(curv, -1e-15), 0, 1), 1.0)
        gamma = np.where((curv >= -1e-15) & (h_one < h), 0.0, gamma)
        X = X + gamma[:, None, None] * (S - X)
    w, v = np.linalg.eigh(X)
    q = v[..., -1]
    t = _h_and_gradient(terms, np.einsum("na,nb->nab", q, q))[2]
    return best, t, q


@dataclass(frozen=True)
class SetBound:
    """One latent set's assignments: which candidate child fills each slot, the upper bound
    of each, and the pose of the set's top node that is best for each (see `polish`)."""

    slots: tuple[tuple[int, int, int], ...]  # (member node, rule, child set)
    assignment: IntArray  # (A, n_slots) candidate index of each slot's child
    upper: FloatArray  # (A,)
    xyz: FloatArray  # (A, 3)
    quat: FloatArray  # (A, 4)
    parent: tuple[FloatArray, FloatArray] | None  # the pose the set's own rule is scored at


def set_bounds(
    grammar: Grammar, st: Supertree, cand: Candidates, deadline: float | None = None
) -> dict[int, SetBound] | None:
    """Bounds for every latent set, or None when some latent set is outside the scope."""
    out: dict[int, SetBound] = {}
    latent = latent_sets(st)
    memo: dict[tuple, SetBound] = {}
    for e in np.flatnonzero(latent):
        slots = _slots(grammar, st, int(e), latent)
        parent = known_parent(grammar, st, cand, int(e))
        if slots is None or parent is False:
            return None
        key = (
            int(st.type[st.set_top[e]]),
            int(st.rule[st.set_top[e]]),
            None if parent is None else (parent[0].tobytes(), parent[1].tobytes()),
            tuple(
                (r, st.offset_xyz[v].tobytes(), cand.xyz[c].tobytes(), cand.quat[c].tobytes())
                for v, r, c in slots
            ),
        )  # the copies of a `repeat` share one computation
        if key not in memo:
            bound = _bound_one(grammar, st, cand, int(e), slots, parent, deadline)
            if bound is None:
                return None
            memo[key] = bound
        m = memo[key]
        out[int(e)] = SetBound(slots, m.assignment, m.upper, m.xyz, m.quat, parent)
    return out


def _slots(grammar: Grammar, st: Supertree, e: int, latent: NDArray[np.bool_]):  # type: ignore[no-untyped-def]
    """(member, rule, child set) per child slot, or None when the set is out of scope."""
    slots = []
    for v in np.flatnonzero(st.set_of == e):
        node = grammar.types[st.type[v]]
        kids = st.children[v]
        if node.kind == Kind.TERMINAL and not kids:
            continue
        if node.kind != Kind.AND or len({int(st.rule[c]) for c in kids}) != len(kids):
            return None
        for c in kids:
            e_c = int(st.set_of[c])
            if e_c != e:
                if latent[e_c]:
                    return None
                slots.append((int(v), int(st.rule[c]), e_c))
    return tuple(slots)


def _bound_one(grammar, st, cand, e, slots, parent, deadline):  # type: ignore[no-untyped-def]
    sizes = [len(cand.xyz[s[2]]) for s in slots]
    if int(np.prod(sizes, dtype=float)) > MAX_ASSIGNMENTS:
        return None
    grids = np.meshgrid(*[np.arange(k) for k in sizes], indexing="ij")
    assignment = np.stack([gr.ravel() for gr in grids], axis=1).astype(np.int64)
    if not slots:
        assignment = np.zeros((1, 0), np.int64)
    local = _LocalBounds(grammar, len(assignment))
    local.prior(int(st.rule[st.set_top[e]]), parent)
    for k, (v, r, e_c) in enumerate(slots):
        idx = assignment[:, k]
        local.child(r, st.offset_xyz[v], st.offset_quat[v], cand.xyz[e_c][idx], cand.quat[e_c][idx])
    upper, t, q = relaxed_upper_bound(local.terms(), FW_ITERATIONS, deadline)
    bound = SetBound(slots, assignment, upper, t, q, parent)
    xyz, quat = polish(grammar, st, cand, int(st.rule[st.set_top[e]]), bound, deadline)
    return SetBound(slots, assignment, upper, xyz, quat, parent)


def polish(
    grammar: Grammar,
    st: Supertree,
    cand: Candidates,
    top_rule: int,
    bound: SetBound,
    deadline: float | None,
) -> tuple[FloatArray, FloatArray]:
    """Each assignment's best top pose under the exact densities, from the relaxation's pose
    (Newton, all assignments at once).  When the relaxation is tight this is the global
    optimum, and the bound certifies it."""
    n = len(bound.assignment)
    px, pq = bound.parent if bound.parent is not None else (np.zeros(3), IDENTITY)
    rule, pb, pxyz, pquat = (
        [np.full(n, top_rule)],
        [np.full(n, -1)],
        [np.tile(px, (n, 1))],
        [np.tile(pq, (n, 1))],
    )
    cb, cxyz, cquat = [np.arange(n)], [np.zeros((n, 3))], [np.tile(IDENTITY, (n, 1))]
    for k, (v, r, e_c) in enumerate(bound.slots):
        idx = bound.assignment[:, k]
        rule.append(np.full(n, r))
        pb.append(np.arange(n))
        pxyz.append(np.tile(st.offset_xyz[v], (n, 1)))
        pquat.append(np.tile(st.offset_quat[v], (n, 1)))
        cb.append(np.full(n, -1))
        cxyz.append(cand.xyz[e_c][idx])
        cquat.append(cand.quat[e_c][idx])
    cat = np.concatenate
    edges = PoseEdges(
        cat(rule).astype(np.int64),
        cat(pb).astype(np.int64),
        cat(pxyz),
        cat(pquat),
        cat(cb).astype(np.int64),
        cat(cxyz),
        cat(cquat),
    )
    return maximize_independent(grammar, edges, bound.xyz, bound.quat, deadline=deadline)


class AssignmentReduction:
    """The assignment model (`assignment_problem`), for latent grammars whose latent sets all
    have assignments (`set_bounds`), within the unrolled model's MAX_INSTANCES."""

    def accepts(self, request: Request) -> bool:
        return request.bounds is not None and self._count(request) <= MAX_INSTANCES

    def refusal(self, request: Request) -> str | None:
        if request.bounds is None or self._count(request) <= MAX_INSTANCES:
            return None
        return too_many_instances(request.scene)

    def apply(self, request: Request) -> tuple[Milp, PosedProblem]:
        r = request
        assert r.bounds is not None
        problem = assignment_problem(
            r.grammar, r.supertree, r.scene, r.cand, r.bounds, deadline=r.deadline
        )
        return problem.milp, problem

    def invert(self, problem: PosedProblem, x: FloatArray) -> Trees:
        return problem.invert(x)

    @staticmethod
    def _count(request: Request) -> int:
        assert request.bounds is not None
        posed = assignment_candidates(request.cand, request.bounds)
        return instance_count(request.supertree, posed, frozenset(request.bounds))


def assignment_candidates(cand: Candidates, bounds: dict[int, SetBound]) -> Candidates:
    """The candidates with each latent set's replaced by its assignments' best poses."""
    posed = Candidates(list(cand.xyz), list(cand.quat))
    for e, sb in bounds.items():
        posed.xyz[e], posed.quat[e] = sb.xyz, sb.quat
    return posed


def assignment_problem(
    grammar: Grammar,
    st: Supertree,
    scene: Scene,
    cand: Candidates,
    bounds: dict[int, SetBound],
    upper: bool = False,
    deadline: float | None = None,
) -> PosedProblem:
    """The unrolled MILP whose latent nodes stand for assignments of children.

    Each latent set's candidates are its assignments, one instance each, and of an instance's
    children only those its assignment names stay.  With `upper=False` the instance sits at
    the assignment's best pose and every score is exact: each tree has one encoding and the
    optimum is the MAP over the poses found.  With `upper=True` the top instance carries the
    assignment's upper bound instead (its children's edges score 0, the bound counts them);
    everything else — structure, count laws, correspondences, observed edges — is unchanged,
    so the optimum is an upper bound on the MAP score.
    """
    posed = assignment_candidates(cand, bounds)

    restrict = {
        e: (tuple((v, r) for v, r, _ in sb.slots), sb.assignment) for e, sb in bounds.items()
    }

    def adjust(inst: Instances) -> None:
        set_of = st.set_of[inst.st_node]
        for e, sb in bounds.items():
            heads = np.flatnonzero((set_of == e) & (inst.top == np.arange(len(set_of))))
            inst.score[heads] = sb.upper[inst.cand_k[heads]]
        parent_set = set_of[np.maximum(inst.parent, 0)]
        counted = (inst.parent >= 0) & np.isin(parent_set, list(bounds)) & (parent_set != set_of)
        inst.score[counted] = 0.0  # the assignment's bound already counts these edges

    return reduce_posed(grammar, st, scene, posed, adjust if upper else None, restrict, deadline)
