"""Joint bounds along a chain of latent sets: a set placed relative to a latent parent.

`bound.py` bounds each latent set over its assignments of children.  A latent set whose parent
is itself latent (its rule is relative to a pose that is not known) used to count its rule's
supremum (`decoupled`), so the chain's bound was loose.  This module *lifts* such a child set
into its parent's assignments: one column of the parent names the child's assignment row (the
child's rows are its parent's candidates), and the parent's bound then holds the chain jointly.

The lift rests on one identity.  With its rotation pinned, or with no term that turns with it,
the child set's score over its own children is a concave quadratic of its position t_c,
Q(t_c) = -½ (t_c - ĉ)ᵀ P̂ (t_c - ĉ) + κ (`collapse`).  Its rule's Normal translation is a
concave quadratic of t_c - a (a: the mean the rule gives at the parent's pose), and the
maximum over t_c of the two is closed form:

    max_t -½ (t - a)ᵀ Pₑ (t - a) - ½ (t - ĉ)ᵀ P̂ (t - ĉ) = -½ (a - ĉ)ᵀ Pₛ (a - ĉ),
    Pₛ = Pₑ (Pₑ + P̂)⁺ P̂   (the parallel sum: covariances add along the chain).

So the child's whole subtree enters its parent's relaxation as one more Normal term of the
parent's pose (least squares along the chain), a fixed offset enters as Q itself at
t_p + R_p m, and a box law becomes a box on the parent's position where the child's position
is boxed.  Rows where none of this applies keep the child's own bound (they add nothing).

The parent's row then bounds its own terms *and* the chain; the child's head instance still
carries the child's upper bound in the MILP, so the parent's row subtracts it (`add_column`):
the sum over a tree is the joint bound.  Nothing here is ever below the true maximum: dropping
a constraint (the child's box under a Normal rule) or replacing a term by its supremum only
raises the bound.  Depth costs one lift per level: a chain of k levels is k set bounds, each
over its parent's rows times its child's (capped by `MAX_CHAIN_ROWS`), never K^depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import quat_multiply, quat_rotate, quat_to_matrix
from ssgc.ir import Grammar
from ssgc.laws.base import Frame
from ssgc.laws.position_box import BoxTranslation
from ssgc.parse.set_terms import (
    IDENTITY,
    K_ROT,
    SetBound,
    _arc_lmo,
    _left_linear,
    _LocalBounds,
    _Terms,
    world_part,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

MAX_CHAIN_ROWS = 5_000  # a parent's rows with its lifted children's: past this, no lift


@dataclass(frozen=True)
class ChainRows:
    """A decoupled set's score over its own subtree as a function of its position, one row per
    assignment row: Q(t) = -½ (t - centre)ᵀ precision (t - centre) + kappa, with t in
    [lo, hi] and the rotation at `pin` (NaN: free).  Its own rule is left out.  Rows that are
    not `ok` (a term turns with a rotation that is not pinned) have no such form."""

    ok: BoolArray  # (A,)
    centre: FloatArray  # (A, 3)
    precision: FloatArray  # (A, 3, 3)
    kappa: FloatArray  # (A,)
    lo: FloatArray  # (A, 3)
    hi: FloatArray  # (A, 3)
    pin: FloatArray  # (A, 4)
    # rows whose terms turn with a free rotation, all isotropic (`_turning`): the raw terms
    turning: BoolArray  # (A,)
    c: FloatArray  # (A, K, 3)
    weight: FloatArray  # (A, K): each term's isotropic precision, 0 where absent
    m: FloatArray  # (K, 3)
    B: FloatArray  # (A, 4, 4)
    base: FloatArray  # (A,): the rows' constant, without the own rule's supremum
    # rows whose rotation its children hold to an arc q = V (cos ψ, sin ψ), ψ in `arc`
    revolute: BoolArray  # (A,)
    V: FloatArray  # (A, 4, 2)
    arc: FloatArray  # (A, 2)


@dataclass(frozen=True)
class Lifted:
    """A decoupled child set, row for row as its parent's candidates see it (after its implied
    rows and a `repeat`'s repeated rows): its bound, its free rows and its chain form."""

    upper: FloatArray  # (A,)
    free: BoolArray  # (A,): implied rows, at an exact pose
    xyz: FloatArray  # (A, 3)
    quat: FloatArray  # (A, 4)
    rows: ChainRows  # aligned with the above; `ok` is False on free rows


