"""A certified maximum over the latent rotation for rows with rotating precisions (issue 11).

A child placed by a parent-frame Normal with unequal variances (`parent_normal_offset`) has a
precision that turns with its latent parent: -½ (Rᵀ(c - t) - m)ᵀ P (Rᵀ(c - t) - m) is not
a quadratic form of (t, X = q qᵀ), so `bound.py`'s relaxation counts its supremum.  Here the
set's score, these *rotating* terms included, is maximised over the rotation by
branch-and-bound, with the position eliminated in closed form:

- cells are cubes of rotation vectors ω (R = exp ω, the ball |ω| ≤ π holds every rotation),
  or intervals of a revolute law's half-angle ψ; every R in a cell is E R0 with R0 the cell's
  centre and E a turn by at most δ (the cube's half-diagonal: ∠(exp ω, exp ω') ≤ |ω - ω'|;
  2·half-width on an arc, about the family's world axis);
- on a cell, with the Normal terms' precisions held fixed, the score Φ(R) = max over the
  position of Σ -½ rᵀ W r + ⟨G_B, R⟩ (a Bingham density is linear in R) is concave in R's
  entries, so Φ(R) ≤ Φ(R0) + ⟨∇Φ(R0), R - R0⟩, and the linear term's maximum over the cell
  follows from Rodrigues' formula (`_linear_max`).  Five versions, the lowest bound kept:
  two *second-order* bounds (`_bound_second_order`: every precision and the box exact at the
  centre's best position t0, and what moving t can add paid for by the score's curvature in
  t, so the excess is O(δ²) near a stationary rotation even with an active box or an
  anisotropic world-frame Normal next to a rotating one; the move paid for either over all
  turns at once or, `_coupled_turn`, along each turn with the turn's own gain, which keeps
  the O(δ²) constant near the score's own curvature where the position follows the turn; a
  box that pins some axes and leaves the others open, the common `pin: [z]`, holds the move
  on the pinned axes (`_stiffen_narrow_axes`) and pays for the rounding slope along the open
  ones with curvature (`_curved_slack`), where a linear slack was infinite),
  and three first-order ones:
  the *world frame* (residuals c - t - R m: world-frame precisions exact, rotating ones
  R P Rᵀ replaced on the cell by a lower bound W, R0 P R0ᵀ - εI with ε = 2 sin(δ/2)
  (λmax - λmin), or λmin I: the score only grows), the *top frame* (t = R s, residuals
  Rᵀ c - m - s: the rotating precisions exact, the world-frame ones lowered) and, for a
  pinned position, the exact quadratic of R.  A box on the position enters both frames as
  a box (widened by the cell's turn in the top frame), with the slack max over the box of
  ∇_t·(s - t) for a position that is not the box's exact optimum;
- a cell's centre gives an exact value (a feasible rotation), the incumbent; cells whose bound
  is below it go, cells within the tolerance stop splitting, the rest split (8 cubes, 2
  intervals), best gap first, until every row is within tolerance or the cell budget or the
  deadline runs out.  The row's bound is then the largest of its incumbent and its cells'
  bounds: valid whenever it stops.

The cell bound's error is O(δ²) (the second-order bound everywhere; the first-order ones
where nothing is lowered and no box is active), so cells near the optimum need only
δ ~ √tolerance and a row closes after a few thousand cells: over the 408 two-row problems of
tests/test_bound_rotation.py's grid (seeds 0-11), a median of 3,241 cell evaluations per
problem, 26,275 at the 90th percentile, 66,789 at most, every row closed (with the move paid
for over all turns at once only: 49,287 at the 90th percentile, 7 problems open at the budget).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import axis_angle_to_quat, quat_conjugate, quat_multiply, quat_to_matrix
from ssgc.parse.set_terms import K_ROT, STEEP, Rotating, _isotropic_rows, _subset

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

TOL_REL = 1e-7  # a row stops when its bound is within this of its best value (× max(1, |v|))
MAX_CELLS = 120_000  # cell evaluations per call (all rows together)
BATCH = 4096  # cells split per step, the largest gaps first
CUBE_SPLITS = 4  # the first grid of rotation vectors: 4³ cubes over [-π, π]³
ARC_SPLITS = 8  # the first intervals of a revolute arc
CHUNK = 8192  # cells evaluated at once
FIRST_CELLS = 4 * 64  # a row's first cells (4³ cubes), four times over: at most
# max_cells // FIRST_CELLS rows are searched, the widest gaps first
# cells whose turn is under this take the second-order bounds only: there the first-order
# frames' O(δ) excess never won (the parse tests' 911,410 cells: the same cells with them
# skipped, a sixth less CPU; at 2⁻⁶ they still saved cells)
FIRST_ORDER_DELTA = 2.0**-7
FIXED_WIDTH = 4e-9  # a position box this narrow is a pinned position (bound.BOX_MARGIN ×4)


@cache
def _sym_basis() -> FloatArray:
    """(10, 16) pseudo-inverse of the map (G, b) ↦ Σ G_ij K_ij + b I: a symmetric 4×4 B is
    then qᵀ B q = ⟨G, R(q)⟩ + b on unit quaternions (the 9 K_ij and I span the symmetric
    matrices, so the expansion is exact)."""
    design = np.concatenate([K_ROT.reshape(9, 16), np.eye(4).reshape(1, 16)]).T
    return np.linalg.pinv(design)


@dataclass
class _Problem:
    """Per row: type-A (rotating) and type-B (world-frame) Normal terms, the Bingham part as
    ⟨G_B, R⟩, the constant, the position's box (pinned at t0 where it is a point) and the
    rotation domain."""

    cA: FloatArray
    mA: FloatArray
    PA: FloatArray
    lamA: FloatArray  # (n, J, 2): λmin, λmax of each PA
    cB: FloatArray
    mB: FloatArray
    PB: FloatArray
    lamB: FloatArray  # (n, K, 2)
    GB: FloatArray
    const: FloatArray
    lo: FloatArray
    hi: FloatArray
    fixed: NDArray[np.bool_]
    boxed: NDArray[np.bool_]
    t0: FloatArray
    arc_rows: NDArray[np.bool_]
    V: FloatArray
    arc: FloatArray
    axis: FloatArray  # (n, 3) a revolute family's world axis


def _extremes(P: FloatArray) -> FloatArray:
    if not P.shape[1]:
        return np.zeros((*P.shape[:2], 2))
    return np.linalg.eigvalsh(P)[..., [0, -1]]


def _problem(terms, rot: Rotating) -> _Problem:  # type: ignore[no-untyped-def]
    n = len(rot.c)
    coef = np.einsum("xf,nf->nx", _sym_basis(), terms.B.reshape(n, 16))
    fixed = np.all(terms.hi - terms.lo <= FIXED_WIDTH, axis=1)
    boxed = ~fixed & np.any(np.isfinite(terms.lo) | np.isfinite(terms.hi), axis=1)
    with np.errstate(invalid="ignore"):
        t0 = np.where(fixed[:, None], 0.5 * (terms.lo + terms.hi), 0.0)
    u, w = terms.V[..., 0], terms.V[..., 1]
    axis = quat_multiply(w, quat_conjugate(u))[:, 1:]  # w ⊗ u⁻¹ = (0, R_base·axis)
    a = np.any(rot.P != 0.0, axis=(0, 2, 3))  # terms no row has add nothing: their columns
    b = np.any(terms.P != 0.0, axis=(0, 2, 3))  # pad rows to the widest of the set
    return _Problem(
        rot.c[:, a],
        rot.m[a],
        rot.P[:, a],
        _extremes(rot.P[:, a]),
        terms.c[:, b],
        terms.m[b],
        terms.P[:, b],
        _extremes(terms.P[:, b]),
        coef[:, :9].reshape(n, 3, 3),
        terms.const - rot.lift + coef[:, 9],
        terms.lo,
        terms.hi,
        fixed,
        boxed,
        np.nan_to_num(t0),
        terms.revolute.copy(),
        terms.V,
        terms.arc,
        axis,
    )


def _solve(S: FloatArray, b: FloatArray) -> FloatArray:
    """S⁻¹ b for S (n, d, d), with S = 0 (no Normal term at all) read as the identity (any s
    is best).

    Precisions of very different scales (variances of 1e-12 and 1e6 in one law) can make S
    singular in floating point; b = Σ Pᵢ μᵢ lies in the range of S, so the pseudo-inverse
    gives the maximiser there (the solve raised LinAlgError: an internal error)."""
    empty = np.trace(S, axis1=1, axis2=2) <= 0.0
    S = S + empty[:, None, None] * np.eye(S.shape[-1])
    try:
        return np.linalg.solve(S, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return (np.linalg.pinv(S, hermitian=True) @ b[..., None])[..., 0]


BOX_SWEEPS = 40  # coordinate-ascent sweeps for the best position in a box


def _best_position(
    H: FloatArray, b: FloatArray, lo: FloatArray, hi: FloatArray, boxed: NDArray[np.bool_]
) -> FloatArray:
    """argmax of -½ tᵀ H t + bᵀ t: the free solve, or, on `boxed` rows, coordinate ascent in
    the box from its clipped point (any point of the box: `_box_slack` counts the rest)."""
    t = _solve(H, b)
    if not np.any(boxed):
        return t
    narrow = (hi - lo) <= FIXED_WIDTH
    opened = ~np.isfinite(lo) & ~np.isfinite(hi)
    split = boxed & np.all(narrow | opened, axis=1) & np.any(opened, axis=1)
    if np.any(split):
        t[split] = _pinned_axes_solve(H[split], b[split], lo[split], hi[split], narrow[split])
        boxed = boxed & ~split
        if not np.any(boxed):
            return t
    Hb, bb, lb, hb = H[boxed], b[boxed], lo[boxed], hi[boxed]
    tb = np.clip(t[boxed], lb, hb)
    diag = np.maximum(np.einsum("nii->ni", Hb), 1e-300)
    for _ in range(BOX_SWEEPS):
        for k in range(3):
            rest = bb[:, k] - np.einsum("nj,nj->n", Hb[:, k], tb) + Hb[:, k, k] * tb[:, k]
            tb[:, k] = np.clip(rest / diag[:, k], lb[:, k], hb[:, k])
    t[boxed] = tb
    return t


def _axis_patterns(mask: NDArray[np.bool_]) -> list[tuple[NDArray[np.bool_], IntArray]]:
    """(pattern, rows) for each pattern of the three axes in `mask` (n, 3) that occurs
    (np.unique over rows sorted every cell of the search)."""
    code = mask @ np.array([1, 2, 4])
    return [
        (np.array([c & 1, c & 2, c & 4], bool), np.flatnonzero(code == c))
        for c in np.flatnonzero(np.bincount(code, minlength=8))
    ]


def _pinned_axes_solve(
    H: FloatArray, b: FloatArray, lo: FloatArray, hi: FloatArray, narrow: NDArray[np.bool_]
) -> FloatArray:
    """argmax of -½ tᵀ H t + bᵀ t with the `narrow` axes held at their boxes' middles and the
    others free: the free axes' solve given the held ones (per pattern of held axes).

    Why: a position pinned on some axes and free on the rest (a shelf or a table held at its
    height) is the common box, and coordinate ascent took 40 sweeps of Python-level steps
    on every cell of the rotation search to approach what this solve gives exactly."""
    t = np.where(narrow, 0.5 * (np.where(narrow, lo, 0.0) + np.where(narrow, hi, 0.0)), 0.0)
    for pattern, rows in _axis_patterns(narrow):
        u, k = np.flatnonzero(~pattern), np.flatnonzero(pattern)
        H_r = H[rows]
        rhs = b[rows][:, u] - np.einsum("nuk,nk->nu", H_r[:, u][:, :, k], t[rows][:, k])
        t[np.ix_(rows, u)] = _solve(H_r[:, u][:, :, u], rhs)
    return t


def _box_slack(grad: FloatArray, t: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """max over s in the box of ∇·(s - t): what a concave function can gain on t (∞ where an
    unbounded axis has a nonzero slope)."""
    with np.errstate(invalid="ignore"):
        up, down = grad * (hi - t), grad * (lo - t)
    keep = {"nan": 0.0, "posinf": np.inf, "neginf": -np.inf}  # 0·∞: a flat unbounded axis
    gain = np.maximum(np.nan_to_num(up, **keep), np.nan_to_num(down, **keep))
    return gain.sum(axis=1)


def _curved_slack(  # type: ignore[no-untyped-def]
    grad: FloatArray, K: FloatArray, t: FloatArray, i: IntArray, p
) -> FloatArray:
    """max of ∇·d - ½ dᵀ K d over moves d of t within the box with its half-open axes opened
    (∞ where K is not positive definite on them).

    Why: at the best position t in a box that pins some axes and leaves the others unbounded
    (a shelf held at its height), the slope along the unbounded axes is zero up to rounding,
    but a linear slack counts any slope there as an infinite gain, so the second-order cell
    bound was infinite and the cells never closed (a latent shelf parsed `feasible`, its
    search spending the whole cell budget).  With U the axes with an infinite side and B the
    others, -½ dᵀ K d = -½ yᵀ K_UU y - ½ d_Bᵀ S d_B (y = d_U + K_UU⁻¹ K_UB d_B, S the Schur
    complement, S ⪰ 0), so the maximum is at most ½ ∇_Uᵀ K_UU⁻¹ ∇_U plus the linear slack of
    ∇_B - K_BU K_UU⁻¹ ∇_U over B's box."""
    lo, hi = p.lo[i], p.hi[i]
    opened = ~(np.isfinite(lo) & np.isfinite(hi))
    out = np.full(len(grad), np.inf)
    for pattern, rows in _axis_patterns(opened):
        u, b = np.flatnonzero(pattern), np.flatnonzero(~pattern)
        if not len(u):
            continue
        k_uu = K[rows][:, u][:, :, u]
        w = np.linalg.eigvalsh(k_uu)
        pd = w[:, 0] > 1e-12 * np.maximum(1.0, w[:, -1])
        k_uu = np.where(pd[:, None, None], k_uu, np.eye(len(u)))
        g_u = grad[rows][:, u]
        sol = np.linalg.solve(k_uu, g_u[..., None])[..., 0]
        value = 0.5 * np.sum(g_u * sol, axis=1)
        if len(b):
            g_b = grad[rows][:, b] - np.einsum("nbu,nu->nb", K[rows][:, b][:, :, u], sol)
            value = value + _box_slack(g_b, t[rows][:, b], lo[rows][:, b], hi[rows][:, b])
        out[rows] = np.where(pd, value, np.inf)
    return out


