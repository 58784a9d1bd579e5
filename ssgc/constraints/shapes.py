"""What a type's geometry covers: keep-out radii, bounding spheres and collision shapes.

The one place constraints read a type's `geometry` (so a richer geometry description only
changes this file).  Primitives are centred on the geometry's `origin` (a point in the type's
frame, default the frame's origin); a cylinder's axis is its z axis (as in SDF and FCL).  A
`revolve` (a solid of revolution, ssgc/constraints/revolved.py) has its profile's z = 0 and
axis at the origin.  A `tray` (an open box) is centred as a box is and bounded by its outside
box; FCL collides with its closed surface (a mesh), so what rests in it is apart.  Radii are
about the type's frame, so they include the origin's offset.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc import dsl
from ssgc.constraints.revolved import Revolved


class ShapeError(ValueError):
    """The geometry cannot give what is asked (no geometry, an unreadable mesh)."""


def _mesh_vertices(g: dsl.MeshGeometry, base_dir: Path | None) -> np.ndarray:
    import trimesh

    if base_dir is None:
        raise ShapeError(f"mesh file '{g.file}' cannot be opened without the grammar's directory")
    try:
        mesh = trimesh.load(base_dir / g.file, force="mesh")
    except Exception as exc:  # trimesh raises many kinds for bad files
        raise ShapeError(f"mesh file '{g.file}' cannot be read ({type(exc).__name__})") from None
    scale = np.broadcast_to(np.asarray(g.scale, float), (3,))
    return np.asarray(mesh.vertices, float) * scale


def geometry_origin(geometry: Any) -> np.ndarray:
    """(3,) where the geometry sits in its type's frame (zeros without geometry)."""
    return np.asarray(getattr(geometry, "origin", None) or (0.0, 0.0, 0.0), float)


def keep_out_radius(geometry: Any, base_dir: Path | None = None) -> float:
    """Radius of the vertical cylinder around the type's frame that holds the shape's
    footprint (in the type's own x-y plane): a cylinder's or sphere's radius, a box's half
    diagonal, plus how far the geometry's origin is from the frame's vertical axis."""
    if geometry is None:
        raise ShapeError("it has no geometry")
    ox, oy, _ = geometry_origin(geometry)
    return float(np.hypot(ox, oy)) + _footprint_radius(geometry, base_dir)


def _footprint_radius(geometry: Any, base_dir: Path | None) -> float:
    if isinstance(geometry, dsl.CylinderG):
        return float(geometry.cylinder.radius)
    if isinstance(geometry, dsl.SphereG):
        return float(geometry.sphere.radius)
    if isinstance(geometry, dsl.BoxG | dsl.TrayG):
        x, y, _ = _box_size(geometry)
        return float(np.hypot(x, y) / 2)
    if isinstance(geometry, dsl.RevolveG):
        return Revolved(geometry.revolve.profile).radius
    v = _mesh_vertices(geometry.mesh, base_dir)
    return float(np.max(np.hypot(v[:, 0], v[:, 1]), initial=0.0))


def bounding_radius(geometry: Any, base_dir: Path | None = None) -> float:
    """Radius of a sphere around the type's frame that holds the whole shape."""
    if geometry is None:
        raise ShapeError("it has no geometry")
    return float(np.linalg.norm(geometry_origin(geometry))) + _own_radius(geometry, base_dir)


def _own_radius(geometry: Any, base_dir: Path | None) -> float:
    """Radius of a sphere around the geometry's own origin that holds it."""
    if isinstance(geometry, dsl.CylinderG):
        return float(np.hypot(geometry.cylinder.radius, geometry.cylinder.length / 2))
    if isinstance(geometry, dsl.SphereG):
        return float(geometry.sphere.radius)
    if isinstance(geometry, dsl.BoxG | dsl.TrayG):
        return float(np.linalg.norm(_box_size(geometry)) / 2)
    if isinstance(geometry, dsl.RevolveG):
        return Revolved(geometry.revolve.profile).bounding_radius
    v = _mesh_vertices(geometry.mesh, base_dir)
    return float(np.max(np.linalg.norm(v, axis=1), initial=0.0))


def _box_size(geometry: dsl.BoxG | dsl.TrayG) -> list[float]:
    """A box's sides, or a tray's outside sides."""
    return list(geometry.box.size if isinstance(geometry, dsl.BoxG) else geometry.tray.size)


