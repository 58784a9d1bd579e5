"""glTF binary (`.glb`) through trimesh: one node per object, named by its id, with its pose.

Geometry is the visual surface only (primitives as triangle meshes); glTF has no collision,
mass or fixed/free.  Each type's mesh is stored once and instanced by its objects' nodes.
"""

from __future__ import annotations

import numpy as np

from ssgc.export.bodies import SceneBodies
from ssgc.geometry import quat_to_matrix

SUFFIX = ".glb"


def pose_matrix(xyz: np.ndarray, quat: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(quat)
    m[:3, 3] = xyz
    return m


def trimesh_scene(scene: SceneBodies):  # type: ignore[no-untyped-def]
    import trimesh

    out = trimesh.Scene(base_frame="world")
    for body in scene.bodies:
        if body.shape is not None and body.shape.type not in out.geometry:
            out.geometry[body.shape.type] = body.shape.mesh
        out.graph.update(
            frame_from="world",
            frame_to=body.name,
            matrix=pose_matrix(body.xyz, body.quat),
            geometry=body.shape.type if body.shape is not None else None,
        )
    return out


def files(scene: SceneBodies) -> dict[str, str | bytes]:
    return {f"{scene.name}{SUFFIX}": trimesh_scene(scene).export(file_type="glb")}
