"""Thesis 2.4.1's penalty over a batch of fixed trees, with the work that depends only on the
trees' structure done once.

HMC evaluates the penalty and its gradient thousands of times on the same trees, whose
structure never changes: which pairs a `clearance` constraint checks (exemptions, lineage),
which node is each object's frame, which nodes an `upright` constraint reads.  `Penalty`
finds those once; each evaluation is then a few array expressions over the terms (pairs,
nodes).  The value and gradients are those of `ssgc.constraints.gradients.
penalty_pose_gradient` (the tests compare them): per constraint, the tree's margin is its
smallest term, and the penalty -min(margin, 0)² / (2 ε²) pulls on that term's nodes only.
Kinds without a prepared form (FCL non-penetration, kinds added by users) go through
`pose_gradient` as before.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint, nearest_ancestor
from ssgc.constraints.gradients import pose_gradient
from ssgc.constraints.pose import Clearance, InsideBox, Upright
from ssgc.geometry import quat_rotate
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
UNIT = np.eye(3)


class _Groups:
    """Terms grouped by tree once: per-tree minima by one `reduceat` over the sorted terms."""

    def __init__(self, scene: IntArray, n: int) -> None:
        self.order = np.argsort(scene, kind="stable")
        sorted_scene = scene[self.order]
        self.starts = np.flatnonzero(np.r_[True, sorted_scene[1:] != sorted_scene[:-1]])
        self.trees = sorted_scene[self.starts] if len(scene) else np.zeros(0, np.int64)
        self.scene, self.n = scene, n

    def smallest(self, value: FloatArray) -> tuple[FloatArray, IntArray]:
        """Per tree, the smallest term (+inf without terms) and the index of one term
        reaching it (-1 without terms)."""
        low = np.full(self.n, np.inf)
        at = np.full(self.n, -1, np.int64)
        if not len(value):
            return low, at
        v = value[self.order]
        low[self.trees] = np.minimum.reduceat(v, self.starts)
        hit = np.flatnonzero(v == low[self.scene[self.order]])
        first = hit[
            np.r_[True, self.scene[self.order][hit[1:]] != self.scene[self.order][hit[:-1]]]
        ]
        at[self.scene[self.order][first]] = self.order[first]
        return low, at


class _ClearanceTerms:
    def __init__(self, c: Clearance, trees: Trees) -> None:
        self.i, self.j = c.pairs(trees)
        self.scene = trees.scene[self.i]
        self.reach = c.radius[trees.type[self.i]] + c.radius[trees.type[self.j]]

    def values(self, t: Trees) -> FloatArray:
        dx = t.xyz[self.i, 0] - t.xyz[self.j, 0]
        dy = t.xyz[self.i, 1] - t.xyz[self.j, 1]
        return np.hypot(dx, dy) - self.reach

    def pull(self, t: Trees, k: IntArray, w: FloatArray, gx: FloatArray, gr: FloatArray) -> None:
        i, j = self.i[k], self.j[k]
        d = t.xyz[i, :2] - t.xyz[j, :2]
        unit = np.zeros((len(k), 3))
        unit[:, :2] = d / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-300)[:, None]
        np.add.at(gx, i, w[:, None] * unit)
        np.add.at(gx, j, -w[:, None] * unit)


class _FrameTerms:
    """Nodes of some types with their frame node (-1: the world)."""

    def __init__(self, types: NDArray[np.bool_], frame: int | None, trees: Trees) -> None:
        nodes = np.flatnonzero(types[trees.type])
        anc = (
            nearest_ancestor(trees.parent, trees.type, frame, nodes)
            if frame is not None
            else np.full(len(nodes), -1, np.int64)
        )
        self.has_frame = (anc >= 0) | (frame is None)
        self.nodes, self.anc = nodes[self.has_frame], anc[self.has_frame]
        self.scene = trees.scene[self.nodes]
        self.world = self.anc < 0

    def frame_quat(self, t: Trees) -> FloatArray:
        q = t.quat[np.maximum(self.anc, 0)]
        return np.where(self.world[:, None], [1.0, 0.0, 0.0, 0.0], q)

    def frame_xyz(self, t: Trees) -> FloatArray:
        return np.where(self.world[:, None], 0.0, t.xyz[np.maximum(self.anc, 0)])


class _BoxTerms(_FrameTerms):
    def __init__(self, c: InsideBox, trees: Trees) -> None:
        super().__init__(c.types, c.frame, trees)
        r = c.radius[trees.type[self.nodes]]
        inset = np.stack([r, r, np.zeros_like(r)], axis=1)
        lo = np.where(np.isnan(c.lo), -np.inf, c.lo)
        hi = np.where(np.isnan(c.hi), np.inf, c.hi)
        self.lo, self.hi = inset + lo, hi - inset  # local must be within [lo, hi]
        self.face = np.zeros(len(self.nodes), np.int64)

    def values(self, t: Trees) -> FloatArray:
        q = self.frame_quat(t)
        local = quat_rotate(
            q * np.array([1.0, -1.0, -1.0, -1.0]), t.xyz[self.nodes] - self.frame_xyz(t)
        )
        gaps = np.concatenate([local - self.lo, self.hi - local], axis=1)
        self.face = np.argmin(gaps, axis=1)
        return gaps[np.arange(len(gaps)), self.face]

    def pull(self, t: Trees, k: IntArray, w: FloatArray, gx: FloatArray, gr: FloatArray) -> None:
        face = self.face[k]
        sign = np.where(face < 3, 1.0, -1.0)
        direction = quat_rotate(self.frame_quat(t)[k], UNIT[face % 3]) * (sign * w)[:, None]
        nodes = self.nodes[k]
        np.add.at(gx, nodes, direction)
        framed = ~self.world[k]
        anc = self.anc[k][framed]
        np.add.at(gx, anc, -direction[framed])
        offset = t.xyz[nodes[framed]] - t.xyz[anc]
        np.add.at(gr, anc, np.cross(direction[framed], offset))


class _UprightTerms(_FrameTerms):
    def __init__(self, c: Upright, trees: Trees) -> None:
        super().__init__(c.types, c.frame, trees)
        self.c = c
        self.a = self.b = self.cos = np.zeros(0)

    def values(self, t: Trees) -> FloatArray:
        n = len(self.nodes)
        self.a = quat_rotate(t.quat[self.nodes], np.broadcast_to(UNIT[self.c.axis], (n, 3)))
        self.b = quat_rotate(self.frame_quat(t), np.broadcast_to(UNIT[self.c.frame_axis], (n, 3)))
        self.cos = np.clip(np.sum(self.a * self.b, axis=1), -1.0, 1.0)
        return self.c.max_angle - np.arccos(self.cos)

    def pull(self, t: Trees, k: IntArray, w: FloatArray, gx: FloatArray, gr: FloatArray) -> None:
        sin = np.maximum(np.sqrt(np.maximum(1.0 - self.cos[k] ** 2, 0.0)), 1e-12)
        torque = np.cross(self.a[k], self.b[k]) * (w / sin)[:, None]
        np.add.at(gr, self.nodes[k], torque)
        framed = ~self.world[k]
        np.add.at(gr, self.anc[k][framed], -torque[framed])


def _prepare(c: Constraint, trees: Trees) -> Any:
    if type(c) is Clearance:
        return _ClearanceTerms(c, trees)
    if type(c) is InsideBox:
        return _BoxTerms(c, trees)
    if type(c) is Upright:
        return _UprightTerms(c, trees)
    return None


class Penalty:
    """Σ_C -min(C, 0)² / (2 ε²) over `constraints` on fixed trees, with d / d xyz and the
    torques d / d ω (as `penalty_pose_gradient`)."""

    def __init__(self, constraints: list[Constraint], trees: Trees, eps: float) -> None:
        self.eps, self.n = eps, trees.n_scenes
        self.prepared = [(c, _prepare(c, trees)) for c in constraints]
        self.groups = [
            None if terms is None else _Groups(terms.scene, self.n) for _, terms in self.prepared
        ]

    def __call__(self, t: Trees) -> tuple[FloatArray, FloatArray, FloatArray]:
        total = np.zeros(self.n)
        gx, gr = np.zeros((len(t), 3)), np.zeros((len(t), 3))
        for (c, terms), groups in zip(self.prepared, self.groups, strict=True):
            if terms is None or groups is None:
                m, cx, cr = pose_gradient(c, t)
                short = np.where(np.isfinite(m), np.minimum(m, 0.0), 0.0)
                total -= short**2 / (2 * self.eps**2)
                w = (short / self.eps**2)[t.scene][:, None]
                gx -= w * cx
                gr -= w * cr
                continue
            value = terms.values(t)
            low, at = groups.smallest(value)
            bad = np.flatnonzero((low < 0) & np.isfinite(low))
            if not len(bad):
                continue
            short = low[bad]
            total[bad] -= short**2 / (2 * self.eps**2)
            terms.pull(t, at[bad], -short / self.eps**2, gx, gr)
        return total, gx, gr