def collapse(terms: _Terms, own_sup: float) -> ChainRows:
    """Each row's score as a quadratic of the set's position (the module's Q), valid for every
    rotation the row allows.  A pinned rotation fixes every R m_k; with no pin, rows whose
    terms do not turn with the rotation (m_k = 0 wherever P_k ≠ 0) separate, and their
    rotation terms tr(B X) count their maximum (an eigenvalue, or the arc's best point).
    `own_sup` is what the decoupled set counted for its own rule, taken back out."""
    P, c, m = terms.P, terms.c, terms.m
    pinned = terms.pinned
    R = quat_to_matrix(np.where(pinned[:, None], np.nan_to_num(terms.pin), IDENTITY))
    turns = np.linalg.norm(m, axis=1) > 0 if len(m) else np.zeros(0, bool)  # (K,)
    present = np.abs(P).max(axis=(2, 3), initial=0.0) > 0  # (A, K)
    ok = pinned | ~np.any(present & turns[None, :], axis=1)
    Rm = np.einsum("nij,kj->nki", R, m) if len(m) else np.zeros_like(c)
    e = c - np.where(pinned[:, None, None], Rm, 0.0)
    Phat = P.sum(axis=1)
    b = np.einsum("nkij,nkj->ni", P, e)
    centre = np.einsum("nij,nj->ni", np.linalg.pinv(Phat), b)
    kappa_t = -0.5 * np.einsum("nki,nkij,nkj->n", e, P, e) + 0.5 * np.einsum("ni,ni->n", b, centre)
    rot = np.linalg.eigvalsh(terms.B)[:, -1]
    if np.any(terms.revolute):
        rot = np.where(terms.revolute, _arc_lmo(terms, terms.B)[1], rot)
    q = np.nan_to_num(terms.pin)
    rot = np.where(pinned, np.einsum("na,nab,nb->n", q, terms.B, q), rot)
    kappa = terms.const - own_sup + kappa_t + rot
    iso = np.all(np.abs(P - P[..., :1, :1] * np.eye(3)) <= 1e-12 * (1 + np.abs(P)), axis=(1, 2, 3))
    return ChainRows(
        ok,
        centre,
        Phat,
        kappa,
        terms.lo.copy(),
        terms.hi.copy(),
        terms.pin.copy(),
        ~ok & iso,
        c.copy(),
        P[..., 0, 0].copy(),
        np.asarray(m, float).reshape(-1, 3),
        terms.B.copy(),
        terms.const - own_sup,
        terms.revolute.copy(),
        terms.V.copy(),
        terms.arc.copy(),
    )


def lifted(bound: SetBound, rows: ChainRows, source: IntArray) -> Lifted:
    """The child's rows as its parent sees them: `source` maps each final row of `bound` to
    the row it repeats; rows past the assignments (`rows`) are implied (free) rows."""
    n = len(rows.ok)
    src = np.minimum(source, max(n - 1, 0))
    assigned = source < n
    take = (lambda x: x[src]) if n else (lambda x: np.zeros((len(source), *x.shape[1:])))
    chain = ChainRows(
        take(rows.ok).astype(bool) & assigned & ~bound.free_rows,
        take(rows.centre),
        take(rows.precision),
        take(rows.kappa),
        take(rows.lo),
        take(rows.hi),
        np.where(assigned[:, None], take(rows.pin), np.nan),
        take(rows.turning).astype(bool) & assigned & ~bound.free_rows,
        take(rows.c),
        take(rows.weight),
        rows.m,
        take(rows.B),
        take(rows.base),
        take(rows.revolute).astype(bool) & assigned & ~bound.free_rows,
        take(rows.V),
        take(rows.arc),
    )
    return Lifted(bound.upper, bound.free_rows, bound.xyz, bound.quat, chain)


def children_to_lift(st, e: int, chains: dict[int, Lifted]) -> dict[int, Lifted]:  # type: ignore[no-untyped-def]
    """The decoupled child sets directly below set e whose rows can join e's assignments."""
    return {
        e_c: lift for e_c, lift in chains.items() if int(st.set_of[st.parent[st.set_top[e_c]]]) == e
    }


