"""`ssg export`: scenes as files simulators and 3D tools load (docs/export.md).

Also the `--export` and `--settle` options of `ssg sample`, through `SampleExtras`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssgc.assets import load_shapes
from ssgc.cli.app import AllowOutside, _command, _progress, app, out
from ssgc.compile import load_grammar
from ssgc.export import SUFFIXES, check_format, scene_bodies
from ssgc.export.bodies import load_export_scenes
from ssgc.export.write import (
    check_export_outputs,
    every_type_scene,
    export_scene,
    grammar_inputs,
    main_names,
    shared_files,
)
from ssgc.io.atomic import write_text_atomic
from ssgc.io.outputs import check_directory
from ssgc.io.scene import Scene, distinct_stems, dumps_json, dumps_scene
from ssgc.ir import Grammar

FORMAT_HELP = "dmd (Drake directives) | sdf (SDFormat world) | mjcf (MuJoCo) | glb | usd"


@app.command("export", short_help="Scenes as Drake, MuJoCo, glTF or USD files.")
@_command
def export_cmd(
    scenes: Annotated[
        Path,
        typer.Argument(
            help="A scene JSON, a directory of them, a sink-format YAML dataset, or the output "
            "of `ssg parse` (each scene's best parse).",
            show_default=False,
        ),
    ],
    grammar: Annotated[Path, typer.Option("-g", "--grammar", help="Grammar YAML file.")],
    fmt: Annotated[str, typer.Option("--format", "-f", help=FORMAT_HELP)],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output directory.")] = Path(
        "export"
    ),
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress or summary.")] = False,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Write each scene as a file a simulator or 3D tool loads: Drake model directives, an
    SDFormat world, MJCF, glTF binary or USD, with geometry, collision, mass and inertia from
    the grammar (docs/export.md)."""
    check_format(fmt)
    check_directory(output)
    g = load_grammar(grammar, allow_outside=allow_outside_files)
    items = load_export_scenes(scenes, g)
    distinct_stems([s.name for s in items], SUFFIXES[fmt], str(scenes))
    # glTF carries no collision geometry, and no masses
    shapes = load_shapes(g, collision=fmt != "glb", masses=fmt != "glb")
    shared = shared_files(g, items, shapes, fmt)
    inputs = [*grammar_inputs(g), scenes]  # never written over (as `ssg settle` refuses it)
    check_export_outputs(output, shared, main_names(items, fmt), fmt, inputs)
    written = []
    with _progress(quiet) as progress:
        task = progress.add_task(f"exporting ({fmt})", total=len(items))
        for scene in items:
            written.append(export_scene(g, scene, shapes, fmt, output))
            progress.advance(task)
    if not quiet:
        out.print(
            f"exported {len(written)} scene(s) as {fmt} to {output}", markup=False, highlight=False
        )


class SampleExtras:
    """What `ssg sample --settle / --export FORMAT` does with each scene it draws: settle it
    (the settled scene is what gets written), then write its exports (into OUTPUT/FORMAT/) and
    last its scene file, which `--resume` takes as the sign that the scene is finished."""

    def __init__(self, g: Grammar, export: list[str], settle: bool, output: Path) -> None:
        self.g = g
        self.formats = [check_format(f) for f in export]
        self.settle = settle
        self.output = output
        if settle:  # before the run writes its manifest
            from ssgc.simulate.settle import require_mujoco

            require_mujoco()
        needs = self.needs_collision()
        self.shapes = load_shapes(g, collision=needs, masses=needs) if export or settle else {}
        self.unsettled = 0
        for fmt in self.formats:  # as `ssg export` does, before anything is written
            shared = shared_files(g, [every_type_scene(g)], self.shapes, fmt)
            check_export_outputs(output / fmt, shared, [], fmt, grammar_inputs(g))

    def needs_collision(self) -> bool:
        """Whether some output carries collision geometry (and masses): glTF has neither, so
        `--export glb` alone neither decomposes meshes (slow) nor needs coacd, nor refuses a
        mass no simulator's file holds, as `ssg export -f glb`."""
        return self.settle or any(f != "glb" for f in self.formats)

    def write(
        self, scene: Scene, path: Path, seed: int, index: int, metadata: dict | None = None
    ) -> None:
        """A `ssgc.sample.run.SceneWriter`.  `metadata` (constrained sampling's method and
        margins) goes into the scene file; a settled scene keeps it under `metadata.settle`
        (it describes the poses before settling), with the run's seed and index."""
        if self.settle:
            from ssgc.simulate.settle import settle_scene, settled_scene_json

            result = settle_scene(scene_bodies(self.g, scene, self.shapes))
            self.unsettled += not result.settled
            source = {"seed": seed, "index": index, "source_log_prob": scene.log_prob}
            doc = settled_scene_json(self.g, scene, result, {**source, **(metadata or {})})
            text = dumps_json(doc)
            scene = Scene(scene.name, scene.types, result.xyz, result.quat)
        else:
            text = dumps_scene(self.g, scene, seed=seed, index=index, metadata=metadata)
        for fmt in self.formats:
            export_scene(self.g, scene, self.shapes, fmt, self.output / fmt)
        write_text_atomic(path, text)
