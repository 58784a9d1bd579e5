"""Writing a scene's export files into a directory: each atomically, the scene's main file last
(`ssg export`, and `ssg sample --export`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ssgc.export import export_files, main_file, scene_bodies
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
