"""`ssg parse`: the most probable parse trees of observed scenes (docs/parsing.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssgc.cli.app import (
    AllowOutside,
    _check_method,
    _command,
    _note_discarded,
    _progress,
    _summary,
    app,
    err,
)
from ssgc.compile import load_grammar
from ssgc.errors import SsgError
from ssgc.io.outputs import Output, check_output, lock_outputs, write_output


@app.command()
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
            "result by a convex relaxation (gap reported); ip uses pose proposals and "
            "refinement (no gap). auto: micp."
        ),
    ] = "auto",
    top: Annotated[int, typer.Option("--top", min=1, help="Distinct parse trees per scene.")] = 1,
    time_limit: Annotated[
        float | None, typer.Option("--time-limit", min=0.001, help="Seconds per scene.")
    ] = None,
    solver: Annotated[str, typer.Option(help="highs | scip")] = "highs",
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

    Exit code 2 when some scene cannot be produced by the grammar.
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
    from ssgc.cli.explain import annotate
    from ssgc.io.journal import ParseJournal, journal_path, run_header, write_parse_output
    from ssgc.io.scene import load_scenes
    from ssgc.parse.parser import Parser

    g = load_grammar(grammar, allow_outside=allow_outside_files)
    items = load_scenes(scenes, g)
    parser = Parser(g, method=method)
    if dest.stream:  # stdout or a device: nothing to resume, so the results are kept in memory
        results = []
        with _progress(quiet) as progress:
            task = progress.add_task("parsing", total=len(items))
            for scene in items:
                result = parser.parse(scene, top=top, time_limit=time_limit)
                results.append(annotate(parser, scene, result, top, explain, time_limit, quiet))
                progress.advance(task)
        with write_output(dest) as f:
            failed = write_parse_output(f, g.name, results)
    else:  # each result goes to the journal as soon as it is known, OUT.json at the end
        header = run_header(g.name, grammar, scenes, items, top, method, time_limit)
        with ParseJournal(journal_path(dest.target), header, resume) as journal:
            _note_discarded(journal, quiet)
            with _progress(quiet) as progress:
                task = progress.add_task("parsing", total=len(items))
                progress.advance(task, journal.done)
                for index in range(journal.done, len(items)):
                    scene = items[index]
                    result = parser.parse(scene, top=top, time_limit=time_limit)
                    row = annotate(parser, scene, result, top, explain, time_limit, quiet)
                    journal.append(index, row)
                    progress.advance(task)
            with write_output(dest, kept=journal.path) as f:
                failed = write_parse_output(f, g.name, journal.results())
        journal.delete()
    for r in failed:
        err.print(f"{r['name']}: {r['status']}: {r['message']}", markup=False, highlight=False)
    if not quiet and not dest.stdout:
        _summary(dest, f"parsed {len(items)} scene(s) -> {dest.name}")
    if any(r["status"] == "error" for r in failed):
        raise typer.Exit(1)
    if failed:
        raise typer.Exit(2)
