"""An upper bound on the MAP score for grammars with latent poses (the certificate of 3.4).

The proposal parser's trees are feasible, so their scores are lower bounds on the MAP score;
this module gives the matching upper bound, so that a parse can report its gap honestly.

The bound keeps the tree structure discrete and relaxes the latent poses.  For a latent set,
the score terms that move with its pose depend only on *which* candidate child fills each of
its slots (an *assignment*: one per rule of an `and`, one option of an `or`, a set of
candidates for a `repeat`).  Writing the set's rotation as X = q qᵀ (the rotation matrix and
every Bingham log-density are linear in X) and relaxing X to {X ⪰ 0, tr X = 1}, Normal
translations are concave quadratics of (t, X), box laws are constraints on t, fixed rotations
pin X, a revolute law holds q to an arc (a second one meets it exactly: a pin, a narrower arc,
or no rotation at all), a fixed offset to a child can pin the arc's angle, and any other term
is replaced by its supremum.  The maximum over t is closed-form (clipped to the box); over X,
where every Normal term is isotropic and t has no box, the score is linear in R on rotations
and its maximum an eigenvector (exact); elsewhere Frank–Wolfe, whose duality gap is a valid
upper bound at every iterate.  The MILP over structures, with each latent node's edge
terms replaced by the bound of its assignment, then bounds the MAP score from above.

A member of the set that may be inactive adds an "off" row; the poses an optional observed
member implies join as free rows, scored exactly (`_implied_rows`).
A latent child placed in the world frame holds its own edge; a latent set whose parent's pose
is not known (a latent parent) counts its rule's supremum (`decoupled`: such bounds only
certify, `certify_only`).  Grammars outside the scope get no bound (gap unknown), never a
wrong one.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import (
    quat_normalize,
)
from ssgc.io.scene import Scene
from ssgc.ir import Grammar, Kind
from ssgc.laws.base import Frame
from ssgc.parse.bound_chain import (
    MAX_CHAIN_ROWS,
    ChainRows,
    Lifted,
    add_column,
    children_to_lift,
    collapse,
    lifted,
    own_world_edge,
    pin_column,
)
from ssgc.parse.bound_rotation import rotation_search
from ssgc.parse.clock import past
from ssgc.parse.milp import Milp
from ssgc.parse.posed import (
    FREE_CHILD,
    MAX_INSTANCES,
    Instances,
    PosedProblem,
    instance_count,
    reduce_posed,
    too_many_instances,
)
from ssgc.parse.poses import PoseEdges, _owned_values, _sub_edges, maximize_independent
from ssgc.parse.proposals import Candidates, known_parent, latent_sets
from ssgc.parse.reduction import Request
from ssgc.parse.set_terms import (
    BOX_MARGIN,
    FW_ITERATIONS,
    IDENTITY,
    SetBound,
    _arc_point,
    _h_and_gradient,
    _LocalBounds,
    _subset,
    _Terms,
    best_position,
    counted_supremum,
    relaxed_upper_bound,
)
from ssgc.parse.supertree import Supertree, hideable_nodes
from ssgc.rules import rotation_log_density, translation_log_density
from ssgc.tree import Trees

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
MAX_ASSIGNMENTS = 20_000


def set_bounds(
    grammar: Grammar, st: Supertree, cand: Candidates, deadline: float | None = None
) -> dict[int, SetBound] | None:
    """Bounds for every latent set, or None when some latent set is outside the scope.

    Children's sets come first: a decoupled child set (placed relative to a latent parent)
    is lifted into its parent's assignments where that stays small (`bound_chain`)."""
    out: dict[int, SetBound] = {}
    latent = latent_sets(st)
    memo: dict[tuple, tuple[SetBound, ChainRows | None]] = {}
    chains: dict[int, Lifted] = {}
    hide = hideable_nodes(grammar, st)
    for e in np.flatnonzero(latent)[::-1]:
        parent = known_parent(grammar, st, cand, int(e))
        lift = children_to_lift(st, int(e), chains)
        groups, seen = _lift_groups(grammar, st, cand, int(e), latent, lift)
        if groups is None:
            return None
        lift = {e_c: lift[e_c] for e_c in lift if e_c in seen}
        key = (
            int(st.type[st.set_top[e]]),
            int(st.rule[st.set_top[e]]),
            parent if parent in (None, False) else (parent[0].tobytes(), parent[1].tobytes()),
            tuple(
                (seen[c].xyz.tobytes(), seen[c].upper.tobytes())
                if c in seen
                else (cand.xyz[c].tobytes(), cand.quat[c].tobytes())
                for *_, c, _, _ in groups
                if c >= 0
            ),
            (cand.xyz[e].tobytes(), cand.quat[e].tobytes()),
            tuple(
                (k, r, len(kids), o, st.offset_xyz[v].tobytes(), st.offset_quat[v].tobytes())
                for k, v, r, c, kids, o in groups
            ),
        )  # the copies of a `repeat` share one computation
        if key not in memo:
            made = _bound_one(grammar, st, cand, int(e), groups, parent, deadline, lift)
            if made is None:
                return None
            memo[key] = made
        bound, rows = memo[key]
        columns = _columns(groups)
        objects = np.array([not latent[c] for *_, c in columns], bool)
        source = _copies_rows(bound, _copies(st, int(e)), objects)
        m = _copies_apart(bound, source)
        placed = None if parent is False else parent
        out[int(e)] = SetBound(
            columns, m.assignment, m.upper, m.xyz, m.quat, placed, parent is False, m.free
        )
        if parent is False and rows is not None and not hide[st.set_top[e]]:
            # a set that can be unseen keeps its own bound: lifted, its edge would sit in
            # its parent's rows, which count it even where the tree leaves it unseen
            chains[int(e)] = lifted(out[int(e)], rows, source)
            out[int(e)] = replace(out[int(e)], chain=chains[int(e)])
    return dict(sorted(out.items()))