def own_world_edge(grammar: Grammar, r: int) -> tuple[FloatArray, FloatArray] | None:
    """A decoupled set's own rule as an edge from the set to itself, for its exact local
    search (`bound.local_edges`): the parent end at the offset (m, w) from the set's own
    pose, where the rule's relative parts are at a constant, finite value whatever that
    pose, so only its world-frame parts move (a world Bingham rotation, a world Normal or box
    translation).  None when it has no such part that varies, or no such offset exists.

    Why: the bound counts those parts exactly (`set_terms._decoupled_prior`), but the local
    search left the whole rule out, so a set's assignment pose ignored (say) its world
    Bingham, and the chain's poses built on it scored far below the bound."""
    from ssgc.rules import rotation_log_density, translation_log_density

    rule = grammar.rules[r]
    law, rot = rule.translation, rule.rotation
    # a world box is left out: `bound._snap` puts the pose inside it, and a constant inside
    # it would only break the ties of the revolute search differently
    moves = (world_part(law) and law.concave_form() is not None) or (
        world_part(rot) and rot.concave_form() is not None
    )
    if not moves:
        return None
    w = IDENTITY.copy()
    if rot.frame == Frame.PARENT and rot.mode() is not None:
        w = np.asarray(rot.point if rot.point is not None else rot.mode(), float)
        w = np.array([w[0], -w[1], -w[2], -w[3]])  # the parent sits at the mode's inverse
    m = np.zeros(3)
    if law.frame == Frame.PARENT:
        form = law.concave_form()
        point = law.point if law.point is not None else (form[0] if form is not None else None)
        if point is None:
            return None
        m = -quat_rotate(w, np.asarray(point, float))  # R(w)ᵀ (t - t_p) = the law's mode
    rules, one = np.array([r]), np.ones((1, 1))
    at = (m[None], w[None])
    value = translation_log_density(grammar, rules, at[0], at[1], np.zeros((1, 3)))
    value = value + rotation_log_density(grammar, rules, at[1], IDENTITY[None] * one)
    return (m, w) if bool(np.isfinite(value[0])) else None


def _parallel(Pe: FloatArray, Phat: FloatArray) -> FloatArray:
    """Pₑ (Pₑ + P̂)⁺ P̂ per row: the precision of the chain's two Normal terms in series."""
    out = np.einsum("ij,njk,nkl->nil", Pe, np.linalg.pinv(Pe + Phat), Phat)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def pin_column(local: _LocalBounds, lift: Lifted, r: int, off_t, off_q, idx, on) -> None:  # type: ignore[no-untyped-def]
    """A lifted column's rotation pins and revolute families on the parent (before any term):
    where the child's rotation is known (an implied row's pose, or a pinned row), its rule's
    fixed or revolute rotation holds the parent's as an observed child's would."""
    if not len(lift.upper):  # a child set without rows: no parent row names it
        return
    free = on & lift.free[idx]
    known = free | (on & lift.rows.ok[idx] & ~np.isnan(lift.rows.pin[idx, 0]))
    cq = np.where(free[:, None], lift.quat[idx], np.nan_to_num(lift.rows.pin[idx]))
    cq = np.where(known[:, None], cq, [1.0, 0.0, 0.0, 0.0])
    local.child_pin(r, off_q, cq, known)
    local.child_family(r, off_q, cq, known)
    local.fixed_children.append((r, off_t, off_q, lift.xyz[idx], free))


def add_column(
    local: _LocalBounds, grammar: Grammar, lift: Lifted, r: int, off_t, off_q, idx, on
) -> None:  # type: ignore[no-untyped-def]
    """A lifted column's terms on the parent's rows `on` (child row `idx` each): the rule's
    edge and the child's subtree, jointly, minus the child's own bound (which its head
    instance still carries in the MILP).  Implied rows are children at an exact pose; rows
    without a chain form add nothing (the child's bound holds them, as before the lift)."""
    if not len(lift.upper):  # a child set without rows: no parent row names it
        return
    free = on & lift.free[idx]
    local.child(r, off_t, off_q, lift.xyz[idx], lift.quat[idx], free)
    local.add(-lift.upper[idx], free)
    rows = lift.rows
    rule = grammar.rules[r]
    turn = on & ~free & rows.turning[idx]
    if np.any(turn) and rule.rotation.point is not None and rule.rotation.frame == Frame.PARENT:
        _turning(local, rule, off_t, off_q, lift, idx, turn)
    col = on & ~free & rows.ok[idx]
    if not np.any(col):
        return
    pinned = col & ~np.isnan(rows.pin[idx, 0])
    cq = np.where(pinned[:, None], np.nan_to_num(rows.pin[idx]), [1.0, 0.0, 0.0, 0.0])
    if not world_part(rule.rotation):  # else the child's own bound holds it already
        local._child_rotation(r, off_q, cq, pinned)
        local.add(np.full(local.n, rule.rotation.supremum()), col & ~pinned)
    _translation(local, rule.translation, off_t, off_q, rows, idx, col)
    local.add(rows.kappa[idx] - lift.upper[idx], col)


