"""`ssg validate`: check grammars, every error located as FILE:LINE:COL."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssgc.assets import check_assets, check_document_meshes
from ssgc.cli.app import AllowOutside, _command, _print_diagnostics, app, err, out
from ssgc.compile import load_grammar
from ssgc.errors import Diagnostic, GrammarError, SsgError
from ssgc.ir import Grammar


@app.command(short_help="Check grammars: FILE:LINE:COL messages.")
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
            g, found = _check(path, allow_outside_files)
        except SsgError as exc:
            _print_diagnostics(exc)
            failed += 1
            continue
        if g is None or any(d.severity == "error" for d in found):
            _print_diagnostics(GrammarError(_shown(found, quiet)))
            failed += 1
            continue
        for w in _shown(found, quiet):
            err.print(str(w), markup=False, highlight=False)
        if not quiet:
            out.print(
                f"{path}: ok ({len(g.types)} types, {len(g.rules)} rules)",
                markup=False,
                highlight=False,
            )
    if failed:
        raise typer.Exit(1)


def _shown(found: list[Diagnostic], quiet: bool) -> list[Diagnostic]:
    """The messages to print: with `-q` ("Print errors only.") the errors alone, so that a
    script checking many grammars sees only what fails them; the exit code is the same."""
    return [d for d in found if d.severity == "error"] if quiet else found


def _check(path: Path, allow_outside: bool) -> tuple[Grammar | None, list[Diagnostic]]:
    """The compiled grammar (None if it has errors) and every message about it: the
    compiler's and, since validate opens every mesh (missing or unreadable is an error), the
    meshes' too, in one round."""
    try:
        g = load_grammar(path, allow_outside=allow_outside)
    except GrammarError as exc:
        return None, _with_meshes(exc.diagnostics, _mesh_errors(path, exc, allow_outside))
    return g, _with_meshes(list(g.warnings), check_assets(g))


def _with_meshes(found: list[Diagnostic], mesh_errors: list[Diagnostic]) -> list[Diagnostic]:
    """The compiler's messages with the mesh errors, errors before warnings as the compiler
    gives them.  The compiler's warning that a mesh is missing is left out where the same
    mesh is reported as an error: one message for one mistake."""
    places = {(d.line, d.column) for d in mesh_errors}
    kept = [d for d in found if d.severity == "error" or (d.line, d.column) not in places]
    errors = [d for d in kept if d.severity == "error"] + mesh_errors
    return errors + [d for d in kept if d.severity != "error"]


def _mesh_errors(path: Path, exc: GrammarError, allow_outside: bool) -> list[Diagnostic]:
    """The mesh files of a grammar that does not compile, opened all the same, so that a
    missing one is reported with the grammar's other errors (docs/grammar.md section 6)."""
    seen = {str(d) for d in exc.diagnostics}
    return [d for d in check_document_meshes(path, allow_outside) if str(d) not in seen]
