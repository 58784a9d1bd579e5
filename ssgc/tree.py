"""Scene trees, stored as flat node arrays so that many trees can be sampled and scored at once.

A `Trees` batch holds every node of every tree: which tree it belongs to, its type, its parent
(an index into the same arrays, -1 for a root), the rule that produced it (a rule id of the
grammar, -1 for a root) and its pose.  Invariants: nodes are grouped by tree in increasing tree
order, and every parent comes before its children (so a parent index is always smaller).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Trees:
    scene: IntArray  # (N,) tree index of each node
    type: IntArray  # (N,)
    parent: IntArray  # (N,) index of the parent node, -1 for a root
    rule: IntArray  # (N,) rule id that produced the node, -1 for a root
    xyz: FloatArray  # (N, 3)
    quat: FloatArray  # (N, 4) wxyz
    n_scenes: int

    def __len__(self) -> int:
        return int(self.type.shape[0])

    @property
    def offsets(self) -> IntArray:
        """offsets[i]:offsets[i+1] are the nodes of tree i."""
        counts = np.bincount(self.scene, minlength=self.n_scenes)
        return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)

    def tree(self, i: int) -> Trees:
        """Tree i on its own, with parent indices renumbered from 0."""
        offsets = self.offsets
        a, b = int(offsets[i]), int(offsets[i + 1])
        parent = self.parent[a:b].copy()
        parent[parent >= 0] -= a
        return Trees(
            scene=np.zeros(b - a, np.int64),
            type=self.type[a:b].copy(),
            parent=parent,
            rule=self.rule[a:b].copy(),
            xyz=self.xyz[a:b].copy(),
            quat=self.quat[a:b].copy(),
            n_scenes=1,
        )

    def first(self, keep: int) -> Trees:
        """The first `keep` trees (their nodes come first, so no index changes)."""
        end = int(self.offsets[keep])
        return Trees(
            self.scene[:end],
            self.type[:end],
            self.parent[:end],
            self.rule[:end],
            self.xyz[:end],
            self.quat[:end],
            keep,
        )

    def select(self, keep: NDArray[np.bool_]) -> Trees:
        """The trees with keep[i] True, renumbered, in their order, each tree's nodes together
        (a store whose trees are interleaved, level by level, comes out grouped) and parents
        before children."""
        idx = np.flatnonzero(keep[self.scene])
        idx = idx[np.argsort(self.scene[idx], kind="stable")]
        new = np.full(len(self), -1, np.int64)
        new[idx] = np.arange(len(idx))
        renumber = np.cumsum(keep) - 1
        par = self.parent[idx]
        return Trees(
            scene=renumber[self.scene[idx]],
            type=self.type[idx],
            parent=np.where(par >= 0, new[np.maximum(par, 0)], -1),
            rule=self.rule[idx],
            xyz=self.xyz[idx],
            quat=self.quat[idx],
            n_scenes=int(np.count_nonzero(keep)),
        )

    @staticmethod
    def concatenate(batches: list[Trees]) -> Trees:
        """Join batches into one, renumbering trees and parent indices."""
        scene, parent = [], []
        n_nodes = n_scenes = 0
        for b in batches:
            scene.append(b.scene + n_scenes)
            parent.append(np.where(b.parent >= 0, b.parent + n_nodes, -1))
            n_nodes += len(b)
            n_scenes += b.n_scenes
        return Trees(
            scene=np.concatenate(scene),
            type=np.concatenate([b.type for b in batches]),
            parent=np.concatenate(parent),
            rule=np.concatenate([b.rule for b in batches]),
            xyz=np.concatenate([b.xyz for b in batches]),
            quat=np.concatenate([b.quat for b in batches]),
            n_scenes=n_scenes,
        )

    def depth(self) -> IntArray:
        """Depth of every node (roots are 0), one vectorised step per tree level."""
        depth = np.zeros(len(self), np.int64)
        anc = self.parent.copy()
        while np.any(anc >= 0):
            has = anc >= 0
            depth[has] += 1
            anc[has] = self.parent[anc[has]]
        return depth