def _translation(local, law, off_t, off_q, rows: ChainRows, idx, col) -> None:  # type: ignore[no-untyped-def]
    """The child's rule's translation and its subtree's quadratic, maximised over the child's
    position, as terms of the parent's pose (the module's docstring)."""
    if world_part(law):  # the child's own bound holds it already (its quadratic or box)
        return
    n = local.n
    centre, Phat = rows.centre[idx], rows.precision[idx]
    form = law.concave_form()
    pinned_p = local.pinned & col
    R0 = quat_to_matrix(local._pin_or_identity())
    if form is not None:
        mean, Pe, c = form
        local.add(np.full(n, c), col)
        if law.frame == Frame.WORLD_OFFSET:
            local.quadratic(centre - mean, np.asarray(off_t, float), _parallel(Pe, Phat), col)
        elif _isotropic(Pe):  # parent frame, turning with the parent: isotropic is the same
            m = off_t + quat_rotate(off_q, mean)
            local.quadratic(centre, m, _parallel(Pe, Phat), col)
        else:  # an anisotropic parent-frame precision: where the parent's rotation is pinned
            m = off_t + quat_rotate(off_q, mean)
            Rc = R0 @ quat_to_matrix(off_q)
            Pw = np.einsum("nij,jk,nlk->nil", Rc, Pe, Rc)
            Ps = _parallel_rows(Pw, Phat)
            local.quadratic(centre - R0 @ m, np.zeros(3), Ps, pinned_p)
            local.add(np.full(n, law.supremum() - c), col & ~pinned_p)
    elif law.point is not None and law.frame == Frame.PARENT:  # t_c = t_p + R_p m exactly
        m = off_t + quat_rotate(off_q, law.point)
        local.quadratic(centre, m, Phat, col)
        local.add(np.full(n, law.supremum()), col)
        exact = pinned_p | (col & bool(np.allclose(m, 0.0)))
        local.box(rows.lo[idx] - R0 @ m, rows.hi[idx] - R0 @ m, exact)
    elif isinstance(law, BoxTranslation) and law.frame == Frame.WORLD_OFFSET:
        local.add(np.full(n, law.supremum()), col)  # t_c - t_p - R_p off_t in the law's box
        at = R0 @ np.asarray(off_t, float)
        exact = pinned_p | (col & bool(np.allclose(off_t, 0.0)))
        local.box(rows.lo[idx] - law.box.hi - at, rows.hi[idx] - law.box.lo - at, exact)
    else:
        local.add(np.full(n, law.supremum()), col)


