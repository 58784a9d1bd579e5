"""`ssg parse`: the most probable parse trees of observed scenes (docs/parsing.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssgc.cli.app import (
    AllowOutside,
    _check_method,
    _command,
    _progress,
    _summary,
    app,
    err,
    finite_from,
)
from ssgc.compile import load_grammar
from ssgc.errors import SsgError
from ssgc.io.outputs import Output, check_output, lock_outputs


@app.command(short_help="Most probable parse trees of scenes.")
@_command
def parse(
    scenes: Annotated[
        Path,
        typer.Argument(
            help="A scene JSON, a directory of them, or a sink-format YAML dataset.",
            show_default=False,
        ),
    ],
    grammar: Annotated[Path, typer.Option("-g", "--grammar", help="Grammar YAML file.")],
    method: Annotated[
        str,
        typer.Option(
            help="auto | ip | micp. Same exact parser for grammars without latent poses. With "
            "latent poses: micp optimises them per assignment of children and certifies the "
            "result by a convex relaxation; ip uses pose proposals and refinement, certified "
            "by the assignment bound where the grammar's shape has one. Both report the gap. "
            "auto: micp."
        ),
    ] = "auto",
    top: Annotated[int, typer.Option("--top", min=1, help="Distinct parse trees per scene.")] = 1,
    time_limit: Annotated[
        float | None,
        typer.Option("--time-limit", callback=finite_from(0.001), help="Seconds per scene."),
    ] = None,
    solver: Annotated[str, typer.Option(help="highs: the MILP solver of this build.")] = "highs",
    output: Annotated[
        Path | None, typer.Option("-o", "--output", help="Write JSON here (default: stdout).")
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    resume: Annotated[
        bool,
        typer.Option("--resume", help="Continue an interrupted run with -o from its journal."),
    ] = False,
    explain: Annotated[
        bool, typer.Option("--explain", help="Add each scene's explanation (as ssg explain).")
    ] = False,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Most probable parse trees of observed scenes (MAP parsing by MILP on HiGHS).

    Exit code 2 when some scene is proven not to be produced by the grammar; 3 when no parse
    was found for some scene without a proof that none exists; 4 when the time limit ran out
    before a parse of some scene was found (docs/parsing.md "Statuses").
    """
    _check_method(method, solver)
    dest = check_output(output or "-", inputs=[grammar, scenes])
    if resume and dest.stream:
        raise SsgError.single(
            "--resume needs -o OUT.json, a file: the progress is kept next to it", dest.name
        )
    with lock_outputs([dest]):
        _parse_into(
            dest,
            scenes,
            grammar,
            method,
            top,
            time_limit,
            quiet,
            resume,
            allow_outside_files,
            explain,
        )


def _parse_into(
    dest: Output,
    scenes: Path,
    grammar: Path,
    method: str,
    top: int,
    time_limit: float | None,
    quiet: bool,
    resume: bool,
    allow_outside_files: bool,
    explain: bool,
) -> None:
    """`ssg parse`'s work, once its output is checked and locked."""
    from ssgc.io.scene import load_scenes
    from ssgc.parse.parser import Parser
    from ssgc.scene_reports import parse_to_output

    g = load_grammar(grammar, allow_outside=allow_outside_files)
    items = load_scenes(scenes, g)
    parser = Parser(g, method=method)

    def note(line: str) -> None:
        err.print(line, markup=False, highlight=False)

    with _progress(quiet) as progress:
        task = progress.add_task("parsing", total=len(items))
        failed = parse_to_output(
            dest,
            grammar,
            scenes,
            parser,
            items,
            top,
            time_limit,
            explain,
            resume,
            step=lambda k: progress.advance(task, k),
            note=None if quiet else note,
        )
    for r in failed:
        err.print(f"{r['name']}: {r['status']}: {r['message']}", markup=False, highlight=False)
    if not quiet and not dest.stdout:
        _summary(dest, f"parsed {len(items)} scene(s) -> {dest.name}")
    from ssgc.parse.parser import exit_code

    if code := exit_code(failed):
        raise typer.Exit(code)
