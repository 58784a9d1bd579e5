"""Writing a scene's export files into a directory: each atomically, the scene's main file last
(`ssg export`, and `ssg sample --export`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ssgc import dsl
from ssgc.assets import mesh_path
from ssgc.errors import Diagnostic, SsgError
from ssgc.export import MAIN_STARTS, SUFFIXES, export_files, main_file, scene_bodies
from ssgc.export.bodies import SceneBodies
from ssgc.io.atomic import write_bytes_atomic, write_text_atomic
from ssgc.io.outputs import check_directory, check_output
from ssgc.io.scene import Scene, scene_stem
from ssgc.ir import Grammar


def write_files(out_dir: Path, files: dict[str, str | bytes], main: str) -> None:
    """Write one scene's files, each atomically, the scene's own file last: a run stopped
    half-way leaves no main file that names a missing mesh or model file.  A failed write
    names the file it was writing, not the temporary file beside it."""
    for rel in [*(r for r in files if r != main), main]:
        path = out_dir / rel
        check_directory(path.parent)
        data = files[rel]
        try:
            if isinstance(data, bytes):
                write_bytes_atomic(path, data)
            else:
                write_text_atomic(path, data)
        except OSError as exc:
            reason = exc.strerror or str(exc)
            raise SsgError.single(f"cannot write the export file: {reason}", str(path)) from None


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


def grammar_inputs(g: Grammar) -> list[Path]:
    """The files an export reads from the grammar: the grammar itself and its mesh files."""
    meshes = [mesh_path(g, t) for t in g.types if isinstance(t.geometry, dsl.MeshG)]
    return [Path(g.file), *meshes]


def shared_files(
    g: Grammar, scenes: list[Scene], shapes: dict[int, Any], fmt: str
) -> dict[str, bytes]:
    """Every mesh and model file the export of `scenes` writes, by path relative to the output
    directory.  One stand-in scene with a body of every type the scenes use (and one without
    geometry, if any has none) gives them all."""
    bodies = {}
    for scene in scenes:
        for body in scene_bodies(g, scene, shapes).bodies:
            bodies.setdefault(body.type if body.shape is not None else None, body)
    stand_in = SceneBodies("stand-in", g.name, tuple(bodies.values()))
    main = main_file(Path(), stand_in, fmt).name
    return {
        rel: data if isinstance(data, bytes) else data.encode("utf-8")
        for rel, data in export_files(stand_in, fmt).items()
        if rel != main
    }


def main_names(scenes: list[Scene], fmt: str) -> list[str]:
    """Each scene's main file, relative to the output directory."""
    return [f"{scene_stem(scene.name)}{SUFFIXES[fmt]}" for scene in scenes]


def check_export_outputs(
    out_dir: Path, shared: dict[str, bytes], mains: list[str], fmt: str, inputs: list[Path]
) -> None:
    """Every file an export will write, checked before any is written (`ssg export`, and
    `ssg sample --export` with no main files yet): each has a place to go (no file where a
    directory is needed, no directory where the file goes), none is an input (a grammar named
    like a scene's main file, a mesh inside the output directory), no main file replaces a
    file that is not an earlier main file of this format, and no shared file changes."""
    for rel in [*shared, *mains]:
        _check_place(out_dir, rel, inputs)
    _refuse_foreign_main_files(out_dir, mains, fmt)
    _refuse_changed_shared_files(out_dir, shared)


def _check_place(out_dir: Path, rel: str, inputs: list[Path]) -> None:
    """`out_dir / rel` can be written: its folders are folders (or absent), it is not a
    directory, and it is not one of the export's inputs (`check_output`'s rule)."""
    path = out_dir / rel
    for folder in reversed(path.relative_to(out_dir).parents):
        if (out_dir / folder).exists() and not (out_dir / folder).is_dir():
            raise SsgError.single(
                f"the export needs a directory here for {rel}, and this is a file; move it, "
                "or export into another directory",
                str(out_dir / folder),
            )
    if path.is_dir():
        raise SsgError.single(
            "the export would write this file, and a directory is in its place; move it, or "
            "export into another directory",
            str(path),
        )
    if os.path.lexists(path):
        check_output(path, "export file", inputs)


def _refuse_foreign_main_files(out_dir: Path, mains: list[str], fmt: str) -> None:
    """A scene's main file replaces only an earlier main file of the same format (a scene of
    that name exported before): not another format's shared file (an MJCF scene `package`
    over the Drake export's `package.xml`), nor a file of the user's."""
    start = MAIN_STARTS[fmt]
    for rel in mains:
        path = out_dir / rel
        if path.is_file() and _first_bytes(path, len(start)) != start:
            raise SsgError.single(
                f"this file is not a {fmt} scene an earlier export wrote (another export's "
                "file, or one of yours), and a scene's main file would replace it; rename the "
                "scene, move the file, or export into another directory",
                str(path),
            )


def _first_bytes(path: Path, n: int) -> bytes:
    try:
        with path.open("rb") as f:
            return f.read(n)
    except OSError:
        return b""


def _refuse_changed_shared_files(out_dir: Path, shared: dict[str, bytes]) -> None:
    """Refuse to change a mesh or model file already in `out_dir`.

    Those files are per type and shared by every scene of the directory: scenes of another
    grammar with a type of the same name, exported there earlier, would silently take this
    grammar's shapes.
    """
    changed = [
        rel
        for rel, data in shared.items()
        if (out_dir / rel).is_file() and (out_dir / rel).read_bytes() != data
    ]
    if changed:
        why = (
            "already holds a different version of this file, which the scenes exported here "
            "before may use (another grammar's, this grammar's before it changed, or, for a "
            "mesh .obj, one an ssgc before 2026-11-29 wrote with 9 decimals); export into "
            "another directory, or remove it first"
        )
        raise SsgError([Diagnostic(why, str(out_dir / rel)) for rel in sorted(changed)])
