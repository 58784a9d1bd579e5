"""A scene reduced once to a list of bodies: the only input every exporter reads.

A body is one observed object: its name (the object id, `TYPE_INDEX` with INDEX its place in
the scene's `objects`), its type's shape (geometry, collision pieces, mass, inertia), its pose
in the world, and whether it is fixed (welded to the world) or free.  Nothing format-specific
reaches back into the grammar or the scene tree.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.assets import Shape
from ssgc.errors import SceneError
from ssgc.geometry import quat_canonical
from ssgc.io.scene import (
    MAX_SCENE_BYTES,
    Scene,
    SceneDoc,
    _LazySource,
    _scene_from_doc,
    load_scenes,
)
from ssgc.ir import Grammar
from ssgc.yamlio import read_text


@dataclass(frozen=True)
class Body:
    name: str
    type: str
    shape: Shape | None  # None: the type has no geometry (exported as a fixed, empty frame)
    xyz: NDArray[np.float64]
    quat: NDArray[np.float64]  # w, x, y, z
    fixed: bool


@dataclass(frozen=True)
class SceneBodies:
    name: str
    grammar: str
    bodies: tuple[Body, ...]


def scene_bodies(grammar: Grammar, scene: Scene, shapes: dict[int, Shape]) -> SceneBodies:
    """One body per object; objects without geometry are fixed (nothing can touch them)."""
    bodies = []
    for i, (t, xyz, quat) in enumerate(zip(scene.types, scene.xyz, scene.quat, strict=True)):
        shape = shapes.get(int(t))
        name = f"{grammar.types[t].name}_{i}"
        fixed = shape is None or shape.static
        bodies.append(Body(name, grammar.types[t].name, shape, xyz, quat_canonical(quat), fixed))
    return SceneBodies(scene.name, grammar.name, tuple(bodies))


def used_shapes(scene: SceneBodies) -> list[Shape]:
    """Each shape of the scene once, in order of first use."""
    seen: dict[str, Shape] = {}
    for b in scene.bodies:
        if b.shape is not None:
            seen.setdefault(b.shape.type, b.shape)
    return list(seen.values())


def obj_text(mesh: object) -> str:
    """A triangle mesh as Wavefront OBJ text (every consumer here reads OBJ)."""
    import trimesh

    return str(
        trimesh.exchange.obj.export_obj(
            mesh, include_normals=False, include_texture=False, digits=9, header=None
        )
    )


def collision_piece(type_name: str, k: int) -> str:
    """The name of convex piece `k` of a type's mesh (its OBJ file without `.obj`, and its
    MJCF mesh asset).  The dots keep it apart from every type's own name, which has none: a
    type called `Cup_collision_0` would otherwise share a file with Cup's first piece."""
    return f"{type_name}.collision.{k}"


def mesh_files(scene: SceneBodies, folder: str = "meshes") -> dict[str, str]:
    """The OBJ files the formats that reference meshes need: `TYPE.obj` for the visual
    surface of a mesh type and `TYPE.collision.K.obj` for its convex pieces."""
    files = {}
    for shape in used_shapes(scene):
        if shape.kind != "mesh":
            continue
        files[f"{folder}/{shape.type}.obj"] = obj_text(shape.mesh)
        for k, piece in enumerate(shape.collision):
            files[f"{folder}/{collision_piece(shape.type, k)}.obj"] = obj_text(piece)
    return files


def principal_axes(inertia: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Principal moments and the rotation matrix whose columns are the axes (det +1)."""
    moments, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:
        axes[:, 0] = -axes[:, 0]
    return moments, axes


# ------------------------------------------------------------------ reading scenes ---


def load_export_scenes(path: str | Path, grammar: Grammar) -> list[Scene]:
    """Scenes to export: a JSON scene, a directory of them, a sink-format dataset, or the
    output of `ssg parse` (each scene's best parse, as the scene of its observed nodes)."""
    path = Path(path)
    if path.is_file() and path.suffix.lower() == ".json":
        text = read_text(path, MAX_SCENE_BYTES, "scene file")
        if (document := _parse_result(text)) is not None:
            return _parsed_scenes(document, text, str(path), grammar)
    return load_scenes(path, grammar)


def _parse_result(text: str) -> dict[str, Any] | None:
    """An `ssg parse` output, decoded: a document with `scenes` and no `objects` of its own
    (as `ssg render` reads it).  Only its top-level keys decide: a diagnosis or an explanation
    early in the file holds `"objects"` too.  Text that is not JSON is left to the scene
    reader, which says where it fails."""
    if not text.lstrip().startswith("{"):
        return None
    try:
        data = json.loads(text)
    except (ValueError, RecursionError):
        return None
    is_result = isinstance(data, dict) and "scenes" in data and "objects" not in data
    return data if is_result else None


def _parsed_scenes(document: dict[str, Any], text: str, file: str, grammar: Grammar) -> list[Scene]:
    """Each parsed scene's best tree as a scene (`text` locates its mistakes)."""
    results = document["scenes"]
    if not isinstance(results, list):
        raise SceneError.single("not a scene file or an `ssg parse` output", file)
    scenes = []
    for k, result in enumerate(results):
        parses = result.get("parses") if isinstance(result, dict) else None
        if not parses:
            continue  # an infeasible or failed scene has no parse to export
        nodes = parses[0]["tree"]["nodes"]
        doc = {
            "name": result.get("name") or f"scene_{k}",
            "objects": [
                {"type": n["type"], "pose": n["pose"]}
                for n in nodes
                if grammar.type_ids.get(n["type"]) is not None
                and grammar.types[grammar.type_ids[n["type"]]].observed
            ],
        }
        try:
            scene_doc = SceneDoc.model_validate(doc)
        except ValueError:
            raise SceneError.single(
                f"scene {k}: its best parse is not a valid tree", file
            ) from None
        scenes.append(_scene_from_doc(scene_doc, grammar, _LazySource(text, file), doc["name"]))
    if not scenes:
        raise SceneError.single("the parse output holds no parsed scene", file)
    return scenes