def _turning(local, rule, off_t, off_q, lift: Lifted, idx, turn) -> None:  # type: ignore[no-untyped-def]
    """Rows whose child's terms turn with its rotation, where its rule fixes that rotation to
    the parent's (R_c = R_p R_w, w = off_q ⊗ the rule's offset) and every term is isotropic.

    Centred on the p-weighted means ĉ, m̄ (as `bound._isotropic_bound`), the child's terms are
    -½ Σ p_k (|c'_k|² + |m'_k|²) + ⟨Σ p_k c'_k (R_w m'_k)ᵀ, R_p⟩ - ½ P̂ |ĉ - t_c - R_p R_w m̄|²:
    a term linear in R_p (a Bingham-like matrix on the parent's X) and one isotropic Normal
    term, which the rule's translation then joins as for unturned rows, its m now
    off_t + R_w m̄ (one term per distinct m̄).  The child's own Bingham terms follow X_c =
    L X_p Lᵀ.  Rule translations without a closed form leave the rows as they are, and so
    does an anisotropic one where the parent's rotation is neither pinned nor held to a
    revolute family: the relaxation over all X (its hull shrinks |R m|) would then be looser
    than the child's own bound, while along an arc the rotation search bounds it exactly."""
    from ssgc.geometry import quat_multiply as qmul

    law, form = rule.translation, rule.translation.concave_form()
    inside = world_part(law)  # the child's own terms hold it: t_c is then free
    if not inside and form is None and not (law.point is not None and law.frame == Frame.PARENT):
        return
    if form is not None and law.frame == Frame.PARENT and not _isotropic(form[1]):
        return
    if not inside and form is not None and not _isotropic(form[1]):
        # a world-frame anisotropic term turning with R_p: exact where R_p is pinned, and
        # on a revolute family the rotation search (`bound_rotation`) bounds it along the arc
        turn = turn & (local.pinned | ~np.isnan(local.fam_base[:, 0]))
        if not np.any(turn):
            return
    rows = lift.rows
    n = local.n
    w_q = qmul(np.asarray(off_q, float), rule.rotation.point)
    Rw = quat_to_matrix(w_q)
    p = rows.weight[idx]  # (n, K)
    total = p.sum(axis=1)
    share = p / np.where(total > 0, total, 1.0)[:, None]
    c = rows.c[idx]
    chat = np.einsum("nk,nki->ni", share, c)
    mbar = share @ rows.m  # (n, 3)
    c1 = c - chat[:, None, :]
    m1 = (rows.m[None] - mbar[:, None, :]) @ Rw.T  # R_w m'_k
    G = np.einsum("nk,nki,nkj->nij", p, c1, m1)
    B = np.einsum("nij,ijab->nab", G, K_ROT)
    L = _left_linear(lambda q: qmul(q, np.broadcast_to(w_q, q.shape)), 1)[0]
    B = B + np.einsum("ba,nbc,cd->nad", L, rows.B[idx], L)
    local.B += np.where(turn[:, None, None], B, 0.0)
    const = -0.5 * (np.einsum("nk,nki,nki->n", p, c1, c1) + np.einsum("nk,nki,nki->n", p, m1, m1))
    local.add(const + rows.base[idx] - lift.upper[idx] + rule.rotation.supremum(), turn)
    if inside:  # no rule term for t_c: its best value leaves -½ P̂ |…|² at 0
        return
    if form is not None:
        mean, Pe, c_e = form
        local.add(np.full(n, c_e), turn)
        Ps = _parallel(Pe, total[:, None, None] * np.eye(3))
        shift = np.asarray(off_t, float) + (
            quat_rotate(off_q, mean) if law.frame == Frame.PARENT else 0.0
        )
        centre = chat - (mean if law.frame == Frame.WORLD_OFFSET else 0.0)
    else:
        local.add(np.full(n, law.supremum()), turn)
        Ps = total[:, None, None] * np.eye(3)
        shift = np.asarray(off_t, float) + quat_rotate(off_q, law.point)
        centre = chat
    m_all = shift + mbar @ Rw.T
    keys = np.round(m_all, 12)
    for key in np.unique(keys[turn], axis=0):
        group = turn & np.all(keys == key, axis=1)
        local.quadratic(centre, m_all[np.flatnonzero(group)[0]], Ps, group)


def _parallel_rows(Pe: FloatArray, Phat: FloatArray) -> FloatArray:
    """`_parallel` with a precision per row."""
    out = np.einsum("nij,njk,nkl->nil", Pe, np.linalg.pinv(Pe + Phat), Phat)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def _isotropic(precision: FloatArray) -> bool:
    return bool(precision[0, 0] > 0 and np.allclose(precision, precision[0, 0] * np.eye(3)))


MAX_CHAIN_POSES = 200  # joint poses offered to `ip` per lifted column, best parent rows first


def add_chain_poses(grammar: Grammar, st, cand, bounds: dict[int, SetBound]) -> None:  # type: ignore[no-untyped-def]
    """Offer each lifted child set the pose that is best for it *given* its parent's row pose
    (the parent's pose there is the chain's joint optimum, found by the parent's bound):
    its subtree's quadratic and its rule's translation combined, its rotation put where its
    rule allows.  The child's own assignment poses ignore the parent, and refinement cannot
    always move a chain joined by a fixed translation, so without these `ip` may stop at a
    tree below the (tight) joint bound."""
    for e_p, sb in bounds.items():
        best = np.argsort(-sb.upper, kind="stable")
        best = best[~sb.free_rows[best]]
        made: dict[tuple[int, int, int], list[tuple[IntArray, FloatArray, FloatArray]]] = {}
        for k, (v, r, e_c) in enumerate(sb.slots):
            child = bounds.get(e_c)
            if child is None or child.chain is None:
                continue
            rows = best[sb.assignment[best, k] >= 0][:MAX_CHAIN_POSES]
            if not len(rows):
                continue
            idx = sb.assignment[rows, k]
            xv = sb.xyz[rows] + quat_rotate(sb.quat[rows], st.offset_xyz[v])
            qv = quat_multiply(sb.quat[rows], st.offset_quat[v])
            quat = _child_rotation(grammar, r, child.chain, idx, qv)
            xyz = _child_position(grammar.rules[r].translation, child.chain, idx, xv, qv, quat)
            cand.add(e_c, xyz, quat)
            _aimed(grammar, r, cand, e_c, child.chain, idx, xv, qv)
            copies = sum(1 for c in st.children[v] if st.rule[c] == r)
            _at_rule_mode(grammar, r, cand, e_c, child.chain, idx, xv, qv, copies)
            _turned_parent(grammar, st, cand, e_p, sb, k, child.chain, rows[:MAX_TURNED])
            earlier = made.setdefault((v, r, e_c), [])
            for rows_0, xyz_0, quat_0 in earlier:  # copies of a `repeat` at one pose
                _append_shared(cand, e_c, rows, xyz, quat, rows_0, xyz_0, quat_0)
            earlier.append((rows, xyz, quat))