def _lift_groups(grammar, st, cand, e, latent, lift):  # type: ignore[no-untyped-def]
    """Set e's groups with its decoupled child sets lifted in (`bound_chain`), when the
    assignments stay within MAX_CHAIN_ROWS; else the groups without them.  Returns the groups
    and the lifted children that are columns."""
    if lift:
        groups = _groups(grammar, st, e, latent, frozenset(lift))
        if groups is not None:
            made = _assignments(_lifted_candidates(cand, lift), groups)
            if made is not None and len(made[1]) <= MAX_CHAIN_ROWS:
                return groups, lift
    return _groups(grammar, st, e, latent), {}


def _lifted_candidates(cand: Candidates, lift: dict[int, Lifted]) -> Candidates:
    """The candidates with each lifted child set's replaced by its rows' poses."""
    if not lift:
        return cand
    out = Candidates(list(cand.xyz), list(cand.quat))
    for e_c, rows in lift.items():
        out.xyz[e_c], out.quat[e_c] = rows.xyz, rows.quat
    return out


def _copies(st: Supertree, e: int) -> int:
    """How many copies of the rule entering set e its parent node has (a `repeat`'s max)."""
    top = int(st.set_top[e])
    parent = int(st.parent[top])
    return sum(1 for c in st.children[parent] if st.rule[c] == st.rule[top])


def _copies_rows(bound: SetBound, copies: int, objects: NDArray[np.bool_]) -> IntArray:
    """The rows of `_copies_apart`'s bound, as indices of `bound`'s rows.  `objects` marks
    the columns whose child set is observed (the others are lifted latent sets)."""
    n = len(bound.assignment)
    no_object = np.all((bound.assignment < 0) | ~objects, axis=1)
    empty = np.flatnonzero(no_object & ~bound.free_rows)
    if copies < 2 or not len(empty):
        return np.arange(n)
    return np.concatenate([np.arange(n), np.repeat(empty, copies - 1)])


