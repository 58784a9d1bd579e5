"""Pose constraints on primitives' origins, axes and keep-out discs (thesis 2.4, 2.6.4).

Everything is one array expression over all selected nodes (or node pairs) of the batch;
a tree's margin is the minimum over its nodes or pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import (
    Constraint,
    FloatArray,
    fresh_pairs,
    lineal,
    lineal_few,
    nearest_ancestor,
    pair_chunks,
    per_scene_argmin,
    per_scene_min,
    tree_pairs,
)
from ssgc.constraints.shapes import Extents, frame_extents
from ssgc.geometry import quat_conjugate, quat_multiply, quat_rotate, quat_to_matrix
from ssgc.tails import FLOATING, OUTSIDE, Tail

UNIT = np.eye(3)


def _selected(batch: Any, mask: NDArray[np.bool_]) -> NDArray[np.int64]:
    return np.flatnonzero(mask[batch.type])


def frame_of(batch: Any, nodes: NDArray[np.int64], frame: int | None) -> tuple[Any, Any, Any]:
    """Position and rotation of each node's frame (world, or its nearest `frame` ancestor),
    and a mask of the nodes that have one."""
    if frame is None:
        n = len(nodes)
        return np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), np.ones(n, bool)
    anc = nearest_ancestor(batch.parent, batch.type, frame, nodes)
    ok = anc >= 0
    a = np.maximum(anc, 0)
    return batch.xyz[a], batch.quat[a], ok


@dataclass(frozen=True)
class InsideBox(Constraint):
    """Origins of the `types` nodes inside [lo, hi] in the frame (per axis; nan = unbounded);
    with keep-out radii, the x-y disc of each object inside too; with `shapes`, the whole
    geometry (`ssg explain` reads such a box as a container's floor and walls: ssgc/support.py)."""

    types: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    frame: int | None = None
    lo: FloatArray = field(default_factory=lambda: np.full(3, np.nan))
    hi: FloatArray = field(default_factory=lambda: np.full(3, np.nan))
    radius: FloatArray = field(default_factory=lambda: np.zeros(0))  # per type; 0 without keep_out
    shapes: Extents | None = None  # `geometry: true`: the whole geometry must be inside
    # How rare floating and going through the floor or walls are in real scenes (`ssg explain`,
    # ssgc/support.py): the grammar's `floating:` and `outside:`, else the sink defaults.
    floating: Tail = FLOATING
    outside: Tail = OUTSIDE
    kind: ClassVar[str] = "pose"
    word: ClassVar[str] = "inside_box"

    def _gaps(self, batch: Any) -> tuple[NDArray[np.int64], Any, Any, NDArray[np.float64]]:
        """(nodes, frame rotations, whether each node has its frame, the six signed distances
        of each node to the box's faces, inset by its keep-out radius in x and y; NaN where a
        bound is absent)."""
        nodes = _selected(batch, self.types)
        if getattr(batch, "fresh", None) is not None:
            nodes = nodes[batch.fresh[nodes]]
        p, q, ok = frame_of(batch, nodes, self.frame)
        local = quat_rotate(quat_conjugate(q), batch.xyz[nodes] - p)
        if self.shapes is not None:  # the geometry's reach along the frame's axes
            rel = quat_to_matrix(quat_multiply(quat_conjugate(q), batch.quat[nodes]))
            low, high = frame_extents(self.shapes, batch.type[nodes], rel)
        else:
            r = self.radius[batch.type[nodes]]
            high = np.stack([r, r, np.zeros_like(r)], axis=1)
            low = -high
        with np.errstate(invalid="ignore"):
            gaps = np.concatenate([local + low - self.lo, self.hi - high - local], axis=1)
        return nodes, q, ok, gaps

    def face_gaps(self, batch: Any) -> tuple[NDArray[np.int64], Any, Any, NDArray[np.float64]]:
        """(nodes, frame rotations, whether each node has its frame, (n, 6) signed distances
        inside the faces min x, y, z then max x, y, z; NaN where unbounded): what
        `ssg explain` reads as floor and walls (ssgc/support.py)."""
        return self._gaps(batch)

    def margin(self, batch: Any) -> FloatArray:
        nodes, _, ok, gaps = self._gaps(batch)
        gaps = np.where(np.isnan(gaps), np.inf, gaps)
        value = np.where(ok, gaps.min(axis=1, initial=np.inf), -np.inf)
        return per_scene_min(batch.scene[nodes], value, batch.n_scenes)

    def gradient(self, batch: Any) -> tuple[FloatArray, FloatArray]:
        """(margins, d margin / d xyz of every node): the gradient of each tree's margin with
        respect to node positions (rotations held), nonzero at its closest node and frame."""
        nodes, q, ok, gaps = self._gaps(batch)
        gaps = np.where(np.isnan(gaps) | ~ok[:, None], np.inf, gaps)
        face = np.argmin(gaps, axis=1)
        value = gaps[np.arange(len(nodes)), face]
        grad = np.zeros((len(batch.type), 3))
        best = per_scene_argmin(batch.scene[nodes], value, batch.n_scenes)
        k = best[(best >= 0)]
        k = k[np.isfinite(value[k])]
        axis, sign = face[k] % 3, np.where(face[k] < 3, 1.0, -1.0)
        # local = R^T (x - p): d local[a] / d x = R[:, a], the frame's a-th axis in the world
        direction = quat_rotate(q[k], np.eye(3)[axis]) * sign[:, None]
        np.add.at(grad, nodes[k], direction)
        if self.frame is not None:
            anc = nearest_ancestor(batch.parent, batch.type, self.frame, nodes[k])
            np.add.at(grad, anc, -direction)
        return per_scene_min(batch.scene[nodes], value, batch.n_scenes), grad


@dataclass(frozen=True)
class Clearance(Constraint):
    """World x-y distance between two objects minus their keep-out radii, over every pair of
    `types` nodes of a tree that is not exempt."""

    types: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    radius: FloatArray = field(default_factory=lambda: np.zeros(0))  # per type
    exempt: NDArray[np.bool_] = field(default_factory=lambda: np.zeros((0, 0), bool))
    exempt_ancestors: bool = False
    kind: ClassVar[str] = "pose"
    word: ClassVar[str] = "clearance"
    rank: ClassVar[int] = 0  # crowded scenes fail it most

    def pairs(self, batch: Any) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Every pair the constraint checks (exempt ones left out)."""
        i, j = self.typed_pairs(batch)
        if self.exempt_ancestors and len(i):
            related = lineal(i, j, batch.parent)
            i, j = i[~related], j[~related]
        return i, j

    def gradient(self, batch: Any) -> tuple[FloatArray, FloatArray]:
        """(margins, d margin / d xyz of every node), nonzero at each tree's closest pair."""
        i, j = self.pairs(batch)
        dx = batch.xyz[i, :2] - batch.xyz[j, :2]
        d = np.hypot(dx[:, 0], dx[:, 1])
        gap = d - self.radius[batch.type[i]] - self.radius[batch.type[j]]
        best = per_scene_argmin(batch.scene[i], gap, batch.n_scenes)
        k = best[best >= 0]
        unit = np.zeros((len(k), 3))
        unit[:, :2] = dx[k] / np.maximum(d[k], 1e-300)[:, None]
        grad = np.zeros((len(batch.type), 3))
        np.add.at(grad, i[k], unit)
        np.add.at(grad, j[k], -unit)
        return per_scene_min(batch.scene[i], gap, batch.n_scenes), grad

    def typed_pairs(
        self, batch: Any, fresh: NDArray[np.bool_] | None = None
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """The pairs of `types` nodes of a tree (with `fresh`, only those with a fresh node),
        exempt type pairs left out."""
        nodes = _selected(batch, self.types)
        if fresh is None:
            i, j = tree_pairs(nodes, batch.scene)
        else:
            i, j = fresh_pairs(nodes, batch.scene, fresh)
        keep = ~self.exempt[batch.type[i], batch.type[j]]
        return i[keep], j[keep]

    def margin(self, batch: Any) -> FloatArray:
        """Per tree, the smallest gap; with `batch.fresh`, over the pairs with a fresh node.
        The pairs are formed and measured in chunks (`pair_chunks`): a batch of candidates
        has candidates × objects² / 2 of them, 250 million for 1,024 trees of 700 objects."""
        nodes = _selected(batch, self.types)
        out = np.full(batch.n_scenes, np.inf)
        for i, j in pair_chunks(nodes, batch.scene, getattr(batch, "fresh", None)):
            keep = ~self.exempt[batch.type[i], batch.type[j]]
            np.minimum(out, self._chunk_margin(batch, i[keep], j[keep]), out=out)
        return out

    def _chunk_margin(self, batch: Any, i: NDArray[np.int64], j: NDArray[np.int64]) -> FloatArray:
        """Per tree, the smallest gap over the pairs (i, j) (with `exempt_ancestors`, over
        those that are not lineal); +inf for a tree with none."""
        x, y = batch.xyz[:, 0], batch.xyz[:, 1]  # 1-D gathers are much cheaper than 2-D
        r = self.radius[batch.type]
        gap = np.hypot(x[i] - x[j], y[i] - y[j]) - r[i] - r[j]
        if not self.exempt_ancestors:
            return per_scene_min(batch.scene[i], gap, batch.n_scenes)
        # Ancestry is looked up only where it can matter: the overlapping pairs (a stack's
        # parts overlap), then each tree's closest pair until it is not a lineal one.
        live = np.ones(len(i), bool)
        near = np.flatnonzero(gap < 0)
        depth = getattr(batch, "depth", None)  # node depths, where the batch keeps them
        depth = depth if isinstance(depth, np.ndarray) else None
        live[near[lineal_few(i[near], j[near], batch.parent, depth)]] = False
        scene = batch.scene[i]
        while True:
            best = per_scene_min(scene[live], gap[live], batch.n_scenes)
            at = np.flatnonzero(live & (gap == best[scene]) & (gap >= 0))
            related = at[lineal_few(i[at], j[at], batch.parent, depth)]
            if not len(related):
                return best
            live[related] = False


@dataclass(frozen=True)
class Upright(Constraint):
    """Angle between each object's `axis` and its frame's `frame_axis`, at most `max_angle`
    (radians); the margin is max_angle - angle."""

    types: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    axis: int = 2
    frame: int | None = None
    frame_axis: int = 2
    max_angle: float = 0.0
    kind: ClassVar[str] = "pose"
    word: ClassVar[str] = "upright"

    def margin(self, batch: Any) -> FloatArray:
        nodes = _selected(batch, self.types)
        _, q, ok = frame_of(batch, nodes, self.frame)
        mine = quat_rotate(batch.quat[nodes], np.broadcast_to(UNIT[self.axis], (len(nodes), 3)))
        ref = quat_rotate(q, np.broadcast_to(UNIT[self.frame_axis], (len(nodes), 3)))
        cos = np.clip(np.sum(mine * ref, axis=1), -1.0, 1.0)
        value = np.where(ok, self.max_angle - np.arccos(cos), -np.inf)
        return per_scene_min(batch.scene[nodes], value, batch.n_scenes)
