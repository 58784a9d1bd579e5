"""Continuous pose optimisation with the tree structure fixed (thesis 3.6.1, "refinement").

A latent pose (a node of a constituency grammar that no observation pins down) enters the score
only through the rule log-densities of the edges that touch it.  `PoseEdges` lists those edges;
each end is either a fixed pose or a pose attached, by a fixed offset, to one of B free *block*
poses.  `maximize` moves the blocks to maximise the sum of the edge log-densities with scipy's
L-BFGS, using the grammar's own density code (`ssgc.rules`) so that refinement and scoring can
never disagree.

The gradient is a central difference taken for every block at once: for each of the 6 pose
coordinates, all blocks are moved together, first on the parent end of every edge only and then
on the child end only.  Each edge's change is then the partial derivative with respect to the
block on that end, so 24 evaluations give the whole gradient whatever B is; they are stacked
into one vectorised call.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from ssgc.geometry import (
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
)
from ssgc.ir import Grammar
from ssgc.laws.base import Frame
from ssgc.laws.position_box import BoxTranslation
from ssgc.laws.rotation_revolute import RevoluteRotation
from ssgc.parse.hard_laws import PinGroup, parallel_pin_groups, turn_pins_parallel
from ssgc.rules import rotation_log_density, translation_log_density
from ssgc.tree import Trees

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
STEP = 1e-6  # finite-difference step: meters and radians
PENALTY = 1e30  # the cost of a point outside every rule's support


@dataclass(frozen=True)
class PoseEdges:
    """Edges whose log-density depends on free block poses.

    `p_block[m] >= 0`: the parent end is block p_block[m] composed with the offset
    (p_xyz[m], p_quat[m]); `p_block[m] == -1`: (p_xyz[m], p_quat[m]) is the parent's fixed pose.
    The same holds for the child end.
    """

    rule: IntArray
    p_block: IntArray
    p_xyz: FloatArray
    p_quat: FloatArray
    c_block: IntArray
    c_xyz: FloatArray
    c_quat: FloatArray


def is_fixed(grammar: Grammar, rules: IntArray) -> NDArray[np.bool_]:
    return grammar.tables.point[rules]


@dataclass(frozen=True)
class Links:
    """Blocks whose position follows from a neighbour's pose through a fixed-offset edge
    (`same`, `offset`) whose rotation is free: block[k] is placed by edge[k], as that edge's
    child when as_child[k], else as its parent, after every block of a lower level[k]; arm[k]
    is the child end's position in the parent block's frame (the parent end's offset plus
    the rule's offset turned by it).  group and rank (per block, -1 outside a linked group)
    number the groups and each group's blocks, for the Jacobian (`_placed_jacobian`).

    Why: such an edge is a hard equality between two blocks (or a block and a fixed pose).
    Moving either block alone leaves the law's support, so L-BFGS never moved them and the
    pose stayed where rule inversion put it (a chain L1 -same-> L2 -offset-> observed B,
    both rotations uniform, kept L1 150 nats below its best).  A placed block keeps its
    rotation as a variable and takes its position from the link, so the chain moves as one.
    """

    block: IntArray
    edge: IntArray
    as_child: NDArray[np.bool_]
    arm: FloatArray
    level: IntArray
    group: IntArray
    rank: IntArray


def no_links(n_blocks: int) -> Links:
    empty = np.zeros(0, np.int64)
    none = np.full(n_blocks, -1, np.int64)
    return Links(empty, empty, np.zeros(0, bool), np.zeros((0, 3)), empty, none, none)


NO_LINKS = no_links(0)


def tied_links(grammar: Grammar, edges: PoseEdges, n_blocks: int) -> Links:
    """The links of `Links` for the blocks of `edges`.

    The edges whose translation is a fixed offset join blocks into groups (a forest: blocks
    partition a tree).  A group with one such edge to a fixed pose is placed from it; a
    group with none from its first block, whose position stays a variable; a group with
    two or more is over-determined and left as it was (no block of it placed)."""
    law = [grammar.rules[int(r)].translation for r in edges.rule]
    tied = np.flatnonzero([t.point is not None for t in law])
    tied = tied[(edges.p_block[tied] >= 0) | (edges.c_block[tied] >= 0)]
    if len(tied) == 0:
        return no_links(n_blocks)
    group = np.arange(n_blocks)

    def find(b: int) -> int:
        while group[b] != b:
            b = int(group[b])
        return b

    for m in tied:
        pb, cb = int(edges.p_block[m]), int(edges.c_block[m])
        if pb >= 0 and cb >= 0:
            group[find(pb)] = find(cb)
    roots = np.array([find(b) for b in range(n_blocks)], np.int64)
    return _placement(grammar, edges, tied, roots)


def _placement(grammar: Grammar, edges: PoseEdges, tied: IntArray, roots: IntArray) -> Links:
    """Each group's blocks in the order a breadth-first walk from its anchor reaches them,
    with their depth in the walk (the anchor 0, placed from its fixed pose or not at all)."""
    own = np.where(edges.p_block >= 0, edges.p_block, edges.c_block)  # an edge's block end
    fixed_end = (edges.p_block[tied] < 0) | (edges.c_block[tied] < 0)
    anchors, between = tied[fixed_end], tied[~fixed_end]
    n_fixed = np.bincount(roots[own[anchors]], minlength=len(roots))
    order: list[tuple[int, int, int]] = []  # (block, edge that places it, depth)
    group, rank = np.full(len(roots), -1, np.int64), np.full(len(roots), -1, np.int64)
    n_groups = 0
    for root in np.unique(roots):
        if n_fixed[root] > 1:
            continue
        start = int(root)
        if n_fixed[root] == 1:
            m = int(anchors[roots[own[anchors]] == root][0])
            start = int(own[m])
            order.append((start, m, 0))
        walked = _walk(edges, between, start)
        if not walked and n_fixed[root] == 0:
            continue  # a lone block: nothing to place
        members = [start] + [b for b, _, _ in walked]
        group[members], rank[members] = n_groups, np.arange(len(members))
        n_groups += 1
        order += walked
    order.sort(key=lambda o: o[2])  # stable: within a level, any order
    block = np.array([o[0] for o in order], np.int64)
    edge = np.array([o[1] for o in order], np.int64)
    offset = [grammar.rules[int(r)].translation.point for r in edges.rule[edge]]
    arm = edges.p_xyz[edge] + quat_rotate(edges.p_quat[edge], np.reshape(offset, (-1, 3)))
    level = np.array([o[2] for o in order], np.int64)
    as_child = edges.c_block[edge] == block
    return Links(block, edge, as_child, arm.reshape(-1, 3), level, group, rank)


def _walk(edges: PoseEdges, between: IntArray, start: int) -> list[tuple[int, int, int]]:
    """(block, edge, depth) for the blocks reached from `start` over the edges `between`,
    breadth first: each is placed by the edge that reached it."""
    seen, frontier, out = {start}, [(start, 0)], []
    for b, depth in frontier:  # grows while walked
        for m in between[(edges.p_block[between] == b) | (edges.c_block[between] == b)]:
            other = int(edges.c_block[m] if edges.p_block[m] == b else edges.p_block[m])
            if other not in seen:
                seen.add(other)
                frontier.append((other, depth + 1))
                out.append((other, int(m), depth + 1))
    return out


def placed(edges: PoseEdges, links: Links, bx: FloatArray, bq: FloatArray) -> FloatArray:
    """Block positions (..., B, 3) with the linked blocks moved to where their links put
    them, at rotations bq (..., B, 4): level by level, each level at once."""
    x = bx.copy()
    for level in np.unique(links.level):
        k = np.flatnonzero(links.level == level)
        d, m = links.block[k], links.edge[k]
        pb, cb = np.maximum(edges.p_block[m], 0), np.maximum(edges.c_block[m], 0)
        turned_c = quat_rotate(bq[..., d, :], edges.c_xyz[m])
        # as a child: x_d + R_d c = x_p + R_p arm
        from_parent = x[..., pb, :] + quat_rotate(bq[..., pb, :], links.arm[k]) - turned_c
        # as a parent: the child end, fixed or a block, sits at x_d + R_d arm
        child_end = x[..., cb, :] + quat_rotate(bq[..., cb, :], edges.c_xyz[m])
        child_end = np.where((edges.c_block[m] >= 0)[:, None], child_end, edges.c_xyz[m])
        from_child = child_end - quat_rotate(bq[..., d, :], links.arm[k])
        x[..., d, :] = np.where(links.as_child[k][:, None], from_parent, from_child)
    return x


def log_quat(q: FloatArray) -> FloatArray:
    """The rotation vector of unit quaternions q (`exp_quat`'s inverse, the shorter turn)."""
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0)
    return scale * q[..., 1:]


def exp_quat(w: FloatArray) -> FloatArray:
    """The unit quaternion of rotation vector w (angle |w| about w / |w|)."""
    angle = np.linalg.norm(w, axis=-1, keepdims=True)
    half = 0.5 * angle
    scale = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-300), 0.5)
    return np.concatenate([np.cos(half), scale * w], axis=-1)