def _copies_apart(bound: SetBound, rows: IntArray) -> SetBound:
    """The bound with each assignment that names no object repeated once per further copy
    of a `repeat` (`_copies_rows`).

    The unrolled model gives a `repeat`'s copies distinct candidates.  Assignments that name
    an object are distinct by nature (an object has one parent), but several copies may take
    the same assignment naming none — childless, or naming only rows of lifted latent child
    sets (each copy has its own child) — (two latent nodes with the same best pose): without
    the repeats, a tree using it twice would have no encoding and the bound could miss it.
    Found by the generated grammars with `max_nesting`: two copies of a latent node whose
    latent child ends the chain (a blocked `or`) were certified at one copy's score."""
    if len(rows) == len(bound.assignment):
        return bound
    return SetBound(
        bound.slots,
        bound.assignment[rows],
        bound.upper[rows],
        bound.xyz[rows],
        bound.quat[rows],
        bound.parent,
        bound.decoupled,
        bound.free_rows[rows],
    )


def _groups(  # type: ignore[no-untyped-def]
    grammar: Grammar,
    st: Supertree,
    e: int,
    latent: NDArray[np.bool_],
    lifted: frozenset[int] = frozenset(),
):
    """(kind, member, rule, child set, copies, optional) per rule leaving the set.

    A member is *optional* when it may be inactive while the set's top is active (below an
    `or`, a `repeat` or an `independent` inside the set): its columns may then all be empty
    as well (`_member_rows`).  Rows that switch a member's columns on while the MILP leaves
    the member off encode no tree the rows do not already hold at an exact score (the
    member's children stay off), so they only add encodings: the bound stays an upper bound.
    A latent child set holds its own edge (its bound: see `set_bounds`), so it has no column,
    unless it is `lifted` (`bound_chain`): its rows are then this set's candidates.
    """
    groups = []
    sure = {int(st.set_top[e])}
    for v in np.flatnonzero(st.set_of == e):
        v = int(v)
        node = grammar.types[st.type[v]]
        optional = v not in sure
        by_rule: dict[int, list[int]] = {}
        for c in st.children[v]:
            by_rule.setdefault(int(st.rule[c]), []).append(int(c))
        inner = False
        for r, kids in by_rule.items():
            e_c = int(st.set_of[kids[0]])
            if e_c == e:
                inner = True
                if node.kind == Kind.AND and not optional:
                    sure.update(kids)
                continue
            if latent[e_c] and e_c not in lifted:  # its own bound holds the edge: no column
                inner = True
                continue
            groups.append((node.kind, v, r, e_c, tuple(kids), optional))
        if node.kind == Kind.OR and inner:
            groups.append((Kind.OR, v, -1, -1, (), optional))  # the option staying inside
    return tuple(groups)


def _independent(grammar: Grammar, r: int) -> bool:
    """Whether rule r's child pose ignores its parent's (world-frame translation and
    rotation): a latent child set's own bound then holds the edge whatever its parent's pose."""
    rule = grammar.rules[r]
    return rule.translation.frame == Frame.WORLD and rule.rotation.frame == Frame.WORLD


def _columns(groups) -> tuple[tuple[int, int, int], ...]:  # type: ignore[no-untyped-def]
    """The set's own columns (member, rule, child set), in `_member_rows`' order: the copies
    of a `repeat` share one computation, but each keeps its own nodes."""
    members: dict[int, list] = {}
    for g in groups:
        members.setdefault(g[1], []).append(g)
    cols = []
    for v, gs in members.items():
        for kind, _, r, e_c, kids, _ in gs:
            if r >= 0:
                cols += [(v, r, e_c)] * (len(kids) if kind == Kind.REPEAT else 1)
    return tuple(cols)


