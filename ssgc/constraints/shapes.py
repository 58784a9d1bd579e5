"""What a type's geometry covers: keep-out radii, bounding spheres and collision shapes.

The one place constraints read a type's `geometry` (so a richer geometry description only
changes this file).  Primitives are centred on the type's origin; a cylinder's axis is its
z axis (as in SDF and FCL).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ssgc import dsl


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


def keep_out_radius(geometry: Any, base_dir: Path | None = None) -> float:
    """Radius of the vertical cylinder around the origin that holds the shape's footprint
    (in the type's own x-y plane): a cylinder's or sphere's radius, a box's half diagonal."""
    if geometry is None:
        raise ShapeError("it has no geometry")
    if isinstance(geometry, dsl.CylinderG):
        return float(geometry.cylinder.radius)
    if isinstance(geometry, dsl.SphereG):
        return float(geometry.sphere.radius)
    if isinstance(geometry, dsl.BoxG):
        x, y, _ = geometry.box.size
        return float(np.hypot(x, y) / 2)
    v = _mesh_vertices(geometry.mesh, base_dir)
    return float(np.max(np.hypot(v[:, 0], v[:, 1]), initial=0.0))


def bounding_radius(geometry: Any, base_dir: Path | None = None) -> float:
    """Radius of a sphere around the origin that holds the whole shape."""
    if geometry is None:
        raise ShapeError("it has no geometry")
    if isinstance(geometry, dsl.CylinderG):
        return float(np.hypot(geometry.cylinder.radius, geometry.cylinder.length / 2))
    if isinstance(geometry, dsl.SphereG):
        return float(geometry.sphere.radius)
    if isinstance(geometry, dsl.BoxG):
        return float(np.linalg.norm(geometry.box.size) / 2)
    v = _mesh_vertices(geometry.mesh, base_dir)
    return float(np.max(np.linalg.norm(v, axis=1), initial=0.0))


def collision_shape(geometry: Any, base_dir: Path | None = None) -> Any:
    """An FCL collision geometry (python-fcl), or ShapeError."""
    try:
        import fcl
    except ImportError:
        raise ShapeError(
            "3-D non-penetration needs python-fcl: pip install 'ssgc[constraints]'"
        ) from None
    if geometry is None:
        raise ShapeError("it has no geometry")
    if isinstance(geometry, dsl.CylinderG):
        return fcl.Cylinder(geometry.cylinder.radius, geometry.cylinder.length)
    if isinstance(geometry, dsl.SphereG):
        return fcl.Sphere(geometry.sphere.radius)
    if isinstance(geometry, dsl.BoxG):
        return fcl.Box(*geometry.box.size)
    import trimesh

    v = _mesh_vertices(geometry.mesh, base_dir)
    faces = np.asarray(trimesh.load(base_dir / geometry.mesh.file, force="mesh").faces)  # type: ignore[operator]
    model = fcl.BVHModel()
    model.beginModel(len(v), len(faces))
    model.addSubModel(v, faces)
    model.endModel()
    return model
