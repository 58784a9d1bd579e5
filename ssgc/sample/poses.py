"""The poses of fixed trees in their rules' law coordinates, and back.

Every pose of a tree (except its root's) is a draw of its rule's translation law and rotation
law, each written in a frame (world, offset from the parent, parent frame; `ssgc.laws`).  The
samplers that move poses (`ssgc.sample.hmc`, `rjmcmc`, `project`) work in those coordinates:
a move of one node's law value carries its descendants along exactly as the grammar would
have, and the log-density of the poses given the structure is the sum of the laws'
log-densities of the local values.

With rotations held, world positions are affine in the local translations, so the gradient of
anything in world positions pulls back to the local values with one pass from the leaves up
(`pullback`).  Everything is vectorised over all nodes of a batch; the loops run over depths.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import quat_multiply, quat_rotate
from ssgc.ir import Grammar
from ssgc.laws.base import Frame
from ssgc.rules import rotation_coordinates, translation_coordinates
from ssgc.tree import Trees

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Levels:
    """The nodes of a batch by depth (depth 0, the roots, excluded), and each node's depth."""

    depth: IntArray
    by_depth: list[IntArray]

    @classmethod
    def of(cls, trees: Trees) -> Levels:
        depth = trees.depth()
        top = int(depth.max(initial=0))
        order = np.argsort(depth, kind="stable")
        bounds = np.searchsorted(depth[order], np.arange(1, top + 2))
        return cls(depth, [order[bounds[d] : bounds[d + 1]] for d in range(top)])


def local_poses(grammar: Grammar, trees: Trees) -> tuple[FloatArray, FloatArray]:
    """(u, r): each node's translation and rotation in its rule's law coordinates (roots keep
    their world pose)."""
    u, r = trees.xyz.copy(), trees.quat.copy()
    child = np.flatnonzero(trees.parent >= 0)
    if len(child):
        p, rules = trees.parent[child], trees.rule[child]
        u[child] = translation_coordinates(
            grammar, rules, trees.xyz[p], trees.quat[p], trees.xyz[child]
        )
        r[child] = rotation_coordinates(grammar, rules, trees.quat[p], trees.quat[child])
    return u, r


def world_poses(
    grammar: Grammar, trees: Trees, u: FloatArray, r: FloatArray, levels: Levels | None = None
) -> Trees:
    """The batch with every pose rebuilt from law coordinates (u, r), root to leaves."""
    levels = levels or Levels.of(trees)
    tb = grammar.tables
    xyz, quat = trees.xyz.copy(), trees.quat.copy()
    for at in levels.by_depth:
        p, rules = trees.parent[at], trees.rule[at]
        rframe = tb.rotation.frame[rules]
        quat[at] = np.where((rframe == Frame.WORLD)[:, None], r[at], quat_multiply(quat[p], r[at]))
        tframe = tb.translation.frame[rules]
        step = np.where((tframe == Frame.PARENT)[:, None], quat_rotate(quat[p], u[at]), u[at])
        xyz[at] = np.where((tframe == Frame.WORLD)[:, None], u[at], xyz[p] + step)
    return replace(trees, xyz=xyz, quat=quat)


def pullback(grammar: Grammar, trees: Trees, g_xyz: FloatArray, levels: Levels) -> FloatArray:
    """d f / d u for every node's local translation u, given d f / d xyz (rotations held).

    A node's world position is its parent's plus its own (rotated) local value, unless its
    law is written in the world frame; so the adjoint of a node is its own gradient plus its
    children's adjoints that carry its position, summed from the deepest level up."""
    frame = np.full(len(trees), Frame.WORLD, np.int64)
    child = trees.parent >= 0
    frame[child] = grammar.tables.translation.frame[trees.rule[child]]
    adj = g_xyz.copy()
    for at in reversed(levels.by_depth):
        carry = at[frame[at] != Frame.WORLD]
        np.add.at(adj, trees.parent[carry], adj[carry])
    out = adj.copy()
    par = np.flatnonzero(frame == Frame.PARENT)
    if len(par):  # x = x_p + R(q_p) u: d/du = R^T adj
        q = trees.quat[trees.parent[par]]
        conj = q * np.array([1.0, -1.0, -1.0, -1.0])
        out[par] = quat_rotate(conj, adj[par])
    out[~child] = 0.0  # roots are fixed
    return out