def _world_terms(p: _Problem, i: IntArray, R: FloatArray, QA: FloatArray):  # type: ignore[no-untyped-def]
    """Residuals e = c - R m and precisions of every term in the world frame (QA: the
    rotating terms' precisions, exact or lowered)."""
    c = np.concatenate([p.cA[i], p.cB[i]], axis=1)
    Rm = np.concatenate(
        [np.einsum("nij,kj->nki", R, p.mA), np.einsum("nij,kj->nki", R, p.mB)], axis=1
    )
    return c - Rm, np.concatenate([QA, p.PB[i]], axis=1)


def _position(p: _Problem, i: IntArray, e: FloatArray, Q: FloatArray) -> FloatArray:
    H, b = Q.sum(axis=1), np.einsum("nkij,nkj->ni", Q, e)
    t = _best_position(H, b, p.lo[i], p.hi[i], p.boxed[i])
    return np.where(p.fixed[i][:, None], p.t0[i], t)


def _exact(p: _Problem, i: IntArray, R: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The score at rotations R (N, 3, 3) of rows i, at a position in the box (the best one,
    up to the coordinate ascent's convergence): a feasible value."""
    QA = _turned(R, p.PA[i])
    e, Q = _world_terms(p, i, R, QA)
    t = _position(p, i, e, Q)
    d = e - t[:, None, :]
    value = -0.5 * np.einsum("nki,nkij,nkj->n", d, Q, d)
    return value + np.einsum("nij,nij->n", p.GB[i], R) + p.const[i], t


def _lower(Q0: FloatArray, lam: FloatArray, delta: FloatArray) -> FloatArray:
    """W ⪯ E Q0 Eᵀ for every turn E by at most δ: ‖E Q0 Eᵀ - Q0‖ ≤ 2 sin(δ/2)(λmax - λmin)
    =: ε gives Q0 - εI (kept where ε ≤ λmin/2), and λmin I always holds."""
    lo, hi = lam[..., 0], lam[..., 1]
    eps = 2 * np.sin(0.5 * np.minimum(delta, np.pi))[:, None] * (hi - lo)
    small = eps <= 0.5 * lo
    eye = np.eye(3)
    shifted = Q0 - eps[..., None, None] * eye
    return np.where(small[..., None, None], shifted, lo[..., None, None] * eye)


def _bound_top_frame(p: _Problem, i: IntArray, R: FloatArray, delta: FloatArray):  # type: ignore[no-untyped-def]
    """Φ(R0) + box slack and ∇Φ(R0) in the top frame, t = R s: the rotating precisions are
    exact, the world-frame ones lowered.  The score is jointly concave in (R, u = R0 s), and
    t = E u in the box puts u in the box widened by 2 sin(δ/2)·max |t| (|E u - u| ≤ that):
    a box on u, so the world frame's slack argument holds (exact away from the box's faces)."""
    c = np.concatenate([p.cA[i], p.cB[i]], axis=1)
    m = np.concatenate([p.mA, p.mB], axis=0)
    QB = _turned(np.swapaxes(R, 1, 2), p.PB[i])
    W = np.concatenate([p.PA[i], _lower(QB, p.lamB[i], delta)], axis=1)
    a = np.einsum("nji,nkj->nki", R, c) - m[None]
    H = np.einsum("nij,njk,nlk->nil", R, W.sum(axis=1), R)
    b = np.einsum("nij,nkjl,nkl->ni", R, W, a)
    boxed = p.boxed[i] | p.fixed[i]
    with np.errstate(invalid="ignore"):
        reach = np.linalg.norm(np.maximum(np.abs(p.lo[i]), np.abs(p.hi[i])), axis=1)
    widen = 2 * np.sin(0.5 * np.minimum(delta, np.pi)) * np.where(boxed, reach, 0.0)
    lo, hi = p.lo[i] - widen[:, None], p.hi[i] + widen[:, None]
    u = _best_position(H, b, lo, hi, boxed)
    r = a - np.einsum("nji,nj->ni", R, u)[:, None, :]
    Wr = np.einsum("nkij,nkj->nki", W, r)
    grad_u = np.einsum("nij,nj->ni", R, Wr.sum(axis=1))
    slack = np.where(boxed, _box_slack(grad_u, u, lo, hi), 0.0)
    phi = -0.5 * np.einsum("nki,nki->n", r, Wr)
    return phi + slack, -np.einsum("nki,nkj->nij", c, Wr)


def _bound_world_frame(p: _Problem, i: IntArray, R: FloatArray, delta: FloatArray):  # type: ignore[no-untyped-def]
    """Φ(R0) + box slack and ∇Φ(R0) with t in its box: the world-frame precisions are exact,
    the rotating ones lowered.  g is jointly concave in (t, R), so for t0 in the box
    g(t, R) ≤ g(t0, R0) + ∇_t·(t - t0) + ⟨∇_R, R - R0⟩."""
    QA = _turned(R, p.PA[i])
    e, W = _world_terms(p, i, R, _lower(QA, p.lamA[i], delta))
    t = _position(p, i, e, W)
    d = e - t[:, None, :]
    Wd = np.einsum("nkij,nkj->nki", W, d)
    phi = -0.5 * np.einsum("nki,nki->n", d, Wd)
    slack = np.where(p.boxed[i], _box_slack(Wd.sum(axis=1), t, p.lo[i], p.hi[i]), 0.0)
    m = np.concatenate([p.mA, p.mB], axis=0)
    curved = np.isinf(slack)
    if np.any(curved):  # a rounding error's slope along an unbounded axis (_curved_slack)
        c = curved
        slack[c] = _curved_world_slack(p, i[c], W[c], Wd[c], t[c], m, delta[c])
    return phi + slack, np.einsum("nki,kj->nij", Wd, m)


def _curved_world_slack(  # type: ignore[no-untyped-def]
    p: _Problem, i: IntArray, W: FloatArray, Wd: FloatArray, t: FloatArray, m: FloatArray, delta
) -> FloatArray:
    """The world frame's slack with half of the curvature in t kept: the score is
    g0 + ∇_t·d + ⟨∇_R, ΔR⟩ - ½ Σ (ΔR m_k + d)ᵀ W_k (ΔR m_k + d), and (a + b)ᵀ W (a + b) ≥
    ½ bᵀ W b - aᵀ W a, so the last sum is at most -¼ dᵀ ΣW d plus ½ Σ λmax(W_k)|ΔR m_k|²,
    |ΔR m_k| ≤ 2 sin(δ/2)|m_k| on the cell: `_curved_slack` with K = ½ ΣW, plus that."""
    top = np.linalg.eigvalsh(W)[..., -1]  # (n, K)
    turn = 2.0 * np.sin(0.5 * np.minimum(delta, np.pi))
    extra = 0.5 * turn**2 * np.einsum("nk,k->n", top, np.sum(m * m, axis=1))
    return _curved_slack(Wd.sum(axis=1), 0.5 * W.sum(axis=1), t, i, p) + extra


def _bound_pinned(p: _Problem, i: IntArray, R: FloatArray, delta: FloatArray):  # type: ignore[no-untyped-def]
    """Φ(R0) and ∇Φ(R0) at the pinned position t0: every term is a concave quadratic of R
    itself, the rotating ones as -½ (Rᵀ(c - t0) - m)ᵀ P (…): nothing lowered."""
    t0 = p.t0[i][:, None, :]
    rA = np.einsum("nji,nkj->nki", R, p.cA[i] - t0) - p.mA[None]
    PrA = np.einsum("nkij,nkj->nki", p.PA[i], rA)
    rB = p.cB[i] - t0 - np.einsum("nij,kj->nki", R, p.mB)
    PrB = np.einsum("nkij,nkj->nki", p.PB[i], rB)
    phi = -0.5 * (np.einsum("nki,nki->n", rA, PrA) + np.einsum("nki,nki->n", rB, PrB))
    grad = np.einsum("nki,kj->nij", PrB, p.mB) - np.einsum("nki,nkj->nij", p.cA[i] - t0, PrA)
    return phi, grad


def _bound_second_order(  # type: ignore[no-untyped-def]
    p: _Problem, i: IntArray, R: FloatArray, delta: FloatArray, t0: FloatArray
):
    """Φ-part and ∇_R at (t0, R0) of the *second-order* cell bound: every precision exact,
    the box exact, the position's move paid for by the score's curvature in t.

    For a fixed t, g(t, ·) is concave in R's entries (each term is minus a squared norm of
    an affine function of R), so g(t, E R0) ≤ g(t, R0) + ⟨M(t), E - I⟩ with M(t) =
    ∇_R g(t, R0) R0ᵀ.  Write t = t0 + d.  M(t) = M(t0) + L d - (d dᵀ R0 Σ_A P_A) R0ᵀ
    (L linear: the world-frame terms' -P d mᵀ, the rotating terms' (w dᵀ + d wᵀ) R0 P
    - d mᵀ P, w = c - t0), and ‖E - I‖_F = 2√2 sin(θ/2) =: s, so ⟨M(t) - M(t0), E - I⟩ ≤
    s (|L d| + ‖Σ_A P_A‖ |d|²).  g(t, R0) is a concave quadratic in t with Hessian -H,
    g(t, R0) = g(t0, R0) + ∇_t·d - ½ dᵀ H d, and ∇_t·d ≤ the box slack on the box.  So
    max over the cell and the box ≤ g(t0, R0) + slack + max ⟨M(t0), E - I⟩
    + max over d of [s |L d| - ½ dᵀ (H - 2 s ‖Σ_A P_A‖ I) d], the last = s² λmax(H'⁻¹ LᵀL)/2
    (∞ where H' is not positive definite; also at most s (‖L‖ ρ + ‖Σ P_A‖ ρ²) with ρ the
    box's reach from t0).  Its excess over the true maximum is O(δ²) near a stationary
    rotation, with or without an active box or anisotropic world-frame terms: the
    cells the first-order frames leave at their budget close here.

    Returns (phi + slack + gain, ∇_R g(t0, R0)), like the other frames."""
    eye = np.eye(3)
    w = p.cA[i] - t0[:, None, :]  # (n, J, 3)
    rho = np.einsum("nji,nkj->nki", R, w) - p.mA[None]  # top-frame residuals
    PArho = np.einsum("nkij,nkj->nki", p.PA[i], rho)
    r = p.cB[i] - t0[:, None, :] - np.einsum("nij,kj->nki", R, p.mB)
    PBr = np.einsum("nkij,nkj->nki", p.PB[i], r)
    phi = -0.5 * (np.einsum("nki,nki->n", rho, PArho) + np.einsum("nki,nki->n", r, PBr))
    grad_R = np.einsum("nki,kj->nij", PBr, p.mB) - np.einsum("nki,nkj->nij", w, PArho)
    grad_t = np.einsum("nij,nkj->ni", R, PArho) + PBr.sum(axis=1)
    slack = np.where(p.boxed[i], _box_slack(grad_t, t0, p.lo[i], p.hi[i]), 0.0)
    RPA = np.einsum("nij,nkjl->nkil", R, p.PA[i])  # (n, J, 3, 3): R0 P_A
    H = np.einsum("nkij,nlj->nil", RPA, R) + p.PB[i].sum(axis=1)
    curved = np.isinf(slack)  # a rounding error's slope along an unbounded axis of the box
    if np.any(curved):  # half of the curvature pays for it, the other half for the turn
        slack[curved] = _curved_slack(grad_t[curved], 0.5 * H[curved], t0[curved], i[curved], p)
        H = np.where(curved[:, None, None], 0.5 * H, H)
    # L[n, a] = the 3×3 change of ∇_R g per unit move of t along axis a
    L = -np.einsum("nkia,kj->naij", p.PB[i], p.mB)
    L += np.einsum("nki,nkaj->naij", w, RPA)
    along = np.einsum("nki,nkij->nj", w, RPA) - np.einsum("ki,nkij->nj", p.mA, p.PA[i])
    L += eye[None, :, :, None] * along[:, None, None, :]
    gram = np.einsum("naij,nbij->nab", L, L)
    curv = _extremes(p.PA[i].sum(axis=1, keepdims=True))[:, 0, 1]  # ‖Σ_A P_A‖
    s = 2.0 * np.sqrt(2.0) * np.sin(0.5 * np.minimum(delta, np.pi))
    Hs = H - (2.0 * s * curv)[:, None, None] * eye
    size = np.maximum(1.0, np.sqrt(np.sum(Hs * Hs, axis=(1, 2))))  # ≥ |λ|max, before stiffening
    Hs, pinned_cost = _stiffen_narrow_axes(Hs, size, t0, p.lo[i], p.hi[i])
    h, U = np.linalg.eigh(Hs)
    pd = h[:, 0] > 1e-12 * size  # the stiff axes' own size must not set the threshold
    scale = np.where(pd[:, None], 1.0 / np.sqrt(np.where(pd[:, None], h, 1.0)), 0.0)
    root = np.einsum("nij,nj,nkj->nik", U, scale, U)  # H'^(-1/2)
    top = np.maximum(np.linalg.eigvalsh(np.einsum("nij,njk,nkl->nil", root, gram, root))[:, -1], 0)
    gain = np.where(pd, 0.5 * s**2 * top + pinned_cost, np.inf)
    with np.errstate(invalid="ignore"):
        reach = np.linalg.norm(np.maximum(p.hi[i] - t0, t0 - p.lo[i]), axis=1)
    reach = np.where(np.isnan(reach), np.inf, reach)
    norm_L = np.sqrt(np.maximum(np.linalg.eigvalsh(gram)[:, -1], 0.0))
    with np.errstate(invalid="ignore"):
        boxed_gain = s * (norm_L * reach + curv * reach**2)
    gain = np.minimum(gain, np.where(np.isnan(boxed_gain), np.inf, boxed_gain))
    C, tail = _coupled_turn(L, R, delta, root, np.sqrt(top), pd)
    return phi + slack, grad_R, gain, (C, tail + pinned_cost)


def _stiffen_narrow_axes(
    H: FloatArray, size: FloatArray, t0: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """H with a stiff curvature B along the axes a box pins (width ≤ FIXED_WIDTH), and
    the most that adds: ½ B Σ w², w the farthest the box lets t move from t0 on them.

    Why: the move d of the position is maximised over all of R³, but on a pinned axis the box
    holds it (d_k within the rounding margin).  Where the score has no curvature along that
    axis (a shelf pinned at its height, boxes pinned on it: no Normal term in z), H' lost
    positive definiteness on every cell wider than the curvature, the gain was infinite and
    no cell closed.  f(d) - ½ B d_k² differs from f(d) by at most ½ B w² where the box holds
    d, so the maximum over R³ with B added, plus that, bounds the one over the box."""
    narrow = (hi - lo) <= FIXED_WIDTH
    if not np.any(narrow):
        return H, np.zeros(len(H))
    big = 1e3 * size  # (size ≥ H's largest |eigenvalue|) the pinned axes' share of the gain
    # ≲ 1e-3 of the rest, and the eigenvalues of the rest accurate to ~1e-13 × size
    H = H + big[:, None, None] * (narrow[:, :, None] * np.eye(3))
    with np.errstate(invalid="ignore"):
        width = np.where(narrow, np.maximum(hi - t0, t0 - lo), 0.0)
    return H, 0.5 * big * np.sum(width**2, axis=1)


def _coupled_turn(  # type: ignore[no-untyped-def]
    L: FloatArray,
    R: FloatArray,
    delta: FloatArray,
    root: FloatArray,
    ell: FloatArray,
    pd: NDArray[np.bool_],
):
    """(C, tail): the position's move paid for jointly with the turn's direction u, so
    that max over the cell ≤ Φ(R0) + slack + max ⟨M + C, E - I⟩ + tail.

    `gain` above pairs the best move d with the best turn, separately: its excess is the
    largest coupling over all turns, however little the score gains by turning that way
    (rows whose position follows the turn, with a flat maximum, stayed open at the budget).
    By Rodrigues, E - I = sin θ [u]× + (1 - cos θ)(u uᵀ - I), so with N = (L d) R0ᵀ,
    ⟨N, E - I⟩ ≤ sin θ u·W d + β |L d| (W d the vector of N's skew part, β = √2 (1 - cos δ)),
    and max over d of [sin θ u·W d + β |L d| - ½ dᵀ H' d] ≤ ½ sin²θ uᵀ C u + β ℓ ω sin δ
    + ½ β² ℓ² (C = W H'⁻¹ Wᵀ, ℓ = ‖L H'^(-1/2)‖, ω = ‖W H'^(-1/2)‖).  As ½ sin²θ ≤ 1 - cos θ
    and C ⪰ 0, the first part joins M's symmetric part in `_linear_max`: it is counted only
    along the turn that gains."""
    N = np.einsum("naij,nkj->naik", L, R)
    W = np.moveaxis(_skew_vector(N), -1, 1)  # (n, 3, a): the skew vector of N_a per axis a of d
    WH = np.einsum("nka,nab->nkb", W, root)
    C = np.einsum("nka,nla->nkl", WH, WH)
    omega = np.linalg.norm(WH, ord=2, axis=(1, 2))
    sin = np.sin(np.minimum(delta, 0.5 * np.pi))
    beta = np.sqrt(2.0) * (1.0 - np.cos(np.minimum(delta, np.pi)))
    tail = np.where(pd, beta * ell * omega * sin + 0.5 * (beta * ell) ** 2, np.inf)
    return C, tail


def _turned(R: FloatArray, P: FloatArray) -> FloatArray:
    """R P Rᵀ for every cell n and child k, (n, k, 3, 3): batched matrix products (a
    three-operand einsum took a fifth of a latent shelf's parse)."""
    return R[:, None] @ P @ np.swapaxes(R, 1, 2)[:, None]


def _cell_bound(
    p: _Problem, i: IntArray, R: FloatArray, delta: FloatArray, t0: FloatArray
) -> FloatArray:
    """An upper bound on the score over every rotation E R0 with ∠E ≤ δ (about the family's
    axis on revolute rows): Φ(R0) + max ⟨∇Φ(R0), R - R0⟩ for valid Φ (module docstring),
    the lowest of them: the world frame and the top frame (t in its box, or near it), the
    second-order bound from the best position t0 at R0 and, for a pinned position, the exact
    quadratic of R."""
    lin = p.GB[i]
    base = np.einsum("nij,nij->n", lin, R) + p.const[i]
    phi, grad, gain, (C, tail) = _bound_second_order(p, i, R, delta, t0)
    M = (grad + lin) @ np.swapaxes(R, 1, 2)
    best = base + phi + gain + _linear_max(M, delta, p.axis[i], p.arc_rows[i])
    coupled = base + phi + tail + _linear_max(M + C, delta, p.axis[i], p.arc_rows[i])
    best = np.minimum(best, coupled)
    fixed = p.fixed[i]
    # below FIRST_ORDER_DELTA the second-order bounds win (O(δ²) against O(δ)) unless they are
    # infinite (H' not positive definite where the position can move): the frames stay there
    first = (delta >= FIRST_ORDER_DELTA) | ~np.isfinite(best)
    frames = ((_bound_world_frame, first), (_bound_top_frame, first), (_bound_pinned, fixed))
    for frame, rows in frames:
        if not np.any(rows):
            continue
        k = np.flatnonzero(rows)
        phi, grad = frame(p, i[k], R[k], delta[k])
        M = (grad + lin[k]) @ np.swapaxes(R[k], 1, 2)
        value = base[k] + phi + _linear_max(M, delta[k], p.axis[i[k]], p.arc_rows[i[k]])
        best[k] = np.minimum(best[k], value)
    return best


def _linear_max(
    M: FloatArray, delta: FloatArray, axis: FloatArray, on_axis: NDArray[np.bool_]
) -> FloatArray:
    """max ⟨M, E - I⟩ over turns E by at most δ (about `axis` where `on_axis`):
    E - I = sin θ [a]× + (1 - cos θ)(a aᵀ - I), so ⟨M, E - I⟩ = sin θ a·v + (1 - cos θ)
    (aᵀ M a - tr M), v the vector of M's skew part."""
    v = _skew_vector(M)
    Ms = 0.5 * (M + np.swapaxes(M, 1, 2))
    tr = np.trace(M, axis1=1, axis2=2)
    top = np.linalg.eigvalsh(Ms)[:, -1]
    along = np.einsum("ni,nij,nj->n", axis, Ms, axis)
    first = np.where(on_axis, np.abs(np.einsum("ni,ni->n", axis, v)), np.linalg.norm(v, axis=1))
    second = np.maximum(np.where(on_axis, along, top) - tr, 0.0)
    return (
        np.sin(np.minimum(delta, 0.5 * np.pi)) * first
        + (1 - np.cos(np.minimum(delta, np.pi))) * second
    )


def _skew_vector(M: FloatArray) -> FloatArray:
    """v with ⟨M, [a]×⟩ = a·v for every a, over the last two axes: twice the axial vector of
    M's skew part, the first-order gain of a turn."""
    return np.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]],
        axis=-1,
    )


