"""Solids of revolution: a profile in the (r, z) half plane turned about the z axis.

A bowl, a mug or a plate is hollow: a solid cylinder standing for it overlaps whatever lies in
it, and its rim reaches lower than the real dish's when it is tilted.  A `revolve` geometry
(docs/grammar.md) is the dish's cross-section — a polyline from a point on the axis, around the
material, back to the axis — so the cavity is not part of the solid.

Everything a constraint needs is exact in the meridian plane of a point: the closest point of
the surface to any point lies in the half plane through the axis and that point, so a point's
signed distance to the solid is its (r, z) distance to the profile, and its reach along any
direction is a closed form per profile vertex.  Penetration of two such solids is measured on
points of their surfaces (`surface_points`): the deepest point of either inside the other.
"""

from __future__ import annotations

from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import profile_area

FloatArray = NDArray[np.float64]

MESH_SECTIONS = 48  # facets around the axis of the constraints' mesh (FCL); exports use 32
SAMPLE_SPACING = 0.008  # m: surface points for penetration depths (the samplers' margins)
MAX_SAMPLES = 400  # along the profile and around a ring: a huge profile gets sparser points


class Revolved:
    """One solid of revolution, about its own origin (the geometry's `origin` places it)."""

    def __init__(self, profile: Any) -> None:
        self.rz = np.asarray(profile, float)

    @classmethod
    def cylinder(cls, radius: float, length: float) -> Revolved:
        h = length / 2
        return cls([[0, -h], [radius, -h], [radius, h], [0, h]])

    @classmethod
    def sphere(cls, radius: float, sections: int = 32) -> Revolved:
        t = np.linspace(-np.pi / 2, np.pi / 2, sections + 1)
        return cls(np.stack([np.abs(radius * np.cos(t)), radius * np.sin(t)], axis=1))

    @property
    def radius(self) -> float:
        """Its largest distance from the axis."""
        return float(self.rz[:, 0].max())

    @property
    def bounding_radius(self) -> float:
        """Radius of a sphere about its origin that holds it."""
        return float(np.max(np.hypot(self.rz[:, 0], self.rz[:, 1])))

    def reach(self, axis: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(lo, hi), each (n, 3): its lowest and highest coordinate along each frame axis, for
        n rotations whose third column, `axis` (n, 3), is its z axis in the frame: a vertex
        (r, z) reaches z a_k ± r sqrt(1 - a_k^2) along axis k."""
        side = np.sqrt(np.clip(1.0 - axis**2, 0.0, None))[:, :, None]
        along = axis[:, :, None] * self.rz[:, 1]
        across = side * self.rz[:, 0]
        return (along - across).min(axis=2), (along + across).max(axis=2)

    def signed_distance(self, points: FloatArray) -> FloatArray:
        """(n,) signed distance of points (n, 3), in its own frame, to its surface: negative
        inside (minus the depth), exact (the closest surface point is in the point's meridian
        plane)."""
        r, z = np.hypot(points[:, 0], points[:, 1]), points[:, 2]
        return np.where(self._inside(r, z), -1.0, 1.0) * self._distance(r, z)

    def deepest(self, points: FloatArray) -> float:
        """The depth of the deepest of the points (n, 3), in its own frame, inside it (0 when
        none is): only points within its bounding cylinder are tested."""
        r, z = np.hypot(points[:, 0], points[:, 1]), points[:, 2]
        near = (r < self.radius) & (z > self.rz[:, 1].min()) & (z < self.rz[:, 1].max())
        r, z = r[near], z[near]
        inside = self._inside(r, z)
        return float(self._distance(r[inside], z[inside]).max(initial=0.0))

    def _distance(self, r: FloatArray, z: FloatArray) -> FloatArray:
        """Each (r, z)'s distance to the profile's edges (the axis edge is not surface)."""
        r, z = r[:, None], z[:, None]
        a, b = self.rz[:-1], self.rz[1:]
        d = b - a
        length2 = np.maximum(np.sum(d * d, axis=1), 1e-30)
        t = np.clip(((r - a[:, 0]) * d[:, 0] + (z - a[:, 1]) * d[:, 1]) / length2, 0.0, 1.0)
        return np.hypot(r - (a[:, 0] + t * d[:, 0]), z - (a[:, 1] + t * d[:, 1])).min(axis=1)

    def _inside(self, r: FloatArray, z: FloatArray) -> NDArray[np.bool_]:
        """Whether each (r, z) is inside the closed profile: an odd number of its edges cross
        the ray from the point away from the axis (the axis edge never does)."""
        r, z = r[:, None], z[:, None]
        a, b = self.rz[:-1], self.rz[1:]
        straddle = (a[:, 1] > z) != (b[:, 1] > z)
        with np.errstate(divide="ignore", invalid="ignore"):
            r_cross = a[:, 0] + (z - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        return (np.count_nonzero(straddle & (r_cross > r), axis=1) % 2) == 1

    @cached_property
    def surface_points(self) -> FloatArray:
        """(m, 3) points on its surface, about `SAMPLE_SPACING` apart along the profile and
        around the axis (the points a penetration depth is measured on); farther apart on a
        profile too long or too wide for `MAX_SAMPLES` points along it or around it."""
        edges = np.hypot(*np.diff(self.rz, axis=0).T)
        spacing = max(
            SAMPLE_SPACING, edges.sum() / MAX_SAMPLES, 2 * np.pi * self.radius / MAX_SAMPLES
        )
        pts = [self.rz[:1]]
        for a, b, length in zip(self.rz[:-1], self.rz[1:], edges, strict=True):
            k = max(1, int(np.ceil(length / spacing)))
            pts.append(a + (b - a) * (np.arange(1, k + 1) / k)[:, None])
        rz = np.concatenate(pts)
        rings = np.maximum(1, np.ceil(2 * np.pi * rz[:, 0] / spacing)).astype(np.int64)
        ring = np.repeat(np.arange(len(rz)), rings)
        step = np.arange(len(ring)) - np.repeat(np.cumsum(rings) - rings, rings)
        angle = 2 * np.pi * step / rings[ring]
        r = rz[ring, 0]
        return np.stack([r * np.cos(angle), r * np.sin(angle), rz[ring, 1]], axis=1)

    def mesh(self, sections: int = MESH_SECTIONS) -> tuple[FloatArray, NDArray[np.int64]]:
        """(vertices, triangles) of its closed surface, outward-facing for a profile that goes
        counter-clockwise in the (r, z) plane (faces are flipped otherwise)."""
        angle = 2 * np.pi * np.arange(sections) / sections
        on_axis = self.rz[:, 0] == 0
        first = np.zeros(len(self.rz), np.int64)  # each profile point's first vertex
        count = np.where(on_axis, 1, sections)
        first[1:] = np.cumsum(count)[:-1]
        r, z = self.rz[:, 0], self.rz[:, 1]
        verts = np.concatenate(
            [
                np.array([[0.0, 0.0, z[i]]])
                if on_axis[i]
                else np.stack(
                    [r[i] * np.cos(angle), r[i] * np.sin(angle), np.full(sections, z[i])], 1
                )
                for i in range(len(self.rz))
            ]
        )
        k = np.arange(sections)
        k1 = (k + 1) % sections
        faces = []
        for i in range(len(self.rz) - 1):
            a, b = first[i], first[i + 1]
            if on_axis[i]:
                faces.append(np.stack([np.full(sections, a), b + k1, b + k], 1))
            elif on_axis[i + 1]:
                faces.append(np.stack([a + k, a + k1, np.full(sections, b)], 1))
            else:
                faces.append(np.stack([a + k, a + k1, b + k1], 1))
                faces.append(np.stack([a + k, b + k1, b + k], 1))
        tri = np.concatenate(faces)
        if profile_area(self.rz) < 0:  # clockwise profile: the faces above point inwards
            tri = tri[:, ::-1]
        return verts, tri


def penetration_depth(a: Revolved, b: Revolved, rot_ab: FloatArray, at_ab: FloatArray) -> float:
    """How deep the deepest surface point of either solid lies inside the other (0 if none),
    with b's frame at `at_ab`, turned by `rot_ab` (3, 3), in a's frame.  Only points within
    the other's bounding sphere are turned into its frame and tested."""
    a_in_b = -(rot_ab.T @ at_ab)  # a's origin in b's frame
    near_b = _within(b.surface_points, a_in_b, a.bounding_radius)
    near_a = _within(a.surface_points, at_ab, b.bounding_radius)
    return max(a.deepest(near_b @ rot_ab.T + at_ab), b.deepest((near_a - at_ab) @ rot_ab))


def _within(points: FloatArray, centre: FloatArray, radius: float) -> FloatArray:
    d = points - centre
    return points[np.einsum("ij,ij->i", d, d) <= radius * radius]
