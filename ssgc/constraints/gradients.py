"""Each pose constraint's margin with its gradient w.r.t. node positions, and the thesis's
penalty on it, for the gradient-based samplers (`ssgc.sample.hmc`, `ssgc.sample.project`).

- `inside_box`, `clearance`: exact gradients (`InsideBox.gradient`, `Clearance.gradient`).
- `upright`: a function of rotations only, so its gradient w.r.t. positions is zero; the
  samplers move rotations with proposals that do not need a gradient.
- `non_penetration`: FCL gives distances, not their derivatives; the gradient is a central
  difference of each tree's closest pair's distance (the pair that makes its margin) in the
  positions and turns of that pair's two nodes, every tree of the batch at once: 12 (24 with
  turns) distance evaluations of one pair per tree, where differencing the whole margin
  re-measured every pair for every node (26 s for one gradient of a batch of sink scenes).

A tree's margin is a minimum over nodes or pairs, so its gradient is that of the minimising
term (a subgradient at ties).  The penalty is thesis 2.4.1's log N(min(C, 0); 0, ε), with ε
the standard deviation (as in the Pyro code the thesis used), up to its constant.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from ssgc.constraints.base import Constraint, FloatArray, nearest_ancestor, per_scene_argmin
from ssgc.constraints.penetration import NonPenetration
from ssgc.constraints.pose import Clearance, InsideBox, Upright
from ssgc.geometry import quat_multiply, quat_rotate

FD_STEP = 1e-5  # m
FD_ANGLE = 1e-6  # rad


def margin_gradient(c: Constraint, batch: Any) -> tuple[FloatArray, FloatArray]:
    """(margins (n_scenes,), d margin / d xyz (n_nodes, 3)), rotations held."""
    if isinstance(c, InsideBox | Clearance):
        return c.gradient(batch)
    if isinstance(c, Upright):
        return c.margin(batch), np.zeros((len(batch.type), 3))
    if isinstance(c, NonPenetration):
        m, g_xyz, _ = closest_pair_gradient(c, batch, turns=False)
        return m, g_xyz
    raise TypeError(f"no gradient for constraint kind '{c.word}'")


def closest_pair_gradient(
    c: NonPenetration, batch: Any, turns: bool = True
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(margins, d margin / d xyz, d margin / d ω) of a `non_penetration` margin: central
    differences of each tree's closest pair's distance in the positions (and, with `turns`,
    small world-frame turns) of that pair's two nodes, all trees at once."""
    m, a, b = c.closest_pairs(batch)
    g_xyz, g_rot = np.zeros((len(batch.type), 3)), np.zeros((len(batch.type), 3))
    for nodes in (a, b):
        for axis in range(3):
            g_xyz[nodes, axis] = _pair_difference(c, batch, a, b, nodes, axis, turn=False)
            if turns:
                g_rot[nodes, axis] = _pair_difference(c, batch, a, b, nodes, axis, turn=True)
    return m, g_xyz, g_rot


def _small_turn(axis: int, sign: float) -> FloatArray:
    """The quaternion of a turn by ±FD_ANGLE about a world axis."""
    q = np.zeros(4)
    q[0], q[1 + axis] = np.cos(FD_ANGLE / 2), sign * np.sin(FD_ANGLE / 2)
    return q


def _pair_difference(
    c: NonPenetration, batch: Any, a: Any, b: Any, nodes: Any, axis: int, turn: bool
) -> FloatArray:
    """Central difference of the distances of pairs (a, b) when `nodes` move along, or turn
    about, the world `axis`."""
    diff = np.zeros(len(a))
    for sign in (1.0, -1.0):
        if turn:
            quat = batch.quat.copy()
            quat[nodes] = quat_multiply(_small_turn(axis, sign), quat[nodes])
            moved = replace(batch, quat=quat)
        else:
            xyz = batch.xyz.copy()
            xyz[nodes, axis] += sign * FD_STEP
            moved = replace(batch, xyz=xyz)
        diff += sign * c.distances_of(moved, a, b)
    return diff / (2 * (FD_ANGLE if turn else FD_STEP))