def _rotvec_quat(omega: FloatArray) -> FloatArray:
    angle = np.linalg.norm(omega, axis=1)
    axis = np.where(angle[:, None] > 0, omega / np.where(angle > 0, angle, 1.0)[:, None], 0.0)
    axis[angle == 0, 2] = 1.0
    return axis_angle_to_quat(axis, angle)


def _inside_ball(centre: FloatArray, half: FloatArray) -> NDArray[np.bool_]:
    """Cubes that meet the ball |ω| ≤ π (the rest hold no rotation the ball lacks)."""
    near = np.clip(0.0, centre - half[:, None], centre + half[:, None])
    return np.linalg.norm(near, axis=1) <= np.pi


@dataclass
class _Cells:
    row: IntArray
    centre: FloatArray  # (N, 3): ω for a cube, (ψ, 0, 0) for an arc
    half: FloatArray  # (N,)

    def __len__(self) -> int:
        return len(self.row)

    def take(self, idx: IntArray) -> _Cells:
        return _Cells(self.row[idx], self.centre[idx], self.half[idx])

    @staticmethod
    def join(a: _Cells, b: _Cells) -> _Cells:
        cat = np.concatenate
        return _Cells(cat([a.row, b.row]), cat([a.centre, b.centre]), cat([a.half, b.half]))