def _at_rule_mode(grammar, r, cand, e_c, lift: Lifted, idx, xv, qv, copies) -> None:  # type: ignore[no-untyped-def]
    """The child also at the rotation its rule's parent-frame Bingham puts at its mode, from
    its member's rotation qv (where its own children do not pin it): `_child_rotation` keeps
    the child's own assignment rotation there, which ignores its parent.  A `repeat`'s
    copies each get the pose once (appended as it is, `Candidates.add` would merge them):
    the model over proposals gives a candidate pose to one copy only."""
    rot = grammar.rules[r].rotation
    mode = rot.mode() if rot.frame == Frame.PARENT and rot.point is None else None
    if mode is None or _is_revolute(rot):
        return
    free = ~(lift.rows.ok[idx] & ~np.isnan(lift.rows.pin[idx, 0]))
    if not np.any(free):
        return
    quat = quat_multiply(qv[free], np.broadcast_to(mode, (int(free.sum()), 4)))
    quat = _onto_own_arc(lift.rows, idx[free], quat)
    law = grammar.rules[r].translation
    xyz = _child_position(law, lift, idx[free], xv[free], qv[free], quat)
    cand.add(e_c, xyz, quat)
    if copies > 1:
        n = min(len(xyz), MAX_SHARED_ROWS)
        cand.xyz[e_c] = np.vstack([cand.xyz[e_c], *[xyz[:n]] * (copies - 1)])
        cand.quat[e_c] = np.vstack([cand.quat[e_c], *[quat[:n]] * (copies - 1)])


def _onto_own_arc(rows: ChainRows, idx: IntArray, quat: FloatArray) -> FloatArray:
    """Each rotation moved to the nearest point of its row's arc, where its children hold
    the row's rotation to one (a revolute child): off it the child's density is zero."""
    on = rows.revolute[idx]
    if not np.any(on):
        return quat
    V, arc = rows.V[idx], rows.arc[idx]
    s = np.einsum("nab,na->nb", V, quat)
    psi = np.arctan2(s[:, 1], s[:, 0])
    best, fit = psi, np.full(len(psi), -np.inf)
    for shift in (-np.pi, 0.0, np.pi):  # q and -q are one rotation: ψ is known mod π
        at = np.clip(psi + shift, arc[:, 0], arc[:, 1])
        q = np.einsum("nab,nb->na", V, np.stack([np.cos(at), np.sin(at)], axis=1))
        score = np.abs(np.einsum("na,na->n", q, quat))
        better = score > fit
        best, fit = np.where(better, at, best), np.where(better, score, fit)
    q = np.einsum("nab,nb->na", V, np.stack([np.cos(best), np.sin(best)], axis=1))
    return np.where(on[:, None], q, quat)


def _is_revolute(rot) -> bool:  # type: ignore[no-untyped-def]
    from ssgc.laws.rotation_revolute import RevoluteRotation

    return isinstance(rot, RevoluteRotation)


MAX_TURNED = 50  # parent rows also offered turned to their child's own rotation


