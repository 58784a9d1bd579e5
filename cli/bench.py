"""`ssg bench sample` and `ssg bench parse`: speed measurements, JSON with --json."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from ssgc.bench import bench_sample
from ssgc.cli.app import GrammarArg, _check_method, _command, bench_app, out
from ssgc.compile import load_grammar


@bench_app.command("sample")
@_command
def bench_sample_cmd(
    grammar: GrammarArg,
    n: Annotated[int, typer.Option("-n", "--num", min=1, help="Scenes to sample.")] = 20000,
    seed: Annotated[int, typer.Option("--seed", "-s", min=0, max=2**63 - 1)] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    constraints: Annotated[
        str | None,
        typer.Option(help="Valid scenes/s under: all, or NAME,NAME (-n defaults to 1,000 then)."),
    ] = None,
) -> None:
    """Sampling and scoring speed: scenes per second, seconds per tree score."""
    if constraints is not None:
        from ssgc.bench import bench_constrained

        g = load_grammar(grammar)
        result = bench_constrained(g, constraints, n if n != 20000 else 1000, seed)
    else:
        result = bench_sample(load_grammar(grammar), n, seed)
    if as_json:
        print(json.dumps(result, indent=1))
    else:
        for key, value in result.items():
            out.print(f"{key:>28}: {value}", markup=False, highlight=False)


@bench_app.command("parse")
@_command
def bench_parse_cmd(
    grammar: GrammarArg,
    scenes: Annotated[int, typer.Option("--scenes", min=1, help="Scenes to sample.")] = 100,
    seed: Annotated[int, typer.Option("--seed", "-s", min=0, max=2**63 - 1)] = 0,
    method: Annotated[str, typer.Option(help="auto | ip | micp")] = "auto",
    top: Annotated[int, typer.Option("--top", min=1)] = 1,
    time_limit: Annotated[float | None, typer.Option("--time-limit", min=0.001)] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Sample scenes, parse them, compare with the sampled trees; timings per scene."""
    from ssgc.bench import bench_parse

    _check_method(method, "highs")
    result = bench_parse(load_grammar(grammar), scenes, seed, top, time_limit, method)
    if as_json:
        print(json.dumps(result, indent=1))
    else:
        for key, value in result["summary"].items():
            out.print(f"{key:>22}: {value}", markup=False, highlight=False)