def _member_rows(cand: Candidates, groups) -> tuple[list, list[IntArray]]:  # type: ignore[no-untyped-def]
    """Per member: its columns (member, rule, child set) and its rows of candidate indices
    (-1: no child): AND, one candidate per rule; OR, one option and one candidate;
    INDEPENDENT, no child or one candidate per rule; REPEAT, every set of at most `copies`
    candidates, in increasing order (copies are exchangeable)."""
    from itertools import combinations
    from math import comb

    members: dict[int, list] = {}
    for g in groups:
        members.setdefault(g[1], []).append(g)
    cols_all, rows_all = [], []
    for v, gs in members.items():
        kind, optional = gs[0][0], gs[0][5]
        real = [g for g in gs if g[2] >= 0]
        cols = []
        if kind == Kind.AND:
            sizes = [len(cand.xyz[g[3]]) for g in real]
            if int(np.prod(sizes, dtype=float)) > MAX_ASSIGNMENTS:
                raise _TooMany
            grids = np.meshgrid(*[np.arange(k) for k in sizes], indexing="ij")
            rows = np.stack([gr.ravel() for gr in grids], axis=1).reshape(-1, len(real))
            cols = [(v, g[2], g[3]) for g in real]
        elif kind == Kind.OR:
            cols = [(v, g[2], g[3]) for g in real]
            parts = [np.full((1, len(real)), -1)] if len(real) < len(gs) else []
            for j, g in enumerate(real):
                k = len(cand.xyz[g[3]])
                part = np.full((k, len(real)), -1)
                part[:, j] = np.arange(k)
                parts.append(part)
            rows = np.vstack(parts) if parts else np.zeros((0, len(real)), np.int64)
        elif kind == Kind.INDEPENDENT:  # each rule fires or not: no child, or one candidate
            sizes = [len(cand.xyz[g[3]]) + 1 for g in real]
            if int(np.prod(sizes, dtype=float)) > MAX_ASSIGNMENTS:
                raise _TooMany
            grids = np.meshgrid(*[np.arange(k) - 1 for k in sizes], indexing="ij")
            rows = np.stack([gr.ravel() for gr in grids], axis=1).reshape(-1, len(real))
            cols = [(v, g[2], g[3]) for g in real]
        else:  # REPEAT: one rule, `copies` columns
            (_, _, r, e_c, kids, _), k = real[0], len(cand.xyz[real[0][3]])
            copies = len(kids)
            cols = [(v, r, e_c)] * copies
            # counted before they are listed: 30 candidates and 10 copies are 53 million
            # subsets, which ran out of memory (exit 70) before this check was reached
            if sum(comb(k, j) for j in range(min(copies, k) + 1)) > MAX_ASSIGNMENTS:
                raise _TooMany
            subsets = [s for j in range(min(copies, k) + 1) for s in combinations(range(k), j)]
            rows = np.full((len(subsets), copies), -1)
            for i, s in enumerate(subsets):
                rows[i, : len(s)] = s
        rows = np.asarray(rows, np.int64)
        if optional and not np.any(np.all(rows < 0, axis=1)):
            rows = np.vstack([rows, np.full((1, len(cols)), -1)])  # the member is off
        cols_all.append(cols)
        rows_all.append(rows)
    return cols_all, rows_all


class _TooMany(Exception):
    """More assignments than MAX_ASSIGNMENTS."""


def _assignments(cand: Candidates, groups) -> tuple[tuple, IntArray] | None:  # type: ignore[no-untyped-def]
    """All columns and the product of every member's rows, or None when too many."""
    try:
        cols_all, rows_all = _member_rows(cand, groups)
    except _TooMany:
        return None
    sizes = [len(r) for r in rows_all]
    if int(np.prod(sizes, dtype=float)) > MAX_ASSIGNMENTS:
        return None
    grids = np.meshgrid(*[np.arange(k) for k in sizes], indexing="ij")
    picks = [gr.ravel() for gr in grids] if sizes else []
    n = int(np.prod(sizes, dtype=np.int64)) if sizes else 1
    blocks = [rows[p] for rows, p in zip(rows_all, picks, strict=True)]
    assignment = np.hstack(blocks) if blocks else np.zeros((n, 0), np.int64)
    columns = tuple(c for cols in cols_all for c in cols)
    return columns, assignment.astype(np.int64)