def _turned_parent(grammar, st, cand, e_p, sb, k, lift: Lifted, rows) -> None:  # type: ignore[no-untyped-def]
    """The parent's row pose turned so that its child's own rotation (which its children's
    laws chose, e.g. on a revolute child's arc) is the one its rule puts at its mode, and the
    child at its best position from there.  A parent whose rotation is free in its bound
    (a uniform law) has an arbitrary rotation at its row, from which the child's rule may not
    reach any rotation its own children allow."""
    from ssgc.geometry import axis_angle_to_quat, quat_conjugate
    from ssgc.laws.rotation_revolute import RevoluteRotation

    v, r, _ = sb.slots[k]
    idx = sb.assignment[rows, k]
    rot = grammar.rules[r].rotation
    mode = np.array([1.0, 0.0, 0.0, 0.0])
    if rot.point is not None and rot.frame == Frame.PARENT:
        mode = np.asarray(rot.point, float)
    elif isinstance(rot, RevoluteRotation):
        angle = float(np.clip(0.0, rot.revolute.lo, rot.revolute.hi))
        mode = axis_angle_to_quat(np.asarray(rot.axis, float)[None], np.array([angle]))[0]
    elif rot.frame == Frame.PARENT and rot.mode() is not None:  # a parent-frame Bingham
        mode = np.asarray(rot.mode(), float)
    elif rot.frame != Frame.PARENT:
        return  # the child's rotation does not follow its parent's
    qc = np.where(
        (lift.rows.ok[idx] & ~np.isnan(lift.rows.pin[idx, 0]))[:, None],
        np.nan_to_num(lift.rows.pin[idx]),
        lift.quat[idx],
    )
    qv = quat_multiply(qc, quat_conjugate(np.broadcast_to(mode, qc.shape)))
    qp = quat_multiply(qv, quat_conjugate(np.broadcast_to(st.offset_quat[v], qv.shape)))
    xv = sb.xyz[rows] + quat_rotate(qp, st.offset_xyz[v])
    quat = _child_rotation(grammar, r, lift, idx, qv)
    xyz = _child_position(grammar.rules[r].translation, lift, idx, xv, qv, quat)
    cand.add(e_p, sb.xyz[rows], qp)
    cand.add(sb.slots[k][2], xyz, quat)


MAX_SHARED_ROWS = 20  # parent rows whose `repeat` copies at one pose get their own candidates


def _append_shared(cand, e_c, rows, xyz, quat, rows_0, xyz_0, quat_0) -> None:  # type: ignore[no-untyped-def]
    """Where a parent row puts two copies of a `repeat` at one pose (children joined by
    `same` to a parent between them), that pose once more, as it is: the model over
    proposals gives a candidate to one copy only, and `Candidates.add` would merge it."""
    from ssgc.geometry import quat_angle
    from ssgc.laws.base import POS_TOL, ROT_TOL

    at = {int(r): i for i, r in enumerate(rows_0)}
    pairs = [(i, at[int(r)]) for i, r in enumerate(rows) if int(r) in at][:MAX_SHARED_ROWS]
    if not pairs:
        return
    i, j = np.array(pairs).T
    same = np.linalg.norm(xyz[i] - xyz_0[j], axis=1) <= POS_TOL
    same &= quat_angle(quat[i], quat_0[j]) <= ROT_TOL
    if np.any(same):
        cand.xyz[e_c] = np.vstack([cand.xyz[e_c], xyz[i[same]]])
        cand.quat[e_c] = np.vstack([cand.quat[e_c], quat[i[same]]])


def _child_position(law, lift: Lifted, idx, xv, qv, qc) -> FloatArray:  # type: ignore[no-untyped-def]
    """The child's best position given its member's pose (xv, qv) and its own rotation qc,
    where its row has a chain form (turning rows: at that rotation); elsewhere its own
    assignment's position (moved by a fixed rule)."""
    rows = lift.rows
    ok = rows.ok[idx] | rows.turning[idx]
    centre, Phat = rows.centre[idx].copy(), rows.precision[idx].copy()
    turning = rows.turning[idx]
    if np.any(turning):  # Σ p_k (c_k - R_c m_k) / Σ p_k, at the rotation given
        p = rows.weight[idx]
        total = p.sum(axis=1)
        Rm = np.einsum("nij,kj->nki", quat_to_matrix(qc), rows.m)
        share = p / np.where(total > 0, total, 1.0)[:, None]
        at = np.einsum("nk,nki->ni", share, rows.c[idx] - Rm)
        centre = np.where(turning[:, None], at, centre)
        Phat = np.where(turning[:, None, None], total[:, None, None] * np.eye(3), Phat)
    out = lift.xyz[idx].copy()
    form = law.concave_form()
    if world_part(law):  # the rule's term is among the child's own: Q's best point
        out = np.where(ok[:, None], centre, out)
    elif form is not None:
        mean, Pe, _ = form
        Rv = quat_to_matrix(qv)
        if law.frame == Frame.WORLD_OFFSET:
            a, Pw = xv + mean, np.broadcast_to(Pe, (len(xv), 3, 3))
        else:
            a, Pw = xv + Rv @ mean, np.einsum("nij,jk,nlk->nil", Rv, Pe, Rv)
        rhs = np.einsum("nij,nj->ni", Pw, a) + np.einsum("nij,nj->ni", Phat, centre)
        joint = np.einsum("nij,nj->ni", np.linalg.pinv(Pw + Phat), rhs)
        out = np.where(ok[:, None], joint, out)
    elif law.point is not None and law.frame == Frame.PARENT:
        out = xv + quat_rotate(qv, np.broadcast_to(law.point, xv.shape))
    elif isinstance(law, BoxTranslation) and law.frame == Frame.WORLD_OFFSET:
        free = np.abs(Phat).max(axis=(1, 2), initial=0.0) > 0
        want = np.where((ok & free)[:, None], centre, out)
        out = np.clip(want, xv + law.box.lo, xv + law.box.hi)
    lo, hi = rows.lo[idx] + BOX_MARGIN_IN, rows.hi[idx] - BOX_MARGIN_IN
    inside = ok[:, None] & (lo <= hi)
    return np.where(inside, np.clip(out, lo, hi), out)