def choose(a: Trees, b: Trees, take_b: NDArray[np.bool_]) -> Trees:
    """Tree i of `b` where take_b[i], else tree i of `a` (both batches of the same count)."""
    na = np.flatnonzero(~take_b[a.scene])
    nb = np.flatnonzero(take_b[b.scene])
    scene = np.concatenate([a.scene[na], b.scene[nb]])
    order = np.argsort(scene, kind="stable")  # a tree's nodes keep their order
    new_a = np.full(len(a), -1, np.int64)
    new_b = np.full(len(b), -1, np.int64)
    pos = np.empty(len(order), np.int64)
    pos[order] = np.arange(len(order))
    new_a[na] = pos[: len(na)]
    new_b[nb] = pos[len(na) :]
    pa, pb = a.parent[na], b.parent[nb]
    parent = np.concatenate(
        [
            np.where(pa >= 0, new_a[np.maximum(pa, 0)], -1),
            np.where(pb >= 0, new_b[np.maximum(pb, 0)], -1),
        ]
    )
    cat = np.concatenate
    return Trees(
        scene=scene[order],
        type=cat([a.type[na], b.type[nb]])[order],
        parent=parent[order],
        rule=cat([a.rule[na], b.rule[nb]])[order],
        xyz=cat([a.xyz[na], b.xyz[nb]])[order],
        quat=cat([a.quat[na], b.quat[nb]])[order],
        n_scenes=a.n_scenes,
    )


def pullback_poses(
    grammar: Grammar, trees: Trees, g_xyz: FloatArray, g_rot: FloatArray, levels: Levels
) -> tuple[FloatArray, FloatArray]:
    """(d f / d u, d f / d ω) given d f / d xyz and the torques d f / d ω of every node, where
    the first is w.r.t. each node's local translation (as `pullback`) and the second w.r.t. a
    small world-frame turn ω of each node's rotation carried down the tree as the grammar
    carries it: children whose rotation law is not in the world frame turn with it, and
    children whose translation is in its frame swing about its origin.

    Summed from the deepest level up: torque(n) = own(n) + Σ_c (x_c - x_n) × adjoint(c) over
    children c in n's frame + Σ_c torque(c) over children c whose rotation follows n."""
    child = trees.parent >= 0
    rules = np.maximum(trees.rule, 0)
    tframe = np.where(child, grammar.tables.translation.frame[rules], Frame.WORLD)
    rframe = np.where(child, grammar.tables.rotation.frame[rules], Frame.WORLD)
    adj, torque = g_xyz.copy(), g_rot.copy()
    for at in reversed(levels.by_depth):
        p = trees.parent[at]
        carry = tframe[at] != Frame.WORLD
        np.add.at(adj, p[carry], adj[at[carry]])
        swing = tframe[at] == Frame.PARENT
        arm = trees.xyz[at[swing]] - trees.xyz[p[swing]]
        np.add.at(torque, p[swing], np.cross(arm, adj[at[swing]]))
        turn = rframe[at] != Frame.WORLD
        np.add.at(torque, p[turn], torque[at[turn]])
    out = adj.copy()
    par = np.flatnonzero(tframe == Frame.PARENT)
    if len(par):
        conj = trees.quat[trees.parent[par]] * np.array([1.0, -1.0, -1.0, -1.0])
        out[par] = quat_rotate(conj, adj[par])
    out[~child] = 0.0
    torque[~child] = 0.0
    return out, torque


def pullback_many(grammar: Grammar, trees: Trees, g_xyz: FloatArray, levels: Levels) -> FloatArray:
    """`pullback` of K gradients at once: g_xyz is (K, N, 3), the result (K, N, 3).  The
    projection method needs one per term of a margin (each pair, each box face)."""
    frame = np.full(len(trees), Frame.WORLD, np.int64)
    child = trees.parent >= 0
    frame[child] = grammar.tables.translation.frame[trees.rule[child]]
    adj = np.moveaxis(g_xyz, 0, 1).copy()  # (N, K, 3): nodes first, for the sums over them
    for at in reversed(levels.by_depth):
        carry = at[frame[at] != Frame.WORLD]
        np.add.at(adj, trees.parent[carry], adj[carry])
    out = adj.copy()
    par = np.flatnonzero(frame == Frame.PARENT)
    if len(par):
        q = trees.quat[trees.parent[par]] * np.array([1.0, -1.0, -1.0, -1.0])
        out[par] = quat_rotate(q[:, None, :], adj[par])
    out[~child] = 0.0
    return np.moveaxis(out, 1, 0)