def _bound_one(grammar, st, cand, e, groups, parent, deadline, lift=None):  # type: ignore[no-untyped-def]
    """Set e's bound over its assignments, and (for the chain above it) its rows' chain form
    (`bound_chain.collapse`, only where its parent's pose is not known)."""
    lift = lift or {}
    cand = _lifted_candidates(cand, lift)
    made = _assignments(cand, groups)
    if made is None:
        return None
    columns, assignment = made
    n = len(assignment)
    local = _LocalBounds(grammar, n)
    top_rule = int(st.rule[st.set_top[e]])
    local.prior_pin(top_rule, parent)
    local.prior_family(top_rule, parent)
    picked = []
    for k, (v, r, e_c) in enumerate(columns):
        on = assignment[:, k] >= 0
        idx = np.maximum(assignment[:, k], 0)
        cx = cand.xyz[e_c][idx] if len(cand.xyz[e_c]) else np.zeros((n, 3))
        cq = cand.quat[e_c][idx] if len(cand.quat[e_c]) else np.tile(IDENTITY, (n, 1))
        picked.append((v, r, e_c, on, idx, cx, cq))
        if e_c in lift:
            pin_column(local, lift[e_c], r, st.offset_xyz[v], st.offset_quat[v], idx, on)
            continue
        local.fixed_children.append((r, st.offset_xyz[v], st.offset_quat[v], cx, on))
        local.child_pin(r, st.offset_quat[v], cq, on)
        local.child_family(r, st.offset_quat[v], cq, on)
    local.prior(top_rule, parent)
    for v, r, e_c, on, idx, cx, cq in picked:
        if e_c in lift:
            off_t, off_q = st.offset_xyz[v], st.offset_quat[v]
            add_column(local, grammar, lift[e_c], r, off_t, off_q, idx, on)
        else:
            local.child(r, st.offset_xyz[v], st.offset_quat[v], cx, cq, on)
    keep = local.feasible()
    terms = _subset(local.terms(), keep)
    assignment = assignment[keep]
    rows = None
    if parent is False:
        rows = collapse(terms, counted_supremum(grammar.rules[top_rule]))
    upper, t, q = relaxed_upper_bound(terms, FW_ITERATIONS, deadline)
    # rows the relaxation holds loosely (rotating precisions, revolute arcs): branch-and-bound
    upper, t, q = rotation_search(terms, local.rotating().subset(keep), upper, t, q, deadline)
    bound = SetBound(columns, assignment, upper, t, q, *_placed(parent))
    xyz, quat = t, q
    if not (terms.complete and np.all(terms.pinned)):  # else the relaxation's pose is exact
        xyz, quat = polish(grammar, st, cand, top_rule, bound, deadline)
        xyz, quat = _better_pose(grammar, st, cand, top_rule, bound, terms, (xyz, quat))
    xyz, quat = _snap(terms, xyz, quat, t, q)
    if np.any(terms.revolute):
        edges = local_edges(grammar, st, cand, top_rule, bound)
        xyz, quat = _revolute_search(grammar, terms, edges, xyz, quat, deadline)
    bound = SetBound(columns, assignment, upper, xyz, quat, *_placed(parent))
    implied = _implied_rows(grammar, cand, e, top_rule, parent, len(columns))
    return _with_implied(bound, implied), rows


FREE = FREE_CHILD  # a free row's columns: any candidate child, scored exactly


