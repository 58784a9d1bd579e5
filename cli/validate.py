"""`ssg validate`: check grammars, every error located as FILE:LINE:COL."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssgc.assets import check_assets
from ssgc.cli.app import AllowOutside, _command, _print_diagnostics, app, err, out
from ssgc.compile import load_grammar
from ssgc.errors import GrammarError, SsgError


@app.command()
@_command
def validate(
    grammars: Annotated[list[Path], typer.Argument(help="Grammar YAML files.", show_default=False)],
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print errors only.")] = False,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Check grammars; print FILE:LINE:COL messages; exit 1 if any has an error."""
    failed = 0
    for path in grammars:
        try:
            g = load_grammar(path, allow_outside=allow_outside_files)
            mesh_errors = check_assets(g)  # every mesh opened: missing or unreadable is an error
            if mesh_errors:
                raise GrammarError(mesh_errors)
        except SsgError as exc:
            _print_diagnostics(exc)
            failed += 1
            continue
        for w in g.warnings:
            err.print(str(w), markup=False, highlight=False)
        if not quiet:
            out.print(
                f"{path}: ok ({len(g.types)} types, {len(g.rules)} rules)",
                markup=False,
                highlight=False,
            )
    if failed:
        raise typer.Exit(1)
