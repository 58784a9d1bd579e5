"""Full 3-D non-penetration of the types' geometries, with FCL (python-fcl) distances.

Pairs are first screened with bounding spheres in one array expression: a pair whose spheres
are farther apart than `SCREEN` beyond the required margin cannot decide the constraint, and
its sphere gap (a lower bound of its true distance) stands in for its distance.  Only the
remaining pairs go to FCL, one call each.  So the sign of a tree's margin is always exact;
its value is exact whenever the closest pair was close enough to be measured.

A `revolve` geometry (a hollow dish) goes to FCL as a triangle mesh, whose contacts say that
two shapes touch but not how deeply: when one of a colliding pair is a revolve and the other a
solid of revolution too (revolve, cylinder, sphere), the depth is the deepest surface point of
either inside the other, exact in its meridian plane (ssgc/constraints/revolved.py).  That
depth is small for thin walls that cross; `ssg explain` asks instead for how far one of the
pair must be moved to free it (`separation`), a search with FCL's collision test.  So it does
for a `tray` and a `mesh`, also triangle meshes to FCL, whose contact depth is that of
triangles, not of the solid (a block pushed 2 cm up through a tray's floor read 4.4 cm).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint, FloatArray, per_scene_argmin, per_scene_min
from ssgc.constraints.pose import Clearance
from ssgc.constraints.revolved import Revolved, penetration_depth
from ssgc.constraints.shapes import ClosedSurface
from ssgc.geometry import quat_rotate, quat_to_matrix
from ssgc.tails import OVERLAP, Tail

SCREEN = 0.05  # m
MIN_DEPTH = 1e-4  # m: a colliding pair's least depth (a collision is never a zero margin)
SEPARATION_MAX = 0.5  # m: the farthest a separation search looks
SEPARATION_STEPS = np.concatenate([[0.0], 0.001 * 1.25 ** np.arange(28)])  # m, to 0.41 m
_DIAGONALS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) / np.sqrt(3)
DIRECTIONS = np.concatenate([np.eye(3), -np.eye(3), _DIAGONALS])  # world directions tried


@dataclass(frozen=True)
class NonPenetration(Constraint):
    """Signed distance between the geometries of every non-exempt pair, minus `gap`."""

    pairs_of: Clearance | None = None  # selection, exemptions (radius = bounding radius)
    shapes: tuple[Any, ...] = ()  # per type: FCL geometry or None
    origins: tuple[tuple[float, float, float], ...] = ()  # per type: geometry's place in frame
    solids: tuple[Revolved | None, ...] = ()  # per type: as a solid of revolution, or None
    hollow: tuple[bool, ...] = ()  # per type: a triangle mesh to FCL (revolve, tray, mesh)
    # per type: the closed surface of a hollow type, for what FCL misses (`_buried`), or None
    surfaces: tuple[ClosedSurface | None, ...] = ()
    gap: float = 0.0
    # How rare overlapping is in real scenes (`ssg explain`, ssgc/overlaps.py): the grammar's
    # `tail:`, else the sink default.
    tail: Tail = OVERLAP
    kind: ClassVar[str] = "pose"
    word: ClassVar[str] = "non_penetration"
    rank: ClassVar[int] = 2  # one FCL call per close pair: last, on the fewest candidates
    progressive: ClassVar[bool] = False  # judged once per candidate, after all its poses
    screened: list[int] = field(default_factory=lambda: [0, 0], compare=False)

    def margin(self, batch: Any) -> FloatArray:
        i, _, dist = self.pair_distances(batch)
        return per_scene_min(batch.scene[i], dist - self.gap, batch.n_scenes)

    def pair_distances(
        self, batch: Any, separation: bool = False
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray]:
        """(i, j, distance) for every non-exempt pair: FCL's signed distance (minus the
        penetration depth when they collide) for pairs closer than `SCREEN` beyond the gap,
        their bounding spheres' gap (a lower bound) for the others.  `ssg explain` reads the
        pairs (ssgc/overlaps.py) with `separation`: a colliding pair with a revolve then gets
        minus its `separation` (how far one must move to free it) as its distance."""
        assert self.pairs_of is not None
        i, j = self.pairs_of.pairs(batch)
        return i, j, self.distances_of(batch, i, j, separation)

    def distances_of(
        self,
        batch: Any,
        i: NDArray[np.int64],
        j: NDArray[np.int64],
        separation: bool = False,
        exact: bool = False,
    ) -> FloatArray:
        """The distances of `pair_distances` for the given pairs only (nodes i[k], j[k]);
        `exact`: FCL's for every pair, also those the bounding spheres put far apart (whose
        sphere gap is only a lower bound: how far an object floats above another is not)."""
        assert self.pairs_of is not None
        r = self.pairs_of.radius
        dist = (
            np.linalg.norm(batch.xyz[i] - batch.xyz[j], axis=1)
            - r[batch.type[i]]
            - r[batch.type[j]]
        )
        near = np.arange(len(dist)) if exact else np.flatnonzero(dist < self.gap + SCREEN)
        self.screened[0] += len(i)
        self.screened[1] += len(near)
        if len(near):
            dist[near] = self._distances(batch, i[near], j[near], separation)
        return dist

    def closest_pairs(self, batch: Any) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64]]:
        """(margins (n_scenes,), a, b): each tree's margin and its closest pair's nodes (one
        entry per tree that has pairs).  The margin is the minimum over pairs, so its
        gradient is that pair's distance's (a subgradient at ties): the samplers difference
        two nodes, not every node against every pair."""
        i, j, dist = self.pair_distances(batch)
        m = per_scene_min(batch.scene[i], dist - self.gap, batch.n_scenes)
        best = per_scene_argmin(batch.scene[i], dist, batch.n_scenes)
        k = best[best >= 0]
        return m, i[k], j[k]

    def _distances(
        self, batch: Any, i: NDArray[np.int64], j: NDArray[np.int64], separation: bool = False
    ) -> FloatArray:
        import fcl

        out = np.empty(len(i))
        request = fcl.DistanceRequest(enable_signed_distance=True)
        creq = fcl.CollisionRequest(num_max_contacts=8, enable_contact=True)
        for k, (a, b) in enumerate(zip(i, j, strict=True)):
            oa = self._object(batch, int(a))
            ob = self._object(batch, int(b))
            cres = fcl.CollisionResult()
            if fcl.collide(oa, ob, creq, cres):
                if separation and self._is_hollow(batch, int(a), int(b)):
                    out[k] = -max(MIN_DEPTH, self.separation(oa, ob))
                    continue
                profiled = self._profiled_depth(batch, int(a), int(b))
                depth = contact_depth(cres.contacts) if profiled is None else profiled
                # touching (every contact 0 deep: a mug on a tray's floor) is no overlap
                out[k] = -max(MIN_DEPTH, depth) if depth > 0 else 0.0
            else:
                apart = fcl.distance(oa, ob, request, fcl.DistanceResult())
                buried = self._is_hollow(batch, int(a), int(b)) and self._buried(batch, a, b)
                out[k] = -max(MIN_DEPTH, apart) if buried else apart
        return out

    def _buried(self, batch: Any, a: int, b: int) -> bool:
        """Whether one of a pair that touches no triangle of the other lies inside the solid
        the other's closed surface bounds (FCL reads a sphere inside a revolve's puck as
        apart).  A point of each is tested in the other: a primitive's centre, a point of a
        surface; with no surface crossing, where one point is, the whole object is.  Its
        margin is then minus its distance to the surface around it, the least it is buried."""
        if not self.surfaces:
            return False
        for inner, outer in ((b, a), (a, b)):
            surface = self.surfaces[int(batch.type[outer])]
            point = self._point_of(batch, int(inner))
            if surface is None or point is None:
                continue
            rot = quat_to_matrix(np.asarray(batch.quat[outer], float)[None])[0]
            if surface.inside(rot.T @ (point - self._placed(batch, int(outer)))):
                return True
        return False

    def _point_of(self, batch: Any, node: int) -> FloatArray | None:
        """A point inside a primitive (its centre) or on a closed surface (a vertex); None
        for an open mesh, which has neither (its origin may lie anywhere: a cup's open
        cylinder has it in the cavity, where a ball resting in the cup is)."""
        t = int(batch.type[node])
        at = self._placed(batch, node)
        if not self.hollow[t]:
            return at
        surface = self.surfaces[t]
        if surface is None:
            return None
        return at + quat_rotate(np.asarray(batch.quat[node], float), surface.v0[0])

    def _placed(self, batch: Any, node: int) -> FloatArray:
        """Where the geometry's origin is in the world (it may sit off the object's frame)."""
        t = int(batch.type[node])
        at = np.asarray(batch.xyz[node], float)
        if self.origins and any(self.origins[t]):
            at = at + quat_rotate(
                np.asarray(batch.quat[node], float), np.asarray(self.origins[t], float)
            )
        return at

    def _is_hollow(self, batch: Any, a: int, b: int) -> bool:
        return bool(self.hollow) and (
            self.hollow[int(batch.type[a])] or self.hollow[int(batch.type[b])]
        )

    @staticmethod
    def separation(oa: Any, ob: Any) -> float:
        """How far `ob` must be moved to no longer collide with `oa` (FCL collision objects):
        the least over `DIRECTIONS` and the line between their centres of the first
        `SEPARATION_STEPS` distance that frees it, refined by bisection.  A penetration depth
        that means something for hollow shapes, whose crossing walls are thin
        (`SEPARATION_MAX` when nothing within it frees the pair)."""
        import fcl

        start = np.asarray(ob.getTranslation(), float)
        centre = start - np.asarray(oa.getTranslation(), float)
        norm = np.linalg.norm(centre)
        ways = DIRECTIONS if norm < 1e-9 else np.vstack([DIRECTIONS, centre / norm])
        request = fcl.CollisionRequest()

        def hits(t: float, u: FloatArray) -> bool:
            ob.setTranslation(start + t * u)
            return bool(fcl.collide(oa, ob, request, fcl.CollisionResult()))

        best = SEPARATION_MAX
        for u in ways:
            below = 0.0
            for t in SEPARATION_STEPS[1:]:
                if t >= best:
                    break
                if not hits(float(t), u):
                    for _ in range(6):  # bisect between the last hit and the first miss
                        mid = (below + t) / 2
                        below, t = (mid, t) if hits(mid, u) else (below, mid)
                    best = min(best, float(t))
                    break
                below = float(t)
        ob.setTranslation(start)
        return best

    def _profiled_depth(self, batch: Any, a: int, b: int) -> float | None:
        """The penetration depth of a colliding pair measured on the solids' surface points
        when one is a revolve and both are solids of revolution, else None (FCL's depth).  At
        least `MIN_DEPTH`: FCL found them colliding even if no surface point lies inside (thin
        walls crossing between points)."""
        if not self._is_hollow(batch, a, b):
            return None
        ta, tb = int(batch.type[a]), int(batch.type[b])
        sa, sb = self.solids[ta], self.solids[tb]
        if sa is None or sb is None:
            return None
        ra, rb = quat_to_matrix(np.stack([batch.quat[a], batch.quat[b]]))
        pa = batch.xyz[a] + ra @ np.asarray(self.origins[ta] or (0, 0, 0), float)
        pb = batch.xyz[b] + rb @ np.asarray(self.origins[tb] or (0, 0, 0), float)
        return max(MIN_DEPTH, penetration_depth(sa, sb, ra.T @ rb, ra.T @ (pb - pa)))

    def _object(self, batch: Any, node: int) -> Any:
        import fcl

        t = int(batch.type[node])
        quat = np.asarray(batch.quat[node], float)
        return fcl.CollisionObject(self.shapes[t], fcl.Transform(quat, self._placed(batch, node)))


def contact_depth(contacts: list[Any]) -> float:
    """The deepest of a colliding pair's FCL contacts, as a positive length.  FCL signs the
    depth of a sphere against a triangle mesh (a tray, a mesh) negative (python-fcl 0.7: a ball
    half through a cube's face reads -r), the other pairs positive: taken as it came, such a
    collision had a positive margin and its scene was kept."""
    return max((abs(float(c.penetration_depth)) for c in contacts), default=0.0)
