"""Full 3-D non-penetration of the types' geometries, with FCL (python-fcl) distances.

Pairs are first screened with bounding spheres in one array expression: a pair whose spheres
are farther apart than `SCREEN` beyond the required margin cannot decide the constraint, and
its sphere gap (a lower bound of its true distance) stands in for its distance.  Only the
remaining pairs go to FCL, one call each.  So the sign of a tree's margin is always exact;
its value is exact whenever the closest pair was close enough to be measured.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint, FloatArray, per_scene_min
from ssgc.constraints.pose import Clearance
from ssgc.geometry import quat_rotate

SCREEN = 0.05  # m


@dataclass(frozen=True)
class NonPenetration(Constraint):
    """Signed distance between the geometries of every non-exempt pair, minus `gap`."""

    pairs_of: Clearance | None = None  # selection, exemptions (radius = bounding radius)
    shapes: tuple[Any, ...] = ()  # per type: FCL geometry or None
    origins: tuple[tuple[float, float, float], ...] = ()  # per type: geometry's place in frame
    gap: float = 0.0
    kind: ClassVar[str] = "pose"
    word: ClassVar[str] = "non_penetration"
    rank: ClassVar[int] = 2  # one FCL call per close pair: last, on the fewest candidates
    progressive: ClassVar[bool] = False  # judged once per candidate, after all its poses
    screened: list[int] = field(default_factory=lambda: [0, 0], compare=False)

    def margin(self, batch: Any) -> FloatArray:
        i, _, dist = self.pair_distances(batch)
        return per_scene_min(batch.scene[i], dist - self.gap, batch.n_scenes)

    def pair_distances(self, batch: Any) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray]:
        """(i, j, distance) for every non-exempt pair: FCL's signed distance (minus the
        penetration depth when they collide) for pairs closer than `SCREEN` beyond the gap,
        their bounding spheres' gap (a lower bound) for the others.  `ssg explain` reads the
        pairs (ssgc/overlaps.py)."""
        assert self.pairs_of is not None
        i, j = self.pairs_of.pairs(batch)
        r = self.pairs_of.radius
        dist = (
            np.linalg.norm(batch.xyz[i] - batch.xyz[j], axis=1)
            - r[batch.type[i]]
            - r[batch.type[j]]
        )
        near = np.flatnonzero(dist < self.gap + SCREEN)
        self.screened[0] += len(i)
        self.screened[1] += len(near)
        if len(near):
            dist[near] = self._distances(batch, i[near], j[near])
        return i, j, dist

    def _distances(self, batch: Any, i: NDArray[np.int64], j: NDArray[np.int64]) -> FloatArray:
        import fcl

        out = np.empty(len(i))
        request = fcl.DistanceRequest(enable_signed_distance=True)
        creq = fcl.CollisionRequest(num_max_contacts=8, enable_contact=True)
        for k, (a, b) in enumerate(zip(i, j, strict=True)):
            oa = self._object(batch, int(a))
            ob = self._object(batch, int(b))
            cres = fcl.CollisionResult()
            if fcl.collide(oa, ob, creq, cres):
                depth = [c.penetration_depth for c in cres.contacts]
                out[k] = -max(depth, default=0.0)
            else:
                out[k] = fcl.distance(oa, ob, request, fcl.DistanceResult())
        return out

    def _object(self, batch: Any, node: int) -> Any:
        import fcl

        t = int(batch.type[node])
        quat = np.asarray(batch.quat[node], float)
        at = np.asarray(batch.xyz[node], float)
        if self.origins and any(self.origins[t]):  # the geometry sits off the object's frame
            at = at + quat_rotate(quat, np.asarray(self.origins[t], float))
        return fcl.CollisionObject(self.shapes[t], fcl.Transform(quat, at))