def penalty_gradient(
    constraints: list[Constraint], batch: Any, eps: float
) -> tuple[FloatArray, FloatArray, dict[str, FloatArray]]:
    """(log-penalty per tree, its gradient w.r.t. xyz, each constraint's margins):
    sum over constraints of -min(C, 0)² / (2 ε²)."""
    total = np.zeros(batch.n_scenes)
    grad = np.zeros((len(batch.type), 3))
    margins = {}
    for c in constraints:
        m, g = margin_gradient(c, batch)
        margins[c.name] = m
        short = np.where(np.isfinite(m), np.minimum(m, 0.0), 0.0)
        total -= short**2 / (2 * eps**2)
        grad -= (short / eps**2)[batch.scene][:, None] * g
    return total, grad, margins


def element_gradients(c: Constraint, tree: Any) -> tuple[FloatArray, FloatArray]:
    """For one tree: every term the margin is the minimum of (a pair's gap, a node's distance
    to a box face), and each term's gradient w.r.t. xyz, (K,) and (K, n_nodes, 3); smooth
    where the minimum is not, for constrained optimisers.  Kinds without terms give their
    margin as the one term."""
    n = len(tree.type)
    if isinstance(c, Clearance):
        i, j = c.pairs(tree)
        dx = tree.xyz[i, :2] - tree.xyz[j, :2]
        d = np.hypot(dx[:, 0], dx[:, 1])
        gap = d - c.radius[tree.type[i]] - c.radius[tree.type[j]]
        jac = np.zeros((len(i), n, 3))
        unit = dx / np.maximum(d, 1e-300)[:, None]
        k = np.arange(len(i))
        jac[k, i, :2] = unit
        jac[k, j, :2] -= unit
        return gap, jac
    if isinstance(c, InsideBox):
        nodes, q, ok, gaps = c._gaps(tree)
        face_node, face = np.nonzero(~np.isnan(gaps) & ok[:, None])
        value = gaps[face_node, face]
        axis, sign = face % 3, np.where(face < 3, 1.0, -1.0)
        direction = _rotate_axes(q[face_node], axis) * sign[:, None]
        jac = np.zeros((len(value), n, 3))
        k = np.arange(len(value))
        jac[k, nodes[face_node]] = direction
        if c.frame is not None:
            from ssgc.constraints.base import nearest_ancestor

            anc = nearest_ancestor(tree.parent, tree.type, c.frame, nodes[face_node])
            jac[k, anc] -= direction
        return value, jac
    m, g = margin_gradient(c, tree)
    return np.where(np.isfinite(m), m, 1.0), g[None]


def _rotate_axes(q: FloatArray, axis: Any) -> FloatArray:
    from ssgc.geometry import quat_rotate

    return quat_rotate(q, np.eye(3)[axis])


# ------------------------------------------------------------- with rotations moving ---
#
# A rotation's gradient is a torque: for every node, d margin / d ω, where ω is a small
# world-frame rotation applied to that node's orientation alone, its position and every other
# pose held (q -> exp(ω) ⊗ q).  `ssgc.sample.poses.pullback_poses` carries torques and position
# gradients to the law coordinates of the rotations.


def pose_gradient(c: Constraint, batch: Any) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(margins (n_scenes,), d margin / d xyz (n_nodes, 3), d margin / d ω (n_nodes, 3))."""
    n = len(batch.type)
    if isinstance(c, InsideBox):
        return _inside_box_gradient(c, batch)
    if isinstance(c, Clearance):
        m, g = c.gradient(batch)
        return m, g, np.zeros((n, 3))
    if isinstance(c, Upright):
        return _upright_gradient(c, batch)
    if isinstance(c, NonPenetration):
        return closest_pair_gradient(c, batch)
    raise TypeError(f"no gradient for constraint kind '{c.word}'")


def _inside_box_gradient(c: InsideBox, batch: Any) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The closest node's face distance: local = Rᵀ (x - p), so the frame's rotation turns
    the node about the frame's origin: d gap / d ω_frame = direction × (x - p)."""
    m, g_xyz = c.gradient(batch)
    g_rot = np.zeros((len(batch.type), 3))
    if c.shapes is not None:  # `geometry: true`: the reach turns with the node and the frame
        turned = c.types.copy()
        if c.frame is not None:
            turned[c.frame] = True
        return m, g_xyz, rotation_difference(c, batch, turned)
    if c.frame is None:
        return m, g_xyz, g_rot
    nodes, q, ok, gaps = c._gaps(batch)
    gaps = np.where(np.isnan(gaps) | ~ok[:, None], np.inf, gaps)
    face = np.argmin(gaps, axis=1)
    value = gaps[np.arange(len(nodes)), face]
    best = per_scene_argmin(batch.scene[nodes], value, batch.n_scenes)
    k = best[best >= 0]
    k = k[np.isfinite(value[k])]
    axis, sign = face[k] % 3, np.where(face[k] < 3, 1.0, -1.0)
    direction = quat_rotate(q[k], np.eye(3)[axis]) * sign[:, None]
    anc = nearest_ancestor(batch.parent, batch.type, c.frame, nodes[k])
    offset = batch.xyz[nodes[k]] - batch.xyz[anc]
    np.add.at(g_rot, anc, np.cross(direction, offset))
    return m, g_xyz, g_rot