def collision_shape(geometry: Any, base_dir: Path | None = None) -> Any:
    """An FCL collision geometry (python-fcl) about the geometry's own origin (place it at
    `geometry_origin` in the object's frame), or ShapeError."""
    try:
        import fcl
    except ImportError:
        raise ShapeError(
            "3-D non-penetration needs python-fcl, a dependency of ssgc that is not installed: "
            "pip install python-fcl"
        ) from None
    if geometry is None:
        raise ShapeError("it has no geometry")
    if isinstance(geometry, dsl.CylinderG):
        return fcl.Cylinder(geometry.cylinder.radius, geometry.cylinder.length)
    if isinstance(geometry, dsl.SphereG):
        return fcl.Sphere(geometry.sphere.radius)
    if isinstance(geometry, dsl.BoxG):
        return fcl.Box(*geometry.box.size)
    v, faces = surface_mesh(geometry, base_dir)
    model = fcl.BVHModel()
    model.beginModel(len(v), len(faces))
    model.addSubModel(v, faces)
    model.endModel()
    return model


def surface_mesh(geometry: Any, base_dir: Path | None = None) -> tuple[Any, Any]:
    """(vertices, triangles) of a revolve's, a tray's or a mesh's surface, about the
    geometry's origin: what FCL gets for them (triangles, not a solid)."""
    if isinstance(geometry, dsl.RevolveG):
        return Revolved(geometry.revolve.profile).mesh()
    if isinstance(geometry, dsl.TrayG):
        return geometry.tray.mesh()
    import trimesh

    v = _mesh_vertices(geometry.mesh, base_dir)
    faces = np.asarray(trimesh.load(base_dir / geometry.mesh.file, force="mesh").faces)  # type: ignore[operator]
    return v, faces


