"""Scenes as files simulators and 3D tools load (docs/export.md).

A scene is reduced once to bodies (`bodies.scene_bodies`); each format is one module with a
`files(SceneBodies) -> {relative path: text or bytes}` function, registered in `FORMATS`
(and, if it needs an optional package, its check in `REQUIRES`).  Adding a format is adding a
module and a line here.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ssgc.errors import SsgError
from ssgc.export import dmd, glb, mjcf, sdf, usd
from ssgc.export.bodies import SceneBodies, scene_bodies

Files = dict[str, str | bytes]
FORMATS: dict[str, Callable[[SceneBodies], Files]] = {
    "dmd": dmd.files,
    "sdf": sdf.files,
    "mjcf": mjcf.files,
    "glb": glb.files,
    "usd": usd.files,
}
SUFFIXES = {
    "dmd": dmd.SUFFIX,
    "sdf": sdf.SUFFIX,
    "mjcf": mjcf.SUFFIX,
    "glb": glb.SUFFIX,
    "usd": usd.SUFFIX,
}
# How each format's main file begins: a file there that does not is not an earlier export's
# scene (another format's shared `package.xml`, the user's own file), and is not written over.
MAIN_STARTS = {
    "dmd": dmd.MAIN_START,
    "sdf": sdf.MAIN_START,
    "mjcf": mjcf.MAIN_START,
    "glb": glb.MAIN_START,
    "usd": usd.MAIN_START,
}
REQUIRES: dict[str, Callable[[], None]] = {"usd": usd.require}  # optional packages, checked first


def check_format(fmt: str) -> str:
    """`fmt` if it names a format, else the user's mistake."""
    if fmt not in FORMATS:
        raise SsgError.single(f"unknown export format '{fmt}'; choose one of {', '.join(FORMATS)}")
    if fmt in REQUIRES:
        REQUIRES[fmt]()
    return fmt


def export_files(scene: SceneBodies, fmt: str) -> Files:
    """The files of one scene in one format, paths relative to the output directory."""
    return FORMATS[check_format(fmt)](scene)


def main_file(out_dir: Path, scene: SceneBodies, fmt: str) -> Path:
    return out_dir / f"{scene.name}{SUFFIXES[fmt]}"


__all__ = [
    "FORMATS",
    "MAIN_STARTS",
    "SUFFIXES",
    "SceneBodies",
    "check_format",
    "export_files",
    "main_file",
    "scene_bodies",
]