def _upright_gradient(c: Upright, batch: Any) -> tuple[FloatArray, FloatArray, FloatArray]:
    """margin = max_angle - arccos(a · b), a the node's axis, b its frame's: turning the node
    by ω moves a by ω × a, so d margin / d ω = (a × b) / sin; the frame gets the opposite."""
    n = len(batch.type)
    nodes = np.flatnonzero(c.types[batch.type])
    anc = (
        nearest_ancestor(batch.parent, batch.type, c.frame, nodes)
        if c.frame is not None
        else np.full(len(nodes), -1)
    )
    ok = (anc >= 0) | (c.frame is None)
    q_ref = np.where((anc >= 0)[:, None], batch.quat[np.maximum(anc, 0)], [1.0, 0, 0, 0])
    a = quat_rotate(batch.quat[nodes], np.broadcast_to(np.eye(3)[c.axis], (len(nodes), 3)))
    b = quat_rotate(q_ref, np.broadcast_to(np.eye(3)[c.frame_axis], (len(nodes), 3)))
    cos = np.clip(np.sum(a * b, axis=1), -1.0, 1.0)
    value = np.where(ok, c.max_angle - np.arccos(cos), -np.inf)
    m = c.margin(batch)
    best = per_scene_argmin(batch.scene[nodes], value, batch.n_scenes)
    k = best[best >= 0]
    k = k[np.isfinite(value[k])]
    sin = np.maximum(np.sqrt(np.maximum(1.0 - cos[k] ** 2, 0.0)), 1e-12)
    torque = np.cross(a[k], b[k]) / sin[:, None]
    g_rot = np.zeros((n, 3))
    np.add.at(g_rot, nodes[k], torque)
    with_frame = anc[k] >= 0
    np.add.at(g_rot, anc[k][with_frame], -torque[with_frame])
    return m, np.zeros((n, 3)), g_rot


def rotation_difference(c: Constraint, batch: Any, types: Any) -> FloatArray:
    """Central differences of every tree's margin w.r.t. small world-frame turns of its
    nodes of the selected `types` (the k-th such node of every tree turned at once)."""
    grad = np.zeros((len(batch.type), 3))
    nodes = np.flatnonzero(types[batch.type])
    if not len(nodes):
        return grad
    scene = batch.scene[nodes]
    order = np.argsort(scene, kind="stable")
    rank = np.empty(len(nodes), np.int64)
    rank[order] = np.arange(len(nodes)) - np.searchsorted(scene[order], scene[order], "left")
    for k in range(int(rank.max()) + 1):
        at = nodes[rank == k]
        for axis in range(3):
            diff = np.zeros(batch.n_scenes)
            for sign in (1.0, -1.0):
                quat = batch.quat.copy()
                quat[at] = quat_multiply(_small_turn(axis, sign), quat[at])
                m = c.margin(replace(batch, quat=quat))
                diff += sign * np.where(np.isfinite(m), m, 0.0)
            grad[at, axis] = diff[batch.scene[at]] / (2 * FD_ANGLE)
    return grad


def penalty_pose_gradient(
    constraints: list[Constraint], batch: Any, eps: float
) -> tuple[FloatArray, FloatArray, FloatArray, dict[str, FloatArray]]:
    """`penalty_gradient` with the torques too: (log-penalty per tree, d / d xyz, d / d ω,
    each constraint's margins)."""
    total = np.zeros(batch.n_scenes)
    g_xyz = np.zeros((len(batch.type), 3))
    g_rot = np.zeros((len(batch.type), 3))
    margins = {}
    for c in constraints:
        m, gx, gr = pose_gradient(c, batch)
        margins[c.name] = m
        short = np.where(np.isfinite(m), np.minimum(m, 0.0), 0.0)
        total -= short**2 / (2 * eps**2)
        w = (short / eps**2)[batch.scene][:, None]
        g_xyz -= w * gx
        g_rot -= w * gr
    return total, g_xyz, g_rot, margins
