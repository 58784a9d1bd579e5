"""`ssg render`: draw scenes, sampled trees and parse results (docs/render.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssgc.compile import load_grammar


def render(
    source: Annotated[
        Path,
        typer.Argument(
            help="A scene or `ssg parse` result JSON file, or a directory of scenes.",
            show_default=False,
        ),
    ],
    output: Annotated[
        Path, typer.Option("-o", "--output", help="Image file: .png or .svg.", show_default=False)
    ],
    num: Annotated[int, typer.Option("-n", "--num", help="Draw the first N scenes as a grid.")] = 1,
    grammar: Annotated[
        Path | None,
        typer.Option("-g", "--grammar", help="Grammar for the objects' geometry (optional)."),
    ] = None,
    scene: Annotated[
        str | None, typer.Option("--scene", help="Draw only the scene of this name.")
    ] = None,
    quiet: Annotated[bool, typer.Option("-q", "--quiet", help="No summary line.")] = False,
    allow_outside_files: Annotated[  # app.AllowOutside, which this module cannot import first
        bool,
        typer.Option(
            "--allow-outside-files",
            help="Allow mesh and model files outside the grammar's directory.",
        ),
    ] = False,
) -> None:
    """Draw scenes in 3-D and from above, with their trees; a parse's edges by rule score."""
    from ssgc.cli.app import _warnings_about  # here: app imports this module at its top
    from ssgc.io.outputs import lock_outputs
    from ssgc.render.scene import check_output, render_file, require_matplotlib

    dest, _ = check_output(output, inputs=(source,))
    require_matplotlib()
    with lock_outputs([dest]):  # one writer per output (docs/robustness.md)
        g = None if grammar is None else load_grammar(grammar, allow_outside=allow_outside_files)
        with _warnings_about(source):
            count = render_file(source, output, n=num, grammar=g, scene=scene)
    if not quiet:  # on stderr when the picture went to stdout
        typer.echo(f"drew {count} scene(s) of {source} to {output}", err=dest.stdout)


def diagram(grammar_path: Path, output: Path, allow_outside: bool) -> None:
    """`ssg inspect --diagram`: the grammar's types and rules as a layered graph."""
    from ssgc.cli.app import _warnings_about
    from ssgc.io.outputs import lock_outputs
    from ssgc.render.diagram import DIAGRAM_EXAMPLE, render_diagram
    from ssgc.render.scene import check_output, require_matplotlib

    dest, _ = check_output(output, inputs=(grammar_path,), example=DIAGRAM_EXAMPLE)
    require_matplotlib()
    with lock_outputs([dest]), _warnings_about(grammar_path):  # one writer per output
        render_diagram(load_grammar(grammar_path, allow_outside=allow_outside), output)
    typer.echo(f"drew the diagram of {grammar_path} to {output}", err=dest.stdout)