def _implied_rows(grammar, cand, e, top_rule, parent, n_cols):  # type: ignore[no-untyped-def]
    """The set's poses implied by an optional observed member (`candidate_poses`), as rows
    whose children the MILP chooses freely at their exact scores: a tree with such a member
    on has its set at one of these poses, so the assignments (bounded with every optional
    member's constraint dropped) and these rows hold every tree.  Their `upper` is the set's
    own edge at its parent's pose, exact, or its rule's supremum when that pose is unknown."""
    xyz, quat = cand.xyz[e], cand.quat[e]
    n = len(xyz)
    rule = grammar.rules[top_rule]
    if parent is False:
        upper = np.full(n, rule.translation.supremum() + rule.rotation.supremum())
    else:
        px, pq = parent if parent is not None else (np.zeros(3), IDENTITY)
        rules = np.full(n, top_rule)
        upper = translation_log_density(
            grammar, rules, np.tile(px, (n, 1)), np.tile(pq, (n, 1)), xyz
        )
        upper = upper + rotation_log_density(grammar, rules, np.tile(pq, (n, 1)), quat)
    return np.full((n, n_cols), FREE, np.int64), upper, xyz.copy(), quat.copy()


def _with_implied(bound: SetBound, rows) -> SetBound:  # type: ignore[no-untyped-def]
    assignment, upper, xyz, quat = rows
    if not len(upper):
        return bound
    cat = np.concatenate
    free = cat([bound.free_rows, np.ones(len(upper), bool)])
    return SetBound(
        bound.slots,
        cat([bound.assignment, assignment]),
        cat([bound.upper, upper]),
        cat([bound.xyz, xyz]),
        cat([bound.quat, quat]),
        bound.parent,
        bound.decoupled,
        free,
    )


REVOLUTE_GRID = 48  # angles tried along a revolute law's arc, then as many around the best
REVOLUTE_LEVELS = 4  # grids, each 24 times finer: the last step is ~1e-6 of the arc


def _revolute_search(grammar, terms, edges, xyz, quat, deadline=None):  # type: ignore[no-untyped-def]
    """For rows held to a revolute family, the best rotation along its arc under the exact
    densities (a grid, then a finer grid around its best point), each with its best position;
    a row keeps its pose unless the search finds a better one.  The Newton polish cannot move
    along the arc: off it the law's density is -inf.  Past the deadline the search stops, at
    any grid point (the pose found so far stands: the bound does not depend on it); the first
    grid alone took 0.3 s of CPU on a random latent grammar's rows."""
    rows = np.flatnonzero(terms.revolute)
    owner = np.where(edges.p_block >= 0, edges.p_block, edges.c_block)
    sub, _ = _sub_edges(edges, owner, rows)
    sub_owner = np.where(sub.p_block >= 0, sub.p_block, sub.c_block)
    part = _subset(terms, terms.revolute)
    best_x, best_q = xyz[rows].copy(), quat[rows].copy()
    best_v = _owned_values(grammar, sub, sub_owner, best_x, best_q)
    lo, hi = part.arc[:, 0], part.arc[:, 1]
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    for width in (2.0 / REVOLUTE_GRID) ** np.arange(REVOLUTE_LEVELS):
        psi0 = centre.copy()  # a grid that finds nothing better keeps its centre
        for f in np.linspace(-1.0, 1.0, REVOLUTE_GRID):
            if past(deadline):
                break
            psi = np.clip(centre + f * half * width, lo, hi)
            q = _arc_point(part, psi)
            # the relaxation's best position for this rotation (exact where every
            # translation term is; with a steep stand-in for a fixed child offset, within
            # ~1e-7 m of the child's place), and else also the best position so far
            t_best = _h_and_gradient(part, np.einsum("na,nb->nab", q, q))[2]
            for t in (t_best,) if part.t_complete else (t_best, best_x):
                t = part.onto_planes(t)
                t = np.clip(t, part.lo + SNAP_MARGIN, np.maximum(part.hi - SNAP_MARGIN, part.lo))
                v = _owned_values(grammar, sub, sub_owner, t, q)
                better = v > best_v
                best_v = np.where(better, v, best_v)
                best_x = np.where(better[:, None], t, best_x)
                best_q = np.where(better[:, None], q, best_q)
                psi0 = np.where(better, psi, psi0)
        centre = np.where(np.isfinite(best_v), psi0, centre)
        if past(deadline):
            break
    xyz, quat = xyz.copy(), quat.copy()
    xyz[rows], quat[rows] = best_x, best_q
    return xyz, quat