BOX_MARGIN_IN = 2e-9  # metres: a proposal inside the child's box (the bound widened it by 1e-9)


def _child_rotation(grammar: Grammar, r: int, lift: Lifted, idx, qv, xv=None) -> FloatArray:  # type: ignore[no-untyped-def]
    """The child's rotation: its pin, else what its rule makes of the member's rotation (a
    fixed offset; a revolute law's rotation nearest its own assignment's, or, given `xv`,
    the one that points its children's mean offset at their mean position seen from where
    the rule puts it), else its own."""
    from ssgc.parse.proposals import onto_arc, revolute_arc

    rot = grammar.rules[r].rotation
    pinned = lift.rows.ok[idx] & ~np.isnan(lift.rows.pin[idx, 0])
    out = lift.quat[idx].copy()
    if rot.point is not None and rot.frame == Frame.PARENT:
        out = quat_multiply(qv, np.broadcast_to(rot.point, qv.shape))
    elif (arc := revolute_arc(grammar, r)) is not None:
        aligns = ()
        if xv is not None:  # `_aimed`: rows whose children turn with the child
            aligns = (_turning_aim(grammar.rules[r].translation, lift, idx, xv, qv),)
        out = onto_arc(qv, arc, out, aligns)
    return np.where(pinned[:, None], np.nan_to_num(lift.rows.pin[idx]), out)


def _aimed(grammar, r, cand, e_c, lift: Lifted, idx, xv, qv) -> None:  # type: ignore[no-untyped-def]
    """The child also at the rotation of its rule's revolute arc that aims its turning
    children (`_turning_aim`), as a further candidate: its own assignment's rotation, which
    `_child_rotation` moves onto the arc, is arbitrary where its position was free."""
    from ssgc.parse.proposals import revolute_arc

    turning = lift.rows.turning[idx]
    if revolute_arc(grammar, r) is None or not np.any(turning):
        return
    sel = np.flatnonzero(turning)
    quat = _child_rotation(grammar, r, lift, idx[sel], qv[sel], xv[sel])
    law = grammar.rules[r].translation
    cand.add(e_c, _child_position(law, lift, idx[sel], xv[sel], qv[sel], quat), quat)


def _turning_aim(law, lift: Lifted, idx, xv, qv) -> tuple[FloatArray, FloatArray]:  # type: ignore[no-untyped-def]
    """For rows whose children turn with the child set's rotation: their weighted mean
    offset m̄ (in the set's frame) and the world direction from the set's likely position
    (its rule's mode from the member pose (xv, qv), else its own) to their mean position ĉ.
    A revolute law then fixes its angle by mapping the one onto the other (`onto_arc`): the
    child's own assignment rotation is arbitrary there (its position was free)."""
    rows = lift.rows
    p = rows.weight[idx]
    total = p.sum(axis=1)
    share = p / np.where(total > 0, total, 1.0)[:, None]
    m_bar = share @ rows.m if len(rows.m) else np.zeros((len(idx), 3))
    c_hat = np.einsum("nk,nki->ni", share, rows.c[idx])
    form = law.concave_form()
    at = lift.xyz[idx]
    if law.point is not None and law.frame == Frame.PARENT:
        at = xv + quat_rotate(qv, np.broadcast_to(law.point, xv.shape))
    elif form is not None and law.frame == Frame.PARENT:
        at = xv + quat_rotate(qv, np.broadcast_to(form[0], xv.shape))
    elif form is not None and law.frame == Frame.WORLD_OFFSET:
        at = xv + form[0]
    return m_bar, c_hat - at
