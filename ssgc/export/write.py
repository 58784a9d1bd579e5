"""Writing a scene's export files into a directory: each atomically, the scene's main file last
(`ssg export`, and `ssg sample --export`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ssgc.errors import Diagnostic, SsgError
from ssgc.export import export_files, main_file, scene_bodies
from ssgc.export.bodies import SceneBodies
from ssgc.io.atomic import write_bytes_atomic, write_text_atomic
from ssgc.io.outputs import check_directory
from ssgc.io.scene import Scene, scene_stem
from ssgc.ir import Grammar


def write_files(out_dir: Path, files: dict[str, str | bytes], main: str) -> None:
    """Write one scene's files, each atomically, the scene's own file last: a run stopped
    half-way leaves no main file that names a missing mesh or model file."""
    for rel in [*(r for r in files if r != main), main]:
        path = out_dir / rel
        check_directory(path.parent)
        data = files[rel]
        if isinstance(data, bytes):
            write_bytes_atomic(path, data)
        else:
            write_text_atomic(path, data)


def export_scene(g: Grammar, scene: Scene, shapes: dict[int, Any], fmt: str, out_dir: Path) -> Path:
    """Write `scene` in format `fmt` into `out_dir` (its files named after the scene, made a
    safe file stem); returns the scene's main file."""
    bodies = scene_bodies(g, scene, shapes)
    bodies = type(bodies)(scene_stem(bodies.name), bodies.grammar, bodies.bodies)
    files = export_files(bodies, fmt)
    main = main_file(out_dir, bodies, fmt)
    write_files(out_dir, files, main.name)
    return main


def every_type_scene(g: Grammar) -> Scene:
    """A stand-in scene with one object of each of the grammar's types: the scenes
    `ssg sample --export` will draw are not known before its shared files are checked."""
    k = len(g.types)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (k, 1))
    return Scene("stand-in", np.arange(k, dtype=np.int64), np.zeros((k, 3)), quat)


def refuse_changed_shared_files(
    g: Grammar, scenes: list[Scene], shapes: dict[int, Any], fmt: str, out_dir: Path
) -> None:
    """Refuse, before anything is written, to change a mesh or model file already in `out_dir`.

    Those files are per type and shared by every scene of the directory: scenes of another
    grammar with a type of the same name, exported there earlier, would silently take this
    grammar's shapes.  One stand-in scene with a body of every type the scenes use (and one
    without geometry, if any has none) gives every shared file this export would write.
    """
    if not out_dir.is_dir():
        return
    bodies = {}
    for scene in scenes:
        for body in scene_bodies(g, scene, shapes).bodies:
            bodies.setdefault(body.type if body.shape is not None else None, body)
    stand_in = SceneBodies("stand-in", g.name, tuple(bodies.values()))
    main = main_file(out_dir, stand_in, fmt).name
    changed = []
    for rel, data in export_files(stand_in, fmt).items():
        path = out_dir / rel
        new = data if isinstance(data, bytes) else data.encode("utf-8")
        if rel != main and path.is_file() and path.read_bytes() != new:
            changed.append(rel)
    if changed:
        why = (
            "already holds a different version of this file, which the scenes exported here "
            "before may use (another grammar's, or this grammar's before it changed); export "
            "into another directory, or remove it first"
        )
        raise SsgError([Diagnostic(why, str(out_dir / rel)) for rel in sorted(changed)])
