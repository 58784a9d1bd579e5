"""glTF binary (`.glb`) through trimesh: one node per object, named by its id, with its pose.

Geometry is the visual surface only (primitives as triangle meshes); glTF has no collision,
mass or fixed/free.  Each type's mesh is stored once and instanced by its objects' nodes.  A
scene without geometry (no object, or only objects of types without one) is still a valid
file, of posed empty nodes, written here: trimesh refuses to export a scene without a mesh.

glTF 2.0 is +Y up, scenes are +Z up: every object node hangs under one root node, `Z_UP`
(ROOT_NAME), turned -90 degrees about x, so viewers show the table standing; each object's own
node keeps its pose in the scene's Z-up world (world pose = root rotation @ node pose).
"""

from __future__ import annotations

import json
import struct

import numpy as np

from ssgc.export.bodies import SceneBodies
from ssgc.geometry import quat_to_matrix

SUFFIX = ".glb"
MAIN_START = b"glTF"  # how every main file begins (the binary header's magic)
ROOT_NAME = "Z_UP"
# -90 degrees about x: the scene's +z (up) becomes glTF's +y (up), its +y becomes -z.
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def pose_matrix(xyz: np.ndarray, quat: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(quat)
    m[:3, 3] = xyz
    return m


def trimesh_scene(scene: SceneBodies):  # type: ignore[no-untyped-def]
    import trimesh

    out = trimesh.Scene(base_frame="world")
    out.graph.update(frame_from="world", frame_to=ROOT_NAME, matrix=Z_UP_TO_Y_UP)
    for body in scene.bodies:
        if body.shape is not None and body.shape.type not in out.geometry:
            out.geometry[body.shape.type] = body.shape.mesh
        out.graph.update(
            frame_from=ROOT_NAME,
            frame_to=body.name,
            matrix=pose_matrix(body.xyz, body.quat),
            geometry=body.shape.type if body.shape is not None else None,
        )
    return out


def nodes_only(scene: SceneBodies) -> bytes:
    """A glb of one empty node per object, with its pose, under the root node that turns Z-up
    into glTF's Y-up (glTF 2.0: a 12-byte header, then a JSON chunk padded with spaces to 4
    bytes; no buffer, and no empty array, which the schema forbids)."""
    root: dict[str, object] = {"name": ROOT_NAME, "matrix": Z_UP_TO_Y_UP.T.ravel().tolist()}
    nodes = [root] + [
        {"name": b.name, "matrix": pose_matrix(b.xyz, b.quat).T.ravel().tolist()}  # columns
        for b in scene.bodies
    ]
    if scene.bodies:
        root["children"] = list(range(1, len(nodes)))
    doc: dict[str, object] = {"asset": {"version": "2.0", "generator": "ssgc"}, "scene": 0}
    doc["nodes"] = nodes
    doc["scenes"] = [{"name": "world", "nodes": [0]}]
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    header = struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(text))
    return header + struct.pack("<I4s", len(text), b"JSON") + text


def files(scene: SceneBodies) -> dict[str, str | bytes]:
    if all(b.shape is None for b in scene.bodies):
        return {f"{scene.name}{SUFFIX}": nodes_only(scene)}
    return {f"{scene.name}{SUFFIX}": trimesh_scene(scene).export(file_type="glb")}