def _first_cells(p: _Problem) -> _Cells:
    """A grid of cubes over the rotation vectors (rows without a family), and of intervals
    over a revolute arc's half-angles."""
    rows_cube = np.flatnonzero(~p.arc_rows)
    h = np.pi / CUBE_SPLITS
    g = (2 * np.arange(CUBE_SPLITS) + 1) * h - np.pi
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    grid = grid[_inside_ball(grid, np.full(len(grid), h))]
    n_cube = len(rows_cube) * len(grid)
    cube = _Cells(
        np.repeat(rows_cube, len(grid)), np.tile(grid, (len(rows_cube), 1)), np.full(n_cube, h)
    )
    rows_arc = np.flatnonzero(p.arc_rows)
    lo, hi = p.arc[rows_arc, 0], p.arc[rows_arc, 1]
    width = (hi - lo) / ARC_SPLITS
    psi = (lo[:, None] + (np.arange(ARC_SPLITS) + 0.5)[None] * width[:, None]).ravel()
    zero = np.zeros_like(psi)
    arc = _Cells(
        np.repeat(rows_arc, ARC_SPLITS),
        np.stack([psi, zero, zero], 1),
        np.repeat(0.5 * width, ARC_SPLITS),
    )
    return _Cells.join(cube, arc)


def _split(p: _Problem, cells: _Cells) -> _Cells:
    arc = p.arc_rows[cells.row]
    a, b = cells.take(np.flatnonzero(arc)), cells.take(np.flatnonzero(~arc))
    signs = np.array([[-1, 1]]).T * np.array([[1.0, 0.0, 0.0]])  # (2, 3)
    h = 0.5 * a.half
    arcs = _Cells(
        np.repeat(a.row, 2),
        (a.centre[:, None, :] + signs[None] * h[:, None, None]).reshape(-1, 3),
        np.repeat(h, 2),
    )
    corners = np.stack(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij"), -1).reshape(8, 3)
    h = 0.5 * b.half
    cubes = _Cells(
        np.repeat(b.row, 8),
        (b.centre[:, None, :] + corners[None] * h[:, None, None]).reshape(-1, 3),
        np.repeat(h, 8),
    )
    cubes = cubes.take(np.flatnonzero(_inside_ball(cubes.centre, cubes.half)))
    return _Cells.join(arcs, cubes)


def _evaluate(p: _Problem, cells: _Cells):  # type: ignore[no-untyped-def]
    """Each cell's centre rotation (as q), its exact value and position, and its bound, in
    chunks of CHUNK cells (the per-term arrays stay small)."""
    if len(cells) > CHUNK:
        parts = [
            _evaluate_chunk(p, cells.take(np.arange(k, min(k + CHUNK, len(cells)))))
            for k in range(0, len(cells), CHUNK)
        ]
        return tuple(np.concatenate(x) for x in zip(*parts, strict=True))
    return _evaluate_chunk(p, cells)


def _evaluate_chunk(p: _Problem, cells: _Cells):  # type: ignore[no-untyped-def]
    arc = p.arc_rows[cells.row]
    q_cube = _rotvec_quat(cells.centre)
    psi = cells.centre[:, 0]
    q_arc = np.einsum("nab,nb->na", p.V[cells.row], np.stack([np.cos(psi), np.sin(psi)], 1))
    q = np.where(arc[:, None], q_arc, q_cube)
    R = quat_to_matrix(q)
    delta = np.where(arc, 2.0 * cells.half, np.sqrt(3.0) * cells.half)
    value, t = _exact(p, cells.row, R)
    upper = np.maximum(_cell_bound(p, cells.row, R, delta, t), value)
    return q, value, t, upper


def rotation_search(
    terms,  # type: ignore[no-untyped-def]
    rot: Rotating,
    upper: FloatArray,
    xyz: FloatArray,
    quat: FloatArray,
    deadline: float | None = None,
    max_cells: int = MAX_CELLS,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rows whose relaxed bound is not exact and not within tolerance of the score at their
    pose: the lower of `upper` and the branch-and-bound's bound, and the pose of its best
    cell (a start for the exact polish).  Other rows pass through unchanged.

    Searched: a free rotation with rotating terms (the relaxation holds their supremum),
    a revolute arc (one dimension: cheap) with anything but isotropic unboxed Normals
    (Frank–Wolfe's hull of the arc), and a boxed position that is not exact (Frank–Wolfe's
    unclipped position) unless a steep stand-in term makes every cell bound loose.  Not
    searched: Frank–Wolfe's other rows over all rotations,
    where many assignments have small gaps that the MILP never picks (the bundled
    singles_pairs_constituency: a tenth of its rows, each over 1e-2) and a search of every
    one would cost more than the parse."""
    inexact = terms.revolute & ~_isotropic_rows(terms)
    boxed = np.any(np.isfinite(terms.lo) | np.isfinite(terms.hi), axis=1) & ~_isotropic_rows(terms)
    boxed &= np.max(np.abs(terms.P), axis=(1, 2, 3), initial=0.0) < STEEP  # cells cannot close
    rows = ~terms.pinned & (rot.rows | inexact | boxed)
    if not np.any(rows):
        return upper, xyz, quat
    p = _problem(_subset(terms, rows), rot.subset(rows))
    idx = np.flatnonzero(rows)
    start, t_start = _exact(p, np.arange(len(idx)), quat_to_matrix(quat[idx]))
    xyz = xyz.copy()  # the best position for each row's rotation, its rotating terms counted
    xyz[idx] = np.where(np.isfinite(start)[:, None], t_start, xyz[idx])
    gap = upper[idx] - start
    open_ = gap > TOL_REL * np.maximum(1.0, np.abs(start))
    if not np.any(open_):
        return upper, xyz, quat
    widest = np.argsort(-gap, kind="stable")[: max(1, max_cells // FIRST_CELLS)]
    open_ &= np.isin(np.arange(len(idx)), widest)  # the rest keep the relaxation's bound
    rows[idx[~open_]] = False
    idx = idx[open_]
    p = _problem(_subset(terms, rows), rot.subset(rows))
    seed = (start[open_], t_start[open_], quat[idx])
    bb, t_best, q_best = branch_and_bound(p, deadline, max_cells, seed)
    upper, xyz, quat = upper.copy(), xyz.copy(), quat.copy()
    upper[idx] = np.minimum(upper[idx], bb)
    xyz[idx], quat[idx] = t_best, q_best
    return upper, xyz, quat


def branch_and_bound(
    p: _Problem,
    deadline: float | None = None,
    max_cells: int = MAX_CELLS,
    seed: tuple[FloatArray, FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per row: an upper bound on the score over the rotation domain, and the best pose
    found (module docstring), from the feasible poses `seed` (value, position, rotation) if
    given.  Valid whenever it stops: pruned cells lie below the row's best value, every
    other cell's bound is counted."""
    n = len(p.const)
    best = np.full(n, -np.inf)
    t_best, q_best = np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1))
    if seed is not None:
        best, t_best, q_best = (x.copy() for x in seed)
    settled = np.full(n, -np.inf)  # the largest bound of the cells that stopped splitting
    new = _first_cells(p)
    live, live_ub = new.take(np.zeros(0, np.int64)), np.zeros(0)
    spent = 0
    while True:
        q, value, t, ub = _evaluate(p, new)
        spent += len(new)
        _improve(new.row, value, t, q, best, t_best, q_best)
        live, live_ub = _Cells.join(live, new), np.concatenate([live_ub, ub])
        tol = TOL_REL * np.maximum(1.0, np.abs(best))
        gap = live_ub - best[live.row]
        done = (gap > 0) & (gap <= tol[live.row])
        np.maximum.at(settled, live.row[done], live_ub[done])
        keep = np.flatnonzero(gap > tol[live.row])
        live, live_ub, gap = live.take(keep), live_ub[keep], gap[keep]
        out_of_time = deadline is not None and time.perf_counter() >= deadline
        if not len(live) or spent >= max_cells or out_of_time:
            break
        pick = np.argsort(-gap, kind="stable")[:BATCH]
        rest = np.ones(len(live), bool)
        rest[pick] = False
        new = _split(p, live.take(pick))
        live, live_ub = live.take(np.flatnonzero(rest)), live_ub[rest]
    np.maximum.at(settled, live.row, live_ub)
    return np.maximum(best, settled), t_best, q_best


def _improve(row, value, t, q, best, t_best, q_best) -> None:  # type: ignore[no-untyped-def]
    """Each row's best cell centre so far (in place)."""
    if not len(row):
        return
    order = np.lexsort((-value, row))
    first = order[np.r_[True, row[order][1:] != row[order][:-1]]]
    better = value[first] > best[row[first]]
    r = row[first][better]
    best[r], t_best[r], q_best[r] = value[first][better], t[first][better], q[first][better]