class PullbackPlan:
    """`pullback_poses` for a batch whose structure is fixed, as sparse matrix products.

    The sums from the leaves up are linear maps fixed by the structure: the adjoint of a
    node's position is M g, M[a, d] = 1 when d's position carries a's (d = a, or each link
    from a down to d has a translation not in the world frame); the torques likewise with
    the links whose rotation follows the parent.  Building M once per batch replaces a pass
    over the depths (with `np.add.at`, slow) at every gradient evaluation by three products."""

    def __init__(self, grammar: Grammar, trees: Trees, levels: Levels) -> None:
        from scipy import sparse

        n = len(trees)
        child = np.flatnonzero(trees.parent >= 0)
        rules = trees.rule[child]
        tframe = grammar.tables.translation.frame[rules]
        rframe = grammar.tables.rotation.frame[rules]
        parent = trees.parent[child]

        def link(mask: NDArray[np.bool_]) -> Any:
            return sparse.csr_matrix(
                (np.ones(int(mask.sum())), (parent[mask], child[mask])), shape=(n, n)
            )

        def closure(step: Any) -> Any:
            total = sparse.identity(n, format="csr")
            power = total
            for _ in levels.by_depth:
                power = step @ power
                if power.nnz == 0:
                    break
                total = total + power
            return total.tocsr()

        self.carry = closure(link(tframe != Frame.WORLD))
        self.turn = closure(link(rframe != Frame.WORLD))
        swing = tframe == Frame.PARENT
        self.parent_of = link(swing)  # sums each swinging child's term into its parent
        self.swing = child[swing]
        self.swing_parent = parent[swing]
        self.is_child = trees.parent >= 0

    def __call__(
        self, trees: Trees, g_xyz: FloatArray, g_rot: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        adj = self.carry @ g_xyz
        arm = np.zeros_like(adj)
        s, p = self.swing, self.swing_parent
        arm[s] = np.cross(trees.xyz[s] - trees.xyz[p], adj[s])
        torque = self.turn @ (g_rot + self.parent_of @ arm)
        out = adj.copy()
        conj = trees.quat[p] * np.array([1.0, -1.0, -1.0, -1.0])
        out[s] = quat_rotate(conj, adj[s])
        out[~self.is_child] = 0.0
        torque[~self.is_child] = 0.0
        return out, torque


class WorldPlan:
    """`world_poses` for a batch whose structure is fixed: each depth's nodes split once by
    the frames of their laws, so an evaluation is a few gathers per depth and no lookups."""

    def __init__(self, grammar: Grammar, trees: Trees, levels: Levels) -> None:
        tb = grammar.tables
        self.steps = []
        for at in levels.by_depth:
            rules = trees.rule[at]
            rworld = tb.rotation.frame[rules] == Frame.WORLD
            tframe = tb.translation.frame[rules]
            split = (
                at[rworld],
                at[~rworld],
                at[tframe == Frame.WORLD],
                at[tframe == Frame.WORLD_OFFSET],
                at[tframe == Frame.PARENT],
            )
            self.steps.append(tuple((nodes, trees.parent[nodes]) for nodes in split))

    def __call__(self, trees: Trees, u: FloatArray, r: FloatArray) -> Trees:
        xyz, quat = trees.xyz.copy(), trees.quat.copy()
        for (rw, _), (rp, rpp), (tw, _), (to, top), (tp, tpp) in self.steps:
            quat[rw] = r[rw]
            quat[rp] = quat_multiply(quat[rpp], r[rp])
            xyz[tw] = u[tw]
            xyz[to] = xyz[top] + u[to]
            xyz[tp] = xyz[tpp] + quat_rotate(quat[tpp], u[tp])
        return replace(trees, xyz=xyz, quat=quat)
