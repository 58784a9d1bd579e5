"""`ssg explain`: why a scene scores what it scores (ssgc.explain; docs/explain.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from .app import AllowOutside, _command, app, err, out

DIAGNOSE_S = 20.0  # seconds (at most) to find the objects that rule out an infeasible scene


def explain_results(grammar: Any, scenes: list[Any], time_limit: float | None) -> list[dict]:
    """One JSON object per scene: its explanation, the diagnosis of a scene proven infeasible
    (`diagnose` runs only then), or, for no_parse, the step that gave up."""
    from ssgc.explain import diagnose, explain_tree
    from ssgc.parse.parser import Parser

    parser = Parser(grammar)
    rows = []
    for scene in scenes:
        result = parser.parse(scene, top=1, time_limit=time_limit)
        if result.parses:
            e = explain_tree(grammar, scene, result.parses[0].tree, parser, time_limit)
            rows.append({"status": result.status, **e.to_json(), "_text": e.text(10)})
        elif result.status == "infeasible":
            d = diagnose(grammar, scene, parser, time_limit=time_limit or DIAGNOSE_S)
            rows.append(
                {
                    "scene": scene.name,
                    "status": "infeasible",
                    "diagnosis": d.to_json(),
                    "_text": d.message,
                }
            )
        else:  # no_parse (not proven: no diagnosis) or error
            row = {"scene": scene.name, "status": result.status, "_text": result.message}
            rows.append(row | ({"phase": result.phase} if result.phase else {}))
    return rows


@app.command()
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
        Path | None, typer.Option("-o", "--output", help="Write the JSON here.")
    ] = None,
    time_limit: Annotated[
        float | None, typer.Option("--time-limit", min=0.001, help="Seconds per scene.")
    ] = None,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Each object's and each rule's share of −log p of the best parse, most unusual first.

    A scene proven infeasible gets the objects and rules that rule it out (exit code 2); one
    without a parse found, unproven, says which step gave up (exit 3; 4 for the time limit).
    """
    from ssgc.compile import load_grammar
    from ssgc.io.outputs import check_output, lock_outputs, write_output_text
    from ssgc.io.scene import load_scenes
    from ssgc.parse.parser import exit_code

    dest = None if output is None else check_output(output, inputs=[grammar, scenes])
    with lock_outputs([dest]):
        g = load_grammar(grammar, allow_outside=allow_outside_files)
        rows = explain_results(g, load_scenes(scenes, g), time_limit)
        texts = [r.pop("_text") for r in rows]
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


def annotate(
    parser: Any,
    scene: Any,
    result: Any,
    top: int,
    explain_it: bool,
    time_limit: float | None,
    quiet: bool,
) -> dict[str, Any]:
    """`ssg parse`'s JSON of one scene, with the diagnosis of an infeasible scene (its message
    names the objects and rules that rule it out), the explanation with --explain, the objects
    each parse leaves to clutter (`observation: clutter`), and a note when fewer than --top
    distinct trees exist."""
    from ssgc.explain import diagnose, explain_tree
    from ssgc.observation import unexplained_objects
    from ssgc.parse.parser import result_to_json

    g = parser.grammar
    row = result_to_json(g, result)
    if result.status == "infeasible":
        d = diagnose(g, scene, parser, time_limit=min(time_limit or DIAGNOSE_S, DIAGNOSE_S))
        row["message"] = d.message
        row["diagnosis"] = d.to_json()
    elif result.parses:
        if g.observation is not None and g.observation.clutter is not None:
            for parse, p in zip(row["parses"], result.parses, strict=True):
                parse["unexplained"] = unexplained_objects(g, scene, p.tree)
        if explain_it:
            e = explain_tree(g, scene, result.parses[0].tree, parser, time_limit)
            row["explanation"] = e.to_json()
        if len(result.parses) < top and not quiet:
            err.print(f"{scene.name}: {result.message}", markup=False, highlight=False)
    return row