def closed_surface(geometry: Any, base_dir: Path | None = None) -> ClosedSurface | None:
    """The geometry's surface when FCL gets it as triangles and it closes a solid (every edge
    shared by exactly two triangles), else None: a point inside it is inside the solid."""
    if not isinstance(geometry, dsl.RevolveG | dsl.TrayG | dsl.MeshG):
        return None
    v, faces = surface_mesh(geometry, base_dir)
    v = np.asarray(v, float)
    corners = _merged_by_position(v)[np.asarray(faces, np.int64)]
    edges = np.sort(corners[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    if not np.all(uses == 2):
        return None
    return ClosedSurface(v[np.asarray(faces, np.int64)])


def _merged_by_position(v: NDArray[np.float64]) -> NDArray[np.int64]:
    """Per vertex, the index of the first vertex at the same position.  A mesh file read with
    texture coordinates or normals (OBJ `f a/t` or `a//n`) keeps one vertex per corner at their
    seams (a cube with `vt`: 20 vertices, not 8), so the triangles on either side of a seam
    share no edge and a closed surface read as open (an object buried in it was kept)."""
    _, first, same = np.unique(v + 0.0, axis=0, return_index=True, return_inverse=True)
    return first[same.reshape(-1)]  # `+ 0.0`: a -0.0 coordinate is the same position as 0.0


# A ray in no axis plane and along no diagonal: the facets of revolves, trays and meshes are
# axis-aligned or regular, so it does not graze their edges.
_RAY = np.array([0.5349, 0.6195, 0.5745]) / np.linalg.norm([0.5349, 0.6195, 0.5745])
_ACROSS = np.linalg.svd(_RAY[None])[2][1:]  # (2, 3): an orthonormal basis across the ray


class ClosedSurface:
    """A closed triangle surface, about its geometry's origin: `inside(point)` by the parity
    of the surface's crossings along a ray (Möller–Trumbore).  FCL sees such a surface as
    triangles only, so an object buried in the solid it bounds, touching no triangle, is
    apart for FCL; this says it is inside.  Only the triangles whose shadow along the ray
    covers the point are intersected (their bounds across the ray are kept): a mesh of 80,000
    triangles made every close pair of a constrained sample 6 times slower."""

    def __init__(self, triangles: NDArray[np.float64]) -> None:
        self.v0 = triangles[:, 0]
        self.e1 = triangles[:, 1] - self.v0
        self.e2 = triangles[:, 2] - self.v0
        self.lo, self.hi = (
            triangles.reshape(-1, 3).min(axis=0),
            triangles.reshape(-1, 3).max(axis=0),
        )
        across = triangles @ _ACROSS.T  # (n, 3 corners, 2): coordinates across the ray
        self.shadow_lo, self.shadow_hi = across.min(axis=1), across.max(axis=1)

    def inside(self, point: NDArray[np.float64]) -> bool:
        if np.any(point < self.lo) or np.any(point > self.hi):
            return False
        at = _ACROSS @ point
        k = np.flatnonzero(np.all((self.shadow_lo <= at) & (at <= self.shadow_hi), axis=1))
        v0, e1, e2 = self.v0[k], self.e1[k], self.e2[k]
        p = np.cross(_RAY, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-30
        det = np.where(ok, det, 1.0)
        s = point - v0
        u = np.einsum("ij,ij->i", s, p) / det
        q = np.cross(s, e1)
        w = (q @ _RAY) / det
        t = np.einsum("ij,ij->i", e2, q) / det
        hits = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
        return bool(np.count_nonzero(hits) % 2)


def solid_of(geometry: Any) -> Revolved | None:
    """The geometry as a solid of revolution about its origin (a revolve, a cylinder, a
    sphere), whose penetration depths are measured on its surface points; None for a box, a
    mesh or no geometry."""
    if isinstance(geometry, dsl.RevolveG):
        return Revolved(geometry.revolve.profile)
    if isinstance(geometry, dsl.CylinderG):
        return Revolved.cylinder(geometry.cylinder.radius, geometry.cylinder.length)
    if isinstance(geometry, dsl.SphereG):
        return Revolved.sphere(geometry.sphere.radius)
    return None


@dataclass(frozen=True)
class Extents:
    """Per type, what `frame_extents` needs to bound its geometry along any axes: the kind
    (0 none, 1 box, 2 cylinder, 3 sphere, 4 mesh, 5 revolve), the half sizes (box: half sides;
    cylinder: radius, half length; sphere: radius), the geometry's origin in the type's frame,
    and a mesh's vertices (about its own origin) or a revolve's solid."""

    kind: NDArray[np.int64]
    half: NDArray[np.float64]  # (types, 3)
    origin: NDArray[np.float64]  # (types, 3)
    vertices: tuple[NDArray[np.float64] | Revolved | None, ...]


NO_SHAPE, BOX, CYLINDER, SPHERE, MESH, REVOLVE = range(6)


def extents_of(geometries: list[Any], base_dir: Path | None = None) -> Extents:
    """The `Extents` of each type's geometry (None: a point at the type's origin)."""
    n = len(geometries)
    kind, half, origin = np.zeros(n, np.int64), np.zeros((n, 3)), np.zeros((n, 3))
    vertices: list[NDArray[np.float64] | Revolved | None] = [None] * n
    for t, g in enumerate(geometries):
        if g is None:
            continue
        origin[t] = geometry_origin(g)
        if isinstance(g, dsl.BoxG | dsl.TrayG):  # a tray reaches as far as its outside box
            kind[t], half[t] = BOX, np.asarray(_box_size(g), float) / 2
        elif isinstance(g, dsl.CylinderG):
            kind[t], half[t] = CYLINDER, (g.cylinder.radius, g.cylinder.length / 2, 0.0)
        elif isinstance(g, dsl.SphereG):
            kind[t], half[t] = SPHERE, (g.sphere.radius, 0.0, 0.0)
        elif isinstance(g, dsl.RevolveG):
            kind[t], vertices[t] = REVOLVE, Revolved(g.revolve.profile)
        else:
            kind[t], vertices[t] = MESH, _mesh_vertices(g.mesh, base_dir)
    return Extents(kind, half, origin, tuple(vertices))


def frame_extents(
    ext: Extents, types: NDArray[np.int64], rot: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(lo, hi), each (n, 3): the lowest and highest coordinate of each node's geometry along
    the axes of a frame, relative to the node's origin, where `rot` (n, 3, 3) is the node's
    rotation in that frame.  Closed forms for primitives (a cylinder of axis a reaches
    |a_k| h + r sqrt(1 - a_k^2) along axis k) and per profile vertex for a revolve
    (`Revolved.reach`); a mesh's vertices otherwise."""
    centre = np.einsum("nij,nj->ni", rot, ext.origin[types])
    half = np.zeros((len(types), 3))
    k, h = ext.kind[types], ext.half[types]
    box = k == BOX
    half[box] = np.einsum("nij,nj->ni", np.abs(rot[box]), h[box])
    cyl = k == CYLINDER
    axis = rot[cyl][:, :, 2]  # the cylinder's axis in the frame
    side = np.sqrt(np.clip(1.0 - axis**2, 0.0, None))
    half[cyl] = np.abs(axis) * h[cyl][:, 1:2] + side * h[cyl][:, :1]
    sph = k == SPHERE
    half[sph] = h[sph][:, :1]
    lo, hi = centre - half, centre + half
    for t in np.unique(types[k == MESH]):
        m = np.flatnonzero(types == t)
        v = np.einsum("nij,vj->nvi", rot[m], ext.vertices[int(t)])
        lo[m], hi[m] = centre[m] + v.min(axis=1), centre[m] + v.max(axis=1)
    for t in np.unique(types[k == REVOLVE]):
        m = np.flatnonzero(types == t)
        solid = ext.vertices[int(t)]
        assert isinstance(solid, Revolved)
        low, high = solid.reach(rot[m][:, :, 2])
        lo[m], hi[m] = centre[m] + low, centre[m] + high
    return lo, hi
