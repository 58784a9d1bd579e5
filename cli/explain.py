"""`ssg explain`: why a scene scores what it scores (ssgc.explain; docs/explain.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from .app import AllowOutside, _command, app, err, finite_from, out


@app.command(short_help="Which objects make a scene unusual, and why.")
@_command
def explain(
    scenes: Annotated[
        Path,
        typer.Argument(
            help="A scene JSON, a directory of them, or a sink-format YAML dataset.",
            show_default=False,
        ),
    ],
    grammar: Annotated[Path, typer.Option("-g", "--grammar", help="Grammar YAML file.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
    output: Annotated[
        Path | None,
        typer.Option("-o", "--output", help="Write the JSON here (no text is printed)."),
    ] = None,
    time_limit: Annotated[
        float | None,
        typer.Option(
            "--time-limit",
            callback=finite_from(0.001),
            help="Seconds per scene: the parse, then the per-object re-parses in what is "
            "left (without it the re-parses share 30 s).",
        ),
    ] = None,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Each object's and each rule's share of −log p of the best parse, most unusual first.

    The text lists the 10 most unusual objects and the 10 largest rules, and counts the rest;
    --json lists all.  A best parse not proven best (status feasible) is said to be so.

    A scene proven infeasible gets the objects and rules that rule it out (exit code 2); one
    without a parse found, unproven, says which step gave up (exit 3; 4 for the time limit).
    """
    from ssgc.compile import load_grammar
    from ssgc.io.outputs import check_output, lock_outputs, write_output_text
    from ssgc.io.scene import load_scenes
    from ssgc.parse.parser import Parser, exit_code
    from ssgc.scene_reports import explain_document

    dest = None if output is None else check_output(output, inputs=[grammar, scenes])
    with lock_outputs([dest]):
        g = load_grammar(grammar, allow_outside=allow_outside_files)
        parser = Parser(g)
        made = [explain_document(g, parser, s, time_limit) for s in load_scenes(scenes, g)]
        rows, texts = [row for row, _ in made], [text for _, text in made]
        doc = {"grammar": g.name, "scenes": rows}
        if dest is not None:
            write_output_text(dest, json.dumps(doc, indent=1) + "\n")
    if dest is None and as_json:
        print(json.dumps(doc, indent=1))
    for r, text in zip(rows, texts, strict=True):
        if "objects" not in r:  # one line per scene, as `ssg parse` reports failures
            err.print(f"{r['scene']}: {r['status']}: {text}", markup=False, highlight=False)
        elif not as_json and output is None:
            out.print(text, markup=False, highlight=False)
    if code := exit_code(rows):
        raise typer.Exit(code)
