"""One latent set's rows as score terms, and their convex relaxation (the per-set half of
`bound.py`, thesis 3.4): `_Terms` (the Normal, Bingham, box, pin and arc terms of each
assignment row), `_LocalBounds` (how a set's members and rules become those terms),
`relaxed_upper_bound` (closed form in t; over X = q qᵀ an eigenvector where exact, else
Frank–Wolfe, whose duality gap bounds at every iterate) and `SetBound` (a set's assignments
with their bounds and poses).

Why a module of its own: `bound.py` (the MILP over assignments), `bound_chain.py` (a set lifted
into its latent parent's rows) and `bound_rotation.py` (branch-and-bound over a set's rotation)
all build on these terms; here they import it, and nothing here imports them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import (
    axis_angle_to_quat,
    quat_angle,
    quat_between,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
)
from ssgc.ir import Grammar
from ssgc.laws.base import POS_TOL, ROT_TOL, Frame
from ssgc.laws.position_box import BoxTranslation
from ssgc.laws.rotation_revolute import RevoluteRotation
from ssgc.rules import rotation_log_density, translation_log_density

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
FW_ITERATIONS = 150
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
    """g(t, X) = -½ Σ_k (c_k - t - R(X) m_k)ᵀ P_k (…) + tr(B X) + const, per assignment, with
    t in the box [lo, hi] and, where `pin` is not NaN, X = pin pinᵀ (a fixed rotation)."""

    c: FloatArray  # (A, K, 3)
    m: FloatArray  # (K, 3)
    P: FloatArray  # (A, K, 3, 3): zero where the term's child is absent
    B: FloatArray  # (A, 4, 4)
    const: FloatArray  # (A,)
    lo: FloatArray  # (A, 3): box laws and fixed translations, widened by BOX_MARGIN
    hi: FloatArray  # (A, 3)
    pin: FloatArray  # (A, 4): the rotation a fixed rotation law forces, NaN where free
    complete: bool  # every pose-dependent term is in the relaxation exactly
    t_complete: bool  # every translation term is: t* is the best position for a rotation
    V: FloatArray  # (A, 4, 2): a revolute law's rotations q = V (cos ψ, sin ψ), ψ in `arc`
    arc: FloatArray  # (A, 2): half the law's angle range
    revolute: NDArray[np.bool_]  # (A,): rows whose rotation is held to such a family
    hard: NDArray[np.bool_] | None = None  # (K,): terms standing in for a fixed translation
    # the planes of pinned Normal axes, t = Q t + t0 (`_LocalBounds.plane`); None: no planes
    Q: FloatArray | None = None  # (A, 3, 3): the projector onto the directions t may move in
    t0: FloatArray | None = None  # (A, 3): the point of the planes nearest the origin

    @property
    def pinned(self) -> NDArray[np.bool_]:
        return ~np.isnan(self.pin[:, 0])

    @property
    def planed(self) -> NDArray[np.bool_]:
        """Rows whose position is held to planes (pinned axes of Normal laws)."""
        if self.Q is None:
            return np.zeros(len(self.c), bool)
        return np.abs(self.Q - np.eye(3)).max(axis=(1, 2), initial=0.0) > 1e-12

    def onto_planes(self, t: FloatArray) -> FloatArray:
        """Positions moved onto their rows' planes (orthogonally); unchanged without."""
        if self.Q is None:
            return t
        return np.einsum("nij,nj->ni", self.Q, t) + self.t0

    @cached_property
    def inverse(self) -> FloatArray:
        """The pseudo-inverse of each row's total precision (computed once per set)."""
        return np.linalg.pinv(self.P.sum(axis=1))

    @cached_property
    def affine(self) -> tuple[FloatArray, FloatArray]:
        """(L, a): the best t on the rows' planes of Σ -½ (e_k - t)ᵀ P_k (e_k - t) is
        L Σ P_k e_k + a (t = t0 + Q s, s eliminated in closed form); without planes L is the
        inverse and a is 0."""
        if self.Q is None:
            return self.inverse, np.zeros((len(self.c), 3))
        H = self.P.sum(axis=1)
        L = np.linalg.pinv(self.Q @ H @ self.Q) @ self.Q
        return L, self.t0 - np.einsum("nij,njk,nk->ni", L, H, self.t0)

    @cached_property
    def diagonal(self) -> NDArray[np.bool_]:
        """Where the total precision is diagonal (on the axes the planes leave free, which
        must be world axes): clipping the best t to the box is then the best t in the box
        (the problem separates by axis)."""
        P = self.P.sum(axis=1)
        if self.Q is not None:
            P = self.Q @ P @ self.Q
        off = np.abs(P - P * np.eye(3)).max(axis=(1, 2), initial=0.0)
        out = off <= 1e-12 * (1.0 + np.abs(P).max(axis=(1, 2), initial=0.0))
        if self.Q is not None:  # a plane across the axes does not separate
            out &= np.abs(self.Q - self.Q * np.eye(3)).max(axis=(1, 2), initial=0.0) <= 1e-12
        return out


def _plane(base: FloatArray, axis: FloatArray, post: FloatArray) -> FloatArray:
    """(n, 4, 2): the orthonormal basis (base ⊗ post, base ⊗ axis ⊗ post) of the plane whose
    unit vectors are the family q = base ⊗ rot(axis, φ) ⊗ post, q = U (cos φ/2, sin φ/2)."""
    axis_q = np.hstack([np.zeros((len(axis), 1)), axis])
    u = quat_multiply(base, post)
    w = quat_multiply(quat_multiply(base, axis_q), post)
    return np.stack([u, w], axis=-1)


def _on_arc(s: FloatArray, arc: FloatArray) -> NDArray[np.bool_]:
    """Whether the plane point s = ±(cos ψ, sin ψ) has ψ in the half-angle arc (mod π, the
    sign of a quaternion), within ROT_TOL."""
    psi = np.arctan2(s[:, 1], s[:, 0])
    rel = np.mod(psi - arc[:, 0], np.pi)
    return (rel <= arc[:, 1] - arc[:, 0] + ROT_TOL) | (rel >= np.pi - ROT_TOL)


