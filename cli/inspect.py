"""`ssg inspect`: a grammar's node types and rules as tables or JSON, or its diagram."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from ssgc.cli import render as render_cli
from ssgc.cli.app import AllowOutside, GrammarArg, _command, app, out
from ssgc.compile import load_grammar
from ssgc.errors import SsgError
from ssgc.inspect import grammar_summary


@app.command(short_help="A grammar's types, rules and supertree size.")
@_command
def inspect(
    grammar: GrammarArg,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of tables.")] = False,
    allow_outside_files: AllowOutside = False,
    diagram: Annotated[
        Path | None, typer.Option("--diagram", help="Draw the grammar to OUT.svg or OUT.png.")
    ] = None,
) -> None:
    """Show the node types and rules of a grammar, and its supertree size."""
    if diagram is not None and as_json:
        raise SsgError.single("--diagram draws the grammar and --json prints it: give one")
    if diagram is not None:  # docs/render.md
        return render_cli.diagram(grammar, diagram, allow_outside_files)
    g = load_grammar(grammar, allow_outside=allow_outside_files)
    summary = grammar_summary(g)
    if as_json:
        print(json.dumps(summary, indent=1))
        return
    types = Table(title=f"grammar '{g.name}': node types")
    for col in ("type", "kind", "observed", "rules", "choice", "added by observation"):
        types.add_column(col)
    for t in summary["types"]:
        observed, added = "yes" if t["observed"] else "", t["synthetic"] or ""
        types.add_row(t["name"], t["kind"], observed, str(len(t["rules"])), t["choice"], added)
    rules = Table(title="rules")
    for col in ("id", "parent[i] -> child", "translation", "rotation"):
        rules.add_column(col)
    for r in summary["rules"]:
        rules.add_row(str(r["id"]), r["name"], r["translation"], r["rotation"])
    out.print(types)
    out.print(rules)
    size = summary["supertree_nodes"]
    nodes = "too large to count" if size is None else f"{size} nodes"
    out.print(f"root: {summary['root']}   supertree: {nodes}")
