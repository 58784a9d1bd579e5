"""A scene reduced once to a list of bodies: the only input every exporter reads.

A body is one observed object: its name (the object id, `TYPE_INDEX` with INDEX its place in
the scene's `objects`), its type's shape (geometry, collision pieces, mass, inertia), its pose
in the world, and whether it is fixed (welded to the world) or free.  Nothing format-specific
reaches back into the grammar or the scene tree.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ssgc.assets import Shape
from ssgc.geometry import quat_canonical
from ssgc.io.parsed import parsed_scenes, read_parse_doc
from ssgc.io.scene import (
    Scene,
    is_parse_result,
    lazy_source,
    load_scenes,
    loads_json,
    read_scene_text,
)
from ssgc.ir import Grammar


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


def flushed(value: float) -> float:
    """`value`, or 0 when it is subnormal (below 2.2e-308 in size, not 0): Drake's SDFormat
    reader refused such a number ("Out of range. Unable to set value [2e-310]"), and no shape
    or pose is that fine.  Every format writes its numbers through this."""
    v = float(value)
    return 0.0 if abs(v) < sys.float_info.min else v


def num(value: float) -> str:
    """A number as the exporters write it: exact (`repr`), subnormals as 0."""
    return repr(flushed(value))


def obj_text(mesh: object) -> str:
    """A triangle mesh as Wavefront OBJ text (every consumer here reads OBJ), its coordinates
    exact: a fixed number of decimal places (trimesh's `digits=9`) rounded a mesh scaled by
    1e-6 to the nanometre, and MuJoCo refused its collapsed faces."""
    vertices = np.asarray(mesh.vertices, dtype=float)  # type: ignore[attr-defined]
    faces = np.asarray(mesh.faces, dtype=np.int64) + 1  # type: ignore[attr-defined]
    lines = [f"v {num(x)} {num(y)} {num(z)}" for x, y, z in vertices]
    lines += [f"f {a} {b} {c}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def collision_piece(type_name: str, k: int) -> str:
    """The name of convex piece `k` of a type's mesh (its OBJ file without `.obj`, and its
    MJCF mesh asset).  The dots keep it apart from every type's own name, which has none: a
    type called `Cup_collision_0` would otherwise share a file with Cup's first piece."""
    return f"{type_name}.collision.{k}"


def mesh_files(
    scene: SceneBodies, folder: str = "meshes", collision: bool = False
) -> dict[str, str]:
    """The OBJ files the formats that reference meshes need: `TYPE.obj` for the visual
    surface of a type that is not a primitive (a mesh, a revolve, a tray) and, with
    `collision` (SDFormat names every convex piece by file; MJCF writes them inline),
    `TYPE.collision.K.obj` for its convex pieces."""
    files = {}
    for shape in used_shapes(scene):
        if shape.primitive:
            continue
        files[f"{folder}/{shape.type}.obj"] = obj_text(shape.mesh)
        for k, piece in enumerate(shape.collision if collision else ()):
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
    output of `ssg parse` (each scene's best parse, as the scene of its observed nodes, read
    by the checked reader `ssg render` uses too)."""
    path = Path(path)
    if path.is_file() and path.suffix.lower() == ".json":
        text = read_scene_text(path)
        data = loads_json(text, str(path))
        if is_parse_result(data):
            doc = read_parse_doc(data, text, str(path))
            return parsed_scenes(doc, grammar, lazy_source(text, str(path)), str(path))
    return load_scenes(path, grammar)
