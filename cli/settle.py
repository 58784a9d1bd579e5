"""`ssg settle`: simulate scenes to static stability (MuJoCo, headless, CPU)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any

import typer

from ssgc.assets import load_shapes
from ssgc.cli.app import AllowOutside, _command, _progress, app, err, finite_from, out
from ssgc.compile import load_grammar
from ssgc.errors import SsgError
from ssgc.export import scene_bodies
from ssgc.export.bodies import load_export_scenes
from ssgc.io.atomic import write_text_atomic
from ssgc.io.outputs import (
    Output,
    check_directory,
    check_output,
    directory_lock,
    write_output_text,
)
from ssgc.io.resume import MANIFEST
from ssgc.io.scene import distinct_stems, dumps_json
from ssgc.simulate.settle import SettleOptions, settle_scene, settle_summary, settled_scene_json


def write_settled(path: Path, doc: dict[str, Any]) -> None:
    write_text_atomic(path, dumps_json(doc))


def _check_scene_outputs(
    output: Path, stems: list[str], inputs: list[Path], report: Output | None
) -> None:
    """Each settled scene's file, checked before any scene is simulated (under the directory's
    lock): never an input (a scene file settled into its own directory would replace itself),
    never the report, and never another command's work: not into a directory of `ssg sample`
    (its manifest and scene files make its `--resume`, which a replaced scene file broke), and
    over no file but a settled scene (an earlier `ssg settle` into the same directory)."""
    others = [] if report is None else [report]
    paths = [output / f"{stem}.json" for stem in stems]
    for path in paths:
        check_output(path, "settled scene", inputs, others=others)
    if (output / MANIFEST).exists():
        raise SsgError.single(
            f"the output directory holds a run of `ssg sample` ({MANIFEST}): settled scenes "
            "would replace or join its scenes, and its --resume would then fail; write to "
            "another -o",
            str(output),
        )
    for path in paths:
        if path.exists() and not _is_settled_scene(path):
            raise SsgError.single(
                "this file is not a scene `ssg settle` wrote, and its settled scene would "
                "replace it; write to another -o, or move it",
                str(path),
            )


def _is_settled_scene(path: Path) -> bool:
    """Whether `path` holds a scene written by `ssg settle` (its `metadata.settle`)."""
    try:
        doc = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError):
        return False
    metadata = doc.get("metadata") if isinstance(doc, dict) else None
    return isinstance(metadata, dict) and isinstance(metadata.get("settle"), dict)


def _options(max_time: float) -> SettleOptions:
    """The settle options, `--max-time` checked before any work: a scene settles only after
    `still_time` of stillness, so a shorter time could settle no scene at all."""
    still = SettleOptions.still_time
    if not max_time >= still:
        raise SsgError.single(
            f"--max-time {max_time:g} is shorter than the {still:g} s every object must stay "
            f"still to count as settled, so no scene could settle; give at least {still:g}"
        )
    return SettleOptions(max_time=max_time)


def _line(r: dict[str, Any]) -> str:
    state = "settled" if r["settled"] else f"not settled: {r['reason']}"
    return (
        f"{r['name']}: {state}; largest displacement {1000 * r['max_displacement']:.1f} mm; "
        "penetration "
        f"{1000 * r['penetration_before']:.2f} → {1000 * r['penetration_after']:.2f} mm; "
        f"{r['sim_time']:.2f} s simulated in {r['wall_time']:.2f} s"
    )


@app.command("settle", short_help="Simulate scenes until nothing moves.")
@_command
def settle_cmd(
    scenes: Annotated[
        Path,
        typer.Argument(
            help="A scene JSON, a directory of them, a sink-format YAML dataset, or the output "
            "of `ssg parse`.",
            show_default=False,
        ),
    ],
    grammar: Annotated[Path, typer.Option("-g", "--grammar", help="Grammar YAML file.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output directory.")] = Path(
        "settled"
    ),
    engine: Annotated[str, typer.Option(help="Physics engine: mujoco.")] = "mujoco",
    max_time: Annotated[
        float,
        typer.Option(
            "--max-time",
            callback=finite_from(-math.inf, 3600.0),  # below 0.2: _options says why
            help="Simulated seconds per scene, at most: from 0.2 (the time every object must "
            "stay still) to 3600.",
        ),
    ] = 5.0,
    report: Annotated[
        Path | None, typer.Option("--report", help="Also write the per-scene report as JSON.")
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Summary line only.")] = False,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Simulate each scene until nothing moves; write the settled scenes (same format, with
    provenance in metadata.settle) and report per scene: settled or not, the largest
    displacement, the deepest penetration before and after.  Exit 2 if some scene did not
    settle."""
    if engine != "mujoco":
        raise SsgError.single(f"unknown engine '{engine}'; the only engine is mujoco")
    options = _options(max_time)
    if scenes.is_dir() and output.resolve() == scenes.resolve():
        raise SsgError.single(
            "the output directory is the input: settled scenes would replace "
            "the scenes they come from; write to another -o",
            str(output),
        )
    check_directory(output)
    report_dest = None if report is None else check_output(report, "report", [grammar, scenes])
    g = load_grammar(grammar, allow_outside=allow_outside_files)
    items = load_export_scenes(scenes, g)
    stems = distinct_stems([s.name for s in items], ".json", str(scenes))
    said = err if report_dest is not None and report_dest.stdout else out  # not into the JSON
    with directory_lock(output):  # one writer, as `ssg sample` into the same directory
        _check_scene_outputs(output, stems, [grammar, scenes], report_dest)
        shapes = load_shapes(g)
        reports = []
        with _progress(quiet) as progress:
            task = progress.add_task("settling", total=len(items))
            for scene, stem in zip(items, stems, strict=True):
                result = settle_scene(scene_bodies(g, scene, shapes), options)
                source = {"source": str(scenes), "source_scene": scene.name}
                doc = settled_scene_json(g, scene, result, source)
                write_settled(output / f"{stem}.json", doc)
                reports.append(result.report())
                if not result.settled:  # a reason for exit code 2, quiet or not
                    err.print(_line(reports[-1]), markup=False, highlight=False)
                elif not quiet:
                    said.print(_line(reports[-1]), markup=False, highlight=False)
                progress.advance(task)
        summary = settle_summary(reports)
        if report_dest is not None:
            doc = {"summary": summary, "scenes": reports}
            write_output_text(report_dest, json.dumps(doc, indent=1) + "\n")
    said.print(
        f"settled {summary['settled']} of {summary['scenes']} scene(s) -> {output}; median "
        f"displacement {1000 * summary['median_displacement']:.1f} mm, largest "
        f"{1000 * summary['max_displacement']:.1f} mm",
        markup=False,
        highlight=False,
    )
    if summary["settled"] < summary["scenes"]:
        raise typer.Exit(2)
