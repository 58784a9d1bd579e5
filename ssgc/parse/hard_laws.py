"""Latent poses that satisfy the hard laws around them exactly (issue 11).

A latent pose is held by hard laws from both sides: its own rule at its parent's pose (a fixed
offset or rotation pins it, a box holds its position, a revolute law holds its rotation to an
arc) and the rules to its children at their poses (a child at a fixed offset pins the position
for each rotation, a child placed by a revolute law holds the rotation to an arc about the
child's axis, a child in a box offset holds the position to a box).  Proposals made by rule
inversion and Newton steps put a pose at the mode of one soft law and rarely meet all of those
at once; the model over proposals then has no tree (`no_parse`), although the scene was sampled
from the grammar.

`hard_poses` solves the hard laws instead: the rotation first (pins; arcs, intersected exactly
where two meet in a point, or sampled along their common stretch; relays, the arcs of a
grandchild through a latent child's revolute law, met by Paden–Kahan's second subproblem),
then, for each rotation, the position (a pin, or the soft laws' target clipped into the
boxes' intersection).  Every pose is
then checked with the grammar's own densities; only poses every law involved accepts are kept,
best (by the involved laws' log-densities) first.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import (
    quat_between,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
)
from ssgc.ir import Grammar
from ssgc.laws.base import Frame
from ssgc.laws.position_box import BoxTranslation
from ssgc.laws.position_normal import NormalTranslation
from ssgc.laws.rotation_revolute import RevoluteRotation
from ssgc.parse.set_terms import IDENTITY, _plane
from ssgc.rules import rotation_log_density, translation_log_density

FloatArray = NDArray[np.float64]
ARC_GRID = 48  # rotations sampled along an arc (plus its ends and the other arcs' ends)
ARC_GRID_BOXED = 720  # the same where a box holds the position (which moves with the angle)
ON_ARC = 1e-9  # 1 - |projection| at most this: a rotation lies on an arc's plane


@dataclass(frozen=True)
class Arc:
    """Rotations q = left ⊗ R(axis, φ) ⊗ right, φ in [lo, hi] (lo == hi: a pin)."""

    left: FloatArray
    axis: FloatArray
    lo: float
    hi: float
    right: FloatArray

    @cached_property
    def plane(self) -> FloatArray:
        """(4, 2): q(φ) = plane @ (cos φ/2, sin φ/2) (computed once: an arc is met, sampled
        and checked many times while a set's hard laws are solved)."""
        return _plane(self.left[None], self.axis[None], self.right[None])[0]

    def at(self, phi: FloatArray) -> FloatArray:
        half = 0.5 * np.asarray(phi, float)
        return np.stack([np.cos(half), np.sin(half)], axis=1) @ self.plane.T

    def holds(self, q: FloatArray, tol: float = 1e-7) -> NDArray[np.bool_]:
        """Whether each rotation lies on the arc (within `tol` radians of its range)."""
        s = q @ self.plane
        on = np.linalg.norm(s, axis=1) >= 1.0 - ON_ARC
        phi = 2.0 * np.arctan2(s[:, 1], s[:, 0])
        rel = np.mod(phi - self.lo, 2.0 * np.pi)
        inside = (rel <= self.hi - self.lo + tol) | (rel >= 2.0 * np.pi - tol)
        return on & inside


@dataclass
class Laws:
    """The hard and soft laws on one latent pose, from its parent's side and its children's."""

    arcs: list[Arc]
    soft_quat: list[FloatArray]  # (4,) rotation targets of soft laws
    pins: list[tuple[FloatArray, FloatArray]]  # (A (3,), B (3, 3)...) position x = A - R(q) B
    boxes: list[tuple[FloatArray, FloatArray, FloatArray]]  # lo, hi, shift: x + R(q) shift ∈ box
    soft_xyz: list[tuple[FloatArray, FloatArray]]  # target x = A - R(q) B
    # (rule, whether the set is the rule's child, the other end's pose, the member's offset)
    checks: list[tuple[int, bool, FloatArray, FloatArray, FloatArray, FloatArray]]
    relays: list[Relay] = field(default_factory=list)  # arcs held through a revolute child
    child_pins: list[ChildPin] = field(default_factory=list)  # children's parent-frame pins
    # planes n·x = t of the set's own rule's pinned axes in its known parent's frame
    planes: list[tuple[FloatArray, float]] = field(default_factory=list)


@dataclass(frozen=True)
class ChildPin:
    """A child at `c_xyz` whose parent-frame Normal pins axes: (R_vᵀ (c - x_v))[pinned] =
    mean[pinned], with x_v = x + R(q) member_xyz and R_v = R(q ⊗ member_quat).  A condition
    on the set's rotation where its position is held, on its position (planes) where not."""

    c_xyz: FloatArray
    member_xyz: FloatArray
    member_quat: FloatArray
    pinned: NDArray[np.bool_]
    mean: FloatArray


@dataclass(frozen=True)
class Relay:
    """Rotations q with q ⊗ turn ⊗ R(axis, φ) on `arc` for some φ in [lo, hi]: a latent child
    placed by a revolute law, whose own rotation its children hold to `arc`."""

    arc: Arc
    turn: FloatArray  # the member's rotation in the set's frame
    axis: FloatArray
    lo: float
    hi: float


def empty_laws() -> Laws:
    return Laws([], [], [], [], [], [])


def add_parent_rule(
    laws: Laws, grammar: Grammar, r: int, p_xyz: FloatArray | None, p_quat: FloatArray | None
) -> None:
    """The set's own rule r at its parent node's pose (None: the rule is in the world frame,
    or the parent's pose is unknown and only world-frame parts are used)."""
    rule = grammar.rules[r]
    tl, rl = rule.translation, rule.rotation
    known = p_xyz is not None and p_quat is not None
    if known:
        laws.checks.append((r, True, p_xyz, p_quat, np.zeros(3), IDENTITY))  # type: ignore[arg-type]
    if rl.point is not None and (known or rl.frame == Frame.WORLD):
        base = p_quat if rl.frame == Frame.PARENT and known else IDENTITY
        q = quat_multiply(base, rl.point)
        laws.arcs.append(Arc(q, np.array([1.0, 0, 0]), 0.0, 0.0, IDENTITY))
    elif isinstance(rl, RevoluteRotation) and known:
        lo, hi = float(rl.revolute.lo), float(rl.revolute.hi)
        laws.arcs.append(Arc(p_quat, np.asarray(rl.axis, float), lo, hi, IDENTITY))  # type: ignore[arg-type]
    elif rl.mode() is not None and (known or rl.frame == Frame.WORLD):
        base = p_quat if rl.frame == Frame.PARENT and known else IDENTITY
        laws.soft_quat.append(quat_multiply(base, rl.mode()))
    zero = np.zeros(3)
    if tl.frame == Frame.PARENT and not known:
        return
    origin = p_xyz if known and tl.frame != Frame.WORLD else zero
    if tl.point is not None:  # fixed translations are parent-frame
        laws.pins.append((origin + quat_rotate(p_quat, tl.point), zero))  # type: ignore[arg-type]
    elif isinstance(tl, BoxTranslation) and tl.frame != Frame.PARENT:
        laws.boxes.append((origin + tl.box.lo, origin + tl.box.hi, zero))  # type: ignore[operator]
    elif isinstance(tl, NormalTranslation):
        mean = quat_rotate(p_quat, tl.offset) if tl.frame == Frame.PARENT else tl.offset  # type: ignore[arg-type]
        laws.soft_xyz.append((origin + mean, zero))  # type: ignore[operator]
        if tl.frame == Frame.PARENT and not np.all(tl.free):  # planes in the parent's frame
            for a in np.flatnonzero(~np.asarray(tl.free, bool)):
                n = quat_rotate(p_quat, np.eye(3)[a])  # type: ignore[arg-type]
                laws.planes.append((n, float(n @ origin) + float(tl.offset[a])))  # type: ignore[operator]
        if tl.frame != Frame.PARENT and not np.all(tl.free):  # pinned world axes: a flat box
            lo = np.where(tl.free, -np.inf, origin + tl.offset)  # type: ignore[operator]
            hi = np.where(tl.free, np.inf, origin + tl.offset)  # type: ignore[operator]
            laws.boxes.append((lo, hi, zero))


def add_child_rule(
    laws: Laws,
    grammar: Grammar,
    r: int,
    member_xyz: FloatArray,
    member_quat: FloatArray,
    c_xyz: FloatArray,
    c_quat: FloatArray,
) -> None:
    """A child at (c_xyz, c_quat) placed by rule r from member v, whose pose is
    (member_xyz, member_quat) relative to the set's top: x_v = x + R(q) member_xyz."""
    rule = grammar.rules[r]
    tl, rl = rule.translation, rule.rotation
    laws.checks.append((r, False, c_xyz, c_quat, member_xyz, member_quat))
    inv_m = quat_conjugate(member_quat)
    if rl.frame == Frame.PARENT and rl.point is not None:
        q = quat_multiply(quat_multiply(c_quat, quat_conjugate(rl.point)), inv_m)
        laws.arcs.append(Arc(q, np.array([1.0, 0, 0]), 0.0, 0.0, IDENTITY))
    elif isinstance(rl, RevoluteRotation):
        lo, hi = float(rl.revolute.lo), float(rl.revolute.hi)
        laws.arcs.append(Arc(c_quat, np.asarray(rl.axis, float), -hi, -lo, inv_m))
    elif rl.frame == Frame.PARENT and rl.mode() is not None:
        laws.soft_quat.append(
            quat_multiply(quat_multiply(c_quat, quat_conjugate(rl.mode())), inv_m)
        )
    if tl.frame == Frame.WORLD:
        return
    # x = c - R(q) (member_xyz + R(member_quat) m) for a parent-frame offset m
    if tl.point is not None:
        laws.pins.append((c_xyz, member_xyz + quat_rotate(member_quat, tl.point)))
    elif isinstance(tl, BoxTranslation):  # world offset: c - x_v in [lo, hi]
        laws.boxes.append((c_xyz - tl.box.hi, c_xyz - tl.box.lo, member_xyz))
    elif isinstance(tl, NormalTranslation):
        if tl.frame == Frame.PARENT:
            laws.soft_xyz.append((c_xyz, member_xyz + quat_rotate(member_quat, tl.offset)))
            if not np.all(tl.free):
                pinned = ~np.asarray(tl.free, bool)
                mean = np.asarray(tl.offset, float)
                laws.child_pins.append(ChildPin(c_xyz, member_xyz, member_quat, pinned, mean))
        else:
            laws.soft_xyz.append((c_xyz - tl.offset, member_xyz))
            if not np.all(tl.free):  # pinned world-offset axes: a flat box
                lo = np.where(tl.free, -np.inf, c_xyz - tl.offset)
                hi = np.where(tl.free, np.inf, c_xyz - tl.offset)
                laws.boxes.append((lo, hi, member_xyz))


def add_grandchild_rule(
    laws: Laws,
    grammar: Grammar,
    link: int,
    member_quat: FloatArray,
    r: int,
    child_xyz: FloatArray,
    child_quat: FloatArray,
    g_xyz: FloatArray,
    g_quat: FloatArray,
) -> None:
    """A grandchild at (g_xyz, g_quat), placed by rule r from member (child_xyz, child_quat)
    of a latent child set, which rule `link` places from member `member_quat` of this set.

    The grandchild holds the child set's rotation to arcs (`add_child_rule`); through a fixed
    rotation `link` those are arcs of this set's rotation (q_c = q ⊗ m ⊗ point), through a
    revolute `link` they are relays (q_c = q ⊗ m ⊗ R(axis, φ)), which meet this set's own arcs
    in isolated rotations (`relay_meets`).  Why: two revolute laws in a row hold two latent
    rotations only jointly, and solving each set from the other's guessed poses never meets
    both arcs (issue 11, `no_parse`)."""
    sub = empty_laws()
    add_child_rule(sub, grammar, r, child_xyz, child_quat, g_xyz, g_quat)
    rl = grammar.rules[link].rotation
    if rl.frame != Frame.PARENT:
        return
    for arc in sub.arcs:
        if rl.point is not None:
            back = quat_multiply(quat_conjugate(rl.point), quat_conjugate(member_quat))
            right = quat_multiply(arc.right, back)
            laws.arcs.append(Arc(arc.left, arc.axis, arc.lo, arc.hi, right))
        elif isinstance(rl, RevoluteRotation):
            lo, hi = float(rl.revolute.lo), float(rl.revolute.hi)
            laws.relays.append(Relay(arc, member_quat, np.asarray(rl.axis, float), lo, hi))


def two_axis_angles(
    a: FloatArray, b: FloatArray, p: FloatArray, q: FloatArray
) -> list[tuple[float, float]]:
    """The angles (ψ, φ) with R(a, ψ) R(b, φ) p = q (unit axes a, b not parallel): Paden–
    Kahan's second subproblem.  z = R(b, φ) p = R(a, -ψ) q keeps b·z = b·p, a·z = a·q and
    |z| = |p|, so z = α a + β b ± γ (a × b); each z gives φ and ψ by the first subproblem."""
    ab = float(a @ b)
    denom = 1.0 - ab * ab
    if denom < 1e-12 or abs(float(p @ p) - float(q @ q)) > 1e-9 * max(1.0, float(p @ p)):
        return []
    alpha = (float(a @ q) - ab * float(b @ p)) / denom
    beta = (float(b @ p) - ab * float(a @ q)) / denom
    n = np.cross(a, b)
    g2 = (float(p @ p) - alpha**2 - beta**2 - 2 * alpha * beta * ab) / float(n @ n)
    if g2 < -1e-9:
        return []
    g = np.sqrt(max(g2, 0.0))
    # γ² is |p|² less a sum of nearly the same size: its rounding, 4 ε |p|², hides a γ up to
    # `hidden` (p within 4e-9 of a: γ² of 1.6e-17 computed as -1.6e-17), so where γ is no
    # larger, both signs of that size are polished (the same solution twice is returned once).
    hidden = float(np.sqrt(4.0 * np.finfo(float).eps * float(p @ p) / float(n @ n)))
    out: list[tuple[float, float]] = []
    for s in (g, -g) if g > hidden else (hidden, -hidden):
        z = alpha * a + beta * b + s * n
        found = _polish(a, b, p, q, _turn(a, z, q), _turn(b, p, z))
        if not any(abs(found[0] - o[0]) + abs(found[1] - o[1]) < 1e-12 for o in out):
            out.append(found)
    return out


def _polish(
    a: FloatArray, b: FloatArray, p: FloatArray, q: FloatArray, psi: float, phi: float
) -> tuple[float, float]:
    """(ψ, φ) after Gauss–Newton steps on |R(a, ψ) R(b, φ) p - q|, each halved until it lowers
    the residual, until the residual is rounding.  Near tangency (the two solutions about to
    merge, γ ≈ 0) the square root above loses half the digits: an error of 1e-7 where the data
    hold 1e-16.  With p within nanometres of a, ψ turns only p's tiny part across a, so ψ and
    φ act like the angle and radius of polar coordinates near their centre, and a full step
    overshoots (session 26: residuals up to 5.5e-8 before the halving, 1.3e-15 after, on 40,000
    random and near-tangent cases)."""

    def residual(psi: float, phi: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        ra = _axis_quat(a, psi)
        v = quat_rotate(ra, quat_rotate(_axis_quat(b, phi), p))
        return v - q, v, quat_rotate(ra, b)

    r, v, b_now = residual(psi, phi)
    rounding = (4.0 * np.finfo(float).eps * max(1.0, float(np.linalg.norm(p)))) ** 2
    for _ in range(60):
        if not float(r @ r) > rounding:
            break
        jac = np.stack([np.cross(a, v), np.cross(b_now, v)], axis=1)  # d/dψ, d/dφ
        step = np.linalg.lstsq(jac, -r, rcond=None)[0]
        for _ in range(30):  # halved until it lowers the residual: near tangency (p almost
            new = residual(psi + float(step[0]), phi + float(step[1]))  # along a) a full
            if float(new[0] @ new[0]) < float(r @ r):  # step in ψ overshoots
                break
            step = 0.5 * step
        else:
            break
        psi, phi = psi + float(step[0]), phi + float(step[1])
        r, v, b_now = new
    return psi, phi


def _turn(axis: FloatArray, u: FloatArray, v: FloatArray) -> float:
    """The angle about `axis` taking u to v (their parts across the axis)."""
    u = u - axis * float(axis @ u)
    v = v - axis * float(axis @ v)
    return float(np.arctan2(axis @ np.cross(u, v), u @ v))


def _axis_quat(axis: FloatArray, angle: float) -> FloatArray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[np.cos(0.5 * angle), np.sin(0.5 * angle) * axis]


def relay_meets(first: Arc, relay: Relay) -> FloatArray:
    """Rotations on `first` that `relay` holds: first.left R(a1, ψ) first.right ⊗ turn ⊗
    R(b0, φ) = C.left R(a2, χ) C.right (C the relay's arc).  With K = first.right ⊗ turn,
    W = C.right ⊗ K⁻¹ and M = first.left⁻¹ ⊗ C.left ⊗ W this is R(a1, ψ) R(K b0, φ) =
    M R(W⁻¹ a2, χ), and on the vector c = W⁻¹ a2: R(a1, ψ) R(K b0, φ) c = M c."""
    c_arc = relay.arc
    k = quat_multiply(first.right, relay.turn)
    w = quat_multiply(c_arc.right, quat_conjugate(k))
    m = quat_multiply(quat_multiply(quat_conjugate(first.left), c_arc.left), w)
    a1 = first.axis / np.linalg.norm(first.axis)
    b = quat_rotate(k, relay.axis / np.linalg.norm(relay.axis))
    c = quat_rotate(quat_conjugate(w), c_arc.axis / np.linalg.norm(c_arc.axis))
    mc = quat_rotate(m, c)
    # `two_axis_angles` resolves φ to ~1e-16 / δ, δ the angle between the relay's two axes:
    # its meets, where both arcs hold them, are taken first.  When there are none and the
    # axes are one to within δ < 4.5e-7 rad (rounding alone leaves ~5e-8), the relay's angle
    # is free and the meet holds to O(δ).  Taking such axes as one before trying left a meet
    # 1.04e-6 rad off (δ = 1.2e-7; tests/test_parse_hard_poses.py, found by hypothesis).
    found = _isolated_meets(first, relay, a1, b, c, mc)
    if found.size or 1.0 - abs(float(b @ c)) >= 1e-13:
        return found
    off = float(np.linalg.norm(np.cross(b, c)))
    if 1.0 - abs(float(a1 @ c)) < 1e-9 or abs(float(a1 @ c - a1 @ mc)) > 1e-9 + 2 * off:
        return np.zeros((0, 4))  # all coaxial (the sampled arc covers it), or no meet
    q = first.at(np.array([_turn(a1, c, mc)]))
    return q[first.holds(q)]


def _isolated_meets(
    first: Arc, relay: Relay, a1: FloatArray, b: FloatArray, c: FloatArray, mc: FloatArray
) -> FloatArray:
    """The meets `two_axis_angles` finds (at most two), kept where both arcs hold them."""
    c_arc, found = relay.arc, []
    for psi, phi in two_axis_angles(a1, b, c, mc):
        q = first.at(np.array([psi]))
        turned = quat_multiply(quat_multiply(q[0], relay.turn), _axis_quat(relay.axis, phi))
        rel = np.mod(phi - relay.lo, 2.0 * np.pi)
        in_range = rel <= relay.hi - relay.lo + 1e-7 or rel >= 2.0 * np.pi - 1e-7
        if in_range and first.holds(q)[0] and c_arc.holds(quat_normalize(turned)[None])[0]:
            found.append(q[0])
    return np.array(found).reshape(-1, 4)


def rotations(laws: Laws, fallback: FloatArray) -> FloatArray:
    """Rotations on every arc of `laws`: a pin; the point where two arcs' planes meet; or
    points sampled along the first arc (and every arc's ends), kept where all arcs hold them.
    Without arcs: the soft laws' targets and `fallback`."""
    arcs = laws.arcs + _pin_pair_arcs(laws)
    if not arcs:
        return np.vstack([np.zeros((0, 4)), *laws.soft_quat, fallback.reshape(-1, 4)])
    pins = [a for a in arcs if a.hi - a.lo <= 0.0]
    if pins:
        q = pins[0].at(np.zeros(1))
    else:
        first = arcs[0]
        grid = ARC_GRID_BOXED if laws.boxes else ARC_GRID  # a box may take a short stretch
        pts = [first.at(np.linspace(first.lo, first.hi, grid))]
        for other in arcs[1:]:
            pts.append(other.at(np.array([other.lo, other.hi])))
            meet = _plane_meet(first, other)
            if meet is not None:
                pts.append(meet)
        if laws.relays:  # a relay holds the rotation to isolated points of the first arc
            pts = [relay_meets(first, relay) for relay in laws.relays]
        q = np.vstack(pts)
    keep = np.ones(len(q), bool)
    for a in laws.arcs:
        keep &= a.holds(q)
    return quat_normalize(q[keep])


def _pin_pair_arcs(laws: Laws) -> list[Arc]:
    """Two position pins x = a1 - R b1 = a2 - R b2 hold R to the rotations taking
    b = b2 - b1 onto a = a2 - a1: one rotation that does, then any turn about b (an arc).
    Only the first pair whose vectors are long enough to fix a direction is used."""
    a1, b1 = laws.pins[0] if laws.pins else (None, None)
    for a2, b2 in laws.pins[1:]:
        a, b = a2 - a1, b2 - b1  # type: ignore[operator]
        la, lb = np.linalg.norm(a), np.linalg.norm(b)
        if lb < 1e-6 or la < 1e-6 or abs(la - lb) > 1e-6 * max(1.0, lb):
            continue
        return [Arc(quat_between(b[None], a[None])[0], b / lb, -np.pi, np.pi, IDENTITY)]
    return []


def _plane_meet(a: Arc, b: Arc) -> FloatArray | None:
    """The rotation on both arcs' planes when they meet in one line (None when they are one
    plane, which the sampled points cover, or do not meet)."""
    ua, ub = a.plane, b.plane
    u, s, _ = np.linalg.svd(ua.T @ ub)
    if s[0] < 1.0 - ON_ARC or s[1] >= 1.0 - ON_ARC:
        return None
    return (ua @ u[:, 0]).reshape(1, 4)


def positions(laws: Laws, q: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """For each rotation, the position the pins give (or the soft laws' mean target, or the
    boxes' centre), clipped into the boxes' intersection; and whether that is non-empty."""
    n = len(q)
    if laws.pins:
        a, b = laws.pins[0]
        x = a - quat_rotate(q, np.broadcast_to(b, (n, 3)))
    elif laws.soft_xyz:
        x = np.mean(
            [a - quat_rotate(q, np.broadcast_to(b, (n, 3))) for a, b in laws.soft_xyz], axis=0
        )
    else:
        x = np.zeros((n, 3))
    lo, hi = np.full((n, 3), -np.inf), np.full((n, 3), np.inf)
    for blo, bhi, shift in laws.boxes:
        s = quat_rotate(q, np.broadcast_to(shift, (n, 3)))
        lo, hi = np.maximum(lo, blo - s), np.minimum(hi, bhi - s)
    ok = np.all(lo <= hi + 1e-12, axis=1)
    if not laws.pins and not laws.soft_xyz:
        bounded = np.isfinite(lo) & np.isfinite(hi)
        x = np.where(bounded, 0.5 * (np.where(bounded, lo, 0.0) + np.where(bounded, hi, 0.0)), x)
    return np.clip(x, lo, np.maximum(lo, hi)), ok


def score(grammar: Grammar, laws: Laws, x: FloatArray, q: FloatArray) -> FloatArray:
    """The log-densities of every law in `laws.checks` at each pose (-inf: a law refuses it)."""
    total = np.zeros(len(x))
    for r, is_child, xyz, quat, m_xyz, m_quat in laws.checks:
        rules = np.full(len(x), r, np.int64)
        fx, fq = np.broadcast_to(xyz, x.shape), np.broadcast_to(quat, q.shape)
        if is_child:  # the set's top is the child of the fixed pose
            total += translation_log_density(grammar, rules, fx, fq, x)
            total += rotation_log_density(grammar, rules, fq, q)
        else:  # the set's member is the parent of the fixed pose
            vx = x + quat_rotate(q, np.broadcast_to(m_xyz, x.shape))
            vq = quat_multiply(q, np.broadcast_to(m_quat, q.shape))
            total += translation_log_density(grammar, rules, vx, vq, fx)
            total += rotation_log_density(grammar, rules, vq, fq)
    return total


def hard_poses(
    grammar: Grammar, laws: Laws, fallback: FloatArray, keep: int
) -> tuple[FloatArray, FloatArray]:
    """At most `keep` poses that every law in `laws` accepts, best first."""
    q = rotations(laws, fallback)
    if not len(q):
        return np.zeros((0, 3)), np.zeros((0, 4))
    x, ok = positions(laws, q)
    x, q = x[ok], q[ok]
    if laws.child_pins and len(x):
        px, pq = _onto_child_pins(laws, x, q)
        x, q = np.vstack([px, x]), np.vstack([pq, q])
    if laws.pins and not laws.arcs and len(x):
        px, pq = _onto_flat_boxes(laws, q)
        x, q = np.vstack([x, px]), np.vstack([q, pq])
    if not len(x):
        return x, q
    s = score(grammar, laws, x, q)
    good = np.flatnonzero(np.isfinite(s))
    best = good[np.argsort(-s[good], kind="stable")][:keep]
    return x[best], q[best]


CHILD_PIN_ROUNDS = 8  # turns onto every child's pins in turn (several children: alternating)


def turn_onto_pins(
    q_v: FloatArray, u: FloatArray, pinned: NDArray[np.bool_], mean: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Rotations q_v ⊗ S, turned as little as the pins allow, with (R_vᵀ u)[pinned] =
    mean[pinned] for each row's world vector u (the member's vector to its child); and
    whether a turn reaches (|u| at least the pinned components' length).

    The local vector w = R_vᵀ u keeps its length; its pinned components become the means,
    its free ones keep their direction (a free axis where they are zero), and S takes the
    new local vector onto w: R_v S w′ = R_v w = u.  Why: a child's parent-frame Normal with
    a `pin` is a point mass on those axes, so a latent parent whose position is held (a
    `same` link) needs a rotation that puts the child on them; rule inversion and the
    hard laws gave a rotation that ignored them (`no_parse`)."""
    w = quat_rotate(quat_conjugate(q_v), u)
    length2 = np.sum(w * w, axis=1)
    left2 = length2 - np.sum(np.where(pinned, mean, 0.0) ** 2)
    free_w = np.where(pinned, 0.0, w)
    free_norm = np.linalg.norm(free_w, axis=1)
    axis = np.zeros(3)
    axis[int(np.argmin(pinned))] = 1.0  # a free axis, for a vector with no free part
    free_w = np.where(free_norm[:, None] > 1e-12, free_w, axis)
    free_norm = np.linalg.norm(free_w, axis=1)
    ok = left2 >= -1e-12 * np.maximum(1.0, length2)
    scale = np.sqrt(np.maximum(left2, 0.0)) / free_norm
    new_w = np.where(pinned, mean, free_w * scale[:, None])
    turned = quat_multiply(q_v, quat_between(new_w, w))
    return np.where(ok[:, None], turned, q_v), ok


def turn_set_onto_pin(
    q: FloatArray,
    x: FloatArray,
    member_xyz: FloatArray,
    member_quat: FloatArray,
    c_xyz: FloatArray,
    pinned: NDArray[np.bool_],
    mean: FloatArray,
) -> FloatArray:
    """Set rotations q (at positions x) turned so that the member at (member_xyz,
    member_quat) in the set's frame sees its child at c_xyz on its pinned axes
    (`turn_onto_pins` on the member's rotation); the hard laws and the proposals share it."""
    q_v = quat_multiply(q, np.broadcast_to(member_quat, q.shape))
    u = c_xyz - x - quat_rotate(q, np.broadcast_to(member_xyz, (*q.shape[:-1], 3)))
    q_v, _ = turn_onto_pins(q_v, u, pinned, np.asarray(mean, float))
    return quat_normalize(quat_multiply(q_v, quat_conjugate(member_quat)))


def _onto_child_pins(laws: Laws, x: FloatArray, q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The poses moved onto every child's parent-frame pins: where a pin holds the position
    (it moves only with the rotation), the rotation turned (`turn_onto_pins`, the children in
    turn for CHILD_PIN_ROUNDS rounds); elsewhere, the position projected onto the pins'
    planes at the pose's rotation, and onto the set's own pinned world axes (`_flat_axes`:
    projected onto the pins' planes alone, a set held to a line by its own rule left it, and
    every pose was refused).  A pose on an arc keeps its rotation (only the planes)."""
    if laws.pins and not laws.arcs:
        for _ in range(CHILD_PIN_ROUNDS):
            for pin in laws.child_pins:
                q = turn_set_onto_pin(
                    q, x, pin.member_xyz, pin.member_quat, pin.c_xyz, pin.pinned, pin.mean
                )
                x = positions(laws, q)[0]
        return x, q
    if laws.pins:
        return x, q
    q = _turn_pin_normals(laws, q)
    normals, targets = [], []
    for pin in laws.child_pins:  # n·x = n·(c - R member_xyz) - mean_a, n = R_v e_a
        q_v = quat_multiply(q, np.broadcast_to(pin.member_quat, q.shape))
        reach = pin.c_xyz - quat_rotate(q, np.broadcast_to(pin.member_xyz, x.shape))
        for a in np.flatnonzero(pin.pinned):
            n = quat_rotate(q_v, np.broadcast_to(np.eye(3)[a], x.shape))
            normals.append(n)
            targets.append(np.sum(n * reach, axis=1) - pin.mean[a])
    for k, value in _flat_axes(laws):  # the set's own pinned world axes hold as well
        normals.append(np.broadcast_to(np.eye(3)[k], x.shape))
        targets.append(np.full(len(x), value))
    for n, t in laws.planes:  # and its own pinned axes in its parent's frame
        normals.append(np.broadcast_to(n, x.shape))
        targets.append(np.full(len(x), t))
    big_n = np.stack(normals, axis=1)  # (poses, planes, 3)
    miss = np.stack(targets, axis=1) - np.einsum("nkj,nj->nk", big_n, x)
    step = np.einsum("njk,nk->nj", np.linalg.pinv(big_n), miss)
    return x + step, q


def _turn_pin_normals(laws: Laws, q: FloatArray) -> FloatArray:
    """Rotations turned as little as needed for the pin planes of children that share a
    member and a pinned axis to be parallel planes that one position meets
    (`turn_pins_parallel`, every group in turn for CHILD_PIN_ROUNDS rounds).

    Why: objects pinned on a latent surface (a shelf whose height its own rule pins, boxes
    pinned on it in its frame) lie on one tilted plane; at the surface's proposed rotation
    (its soft laws' mode) their planes were parallel but apart, no position met them all,
    and the scene had no parse."""
    rows = [
        (0, pin.member_xyz, pin.member_quat, int(a), pin.c_xyz, float(pin.mean[a]))
        for pin in laws.child_pins
        for a in np.flatnonzero(pin.pinned)
    ]
    groups = parallel_pin_groups(rows)
    for _ in range(CHILD_PIN_ROUNDS):
        for _, end_quat, a, d, delta in groups:
            q = turn_pins_parallel(q, end_quat, a, d, delta)
    return q


# (owner, end rotation, pinned axis, child differences (k, 3), mean differences (k,))
PinGroup = tuple[int, FloatArray, int, FloatArray, FloatArray]


def parallel_pin_groups(
    rows: list[tuple[int, FloatArray, FloatArray, int, FloatArray, float]],
) -> list[PinGroup]:
    """Rows (owner, end_xyz, end_quat, axis, child, mean) of children pinned in a frame
    (n·(child - x_end) = mean, n = R(q ⊗ end_quat) e_axis), grouped by owner, end and axis,
    two or more to a group, in the order the groups first appear: their planes are parallel
    only where that axis, turned, has n·(c_i - c_0) = mean_i - mean_0 (`turn_pins_parallel`).
    The hard laws (one set, owner 0) and refinement (`poses.PinPlanes`, owner a block)
    share them."""
    groups: dict[tuple[int, bytes, bytes, int], list[tuple[FloatArray, float]]] = {}
    ends: dict[tuple[int, bytes, bytes, int], FloatArray] = {}
    for owner, end_xyz, end_quat, a, c, mean in rows:
        key = (owner, np.asarray(end_xyz).tobytes(), np.asarray(end_quat).tobytes(), a)
        groups.setdefault(key, []).append((np.asarray(c, float), float(mean)))
        ends[key] = np.asarray(end_quat, float)
    out: list[PinGroup] = []
    for key, members in groups.items():
        if len(members) < 2:
            continue
        d = np.array([c - members[0][0] for c, _ in members[1:]])
        delta = np.array([m - members[0][1] for _, m in members[1:]])
        out.append((key[0], ends[key], key[3], d, delta))
    return out


def turn_pins_parallel(
    q: FloatArray, end_quat: FloatArray, axis: int, d: FloatArray, delta: FloatArray
) -> FloatArray:
    """Rotations q (..., 4) turned as little as needed for one group of `parallel_pin_groups`
    to lie on parallel planes that one position meets: n = R(q ⊗ end_quat) e_axis must have
    d @ n = delta.  The nearest unit n solving those rows is their least-norm solution plus
    the current n's part across them, scaled to unit length (`nearest_unit_solution`); the
    end is turned onto it by the shortest turn, and the rotation with it."""
    q_end = quat_multiply(q, np.broadcast_to(end_quat, q.shape))
    n = quat_rotate(q_end, np.broadcast_to(np.eye(3)[axis], (*q.shape[:-1], 3)))
    wanted = nearest_unit_solution(d, delta, n.reshape(-1, 3)).reshape(n.shape)
    q_end = quat_multiply(quat_between(n, wanted), q_end)
    return quat_normalize(quat_multiply(q_end, quat_conjugate(end_quat)))


def nearest_unit_solution(d: FloatArray, delta: FloatArray, n: FloatArray) -> FloatArray:
    """Per row of n (k, 3), a unit vector solving d @ v = delta near it: v = pinv(d) delta
    plus n's part in d's null space, scaled to unit length (n itself where none is unit)."""
    _, sv, vt = np.linalg.svd(d)
    rank = int(np.sum(sv > 1e-9 * max(1.0, float(sv.max(initial=0.0)))))
    base = np.linalg.pinv(d, rcond=1e-9) @ delta
    left = 1.0 - float(base @ base)
    null = vt[rank:]  # rows spanning the null space of d
    if left < 0.0 or len(null) == 0:
        return n
    part = (n @ null.T) @ null
    size = np.linalg.norm(part, axis=1, keepdims=True)
    other = np.broadcast_to(null[0], n.shape)  # n lies in d's row space: any null direction
    part = np.where(size > 1e-12, part / np.maximum(size, 1e-300), other)
    return base + np.sqrt(left) * part


def _flat_axes(laws: Laws) -> list[tuple[int, float]]:
    """(world axis, value) of each coordinate a flat box of the set's own position fixes (a
    pinned world axis of its rule)."""
    flat, value = _flat_coordinates(laws)
    return [(int(k), float(value[k])) for k in np.flatnonzero(flat)]


def _flat_coordinates(laws: Laws) -> tuple[NDArray[np.bool_], FloatArray]:
    """Which world coordinates of the set's own position a flat box fixes, and their values
    (0 where none; the first box's where two fix one coordinate)."""
    flat = np.zeros(3, bool)
    value = np.zeros(3)
    for lo, hi, shift in laws.boxes:
        fixed = np.isfinite(lo) & (lo == hi) & np.all(shift == 0)
        value = np.where(fixed & ~flat, lo, value)
        flat |= fixed
    return flat, value


def _onto_flat_boxes(laws: Laws, q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Where the first pin places the set (x = a - R b, a child at a fixed offset under a
    free rotation) and a flat box (a pinned world axis of its own rule) fixes coordinates
    of x: the rotations turned as little as needed to put (R b)_k at a_k - value_k
    (`turn_onto_pins` on the inverse rotation), and the positions there; none without such
    a box.  Also from the rotation that aims x at the soft laws' targets: turned onto the
    plane, that is the point of the circle nearest them.

    Why: the pin holds the set on a sphere about its child and the flat box on a plane; the
    positions clipped into the box left the sphere, so a recursive chain pinned in z with a
    child at a fixed offset on each level got no pose below its first (`no_parse`)."""
    flat, value = _flat_coordinates(laws)
    if not flat.any():
        return np.zeros((0, 3)), np.zeros((0, 4))
    a, b = laws.pins[0]
    targets = [t for t, m in laws.soft_xyz if not np.any(m)]  # soft targets of x itself
    if targets:  # also aimed: x as near the targets' mean as the sphere allows
        aim = quat_between(np.asarray(b, float), a - np.mean(targets, axis=0))
        q = np.vstack([aim.reshape(1, 4), q])
    b_rows = np.broadcast_to(b, (len(q), 3))
    turned, ok = turn_onto_pins(quat_conjugate(q), b_rows, flat, np.where(flat, a - value, 0.0))
    q_new = quat_normalize(quat_conjugate(turned[ok]))
    return positions(laws, q_new)[0], q_new
