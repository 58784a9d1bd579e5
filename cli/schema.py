"""`ssg schema` (hidden): regenerate the JSON Schemas of grammar and scene files."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssgc.cli.app import _command, app, out
from ssgc.io.outputs import Output, check_directory, write_output_text


@app.command("schema", hidden=True)
@_command
def schema_cmd(
    directory: Annotated[Path, typer.Argument(help="Where to write the schemas.")] = Path(
        "schemas"
    ),
) -> None:
    """Regenerate the JSON Schemas of grammar and scene files."""
    from ssgc.schemas import SCHEMA_FILES, schema_text

    check_directory(directory)
    for name, model in SCHEMA_FILES.items():
        path = directory / name
        write_output_text(Output(path, path, "schema file"), schema_text(model))
        out.print(f"wrote {path}", markup=False, highlight=False)