def _better_pose(grammar, st, cand, top_rule, bound, terms, polished):  # type: ignore[no-untyped-def]
    """Per row, the polished pose or the relaxation's (`bound.xyz`, `bound.quat`), both made
    feasible (`_snap`), whichever scores higher exactly: Newton on the exact densities can
    leave a box optimum the relaxation found (a pinned rotation under a turned anisotropic
    Normal and an active box)."""
    edges = local_edges(grammar, st, cand, top_rule, bound)
    owner = np.where(edges.p_block >= 0, edges.p_block, edges.c_block)
    t, q = bound.xyz, bound.quat
    poses = [_snap(terms, *polished, t, q), _snap(terms, t, q, t, q)]
    values = [_owned_values(grammar, edges, owner, x, r) for x, r in poses]
    keep = ~(values[1] > values[0])
    xyz = np.where(keep[:, None], poses[0][0], poses[1][0])
    return xyz, np.where(keep[:, None], poses[0][1], poses[1][1])


def _placed(parent):  # type: ignore[no-untyped-def]
    """SetBound's (parent, decoupled) from `known_parent`'s answer (False: not known)."""
    return (None, True) if parent is False else (parent, False)


SNAP_MARGIN = BOX_MARGIN  # an exact position goes inside the laws' own box


def _snap(terms: _Terms, xyz: FloatArray, quat: FloatArray, t0: FloatArray, q0: FloatArray):  # type: ignore[no-untyped-def]
    """The polished poses made to satisfy the hard constraints: a pinned rotation exactly,
    the position inside its box, and, when the relaxation holds every translation term
    exactly, the best position for the final rotation."""
    bad = ~(np.all(np.isfinite(xyz), axis=1) & np.all(np.isfinite(quat), axis=1))
    xyz = np.where(bad[:, None], t0, xyz)
    quat = np.where(bad[:, None], q0, quat)
    quat = np.where(terms.pinned[:, None], np.nan_to_num(terms.pin), quat)
    if terms.t_complete:
        xyz = best_position(terms, quat)
    xyz = terms.onto_planes(xyz)  # a pinned Normal axis holds exactly (its plane)
    lo, hi = terms.lo + SNAP_MARGIN, terms.hi - SNAP_MARGIN
    with np.errstate(invalid="ignore"):  # -inf + inf on an unbounded axis: never used
        mid = 0.5 * (terms.lo + terms.hi)
    lo, hi = np.where(lo <= hi, lo, mid), np.where(lo <= hi, hi, mid)
    return np.clip(xyz, lo, hi), quat_normalize(quat)


def local_edges(
    grammar: Grammar, st: Supertree, cand: Candidates, top_rule: int, bound: SetBound
) -> PoseEdges:
    """The edges whose densities move with the set's pose, one block per assignment: its own
    rule at its parent's pose, and each named child at its candidate pose."""
    n = len(bound.assignment)
    px, pq = bound.parent if bound.parent is not None else (np.zeros(3), IDENTITY)
    own = 0 if bound.decoupled else n  # a decoupled set's own rule is not scored here
    rule, pb, pxyz, pquat = (
        [np.full(own, top_rule)],
        [np.full(own, -1)],
        [np.tile(px, (own, 1))],
        [np.tile(pq, (own, 1))],
    )
    cb, cxyz, cquat = [np.arange(own)], [np.zeros((own, 3))], [np.tile(IDENTITY, (own, 1))]
    world = own_world_edge(grammar, top_rule) if bound.decoupled else None
    if world is not None:  # its world-frame parts, scored against the set itself
        rule.append(np.full(n, top_rule))
        pb.append(np.arange(n))
        pxyz.append(np.tile(world[0], (n, 1)))
        pquat.append(np.tile(world[1], (n, 1)))
        cb.append(np.arange(n))
        cxyz.append(np.zeros((n, 3)))
        cquat.append(np.tile(IDENTITY, (n, 1)))
    for k, (v, r, e_c) in enumerate(bound.slots):
        rows = np.flatnonzero(bound.assignment[:, k] >= 0)  # -1: no child in this column
        idx = bound.assignment[rows, k]
        rule.append(np.full(len(rows), r))
        pb.append(rows)
        pxyz.append(np.tile(st.offset_xyz[v], (len(rows), 1)))
        pquat.append(np.tile(st.offset_quat[v], (len(rows), 1)))
        cb.append(np.full(len(rows), -1))
        cxyz.append(cand.xyz[e_c][idx].reshape(-1, 3))
        cquat.append(cand.quat[e_c][idx].reshape(-1, 4))
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
    return edges


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
    edges = local_edges(grammar, st, cand, top_rule, bound)
    return maximize_independent(grammar, edges, bound.xyz, bound.quat, deadline=deadline)