def _end(block: IntArray, xyz: FloatArray, quat: FloatArray, bx: FloatArray, bq: FloatArray):  # type: ignore[no-untyped-def]
    """World pose of one end of every edge, given the block poses."""
    on = (block >= 0)[:, None]
    b = np.maximum(block, 0)
    t = np.where(on, bx[b] + quat_rotate(bq[b], xyz), xyz)
    q = np.where(on, quat_multiply(bq[b], quat), quat)
    return t, q


def edge_log_density(
    grammar: Grammar,
    edges: PoseEdges,
    parent_blocks: tuple[FloatArray, FloatArray],
    child_blocks: tuple[FloatArray, FloatArray],
) -> FloatArray:
    pt, pq = _end(edges.p_block, edges.p_xyz, edges.p_quat, *parent_blocks)
    ct, cq = _end(edges.c_block, edges.c_xyz, edges.c_quat, *child_blocks)
    return translation_log_density(grammar, edges.rule, pt, pq, ct) + rotation_log_density(
        grammar, edges.rule, pq, cq
    )


def _moved(x0: FloatArray, q0: FloatArray, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    return x0 + theta[:, :3], quat_multiply(q0, exp_quat(theta[:, 3:]))


def _variants(n_blocks: int, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Parent-end and child-end block offsets of the 25 evaluations: the point itself, then
    +-STEP on each coordinate, on the parent ends only and on the child ends only."""
    p_theta, c_theta = [theta], [theta]
    for j in range(6):
        step = np.zeros_like(theta)
        step[:, j] = STEP
        p_theta += [theta + step, theta - step, theta, theta]
        c_theta += [theta, theta, theta + step, theta - step]
    return np.concatenate(p_theta), np.concatenate(c_theta)


def _tiled(edges: PoseEdges, n_blocks: int, copies: int) -> PoseEdges:
    """The edges repeated `copies` times, copy v pointing at blocks v*B .. v*B + B - 1."""
    shift = np.repeat(np.arange(copies) * n_blocks, len(edges.rule))

    def blocks(b: IntArray) -> IntArray:
        tiled = np.tile(b, copies)
        return np.where(tiled >= 0, tiled + shift, -1)

    return PoseEdges(
        rule=np.tile(edges.rule, copies),
        p_block=blocks(edges.p_block),
        p_xyz=np.tile(edges.p_xyz, (copies, 1)),
        p_quat=np.tile(edges.p_quat, (copies, 1)),
        c_block=blocks(edges.c_block),
        c_xyz=np.tile(edges.c_xyz, (copies, 1)),
        c_quat=np.tile(edges.c_quat, (copies, 1)),
    )


N_VARIANTS = 25


def _value_and_gradient(
    grammar: Grammar,
    tiled: PoseEdges,
    edges: PoseEdges,
    x0: FloatArray,
    q0: FloatArray,
    theta: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Per-edge log-densities at theta (B, 6) and the gradient of their sum, from one
    vectorised evaluation of all 25 variants."""
    n_blocks, m = len(x0), len(edges.rule)
    p_theta, c_theta = _variants(n_blocks, theta)
    x_all, q_all = np.tile(x0, (N_VARIANTS, 1)), np.tile(q0, (N_VARIANTS, 1))
    values = edge_log_density(
        grammar, tiled, _moved(x_all, q_all, p_theta), _moved(x_all, q_all, c_theta)
    ).reshape(N_VARIANTS, m)
    grad = np.zeros((n_blocks, 6))
    ends = ((edges.p_block, 1), (edges.c_block, 3))
    for j in range(6):
        for blocks, first in ends:
            hi, lo = values[1 + 4 * j + first - 1], values[1 + 4 * j + first]
            d = _difference(values[0], hi, lo)
            d = np.where((blocks >= 0) & np.isfinite(d), d, 0.0)
            grad[:, j] += np.bincount(np.maximum(blocks, 0), d, minlength=n_blocks)
    return values[0], grad


def _difference(mid: FloatArray, hi: FloatArray, lo: FloatArray) -> FloatArray:
    """Per edge, the central difference; one-sided where one side leaves the law's support
    (a box's face), so that a pose on the face still sees the slope on its inner side."""
    with np.errstate(invalid="ignore"):
        central = (hi - lo) / (2 * STEP)
        upper = (hi - mid) / STEP
        lower = (mid - lo) / STEP
    return np.where(np.isfinite(central), central, np.where(np.isfinite(upper), upper, lower))


def box_limits(
    grammar: Grammar, edges: PoseEdges, x0: FloatArray, q0: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(lo, hi), each (B, 3): the positions each block may take under the box laws of its
    edges whose other end is fixed (±inf elsewhere), with the block's rotation at q0.

    Why: a box law's density is flat inside and -inf outside, so an unconstrained optimiser
    stops where its next step would leave the box, short of the face where a Normal term pulls
    the exact optimum.  L-BFGS-B reaches the face when it is a bound."""
    n_blocks = len(x0)
    lo, hi = np.full((n_blocks, 3), -np.inf), np.full((n_blocks, 3), np.inf)
    table = grammar.tables.translation
    is_box = np.array([isinstance(r.translation, BoxTranslation) for r in grammar.rules], bool)
    rules = edges.rule
    _pin_limits(grammar, edges, q0, lo, hi)
    if not np.any(is_box[rules]):
        return lo, hi
    frame = table.frame[rules]
    for m in np.flatnonzero(is_box[rules]):
        law = grammar.rules[int(rules[m])].translation
        assert isinstance(law, BoxTranslation)
        pb, cb = int(edges.p_block[m]), int(edges.c_block[m])
        if cb >= 0 and pb < 0:  # the child moves: child position in [a, b]
            off = quat_rotate(q0[cb], edges.c_xyz[m])
            base = 0.0 if frame[m] == Frame.WORLD else edges.p_xyz[m]
            a, b = base + law.box.lo - off, base + law.box.hi - off
            lo[cb], hi[cb] = np.maximum(lo[cb], a), np.minimum(hi[cb], b)
        elif pb >= 0 and cb < 0 and frame[m] == Frame.WORLD_OFFSET:  # the parent moves
            off = quat_rotate(q0[pb], edges.p_xyz[m])
            a, b = edges.c_xyz[m] - law.box.hi - off, edges.c_xyz[m] - law.box.lo - off
            lo[pb], hi[pb] = np.maximum(lo[pb], a), np.minimum(hi[pb], b)
    return lo, hi


def _pin_limits(
    grammar: Grammar, edges: PoseEdges, q0: FloatArray, lo: FloatArray, hi: FloatArray
) -> None:
    """`box_limits` for the pinned axes of Normal laws (`pin`), in place: where a pinned
    axis, in the world, is a world axis (a world frame; a parent frame turned about it), the
    block's coordinate on that axis is held at the pin, as `lo == hi`.

    Why: off its pin a Normal's density is -inf, so a step of L-BFGS or Newton that moves a
    latent set off its pinned plane is rejected whole, and the set stayed where it was
    proposed (its free axes unrefined: a latent `Cluster` with a world Normal pinned in z
    kept the mean of its proposals, 4.7 nats below its best pose)."""
    for m in range(len(edges.rule)):
        law = grammar.rules[int(edges.rule[m])].translation
        free = getattr(law, "free", None)
        if free is None or np.all(free):
            continue
        pb, cb = int(edges.p_block[m]), int(edges.c_block[m])
        if (pb >= 0) == (cb >= 0) or (law.frame == Frame.WORLD and cb < 0):
            continue  # both ends move, or the law ignores the moving parent
        turn = np.eye(3)
        if law.frame == Frame.PARENT:
            pq = edges.p_quat[m] if pb < 0 else quat_multiply(q0[pb], edges.p_quat[m])
            turn = quat_to_matrix(pq)
        # the law's value u = turn^T (child - origin); pinned u_i = offset_i
        for i in np.flatnonzero(~np.asarray(free, bool)):
            n = turn[:, i]
            k = int(np.argmax(np.abs(n)))
            if abs(n[k]) < 1.0 - 1e-12:
                continue  # a plane across the world axes: not a bound
            if cb >= 0:  # the child moves: child_k = origin_k + sign * offset_i
                origin = np.zeros(3) if law.frame == Frame.WORLD else edges.p_xyz[m]
                off = quat_rotate(q0[cb], edges.c_xyz[m])
                at = origin[k] + np.sign(n[k]) * law.offset[i] - off[k]
                block = cb
            else:  # the parent moves: parent_k = child_k - sign * offset_i
                off = quat_rotate(q0[pb], edges.p_xyz[m])
                at = edges.c_xyz[m][k] - np.sign(n[k]) * law.offset[i] - off[k]
                block = pb
            lo[block, k], hi[block, k] = max(lo[block, k], at), min(hi[block, k], at)


def maximize(
    grammar: Grammar,
    edges: PoseEdges,
    x0: FloatArray,
    q0: FloatArray,
    max_iter: int = 200,
    deadline: float | None = None,
    links: Links = NO_LINKS,
) -> tuple[FloatArray, FloatArray]:
    """Block poses that locally maximise the summed edge log-densities, starting at (x0, q0).

    Linked blocks (`Links`) take their positions from their links, at every step.  Never
    worse than the start: if the optimiser ends lower (it can, on a flat or discontinuous
    law), the start is returned.  At the deadline (a `time.perf_counter()` value) it stops
    with the best point so far.
    """
    n_blocks = len(x0)
    if n_blocks == 0 or len(edges.rule) == 0:
        return x0, q0

    tiled = _tiled(edges, n_blocks, N_VARIANTS)
    turns = turning(grammar, edges, n_blocks)
    planes = NO_PLANES if len(links.block) else pin_planes(grammar, edges, n_blocks)

    def cost(flat: FloatArray) -> tuple[float, FloatArray]:
        theta = turns.body(flat.reshape(n_blocks, 6))
        if len(links.block):
            value, grad = _linked_value_and_gradient(grammar, tiled, edges, links, x0, q0, theta)
        elif len(planes.block):
            value, grad = _planed_value_and_gradient(grammar, tiled, edges, planes, x0, q0, theta)
        else:
            value, grad = _value_and_gradient(grammar, tiled, edges, x0, q0, theta)
        total = float(value.sum())
        if not np.isfinite(total):
            return PENALTY, np.zeros_like(flat)
        return -total, -turns.coordinates(grad).ravel()

    def stop_at_deadline(intermediate_result: object) -> None:
        if deadline is not None and time.perf_counter() >= deadline:
            raise StopIteration

    start = cost(np.zeros(6 * n_blocks))[0]
    res = minimize(
        cost,
        np.zeros(6 * n_blocks),
        jac=True,
        method="L-BFGS-B",
        bounds=_theta_bounds(grammar, edges, x0, q0, turns, links),
        callback=stop_at_deadline,
        options={"maxiter": max_iter, "ftol": 1e-12, "gtol": 1e-7},
    )
    if not np.isfinite(res.fun) or res.fun > start:
        if len(links.block) == 0:
            return x0, q0
        res.x = np.zeros(6 * n_blocks)  # the start, with its links closed
    bx, bq = _moved(x0, q0, turns.body(res.x.reshape(n_blocks, 6)))
    bq = quat_normalize(bq)
    return planes.place(placed(edges, links, bx, bq), bq)


@dataclass(frozen=True)
class PinPlanes:
    """Planes a block's position must lie on at its rotation, n·x = t, one per row k of
    block[k]: a pinned axis of a parent-frame Normal from the block to a fixed child (n =
    axis[k] turned by the block's end rotation q ⊗ end_quat[k], t = n·(child[k] - R(q)
    end_xyz[k]) - mean[k]), or, where axis[k] is -1, a pinned axis of the block's own rule
    from a fixed parent (n = normal[k], a world axis or the parent's axis, t = mean[k]).

    Why: a pin in the block's frame couples its rotation to its position.  Any turn of the
    block alone moved its child off the pin (density 0), so refinement kept the rotation the
    proposals gave: a latent shelf pinned in height, boxes pinned on it in its frame, parsed
    below its sampled tree.  A block with planes takes the pinned part of its position from
    them at every step (the least move onto them), as a linked block does from its link."""

    block: IntArray
    axis: IntArray
    normal: FloatArray
    end_xyz: FloatArray
    end_quat: FloatArray
    child: FloatArray
    mean: FloatArray
    # (block, end_quat, axis, child differences (k, 3), mean differences (k,)) of two or more
    # children pinned on one axis of one end: their planes are parallel only where that
    # axis, turned, is square to the differences (`hard_laws.turn_pins_parallel`)
    parallel: tuple[PinGroup, ...] = ()

    def place(self, x: FloatArray, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Poses (..., B, 3), (..., B, 4) moved the least onto their blocks' planes: each
        rotation turned so that its children's planes are parallel (two or more children
        pinned on one axis lie on one plane, a condition on the rotation), then each position
        moved onto the planes at that rotation."""
        q = q.copy()
        for b, end_quat, a, d, delta in self.parallel:
            q[..., b, :] = turn_pins_parallel(q[..., b, :], end_quat, a, d, delta)
        return self.project(x, q), q

    @cached_property
    def by_size(self) -> tuple[tuple[IntArray, IntArray], ...]:
        """(blocks (G,), their rows (G, k)) for each number k of planes a block has: the
        blocks with as many planes are projected together."""
        blocks, counts = np.unique(self.block, return_counts=True)
        out = []
        for k in np.unique(counts):
            same = blocks[counts == k]
            rows = [np.flatnonzero(self.block == b) for b in same]
            out.append((same, np.array(rows, np.int64).reshape(len(same), k)))
        return tuple(out)

    def project(self, x: FloatArray, q: FloatArray) -> FloatArray:
        """Positions (..., B, 3) moved the least onto their blocks' planes at rotations q."""
        if len(self.block) == 0:
            return x
        b = self.block
        qb = q[..., b, :]
        local = np.eye(3)[np.maximum(self.axis, 0)]
        turned = quat_rotate(quat_multiply(qb, self.end_quat), local)
        n = np.where((self.axis >= 0)[:, None], turned, self.normal)
        reach = self.child - quat_rotate(qb, self.end_xyz)
        pinned_t = np.sum(n * reach, axis=-1) - self.mean
        t = np.where(self.axis >= 0, pinned_t, self.mean)
        out = x.copy()
        for blocks, rows in self.by_size:  # n: (..., G, k, 3), x: (..., G, 3)
            nb, xb = n[..., rows, :], x[..., blocks, :]
            miss = t[..., rows] - np.einsum("...kj,...j->...k", nb, xb)
            out[..., blocks, :] = xb + np.einsum("...jk,...k->...j", np.linalg.pinv(nb), miss)
        return out


NO_PLANES = PinPlanes(
    *(np.zeros(0, np.int64),) * 2,
    *(np.zeros((0, 3)),) * 2,
    np.zeros((0, 4)),
    np.zeros((0, 3)),
    np.zeros(0),
)


def pin_planes(grammar: Grammar, edges: PoseEdges, n_blocks: int) -> PinPlanes:
    """`PinPlanes` of the blocks with a child pinned in their frame (none for the others:
    their pinned world axes are bounds, `_pin_limits`), with the pinned axes of their own
    rules from fixed parents (world, world-offset or the parent's frame)."""
    rows: list[tuple[int, int, FloatArray, FloatArray, FloatArray, FloatArray, float]] = []
    none = np.zeros(3)
    for m in range(len(edges.rule)):
        law = grammar.rules[int(edges.rule[m])].translation
        free = getattr(law, "free", None)
        pb, cb = int(edges.p_block[m]), int(edges.c_block[m])
        if free is None or np.all(free) or law.frame != Frame.PARENT or pb < 0 or cb >= 0:
            continue
        for a in np.flatnonzero(~np.asarray(free, bool)):
            c = edges.c_xyz[m]
            rows.append((pb, int(a), none, edges.p_xyz[m], edges.p_quat[m], c, law.offset[a]))
    if not rows:
        return NO_PLANES
    with_planes = {r[0] for r in rows}
    for m in range(len(edges.rule)):  # their own pinned axes, from a fixed parent
        law = grammar.rules[int(edges.rule[m])].translation
        free = getattr(law, "free", None)
        cb = int(edges.c_block[m])
        if free is None or cb not in with_planes or edges.p_block[m] >= 0:
            continue
        if np.any(edges.c_xyz[m] != 0):
            continue  # a member below the block's top: left to the bounds
        turn = quat_to_matrix(edges.p_quat[m]) if law.frame == Frame.PARENT else np.eye(3)
        origin = np.zeros(3) if law.frame == Frame.WORLD else edges.p_xyz[m]
        for k in np.flatnonzero(~np.asarray(free, bool)):
            n = turn[:, k]  # the law's value u = turnᵀ (x - origin); pinned u_k = offset_k
            t = float(n @ origin) + float(law.offset[k])
            rows.append((cb, -1, n, none, IDENTITY_QUAT, none, t))
    pinned = [(b, e_xyz, e_quat, a, c, t) for b, a, _, e_xyz, e_quat, c, t in rows if a >= 0]
    block, axis, normal, end_xyz, end_quat, child, mean = zip(*rows, strict=True)
    return PinPlanes(
        np.array(block, np.int64),
        np.array(axis, np.int64),
        np.array(normal, float),
        np.array(end_xyz, float),
        np.array(end_quat, float),
        np.array(child, float),
        np.array(mean, float),
        tuple(parallel_pin_groups(pinned)),
    )


IDENTITY_QUAT = np.array([1.0, 0.0, 0.0, 0.0])


def _planed_value_and_gradient(
    grammar: Grammar,
    tiled: PoseEdges,
    edges: PoseEdges,
    planes: PinPlanes,
    x0: FloatArray,
    q0: FloatArray,
    theta: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """`_value_and_gradient` with the blocks of `planes` projected onto them: the gradient at
    the projected poses, then, by the chain rule, through the projection (which depends on
    each block's own pose only), its Jacobian by central differences.  The point and its 12
    neighbours are placed in one call: placed one by one, they took most of refinement's
    time on a shelf of pinned boxes."""
    n_blocks, on = len(x0), np.unique(planes.block)
    j = np.arange(6)[:, None]
    step = np.zeros((6, n_blocks, 6))
    step[j, on, j] = STEP  # step j moves coordinate j of every block on planes
    thetas = np.concatenate([theta[None], theta + step, theta - step])  # (13, B, 6)
    s = len(thetas)
    sx, sq = _moved(np.tile(x0, (s, 1)), np.tile(q0, (s, 1)), thetas.reshape(-1, 6))
    sx, sq = planes.place(sx.reshape(s, n_blocks, 3), sq.reshape(s, n_blocks, 4))
    value, grad = _value_and_gradient(grammar, tiled, edges, sx[0], sq[0], np.zeros_like(theta))
    hi_x, hi_q, lo_x, lo_q = sx[1:7, on], sq[1:7, on], sx[7:, on], sq[7:, on]  # (6, blocks, .)
    dx = (hi_x - lo_x) / (2 * STEP)
    dw = log_quat(quat_multiply(quat_conjugate(lo_q), hi_q)) / (2 * STEP)  # in the body frame
    grad[on] = (np.sum(dx * grad[on, :3], axis=-1) + np.sum(dw * grad[on, 3:], axis=-1)).T
    return value, grad


def _linked_value_and_gradient(
    grammar: Grammar,
    tiled: PoseEdges,
    edges: PoseEdges,
    links: Links,
    x0: FloatArray,
    q0: FloatArray,
    theta: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """`_value_and_gradient` with the linked blocks placed: the gradient with every position
    held, plus, by the chain rule, what each variable moves through the placed positions."""
    x, q = _moved(x0, q0, theta)
    x = placed(edges, links, x, q)
    rotations_only = np.hstack([np.zeros((len(x0), 3)), theta[:, 3:]])
    value, grad = _value_and_gradient(grammar, tiled, edges, x, q0, rotations_only)
    var, dx = _placed_jacobian(edges, links, x0, q0, theta)
    moved = links.block
    pull = np.einsum("pkj,kj->pk", dx, grad[moved, :3])  # (perturbation, placed block)
    ok = var[0] >= 0
    np.add.at(grad, (var[0][ok], var[1][ok]), pull[ok])
    grad[moved, :3] = 0.0  # their own positions are not variables
    return value, grad


def _placed_jacobian(
    edges: PoseEdges, links: Links, x0: FloatArray, q0: FloatArray, theta: FloatArray
) -> tuple[tuple[IntArray, IntArray], FloatArray]:
    """How the placed positions move with each variable, by central differences (placing is
    cheap and smooth): ((block, coordinate) of the variable per perturbation and placed
    block, -1 where none), and d(position)/d(variable), (perturbations, placed blocks, 3).

    Groups are independent, so coordinate c of the r-th block of every group is perturbed
    at once: 12 placements per rank, however many groups there are."""
    n_blocks, in_group = len(x0), links.group >= 0
    n_rank = int(links.rank.max(initial=-1)) + 1
    member = np.full((int(links.group.max(initial=-1)) + 1, n_rank), -1, np.int64)
    member[links.group[in_group], links.rank[in_group]] = np.flatnonzero(in_group)
    rank, coord = np.repeat(np.arange(n_rank), 6), np.tile(np.arange(6), n_rank)
    n_pert = len(rank)
    step = np.zeros((n_pert, n_blocks, 6))
    hit = in_group[None, :] & (links.rank[None, :] == rank[:, None])
    step[hit, np.broadcast_to(coord[:, None], hit.shape)[hit]] = STEP
    thetas = np.concatenate([theta + step, theta - step]).reshape(-1, 6)
    sx, sq = _moved(np.tile(x0, (2 * n_pert, 1)), np.tile(q0, (2 * n_pert, 1)), thetas)
    sq = sq.reshape(2 * n_pert, n_blocks, 4)
    sx = placed(edges, links, sx.reshape(2 * n_pert, n_blocks, 3), sq)
    moved = links.block
    dx = (sx[:n_pert, moved] - sx[n_pert:, moved]) / (2 * STEP)
    var_block = member[links.group[moved][None, :], rank[:, None]]  # (perturbation, placed)
    return (var_block, np.broadcast_to(coord[:, None], var_block.shape)), dx


@dataclass(frozen=True)
class Turning:
    """How each block may turn without leaving its edges' rotation laws: a block's rotation
    variables are coordinates in its own body-frame basis (`basis[b]`, columns), and only the
    `free[b]` ones move.

    Why: off a point or an arc a rotation law's density is -inf.  A block with a fixed-rotation
    edge is held whole; a block whose revolute edges share one axis may still turn about it
    (each end keeps its angle on the arc), and only that turn is free.  Held whole, a latent
    table turned by a `revolute` about z stayed at its proposed angle, and the seats around
    it with it (a sampled scene parsed 30 nats below its own tree)."""

    basis: FloatArray  # (B, 3, 3)
    free: NDArray[np.bool_]  # (B, 3)

    def body(self, theta: FloatArray) -> FloatArray:
        """Block moves (B, 6) in body-frame rotation vectors, from basis coordinates."""
        turn = np.einsum("bij,bj->bi", self.basis, theta[:, 3:])
        return np.hstack([theta[:, :3], turn])

    def coordinates(self, grad: FloatArray) -> FloatArray:
        """A gradient (B, 6) w.r.t. body-frame moves, as one w.r.t. basis coordinates."""
        turn = np.einsum("bij,bi->bj", self.basis, grad[:, 3:])
        return np.hstack([grad[:, :3], turn])


def turning(grammar: Grammar, edges: PoseEdges, n_blocks: int) -> Turning:
    """`Turning` for the blocks of `edges`: a full-circle revolute edge's axis, turned into the
    block's frame by the end's offset (`end = block * offset`, so the end turns about the axis
    when the block turns about offset * axis), frees that turn; two axes that differ, a
    fixed-rotation edge, or a revolute range short of the circle (a turn would run off its
    end, where the density is -inf: the review found a seat left at its limit, 60 nats below
    its sampled tree) hold the block whole."""
    basis = np.broadcast_to(np.eye(3), (n_blocks, 3, 3)).copy()
    free = np.ones((n_blocks, 3), bool)
    axis = np.full((n_blocks, 3), np.nan)
    for m, r in enumerate(edges.rule):
        law = grammar.rules[int(r)].rotation
        revolute = isinstance(law, RevoluteRotation)
        if law.point is None and not revolute:
            continue
        ends = ((edges.p_block[m], edges.p_quat[m]), (edges.c_block[m], edges.c_quat[m]))
        for block, offset in ends:
            b = int(block)
            if b < 0 or not np.any(free[b]):
                continue
            if not revolute or law.revolute.hi - law.revolute.lo < 2.0 * np.pi - 1e-9:
                free[b] = False
                continue
            a = quat_rotate(offset, law.axis)
            if np.isnan(axis[b, 0]):
                axis[b] = a
            elif np.linalg.norm(np.cross(axis[b], a)) > 1e-9:
                free[b] = False
    turned = np.flatnonzero(~np.isnan(axis[:, 0]) & free[:, 0])
    for b in turned:
        basis[b] = _basis_from(axis[b])
        free[b] = [True, False, False]
    return Turning(basis, free)


def _basis_from(a: FloatArray) -> FloatArray:
    """An orthonormal basis (columns) whose first column is the unit vector a."""
    other = np.eye(3)[int(np.argmin(np.abs(a)))]
    e2 = np.cross(a, other)
    e2 /= np.linalg.norm(e2)
    return np.column_stack([a, e2, np.cross(a, e2)])


def _theta_bounds(
    grammar: Grammar,
    edges: PoseEdges,
    x0: FloatArray,
    q0: FloatArray,
    turns: Turning,
    links: Links = NO_LINKS,
) -> list[tuple[float | None, float | None]]:
    """L-BFGS-B's bounds on the blocks' moves: box laws on the positions (`box_limits`, never
    excluding the start); the rotation coordinates a block may not turn (`Turning`) stay, and
    so does a linked block's position variable (`Links`: its link places it)."""
    lo, hi = box_limits(grammar, edges, x0, q0)
    lo, hi = np.minimum(lo - x0, 0.0), np.maximum(hi - x0, 0.0)
    lo[links.block], hi[links.block] = 0.0, 0.0
    turn = np.where(turns.free, np.inf, 0.0)
    theta_lo = np.hstack([lo, np.broadcast_to(-turn, (len(x0), 3))]).ravel()
    theta_hi = np.hstack([hi, np.broadcast_to(turn, (len(x0), 3))]).ravel()
    return [
        (None if not np.isfinite(a) else float(a), None if not np.isfinite(b) else float(b))
        for a, b in zip(theta_lo, theta_hi, strict=True)
    ]


def maximize_independent(
    grammar: Grammar,
    edges: PoseEdges,
    x0: FloatArray,
    q0: FloatArray,
    max_iter: int = 50,
    deadline: float | None = None,
) -> tuple[FloatArray, FloatArray]:
    """`maximize` for blocks that share no edge (each edge touches one block): a damped Newton
    step per block, all blocks at once, with a finite-difference Hessian.

    Independent blocks (the pose proposals of one set) converge in a few Newton steps each,
    where one L-BFGS run over all of them would wait for the slowest.  A block's step is kept
    only if it raises that block's own value; otherwise its damping grows.
    """
    n_blocks = len(x0)
    if n_blocks == 0 or len(edges.rule) == 0:
        return x0, q0
    owner = np.where(edges.p_block >= 0, edges.p_block, edges.c_block)
    bx, bq = x0.copy(), quat_normalize(q0)
    current = _owned_values(grammar, edges, owner, bx, bq)
    damping = np.full(n_blocks, 1e-3)
    active = np.isfinite(current)
    lo, hi = box_limits(grammar, edges, bx, bq)
    limits = np.minimum(lo, bx), np.maximum(hi, bx)  # never excluding the start
    turns = turning(grammar, edges, n_blocks)
    for _ in range(max_iter):
        if not np.any(active) or (deadline is not None and time.perf_counter() >= deadline):
            break
        for start in range(0, int(active.sum()), NEWTON_CHUNK):  # bounded work per deadline check
            if start and deadline is not None and time.perf_counter() >= deadline:
                break
            idx = np.flatnonzero(active)[start : start + NEWTON_CHUNK]
            _newton_update(
                grammar, edges, owner, idx, bx, bq, current, damping, active, limits, turns
            )
    return snap_fixed_offsets(grammar, edges, bx, bq), bq


NEWTON_CHUNK = 512


def _newton_update(
    grammar: Grammar,
    edges: PoseEdges,
    owner: IntArray,
    idx: IntArray,
    bx: FloatArray,
    bq: FloatArray,
    current: FloatArray,
    damping: FloatArray,
    active: NDArray[np.bool_],
    limits: tuple[FloatArray, FloatArray],
    turns: Turning,
) -> None:
    """One damped Newton step on blocks idx, updating the arrays in place; positions stay
    within `limits` (the box laws', `box_limits`)."""
    sub, sub_owner = _sub_edges(edges, owner, idx)
    sub_turns = Turning(turns.basis[idx], turns.free[idx])
    tx, tq, predicted = _newton_step(grammar, sub, bx[idx], bq[idx], damping[idx], sub_turns)
    tx = np.clip(tx, limits[0][idx], limits[1][idx])
    trial = _owned_values(grammar, sub, sub_owner, tx, tq)
    now = current[idx]
    better = np.isfinite(trial) & (trial > now) & (predicted > 0)
    small = predicted <= 1e-12 * np.maximum(1.0, np.abs(now))
    moved = idx[better]
    bx[moved], bq[moved] = tx[better], quat_normalize(tq[better])
    current[moved] = trial[better]
    damping[idx] = np.where(better, np.maximum(damping[idx] / 3, 1e-9), damping[idx] * 4)
    converged = small | (better & (trial - now <= 1e-10 * np.maximum(1.0, np.abs(now))))
    active[idx[converged | (damping[idx] >= 1e8)]] = False


def _owned_values(
    grammar: Grammar, edges: PoseEdges, owner: IntArray, bx: FloatArray, bq: FloatArray
) -> FloatArray:
    v = edge_log_density(grammar, edges, (bx, bq), (bx, bq))
    return np.bincount(np.maximum(owner, 0), v, minlength=len(bx))


def _sub_edges(edges: PoseEdges, owner: IntArray, blocks: IntArray) -> tuple[PoseEdges, IntArray]:
    """The edges of the given blocks, with the blocks renumbered 0..len(blocks)-1.  A block
    may own no edge (it is only the child or parent of others' edges): every block number
    that appears is given a place."""
    arrays = (owner, blocks, edges.p_block, edges.c_block)
    top = max(int(a.max(initial=-1)) for a in arrays)  # a set may have no edge at all
    new = np.full(top + 1, -1, np.int64)
    new[blocks] = np.arange(len(blocks))
    keep = new[owner] >= 0

    def renumber(b: IntArray) -> IntArray:
        return np.where(b >= 0, new[np.maximum(b, 0)], -1)

    sub = PoseEdges(
        rule=edges.rule[keep],
        p_block=renumber(edges.p_block[keep]),
        p_xyz=edges.p_xyz[keep],
        p_quat=edges.p_quat[keep],
        c_block=renumber(edges.c_block[keep]),
        c_xyz=edges.c_xyz[keep],
        c_quat=edges.c_quat[keep],
    )
    return sub, new[owner[keep]]


def _newton_step(
    grammar: Grammar,
    edges: PoseEdges,
    bx: FloatArray,
    bq: FloatArray,
    damping: FloatArray,
    turns: Turning,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A Levenberg–Marquardt step per block: poses after it, and the first-order gain.
    Blocks turn only as `turns` lets them: the step is taken in their basis coordinates."""
    n_blocks = len(bx)
    g, hess = _gradient_and_hessian(grammar, edges, bx, bq)
    to_body = np.zeros((n_blocks, 6, 6))
    to_body[:, :3, :3] = np.eye(3)
    to_body[:, 3:, 3:] = turns.basis
    g = np.einsum("bij,bi->bj", to_body, g)
    hess = np.einsum("bki,bkl,blj->bij", to_body, hess, to_body)
    held = np.hstack([np.zeros((n_blocks, 3), bool), ~turns.free])
    g[held] = 0.0
    hess[np.broadcast_to(held[:, :, None], hess.shape)] = 0.0
    hess[np.broadcast_to(held[:, None, :], hess.shape)] = 0.0
    scale = np.maximum(np.abs(np.diagonal(hess, axis1=1, axis2=2)).max(axis=1), 1.0)
    lhs = -hess + (damping * scale)[:, None, None] * np.eye(6)
    delta = np.linalg.solve(lhs, g[:, :, None])[:, :, 0]
    delta = np.where(np.isfinite(delta), delta, 0.0)
    tx, tq = _moved(bx, bq, turns.body(delta))
    return tx, tq, np.einsum("ni,ni->n", g, delta)


HESSIAN_STEP = 1e-4  # the step of the Hessian's forward differences of the gradient


def _gradient_and_hessian(
    grammar: Grammar, edges: PoseEdges, bx: FloatArray, bq: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per block, the gradient (B, 6) and the symmetrised Hessian (B, 6, 6) by forward
    differences of the gradient, the point and its six moved copies in one evaluation (as
    seven calls, the per-call overhead was most of refinement's time on small sets)."""
    n_blocks = len(bx)
    steps = np.zeros((7, n_blocks, 6))
    steps[np.arange(1, 7), :, np.arange(6)] = HESSIAN_STEP
    px, pq = _moved(np.tile(bx, (7, 1)), np.tile(bq, (7, 1)), steps.reshape(-1, 6))
    px[:n_blocks], pq[:n_blocks] = bx, bq  # the point itself, unmoved
    copies = _tiled(edges, n_blocks, 7)  # copy v's edges point at copy v's blocks
    tiled = _tiled(copies, 7 * n_blocks, N_VARIANTS)
    zero = np.zeros((7 * n_blocks, 6))
    grads = _value_and_gradient(grammar, tiled, copies, px, pq, zero)[1].reshape(7, n_blocks, 6)
    hess = np.moveaxis((grads[1:] - grads[0]) / HESSIAN_STEP, 0, 2)  # [:, :, j] from step j
    return grads[0], 0.5 * (hess + np.swapaxes(hess, 1, 2))


def free_blocks(grammar: Grammar, tree: Trees) -> tuple[IntArray, IntArray]:
    """(top node of every node's set, the set tops whose pose no observation fixes).

    A node joins its parent's set when its rule is fixed; a set is free when none of its nodes
    is of an observed type and it is not the root's set.
    """
    n = len(tree)
    top = np.arange(n)
    fixed = np.zeros(n, bool)
    has_parent = tree.parent >= 0
    fixed[has_parent] = is_fixed(grammar, tree.rule[has_parent])
    for i in range(n):  # parents come first
        if fixed[i]:
            top[i] = top[tree.parent[i]]
    observed = np.zeros(n, bool)
    np.logical_or.at(observed, top, grammar.tables.type_observed[tree.type])
    tops = np.flatnonzero((top == np.arange(n)) & ~observed & has_parent)
    return top, tops


def snap_fixed_offsets(
    grammar: Grammar, edges: PoseEdges, bx: FloatArray, bq: FloatArray
) -> FloatArray:
    """Block positions moved so that each block's one fixed-offset edge to a fixed pose holds
    exactly.

    Why: the scorer accepts a fixed offset within POS_TOL, and the optimiser's finite
    differences (STEP = POS_TOL) use that slack to lean a latent block towards its other laws'
    modes.  The tree then scores a few 1e-6 nats above the exact optimum, i.e. above an exact
    bound (a false "better than certified").  The rotation is kept; only the slack goes."""
    law = [grammar.rules[int(r)].translation for r in edges.rule]
    fixed = np.array([t.point is not None for t in law], bool)
    one_end = (edges.p_block >= 0) != (edges.c_block >= 0)
    m = np.flatnonzero(fixed & one_end)
    if len(m) == 0:
        return bx
    off = np.array([law[i].point for i in m]).reshape(-1, 3)
    world = np.array([law[i].frame == Frame.WORLD for i in m], bool)
    px, pq = _end(edges.p_block[m], edges.p_xyz[m], edges.p_quat[m], bx, bq)
    cx, _ = _end(edges.c_block[m], edges.c_xyz[m], edges.c_quat[m], bx, bq)
    target = np.where(world[:, None], off, px + quat_rotate(pq, off))
    residual = cx - target  # the child end's error; the parent end moves the other way
    block = np.where(edges.c_block[m] >= 0, edges.c_block[m], edges.p_block[m])
    shift = np.where((edges.c_block[m] >= 0)[:, None], -residual, residual)
    once = np.bincount(block, minlength=len(bx)) == 1  # several such edges: left as they are
    keep = once[block]
    out = bx.copy()
    out[block[keep]] += shift[keep]
    return out


def refine_tree(
    grammar: Grammar, tree: Trees, max_iter: int = 200, deadline: float | None = None
) -> Trees:
    """The same tree with every free (latent) set pose moved to a local maximum of the score."""
    top, tops = free_blocks(grammar, tree)
    if len(tops) == 0:
        return tree
    block = np.full(len(tree), -1, np.int64)
    block[np.isin(top, tops)] = np.searchsorted(tops, top[np.isin(top, tops)])
    member = block >= 0
    # every member's pose in its block's frame
    tq = tree.quat[top]
    off_q = np.where(member[:, None], quat_multiply(quat_conjugate(tq), tree.quat), tree.quat)
    off_t = np.where(
        member[:, None], quat_rotate(quat_conjugate(tq), tree.xyz - tree.xyz[top]), tree.xyz
    )
    child = np.flatnonzero(tree.parent >= 0)
    par = tree.parent[child]
    touches = (block[child] >= 0) | (block[par] >= 0)
    inside = (block[child] == block[par]) & is_fixed(grammar, tree.rule[child])
    child, par = child[touches & ~inside], par[touches & ~inside]
    edges = PoseEdges(
        rule=tree.rule[child],
        p_block=block[par],
        p_xyz=off_t[par],
        p_quat=off_q[par],
        c_block=block[child],
        c_xyz=off_t[child],
        c_quat=off_q[child],
    )
    links = tied_links(grammar, edges, len(tops))
    bx, bq = maximize(grammar, edges, tree.xyz[tops], tree.quat[tops], max_iter, deadline, links)
    bx = snap_fixed_offsets(grammar, edges, bx, bq)
    xyz, quat = tree.xyz.copy(), tree.quat.copy()
    xyz[member], quat[member] = _end(block[member], off_t[member], off_q[member], bx, bq)
    return Trees(
        scene=tree.scene,
        type=tree.type,
        parent=tree.parent,
        rule=tree.rule,
        xyz=xyz,
        quat=quat,
        n_scenes=tree.n_scenes,
    )