def _arc_meet(
    arc: FloatArray, M: FloatArray, half: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Two revolute laws on one plane of quaternions: the old family's half-angle arc (n, 2)
    narrowed to the new law's (`half`, its own half-angles, carried into the old family's
    angle by M = UᵀU', a rotation ψ = ψ' + δ or a reflection ψ = δ - ψ'), and the rows where
    the arcs (mod π, widened by ROT_TOL) do not meet.  Where they meet in two pieces the old
    arc is kept (a larger set: the bound stays valid)."""
    delta = np.arctan2(M[:, 1, 0], M[:, 0, 0])
    turn = np.linalg.det(M) > 0
    b_lo = np.where(turn, half[0] + delta, delta - half[1]) - ROT_TOL
    wb = np.full(len(M), half[1] - half[0] + 2 * ROT_TOL)
    a_lo, wa = arc[:, 0], arc[:, 1] - arc[:, 0]
    if half[1] - half[0] >= np.pi - 1e-12:  # the new law is a full turn: nothing to narrow
        return arc, np.zeros(len(M), bool)
    b0 = a_lo + np.mod(b_lo - a_lo, np.pi)  # the new arc's start, in [a_lo, a_lo + π)
    first = b0 <= a_lo + wa  # a piece from b0 on
    wrap = b0 + wb - np.pi >= a_lo  # a piece from a_lo (the new arc wraps past a_lo + π)
    out = arc.copy()
    full = wa >= np.pi - 1e-12
    one = ~full & (first ^ wrap)
    out[full] = np.stack([b0, b0 + wb], axis=1)[full]
    lo1, hi1 = b0, np.minimum(b0 + wb, a_lo + wa)
    lo2, hi2 = a_lo, np.minimum(a_lo + wa, b0 + wb - np.pi)
    piece = np.where(first[:, None], np.stack([lo1, hi1], 1), np.stack([lo2, hi2], 1))
    out[one] = piece[one]
    return out, ~full & ~first & ~wrap


def _isotropic(precision: FloatArray) -> bool:
    """Whether a Normal's precision is a multiple of the identity (no axis pinned)."""
    return bool(precision[0, 0] > 0 and np.allclose(precision, precision[0, 0] * np.eye(3)))


def _rows(x: FloatArray, n: int, width: int) -> FloatArray:
    return np.broadcast_to(np.asarray(x, float), (n, width))


class _LocalBounds:
    """Upper bounds on the latent-pose-dependent score of one set, for many assignments.

    A law whose log-density is a quadratic form (`concave_form`: a Normal translation is
    concave in the set's position, a Bingham rotation linear in X = q qᵀ) enters the relaxation
    exactly where its frame keeps it so; a box law is a constraint on the position; a fixed
    rotation pins X; a fixed translation pins the position (or, under a free rotation, is a
    steep quadratic: still an upper bound).  Where the rotation is pinned every rotation term
    is exact.  Every other law contributes its supremum (`complete` is then False), or its exact
    value when it does not depend on the set's pose.  Rows whose child is absent (`on` False)
    get nothing.
    """

    def __init__(self, grammar: Grammar, n: int) -> None:
        self.g, self.n = grammar, n
        self.c: list[FloatArray] = []
        self.m: list[FloatArray] = []
        self.P: list[FloatArray] = []
        self.B = np.zeros((n, 4, 4))
        self.const = np.zeros(n)
        self.lo = np.full((n, 3), -np.inf)
        self.hi = np.full((n, 3), np.inf)
        self.pin = np.full((n, 4), np.nan)
        self.clash = np.zeros(n, bool)
        self.complete = True
        self.t_complete = True  # every translation term is exact (t* is the best position)
        # the first revolute law on the set's rotation, per row: q = base ⊗ rot(axis, φ) ⊗ post
        self.fam_base = np.full((n, 4), np.nan)
        self.fam_axis = np.zeros((n, 3))
        self.fam_post = np.tile(IDENTITY, (n, 1))
        self.fam_range = np.zeros((n, 2))
        self.fixed_children: list = []  # (rule, off_t, off_q, cx, on) per column
        self.rot_terms: list[tuple] = []  # rotating precisions (bound_rotation.Rotating)
        self.rot_lift = np.zeros(n)
        self.hard: list[bool] = []  # per term: a steep quadratic standing in for a pin
        self.planes: list[tuple[FloatArray, FloatArray, NDArray[np.bool_]]] = []  # (n, d, on)

    # ---------------------------------------------------------------- building blocks ---

    def quadratic(
        self,
        c: FloatArray,
        m: FloatArray,
        P: FloatArray,
        on: NDArray[np.bool_],
        hard: bool = False,
    ) -> None:
        self.hard.append(hard)
        self.c.append(_rows(c, self.n, 3).copy())
        self.m.append(np.asarray(m, float))
        P = np.broadcast_to(P, (self.n, 3, 3))
        self.P.append(np.where(on[:, None, None], P, 0.0))

    def box(self, lo: FloatArray, hi: FloatArray, on: NDArray[np.bool_]) -> None:
        """t in [lo, hi] on the rows `on`, widened by BOX_MARGIN (rounding)."""
        lo, hi = _rows(lo, self.n, 3) - BOX_MARGIN, _rows(hi, self.n, 3) + BOX_MARGIN
        self.lo = np.where(on[:, None], np.maximum(self.lo, lo), self.lo)
        self.hi = np.where(on[:, None], np.minimum(self.hi, hi), self.hi)

    def add(self, values: FloatArray, on: NDArray[np.bool_]) -> None:
        self.const += np.where(on, values, 0.0)

    def plane(self, normal: FloatArray, value: FloatArray, on: NDArray[np.bool_]) -> None:
        """n·t = d on the rows `on` (n a unit vector): a pinned axis of a Normal law, exact (its
        point mass holds there; `_on_planes`)."""
        normal = _rows(normal, self.n, 3).copy()
        value = np.broadcast_to(np.asarray(value, float), (self.n,)).copy()
        self.planes.append((normal, value, on.copy()))

    def law_planes(self, law, origin: FloatArray, turn: FloatArray, on) -> None:  # type: ignore[no-untyped-def]
        """The planes of a Normal law's pinned axes: the law's frame has its origin at
        `origin` (per row or one) and its axes the columns of `turn` ((3, 3) or per row);
        axis i holds the value `law.offset[i]` there."""
        free = getattr(law, "free", None)
        if free is None or np.all(free):
            return
        turn = np.broadcast_to(np.asarray(turn, float), (self.n, 3, 3))
        origin = _rows(origin, self.n, 3)
        for i in np.flatnonzero(~np.asarray(free, bool)):
            normal = turn[:, :, i]
            self.plane(normal, np.sum(normal * origin, axis=1) + law.offset[i], on)

    def _partial_pins(self, law) -> bool:  # type: ignore[no-untyped-def]
        free = getattr(law, "free", None)
        return free is not None and not np.all(free)

    def pin_rotation(self, q: FloatArray, on: NDArray[np.bool_]) -> None:
        """X = q qᵀ on the rows `on`; two pins further apart than twice ROT_TOL exclude each
        other (no rotation is within ROT_TOL of both)."""
        q = _rows(q, self.n, 4)
        had = ~np.isnan(self.pin[:, 0])
        both = on & had
        if np.any(both):
            far = np.zeros(self.n, bool)
            far[both] = quat_angle(self.pin[both], q[both]) > 2 * ROT_TOL
            self.clash |= far
        self.pin = np.where((on & ~had)[:, None], q, self.pin)

    def family(self, law, base, axis, post, on) -> None:  # type: ignore[no-untyped-def]
        """q = base ⊗ rot(axis, φ) ⊗ post, φ in the law's range, on the rows `on` that have no
        family yet (a later one is left to the exact scorer: the relaxation ignores it)."""
        free = on & np.isnan(self.fam_base[:, 0])
        self._meet(law, base, axis, post, on & ~free & ~self.pinned)
        self.fam_base = np.where(free[:, None], _rows(base, self.n, 4), self.fam_base)
        self.fam_axis = np.where(free[:, None], _rows(axis, self.n, 3), self.fam_axis)
        self.fam_post = np.where(free[:, None], _rows(post, self.n, 4), self.fam_post)
        span = np.array([law.revolute.lo, law.revolute.hi])
        self.fam_range = np.where(free[:, None], span, self.fam_range)

    def _meet(self, law, base, axis, post, rows) -> None:  # type: ignore[no-untyped-def]
        """A second revolute law on rows that already hold a family: the rotations both
        allow.  Each family is a great circle of unit quaternions, the unit vectors of a plane
        of R⁴ (`_plane`); two distinct planes meet in a line or not at all (their principal
        angles, from the SVD of UᵀU').  Meeting in a line on both arcs pins the rotation; not
        within 2·ROT_TOL of each other, or off an arc by more than ROT_TOL, rules the row out
        (no rotation is within ROT_TOL of both, the scorer's tolerance).  Coincident planes
        keep the first family (the second law is then left to the exact scorer)."""
        if not np.any(rows):
            return
        idx = np.flatnonzero(rows)
        U = _plane(self.fam_base[idx], self.fam_axis[idx], self.fam_post[idx])
        n = len(idx)
        U2 = _plane(
            _rows(base, self.n, 4)[idx], _rows(axis, self.n, 3)[idx], _rows(post, self.n, 4)[idx]
        )
        a, sigma, bt = np.linalg.svd(np.einsum("nai,naj->nij", U, U2))
        near = np.arccos(np.clip(sigma, -1.0, 1.0))  # principal angles (quaternion half-angles)
        same = near[:, 1] <= 2 * ROT_TOL
        apart = near[:, 0] > ROT_TOL
        s_old, s_new = a[:, :, 0], bt[:, 0, :]
        q = quat_normalize(np.einsum("nai,ni->na", U, s_old))
        half = np.array([law.revolute.lo, law.revolute.hi]) * 0.5
        on_old = _on_arc(s_old, 0.5 * self.fam_range[idx])
        on_new = _on_arc(s_new, np.broadcast_to(half, (n, 2)))
        clash = ~same & (apart | ~on_old | ~on_new)
        pin = ~same & ~clash
        if np.any(same):
            M = np.einsum("nai,naj->nij", U[same], U2[same])
            arc, empty = _arc_meet(0.5 * self.fam_range[idx[same]], M, half)
            self.fam_range[idx[same]] = 2.0 * arc
            clash[np.flatnonzero(same)[empty]] = True
        self.clash[idx[clash]] = True
        mask = np.zeros(self.n, bool)
        mask[idx[pin]] = True
        full = np.tile(IDENTITY, (self.n, 1))
        full[idx] = q
        self.pin_rotation(full, mask)

    @property
    def pinned(self) -> NDArray[np.bool_]:
        return ~np.isnan(self.pin[:, 0])

    def _pin_or_identity(self) -> FloatArray:
        return np.where(self.pinned[:, None], self.pin, IDENTITY)

    # ------------------------------------------------------------------- rotation pins ---

    def prior_pin(self, r: int, parent) -> None:  # type: ignore[no-untyped-def]
        if parent is False:
            return
        rot = self.g.rules[r].rotation
        if rot.point is not None and rot.frame == Frame.PARENT:
            pq = IDENTITY if parent is None else parent[1]
            self.pin_rotation(quat_multiply(pq, rot.point), np.ones(self.n, bool))

    def child_pin(self, r: int, off_q: FloatArray, cq: FloatArray, on: NDArray[np.bool_]) -> None:
        rot = self.g.rules[r].rotation
        if rot.point is not None and rot.frame == Frame.PARENT:
            q_member = quat_multiply(cq, quat_conjugate(rot.point))
            self.pin_rotation(quat_multiply(q_member, quat_conjugate(off_q)), on)

    def prior_family(self, r: int, parent) -> None:  # type: ignore[no-untyped-def]
        if parent is False:
            return
        rot = self.g.rules[r].rotation
        if isinstance(rot, RevoluteRotation):
            pq = IDENTITY if parent is None else parent[1]
            self.family(rot, pq, rot.axis, IDENTITY, np.ones(self.n, bool))

    def child_family(self, r: int, off_q: FloatArray, cq: FloatArray, on) -> None:  # type: ignore[no-untyped-def]
        """A revolute child: cq = q ⊗ off_q ⊗ rot(a, θ), so q = cq ⊗ rot(-a, θ) ⊗ off_q⁻¹."""
        rot = self.g.rules[r].rotation
        if isinstance(rot, RevoluteRotation):
            self.family(rot, cq, -rot.axis, quat_conjugate(off_q), on)

    # ------------------------------------------------------------------------- terms ---

    def prior(self, r: int, parent) -> None:  # type: ignore[no-untyped-def]
        """The set's own rule, at its known parent pose (None: the rule ignores the parent;
        False: the parent's pose is not known, and the rule counts its supremum)."""
        rule = self.g.rules[r]
        if parent is False:
            self._decoupled_prior(r)
            return
        every = np.ones(self.n, bool)
        px, pq = parent if parent is not None else (np.zeros(3), IDENTITY)
        law, form = rule.translation, rule.translation.concave_form()
        if form is not None:
            mean, P, c = form
            origin, Rp = np.zeros(3), np.eye(3)
            if law.frame == Frame.WORLD_OFFSET:
                origin, mean = px, px + mean
            elif law.frame == Frame.PARENT:
                origin, Rp = px, quat_to_matrix(pq)
                mean, P = px + Rp @ mean, Rp @ P @ Rp.T
            self.quadratic(mean, np.zeros(3), P, every)
            self.law_planes(law, origin, Rp, every)  # its pinned axes hold exactly
            self.const += c
        elif isinstance(law, BoxTranslation):
            shift = px if law.frame == Frame.WORLD_OFFSET else np.zeros(3)
            self.box(shift + law.box.lo, shift + law.box.hi, every)
            self.const += law.supremum()
        elif law.point is not None and law.frame == Frame.PARENT:
            at = px + quat_rotate(pq, law.point)
            self.box(at, at, every)
        else:
            self.const += law.supremum()
            self._translation_exact(False)
        self.translation_pins()
        self._prior_rotation(r, pq)

    def _decoupled_prior(self, r: int) -> None:
        """The set's own rule where its parent's pose is not known: its parts in the world
        frame do not depend on it and enter exactly (`world_part`); the others count their
        supremum (`counted_supremum`, what `bound_chain` takes back out when it lifts)."""
        rule, every = self.g.rules[r], np.ones(self.n, bool)
        law, form = rule.translation, rule.translation.concave_form()
        if world_part(law) and form is not None:
            self.quadratic(form[0], np.zeros(3), form[1], every)
            self.law_planes(law, np.zeros(3), np.eye(3), every)
            self.const += form[2]
        elif world_part(law):
            self.box(law.box.lo, law.box.hi, every)
            self.const += law.supremum()
        else:
            self.const += law.supremum()
            self._translation_exact(False)
        if world_part(rule.rotation):
            self._prior_rotation(r, IDENTITY)
        else:
            self.const += rule.rotation.supremum()
            self.complete = False

    def translation_pins(self) -> None:
        """Rows whose position is pinned and whose rotation is held to a revolute family: a
        child placed by a fixed parent-frame translation (cx = t + R(q) m) then fixes the
        angle, R(axis, φ) u = v with u = post·m and v = base⁻¹·(cx - t), wherever the parts
        of u and v across the axis are long enough (PIN_LEVER) to fix φ to ~POS_TOL / |u⊥|
        and agree.  Elsewhere the steep quadratic of `_child_translation` stays (a bound)."""
        placed = np.all(self.hi - self.lo <= 4 * BOX_MARGIN, axis=1) & ~self.pinned
        with np.errstate(invalid="ignore"):  # rows without a family or a pinned position
            self._family_by_offsets(placed)
        rows = ~np.isnan(self.fam_base[:, 0]) & placed
        if not np.any(rows):
            return
        with np.errstate(invalid="ignore"):
            self._pin_by_offsets(rows)

    def _family_by_offsets(self, rows: NDArray[np.bool_]) -> None:
        """Rows whose position is pinned and whose rotation is free (no family, no pin): a
        child placed by a fixed parent-frame translation m (at least PIN_LEVER long) with
        cx - t of the same length (within PIN_AGREE) holds the rotation to R m = cx - t,
        the family q = align(m → cx - t) ⊗ rot(m̂, φ), φ any angle (a full revolute arc).
        Every rotation of the family puts the child exactly at cx (`_child_translation`
        then drops its steep quadratic), and a second such child pins the angle
        (`_pin_by_offsets`).  Where no child qualifies the rotation stays free.

        A child whose distance from the pinned position differs from |m| by more than the
        scorer's tolerance (√3·POS_TOL, and the position box) fits no rotation: the row is
        ruled out (any family or not)."""
        if not np.any(rows):
            return
        t = 0.5 * (self.lo + self.hi)
        for r, off_t, off_q, cx, on in self.fixed_children:
            law = self.g.rules[r].translation
            if law.point is None or law.frame != Frame.PARENT or not np.any(rows & on):
                continue
            m = off_t + quat_rotate(off_q, law.point)
            length = float(np.linalg.norm(m))
            v = cx - t
            reach = np.linalg.norm(v, axis=1)
            miss = np.abs(reach - length)
            self.clash |= rows & on & (miss > np.sqrt(3.0) * (POS_TOL + 4 * BOX_MARGIN))
            sel = rows & on & np.isnan(self.fam_base[:, 0])
            if length < PIN_LEVER or not np.any(sel):
                continue
            use = sel & (miss <= PIN_AGREE)
            if not np.any(use):
                continue
            a = np.broadcast_to(m / length, (self.n, 3))
            b = v / np.where(reach > 0, reach, 1.0)[:, None]
            self.fam_base = np.where(use[:, None], quat_between(a, b), self.fam_base)
            self.fam_axis = np.where(use[:, None], a, self.fam_axis)
            self.fam_post = np.where(use[:, None], IDENTITY, self.fam_post)
            self.fam_range = np.where(use[:, None], [-np.pi, np.pi], self.fam_range)

    def _pin_by_offsets(self, rows: NDArray[np.bool_]) -> None:
        for r, off_t, off_q, cx, on in self.fixed_children:
            law = self.g.rules[r].translation
            sel = rows & on & ~self.pinned
            if law.point is None or law.frame != Frame.PARENT or not np.any(sel):
                continue
            m = off_t + quat_rotate(off_q, law.point)
            t = 0.5 * (self.lo + self.hi)
            a = self.fam_axis
            u = quat_rotate(self.fam_post, np.broadcast_to(m, (self.n, 3)))
            v = quat_rotate(quat_conjugate(self.fam_base), cx - np.where(sel[:, None], t, 0.0))
            u_perp = u - np.sum(u * a, axis=1)[:, None] * a
            v_perp = v - np.sum(v * a, axis=1)[:, None] * a
            lever, reach = np.linalg.norm(u_perp, axis=1), np.linalg.norm(v_perp, axis=1)
            agree = np.abs(lever - reach) <= PIN_AGREE
            agree &= np.abs(np.sum((u - v) * a, axis=1)) <= PIN_AGREE
            phi = np.arctan2(
                np.sum(a * np.cross(u_perp, v_perp), axis=1), np.sum(u_perp * v_perp, axis=1)
            )
            lo, hi = self.fam_range[:, 0], self.fam_range[:, 1]
            rel = np.mod(phi - lo, 2 * np.pi)
            inside = (rel <= hi - lo + ROT_TOL) | (rel >= 2 * np.pi - ROT_TOL)
            pin = sel & (lever >= PIN_LEVER) & agree & inside
            if np.any(pin):
                axis = np.where(pin[:, None], a, [0.0, 0.0, 1.0])  # rows without a family
                turn = axis_angle_to_quat(axis, np.where(pin, phi, 0.0))
                q = quat_multiply(quat_multiply(self.fam_base, turn), self.fam_post)
                self.pin_rotation(np.where(pin[:, None], q, IDENTITY), pin)

    def _prior_rotation(self, r: int, pq: FloatArray) -> None:
        rot, rform = self.g.rules[r].rotation, self.g.rules[r].rotation.concave_form()
        rules, pinned = np.full(self.n, r), self.pinned
        if rform is not None:
            A, c = rform
            G = np.eye(4)
            if rot.frame == Frame.PARENT:
                G = _left_linear(lambda q: quat_multiply(quat_conjugate(pq), q), 1)[0]
            self.B += G.T @ A @ G
            self.const += c
            return
        exact = rotation_log_density(self.g, rules, _rows(pq, self.n, 4), self._pin_or_identity())
        self.add(exact, pinned)
        self.add(np.full(self.n, rot.supremum()), ~pinned)
        if rot.mode() is not None and not np.all(pinned):
            self.complete = False  # a revolute law's axis is not imposed on a free rotation

    def child(
        self,
        r: int,
        off_t: FloatArray,
        off_q: FloatArray,
        cx: FloatArray,
        cq: FloatArray,
        on: NDArray[np.bool_],
    ) -> None:
        """A child at poses (cx, cq) (one per assignment, where `on`) of the member at offset
        (off_t, off_q) from the set's top."""
        self._child_translation(r, off_t, off_q, cx, on)
        self._child_rotation(r, off_q, cq, on)

    def _child_translation(self, r, off_t, off_q, cx, on) -> None:  # type: ignore[no-untyped-def]
        g, n = self.g, self.n
        law, form = g.rules[r].translation, g.rules[r].translation.concave_form()
        pinned = self.pinned & on
        R0 = quat_to_matrix(self._pin_or_identity())  # (n, 3, 3)
        if law.frame == Frame.WORLD:
            zeros, ident = np.zeros((n, 3)), np.tile(IDENTITY, (n, 1))
            self.add(translation_log_density(g, np.full(n, r), zeros, ident, cx), on)
        elif form is not None and law.frame == Frame.WORLD_OFFSET:
            mean, P, c = form
            self.quadratic(cx - mean, off_t, P, on)
            self.add(np.full(n, c), on)
            if self._partial_pins(law):
                # t = cx - R off_t - u, u_i the mean on a pinned axis i: a plane on t where
                # R is known (pinned, or no offset to turn); elsewhere left out (a bound)
                held = on & (pinned | bool(np.allclose(off_t, 0.0)))
                self.law_planes(law, cx - R0 @ off_t, -np.eye(3), held)
                self._translation_exact(bool(np.all(held == on)))
        elif form is not None and law.frame == Frame.PARENT:
            mean, P, c = form
            m = off_t + quat_rotate(off_q, mean)
            self.add(np.full(n, c), on)
            if _isotropic(P):
                self.quadratic(cx, m, P, on)
                return
            # an anisotropic precision turns with the set: exact only where the rotation is
            Rc = R0 @ quat_to_matrix(off_q)
            self.quadratic(cx - R0 @ m, np.zeros(3), Rc @ P @ np.swapaxes(Rc, 1, 2), pinned)
            if self._partial_pins(law):  # the child's pinned axes, in its member's frame
                # t = cx - R off_t - Rc u, u_i the mean on a pinned axis i: planes on t
                # where R is pinned
                self.law_planes(law, cx - R0 @ off_t, -Rc, pinned)
            self.add(np.full(n, law.supremum() - c), on & ~pinned)
            self._rotating(cx, m, quat_to_matrix(off_q) @ P @ quat_to_matrix(off_q).T, on & ~pinned)
            self.rot_lift += np.where(on & ~pinned, law.supremum() - c, 0.0)
            self._translation_exact(bool(np.all(pinned == on)))
        elif isinstance(law, BoxTranslation) and law.frame == Frame.WORLD_OFFSET:
            at = R0 @ off_t  # the member's offset from the top, turned with the set
            self.add(np.full(n, law.supremum()), on)
            exact = pinned | (np.allclose(off_t, 0.0) & on)
            self.box(cx - law.box.hi - at, cx - law.box.lo - at, exact)
            self._translation_exact(bool(np.all(exact == on)))
        elif law.point is not None and law.frame == Frame.PARENT:
            m = off_t + quat_rotate(off_q, law.point)
            # a child at the member's own position (no offset) pins t whatever the rotation
            exact = pinned | (bool(np.all(np.abs(m) <= 1e-12)) & on)
            self.box(cx - R0 @ m, cx - R0 @ m, exact)
            # on a family whose every rotation turns m alike (m along its axis), the
            # child's place fixes the position exactly: a box, no steep quadratic
            fam = on & ~exact & ~np.isnan(self.fam_base[:, 0])
            u = quat_rotate(self.fam_post, np.broadcast_to(m, (n, 3)))
            along = np.sum(u * self.fam_axis, axis=1)[:, None] * self.fam_axis
            still = fam & (np.linalg.norm(u - along, axis=1) <= PIN_AGREE)
            at = cx - quat_rotate(np.where(still[:, None], self.fam_base, IDENTITY), u)
            self.box(at, at, still)
            self.quadratic(cx, m, STEEP * np.eye(3), on & ~exact & ~still, hard=True)
            self._translation_exact(bool(np.all((exact | still) == on)))
        else:
            self.add(np.full(n, law.supremum()), on)
            self._translation_exact(False)

    def _rotating(self, cx, m, P, on) -> None:  # type: ignore[no-untyped-def]
        """A precision that turns with the free rotation: its supremum stands in the
        relaxation, the term itself goes to the rotation search (`bound_rotation`)."""
        self.rot_terms.append((cx, m, np.where(on[:, None, None], P, 0.0)))

    def rotating(self) -> Rotating:
        n, cols = self.n, self.rot_terms
        if not cols:
            return Rotating(
                np.zeros((n, 0, 3)), np.zeros((0, 3)), np.zeros((n, 0, 3, 3)), self.rot_lift
            )
        c = np.stack([_rows(cx, n, 3) for cx, _, _ in cols], axis=1)
        m = np.stack([np.asarray(mm, float) for _, mm, _ in cols])
        return Rotating(c, m, np.stack([P for *_, P in cols], axis=1), self.rot_lift)

    def _translation_exact(self, exact: bool) -> None:
        self.complete &= exact
        self.t_complete &= exact

    def _child_rotation(self, r, off_q, cq, on) -> None:  # type: ignore[no-untyped-def]
        g, n = self.g, self.n
        rot, rform = g.rules[r].rotation, g.rules[r].rotation.concave_form()
        rules, pinned = np.full(n, r), self.pinned & on
        if rot.frame == Frame.WORLD:
            self.add(rotation_log_density(g, rules, np.tile(IDENTITY, (n, 1)), cq), on)
        elif rform is not None and rot.frame == Frame.PARENT:
            A, c = rform
            inv_off = quat_conjugate(off_q)
            G = _left_linear(
                lambda q: quat_multiply(quat_multiply(inv_off, quat_conjugate(q)), cq), n
            )
            self.B += np.where(on[:, None, None], np.einsum("nki,kl,nlj->nij", G, A, G), 0.0)
            self.add(np.full(n, c), on)
        else:
            member_q = quat_multiply(self._pin_or_identity(), off_q)
            self.add(rotation_log_density(g, rules, member_q, cq), pinned)
            self.add(np.full(n, rot.supremum()), on & ~pinned)
            if rot.mode() is not None and not np.all(pinned == on):
                self.complete = False

    def terms(self) -> _Terms:
        n = self.n
        if not self.c:
            c, m, P = np.zeros((n, 0, 3)), np.zeros((0, 3)), np.zeros((n, 0, 3, 3))
        else:
            c, m, P = np.stack(self.c, axis=1), np.stack(self.m), np.stack(self.P, axis=1)
        revolute = ~np.isnan(self.fam_base[:, 0]) & ~self.pinned
        base = np.where(revolute[:, None], self.fam_base, IDENTITY)
        axis_q = np.hstack([np.zeros((n, 1)), self.fam_axis])
        u = quat_multiply(base, self.fam_post)
        w = quat_multiply(quat_multiply(base, axis_q), self.fam_post)
        Q, t0, _, lo, hi = self._on_planes()
        return _Terms(
            c,
            m,
            P,
            self.B,
            self.const,
            lo,
            hi,
            self.pin,
            self.complete,
            self.t_complete,
            np.stack([u, w], axis=-1),
            0.5 * self.fam_range,
            revolute,
            np.array(self.hard, bool),
            Q,
            t0,
        )

    def _on_planes(self):  # type: ignore[no-untyped-def]
        """(Q, t0, apart, lo, hi): the rows' planes as t = Q t + t0 (Q the projector onto
        their common directions, t0 their point nearest the origin), the rows whose planes do
        not meet (within BOX_MARGIN, as boxes meet), and the box with each plane along a
        world axis added (what the position's clipping and the exact polish see).

        Rows with a steep stand-in term (a fixed child translation under a rotation not
        pinned) keep their planes out (a bound still: a constraint left out): the steep term
        holds t to the child's place for each rotation, and a plane then holds the rotation
        too, which Frank–Wolfe over the rotations' hull does not reach (a revolute shelf
        pinned in x and y, its book at a fixed offset: a bound of 4e5 for a tree of -3.5)."""
        if not self.planes:
            return None, None, np.zeros(self.n, bool), self.lo, self.hi
        steep = np.zeros(self.n, bool)
        for P, hard in zip(self.P, self.hard, strict=True):
            steep |= hard & np.any(P != 0.0, axis=(1, 2))
        N = np.stack([np.where((on & ~steep)[:, None], nv, 0.0) for nv, _, on in self.planes], 1)
        d = np.stack([np.where(on & ~steep, dv, 0.0) for _, dv, on in self.planes], axis=1)
        Ninv = np.linalg.pinv(N)  # (n, 3, K)
        t0 = np.einsum("nik,nk->ni", Ninv, d)
        apart = np.abs(np.einsum("nki,ni->nk", N, t0) - d).max(axis=1) > BOX_MARGIN
        Q = np.eye(3) - Ninv @ N
        # a plane along a world axis k: t_k = t0_k there, a box widened by BOX_MARGIN
        along = np.abs(Q).max(axis=1) <= 1e-12  # (n, 3): axes the planes fix
        lo = np.where(along, np.maximum(self.lo, t0 - BOX_MARGIN), self.lo)
        hi = np.where(along, np.minimum(self.hi, t0 + BOX_MARGIN), self.hi)
        return Q, t0, apart, lo, hi

    def feasible(self) -> NDArray[np.bool_]:
        """Rows whose constraints can all hold: pins agree, boxes and planes meet, no -inf
        term."""
        _, _, apart, lo, hi = self._on_planes()
        meet = ~self.clash & ~apart & np.all(lo <= hi, axis=1)
        return meet & (self.const > -np.inf)


BOX_MARGIN = 1e-9  # metres: rounding allowed on a box constraint in the bound
PIN_LEVER = 0.1  # metres: an offset this far from a revolute axis fixes its angle (to ~1e-5)
PIN_AGREE = 0.5 * BOX_MARGIN  # metres: how well a fixed offset must fit the family to pin
# it, so that the pinned child's box (`_child_translation`) still meets the position's own
STEEP = 1e8  # precision standing in for a fixed child translation under a free rotation


def _best_t(terms: _Terms, e: FloatArray, clip: NDArray[np.bool_]) -> FloatArray:
    """The best t of Σ -½ (e_k - t)ᵀ P_k (e_k - t) on the rows' planes (exact: a pinned
    Normal axis holds), clipped to the box on the rows `clip`."""
    rhs = np.einsum("nkij,nkj->ni", terms.P, e)
    L, a = terms.affine
    t = np.einsum("nij,nj->ni", L, rhs) + a
    inside = np.clip(t, terms.lo, terms.hi)
    return np.where(clip[:, None], inside, t)


def _value(terms: _Terms, e: FloatArray, t: FloatArray, X: FloatArray):  # type: ignore[no-untyped-def]
    d = e - t[:, None, :]
    Pd = np.einsum("nkij,nkj->nki", terms.P, d)
    h = -0.5 * np.einsum("nki,nki->n", d, Pd) + np.einsum("nab,nab->n", terms.B, X) + terms.const
    return h, Pd


def _h_and_gradient(terms: _Terms, X: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """max over t of g(t, X), its gradient in X (Danskin: the gradient at t*), and t*.

    t is confined to its box where that keeps the maximum exact (diagonal total precision);
    elsewhere the free maximum is used, which is larger: still an upper bound, and concave.
    """
    R = np.einsum("ijab,nab->nij", K_ROT, X)  # (A, 3, 3)
    Rm = np.einsum("nij,kj->nki", R, terms.m)  # (A, K, 3)
    e = terms.c - Rm  # d_k = e_k - t
    t = _best_t(terms, e, terms.diagonal)
    h, Pd = _value(terms, e, t, X)
    grad_R = np.einsum("nki,kj->nij", Pd, terms.m)  # d g / d R
    grad_X = np.einsum("nij,ijab->nab", grad_R, K_ROT) + terms.B
    return h, grad_X, t


def _pinned_bound(terms: _Terms, X: FloatArray) -> FloatArray:
    """An upper bound on max over t in the box of g(t, X) at a fixed X, for any precision:
    the free maximum, and the concave g's linear over-estimate from the clipped point
    (g(s) <= g(t) + ∇g(t)·(s - t) <= g(t) + Σ |∇g(t)_i| (hi_i - lo_i) for s in the box)."""
    R = np.einsum("ijab,nab->nij", K_ROT, X)
    e = terms.c - np.einsum("nij,kj->nki", R, terms.m)
    free = _value(terms, e, _best_t(terms, e, np.zeros(len(X), bool)), X)[0]
    t = np.clip(_best_t(terms, e, np.zeros(len(X), bool)), terms.lo, terms.hi)
    h, Pd = _value(terms, e, t, X)
    width = np.where(np.isfinite(terms.hi - terms.lo), terms.hi - terms.lo, np.inf)
    slack = np.einsum("ni,ni->n", np.abs(Pd.sum(axis=1)), width)
    slack = np.where(np.isnan(slack), np.inf, slack)  # a zero gradient on an unbounded axis
    exact = np.where(terms.diagonal, _h_and_gradient(terms, X)[0], np.inf)
    return np.minimum(np.minimum(free, h + slack), np.minimum(exact, _box_bound(terms, e, X)))


BOX_SWEEPS = 60  # coordinate-ascent sweeps for the best position in a box


def _box_position(terms: _Terms, e: FloatArray) -> FloatArray:
    """The best t in the box of Σ -½ (e_k - t)ᵀ P_k (e_k - t) for any total precision:
    coordinate ascent from the clipped free optimum (converges to the box's optimum; any
    point of the box is feasible, and `_box_bound` pays for what is left)."""
    H = terms.P.sum(axis=1)
    b = np.einsum("nkij,nkj->ni", terms.P, e)
    t = np.clip(np.einsum("nij,nj->ni", terms.inverse, b), terms.lo, terms.hi)
    t = np.where(np.isfinite(t), t, 0.0)
    diag = np.maximum(np.einsum("nii->ni", H), 1e-300)
    for _ in range(BOX_SWEEPS):
        for k in range(3):
            rest = b[:, k] - np.einsum("nj,nj->n", H[:, k], t) + H[:, k, k] * t[:, k]
            t[:, k] = np.clip(rest / diag[:, k], terms.lo[:, k], terms.hi[:, k])
    return t


def _box_bound(terms: _Terms, e: FloatArray, X: FloatArray) -> FloatArray:
    """max over t in the box of g(t, X) for a fixed X, as h(t) + max over the box of
    ∇h(t)·(s - t) at the coordinate-ascent point t (concavity): exact at the box's
    optimum, for any total precision (a pinned rotation under a turned anisotropic
    Normal and a box).  Rows with an unbounded axis get ∞ (the other bounds hold)."""
    t = _box_position(terms, e)
    h, Pd = _value(terms, e, t, X)
    grad = Pd.sum(axis=1)
    with np.errstate(invalid="ignore"):
        gain = np.maximum(grad * (terms.hi - t), grad * (terms.lo - t))
    gain = np.where(np.isnan(gain), np.inf, gain).sum(axis=1)
    bounded = np.all(np.isfinite(terms.lo) & np.isfinite(terms.hi), axis=1)
    return np.where(bounded, h + gain, np.inf)


def relaxed_upper_bound(
    terms: _Terms, iterations: int = FW_ITERATIONS, deadline: float | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Frank–Wolfe over {X ⪰ 0, tr X = 1}: the best duality-gap bound per assignment, and the
    pose (t, q) read off the last iterate (q: X's leading eigenvector), a starting point for
    the exact local optimisation.  A pinned rotation keeps X = pin pinᵀ: its bound is the
    maximum over t alone.

    For concave h, h(Y) <= h(X) + <∇h(X), Y - X> <= h(X) + λmax(∇h(X)) - <∇h(X), X> for every
    feasible Y, so every iterate yields a valid upper bound on the relaxation, hence on the
    true maximum over rotations.  Stopping early (at the deadline) leaves a looser, still
    valid bound.
    """
    pinned, fam = terms.pinned, terms.revolute
    v = np.linalg.eigh(terms.B)[1]
    top = np.where(pinned[:, None], np.nan_to_num(terms.pin), v[..., -1])
    top = np.where(fam[:, None], _arc_point(terms, terms.arc.mean(axis=1)), top)
    X = np.einsum("na,nb->nab", top, top)
    best = np.full(len(X), np.inf)
    if np.any(pinned):
        best[pinned] = _pinned_bound(_subset(terms, pinned), X[pinned])
    free = ~pinned
    exact = free & _isotropic_rows(terms)
    if np.any(exact):  # the rotation's exact optimum: an eigenvector (or an arc's best point)
        value, q_best = _isotropic_bound(_subset(terms, exact))
        best[exact] = value
        X[exact] = np.einsum("na,nb->nab", q_best, q_best)
    rest = free & ~exact
    if np.any(rest):  # Frank–Wolfe on the other free rows only
        part = _subset(terms, rest)
        sub_best, sub_X = best[rest], X[rest]
        _frank_wolfe(part, sub_X, sub_best, np.ones(len(sub_X), bool), iterations, deadline)
        best[rest], X[rest] = sub_best, sub_X
    v = np.linalg.eigh(X)[1]
    q = np.where(pinned[:, None], np.nan_to_num(terms.pin), v[..., -1])
    if np.any(fam):  # the family's rotation nearest the leading eigenvector
        c = np.einsum("nab,na->nb", terms.V, q)
        psi = np.clip(np.arctan2(c[:, 1], c[:, 0]), terms.arc[:, 0], terms.arc[:, 1])
        q = np.where(fam[:, None], _arc_point(terms, psi), q)
    return best, best_position(terms, q), q


def best_position(terms: _Terms, q: FloatArray) -> FloatArray:
    """The best position for rotations q: the closed form (clipped where the total
    precision is diagonal, else free), and where it is not diagonal and the box is bounded
    the box's optimum by coordinate ascent (`_box_position`)."""
    X = np.einsum("na,nb->nab", q, q)
    t = _h_and_gradient(terms, X)[2]
    rows = ~terms.diagonal & np.all(np.isfinite(terms.lo) & np.isfinite(terms.hi), axis=1)
    if np.any(rows):
        sub = _subset(terms, rows)
        R = np.einsum("ijab,nab->nij", K_ROT, X[rows])
        t[rows] = _box_position(sub, sub.c - np.einsum("nij,kj->nki", R, sub.m))
    return t


def _isotropic_rows(terms: _Terms) -> NDArray[np.bool_]:
    """Rows whose translation terms all have isotropic precision and whose position has no
    box or is pinned (`_placed`): there max over t of g(t, R) is linear in R on rotations
    (`_isotropic_bound`)."""
    P = terms.P
    iso = np.all(np.abs(P - P[..., :1, :1] * np.eye(3)) <= 1e-12 * (1 + np.abs(P)), axis=(1, 2, 3))
    unboxed = np.all(np.isinf(terms.lo) & np.isinf(terms.hi), axis=1) & ~terms.planed
    return iso & (unboxed | _placed(terms))


def _placed(terms: _Terms) -> NDArray[np.bool_]:
    """Rows whose position is pinned (a box no wider than its rounding margins) and that
    have no steep stand-in term: their best t is the pin, up to a slack `_isotropic_bound`
    pays for (small at moderate precisions, not at STEEP's)."""
    narrow = np.all(terms.hi - terms.lo <= 4 * BOX_MARGIN, axis=1)
    return narrow & (np.max(terms.P[..., 0, 0], axis=1, initial=0.0) < STEEP)


def _isotropic_bound(terms: _Terms) -> tuple[FloatArray, FloatArray]:
    """The exact maximum over rotations (and t) of g for rows of `_isotropic_rows`, and the
    rotation reaching it.

    With P_k = p_k I (P = Σ p_k, e_k = c_k - R m_k), the best t is Σ p_k e_k / P = c̄ - R m̄
    (c̄, m̄ the p-weighted means), so e_k - t = c'_k - R m'_k with c'_k = c_k - c̄ and
    m'_k = m_k - m̄, and max_t g = -½ Σ p_k (|c'_k|² + |m'_k|²) + ⟨Σ p_k c'_k m'_kᵀ, R⟩
    + tr(B X) + const, using |R m'|² = |m'|² on rotations: linear in R, hence in X = q qᵀ,
    and its maximum over unit q is the top eigenvalue of a 4×4 matrix (over a revolute
    family, the arc's best point, `_arc_lmo`).  No relaxation gap.  The centred form keeps
    the sums small where one term is steep (STEEP).  At a pinned position t0 the same holds
    with c'_k = c_k - t0 and m'_k = m_k (plus the slack of the pin's rounding margin).

    A steep term that stands in for a fixed translation (`_Terms.hard`) is a pin: t is then
    its c - R m (the mean of such terms), where the other terms are evaluated exactly, instead
    of a p-weighted mean that leans off the pin by p / STEEP (1e-6 nats and more loose).  Still
    a bound: wherever the pins hold, the value is the score at that rotation."""
    p = terms.P[..., 0, 0]  # (A, K)
    total = p.sum(axis=1)
    weight = p / np.where(total > 0, total, 1.0)[:, None]
    if terms.hard is not None and np.any(terms.hard):
        pin = (p > 0) & terms.hard[None, :]
        count = pin.sum(axis=1)
        by_pin = pin / np.maximum(count, 1)[:, None]
        weight = np.where((count > 0)[:, None], by_pin, weight)
    c = terms.c - np.einsum("nk,nki->ni", weight, terms.c)[:, None, :]
    m = terms.m[None] - np.einsum("nk,ki->ni", weight, terms.m)[:, None, :]
    # a pinned position t0 (`_placed`): e_k - t0 = (c_k - t0) - R m_k, not centred; t may
    # still move by w (half the box) per axis, worth at most |w|·|∇_t| with |∇_t| ≤
    # |Σ p_k (c_k - t0)| + |Σ p_k m_k| (concavity), added to the bound
    placed = _placed(terms) & ~np.all(np.isinf(terms.lo) & np.isinf(terms.hi), axis=1)
    slack = np.zeros(len(p))
    if np.any(placed):
        t0 = 0.5 * (terms.lo[placed] + terms.hi[placed])
        c[placed] = terms.c[placed] - t0[:, None, :]
        m[placed] = terms.m[None]
        half = np.linalg.norm(0.5 * (terms.hi[placed] - terms.lo[placed]), axis=1)
        pull = np.linalg.norm(np.einsum("nk,nki->ni", p[placed], c[placed]), axis=1)
        pull += np.linalg.norm(np.einsum("nk,ki->ni", p[placed], terms.m), axis=1)
        slack[placed] = half * pull
    G_R = np.einsum("nk,nki,nkj->nij", p, c, m)
    C = np.einsum("nij,ijab->nab", G_R, K_ROT) + terms.B
    const = -0.5 * np.einsum("nk,nki,nki->n", p, c, c) - 0.5 * np.einsum("nk,nki,nki->n", p, m, m)
    const += slack
    w, v = np.linalg.eigh(C)
    value, q = w[:, -1], v[..., -1]
    if np.any(terms.revolute):
        q_arc, value_arc = _arc_lmo(terms, C)
        q = np.where(terms.revolute[:, None], q_arc, q)
        value = np.where(terms.revolute, value_arc, value)
    return value + const + terms.const, q


def _frank_wolfe(terms, X, best, free, iterations, deadline):  # type: ignore[no-untyped-def]
    """Frank–Wolfe steps on the rows `free`, updating X and `best` (the lowest duality-gap
    bound seen) in place; returns h at the last iterate (the relaxation's value there)."""
    fam = terms.revolute
    h = np.full(len(X), -np.inf)
    seen: list[FloatArray] = []  # `best` at each iteration, for the stall test
    for _ in range(iterations if np.any(free) else 0):
        if deadline is not None and time.perf_counter() >= deadline and np.all(best < np.inf):
            break
        if _settled(best, h, seen):
            break
        seen.append(best.copy())
        h, G, _ = _h_and_gradient(terms, X)
        Gs = 0.5 * (G + np.swapaxes(G, 1, 2))
        w, v = np.linalg.eigh(Gs)
        top, lmo = v[..., -1], w[:, -1]
        if np.any(fam):  # the linear maximiser over the law's arc of rotations
            s_fam, lmo_fam = _arc_lmo(terms, Gs)
            top = np.where(fam[:, None], s_fam, top)
            lmo = np.where(fam, lmo_fam, lmo)
        bound = h + lmo - np.einsum("nab,nab->n", G, X)
        best[:] = np.where(free, np.minimum(best, bound), best)
        S = np.einsum("na,nb->nab", top, top)
        S = np.where(free[:, None, None], S, X)
        h_half = _h_and_gradient(terms, 0.5 * (X + S))[0]
        h_one = _h_and_gradient(terms, S)[0]
        # h(X + γ(S - X)) is a concave parabola in γ through these three values.
        curv = 2 * (h_one - 2 * h_half + h)
        slope = 4 * h_half - 3 * h - h_one
        gamma = np.where(curv < -1e-15, np.clip(-slope / np.minimum(curv, -1e-15), 0, 1), 1.0)
        gamma = np.where((curv >= -1e-15) & (h_one < h), 0.0, gamma)
        X += gamma[:, None, None] * (S - X)
    return h


FW_STALL = 10  # Frank–Wolfe iterations over which a bound must still fall to go on
FW_TOL = 1e-10  # relative: a bound within this of the iterate's value, or falling by less


def _settled(best: FloatArray, h: FloatArray, seen: list[FloatArray]) -> bool:
    """Whether more Frank–Wolfe steps would no longer move any row's bound: each row's bound
    meets the relaxation's value at the iterate (converged), or fell by less than FW_TOL over
    the last FW_STALL iterations (a relaxation gap the steps do not close).

    Why: the bound certifies to GAP_TOL = 1e-6; most rows settle in 10–40 of the 150 steps,
    and the rest of the steps were a third of `ip`'s time on the constituency benchmark.
    Stopping leaves every row's bound valid (each iterate gives one) and the best seen."""
    if len(seen) < FW_STALL or not np.all(np.isfinite(best)):
        return False
    scale = FW_TOL * np.maximum(1.0, np.abs(best))
    converged = best - h <= scale
    stalled = seen[-FW_STALL] - best <= scale
    return bool(np.all(converged | stalled))


def _arc_point(terms: _Terms, psi: FloatArray) -> FloatArray:
    """The family's rotation at half-angle ψ, per row: V (cos ψ, sin ψ)."""
    return np.einsum("nab,nb->na", terms.V, np.stack([np.cos(psi), np.sin(psi)], axis=1))


def _arc_lmo(terms: _Terms, G: FloatArray) -> tuple[FloatArray, FloatArray]:
    """max over ψ in the arc of sᵀ M s, s = (cos ψ, sin ψ), M = Vᵀ G V, and its maximiser
    V s: sᵀ M s = a + r cos(2ψ - β), so the maximum is at ψ = β/2 (mod π) if the arc holds
    it, else at an end."""
    M = np.einsum("nai,nab,nbj->nij", terms.V, G, terms.V)
    a = 0.5 * (M[:, 0, 0] + M[:, 1, 1])
    beta = np.arctan2(M[:, 0, 1], 0.5 * (M[:, 0, 0] - M[:, 1, 1]))
    r = np.hypot(0.5 * (M[:, 0, 0] - M[:, 1, 1]), M[:, 0, 1])
    lo, hi = terms.arc[:, 0], terms.arc[:, 1]
    peak = 0.5 * beta + np.pi * np.ceil((lo - 0.5 * beta) / np.pi)  # the first peak >= lo
    inside = peak <= hi

    def value(psi: FloatArray) -> FloatArray:
        return a + r * np.cos(2 * psi - beta)

    psi = np.where(inside, peak, np.where(value(lo) >= value(hi), lo, hi))
    return _arc_point(terms, psi), value(psi)


def _subset(terms: _Terms, rows: NDArray[np.bool_]) -> _Terms:
    return _Terms(
        terms.c[rows],
        terms.m,
        terms.P[rows],
        terms.B[rows],
        terms.const[rows],
        terms.lo[rows],
        terms.hi[rows],
        terms.pin[rows],
        terms.complete,
        terms.t_complete,
        terms.V[rows],
        terms.arc[rows],
        terms.revolute[rows],
        terms.hard,
        None if terms.Q is None else terms.Q[rows],
        None if terms.t0 is None else terms.t0[rows],
    )


@dataclass(frozen=True)
class SetBound:
    """One latent set's assignments: which candidate child fills each column (-1: none), the
    upper bound of each, and the pose of the set's top node that is best for each (see
    `polish`).  A column is one child slot, or one copy of a `repeat`."""

    slots: tuple[tuple[int, int, int], ...]  # (member node, rule, child set) per column
    assignment: IntArray  # (A, n_columns) candidate index of each column's child, -1: none
    upper: FloatArray  # (A,)
    xyz: FloatArray  # (A, 3)
    quat: FloatArray  # (A, 4)
    parent: tuple[FloatArray, FloatArray] | None  # the pose the set's own rule is scored at
    decoupled: bool = False  # the parent's pose is unknown: its rule counts its supremum
    free: NDArray[np.bool_] | None = None  # (A,) rows at a pose an observed member implies
    chain: Any = None  # bound_chain.Lifted: a decoupled set lifted into its parent's rows

    @property
    def free_rows(self) -> NDArray[np.bool_]:
        """Rows whose children are not restricted and scored exactly (`_implied_rows`)."""
        return np.zeros(len(self.upper), bool) if self.free is None else self.free


def world_part(law) -> bool:  # type: ignore[no-untyped-def]
    """Whether a decoupled set's own rule holds this part (translation or rotation law)
    exactly in the set's own bound: it is in the world frame, so its parent's pose does not
    matter (a world Normal or box translation; any world rotation)."""
    from ssgc.laws.base import RotationLaw

    if law.frame != Frame.WORLD:
        return False
    return isinstance(law, RotationLaw | BoxTranslation) or law.concave_form() is not None


def counted_supremum(rule) -> float:  # type: ignore[no-untyped-def]
    """What a decoupled set's bound counts for its own rule's parts that are not exact."""
    parts = (rule.translation, rule.rotation)
    return float(sum(p.supremum() for p in parts if not world_part(p)))


@dataclass
class Rotating:
    """The rotating terms of one set's rows: -½ (Rᵀ(c - t) - m)ᵀ P (…) per row and term,
    where the rows' relaxation counts `lift` (their suprema less their normalisers) instead."""

    c: FloatArray  # (A, J, 3) child positions
    m: FloatArray  # (J, 3) the child's mean offset in the set's top frame
    P: FloatArray  # (A, J, 3, 3) precision in the top frame; zero where absent or exact
    lift: FloatArray  # (A,)

    @property
    def rows(self) -> NDArray[np.bool_]:
        return np.any(self.P != 0.0, axis=(1, 2, 3))

    def subset(self, keep: NDArray[np.bool_]) -> Rotating:
        return Rotating(self.c[keep], self.m, self.P[keep], self.lift[keep])