class AssignmentReduction:
    """The assignment model (`assignment_problem`), for latent grammars whose latent sets all
    have assignments (`set_bounds`), within the unrolled model's MAX_INSTANCES."""

    def accepts(self, request: Request) -> bool:
        if request.bounds is None or certify_only(request.bounds):
            return False
        return self._count(request) <= MAX_INSTANCES

    def refusal(self, request: Request) -> str | None:
        if request.bounds is None or certify_only(request.bounds):
            return None
        if self._count(request) <= MAX_INSTANCES:
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
        restricted = frozenset(e for e, b in request.bounds.items() if not np.any(b.free_rows))
        return instance_count(request.supertree, posed, restricted)


def certify_only(bounds: dict[int, SetBound]) -> bool:
    """Whether some set's bound was made without its parent's pose (a latent set placed
    relative to another latent set): the bounds then certify, but their poses are not the
    exact best, so the tree comes from proposals and refinement (`ip`)."""
    return any(b.decoupled for b in bounds.values())


MAX_POSE_PROPOSALS = 200  # assignment poses offered to `ip` per set, best bounds first


def add_assignment_poses(cand: Candidates, bounds: dict[int, SetBound]) -> None:
    """Offer each set's assignment poses (the best bounds first) as proposals: a box or
    revolute law holds them where rule-inversion proposals may not reach."""
    for e, sb in bounds.items():
        best = np.argsort(-sb.upper, kind="stable")[:MAX_POSE_PROPOSALS]
        if len(best):
            cand.add(e, sb.xyz[best], sb.quat[best])


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
    }  # a free row (FREE) leaves its children to the MILP

    def adjust(inst: Instances) -> None:
        set_of = st.set_of[inst.st_node]
        for e, sb in bounds.items():
            heads = np.flatnonzero((set_of == e) & (inst.top == np.arange(len(set_of))))
            inst.score[heads] = sb.upper[inst.cand_k[heads]]
        parent_set = set_of[np.maximum(inst.parent, 0)]
        head = inst.top == np.arange(len(set_of))
        counted = (inst.parent >= 0) & np.isin(parent_set, list(bounds)) & (parent_set != set_of)
        parent_row = inst.cand_k[inst.top[np.maximum(inst.parent, 0)]]
        for e, sb in bounds.items():  # a free row's children are scored exactly, not bounded
            of_e = counted & (parent_set == e)
            counted[of_e] = ~sb.free_rows[parent_row[of_e]]
        counted &= ~(head & np.isin(set_of, list(bounds)))  # a latent child's bound holds it
        # The assignment's bound already counts these edges.  Each named child keeps a share
        # of it, its exact edge at the row's pose where positive (else 0), taken from the
        # head: with every named child present the head and its children add up to the bound
        # (each tree has that encoding, so the bound holds), and a row whose optional child is
        # left out (attached elsewhere) loses the child's share instead of counting it twice.
        share = inst.score[counted]
        share = np.where(np.isfinite(share) & (share > 0.0), share, 0.0)
        np.subtract.at(inst.score, inst.top[inst.parent[counted]], share)
        inst.score[counted] = share

    return reduce_posed(grammar, st, scene, posed, adjust if upper else None, restrict, deadline)
