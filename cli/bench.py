"""`ssg bench sample`, `ssg bench parse` and `ssg bench fit`: speed measurements, JSON with
--json."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from ssgc.bench import bench_sample
from ssgc.cli.app import (
    AllowOutside,
    GrammarArg,
    _check_method,
    _command,
    _in_range,
    bench_app,
    finite_from,
    out,
)
from ssgc.compile import load_grammar
from ssgc.errors import SsgError
from ssgc.laws.rotation_bingham import MAX_CONCENTRATION

SEED = "Seed of the sampled scenes: the same seed, the same scenes."


@bench_app.command("sample", short_help="Sampling and scoring speed.")
@_command
def bench_sample_cmd(
    grammar: GrammarArg,
    n: Annotated[
        int | None,
        typer.Option(
            "-n", "--num", min=1, help="Scenes to sample (20,000; with --constraints 1,000)."
        ),
    ] = None,
    seed: Annotated[int, typer.Option("--seed", "-s", min=0, max=2**63 - 1, help=SEED)] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    constraints: Annotated[
        str | None,
        typer.Option(help="Valid scenes/s under: all, or NAME,NAME (-n defaults to 1,000 then)."),
    ] = None,
    jobs: Annotated[
        int, typer.Option("--jobs", "-j", min=1, help="With --constraints: processes sampling.")
    ] = 1,
    method: Annotated[
        str | None,
        typer.Option(help="With --constraints: the methods to time, M or M,M (default: all)."),
    ] = None,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Sampling and scoring speed: scenes per second, seconds per tree score."""
    if constraints is None and (method is not None or jobs != 1):
        raise SsgError.single("--method and -j time sampling under --constraints, not given")
    g = load_grammar(grammar, allow_outside=allow_outside_files)
    if constraints is not None:
        from ssgc.bench import bench_constrained

        methods = None if method is None else [m.strip() for m in method.split(",")]
        result = bench_constrained(g, constraints, n or 1000, seed, methods, jobs)
    else:
        result = bench_sample(g, n or 20000, seed)
    if as_json:
        print(json.dumps(result, indent=1))
    else:
        for key, value in result.items():
            out.print(f"{key:>28}: {value}", markup=False, highlight=False)


@bench_app.command("parse", short_help="Parse sampled scenes: speed and quality.")
@_command
def bench_parse_cmd(
    grammar: GrammarArg,
    scenes: Annotated[int, typer.Option("--scenes", min=1, help="Scenes to sample.")] = 100,
    seed: Annotated[int, typer.Option("--seed", "-s", min=0, max=2**63 - 1, help=SEED)] = 0,
    method: Annotated[str, typer.Option(help="auto | ip | micp")] = "auto",
    top: Annotated[int, typer.Option("--top", min=1, help="Parse trees per scene.")] = 1,
    time_limit: Annotated[
        float | None,
        typer.Option(
            "--time-limit", callback=finite_from(0.001), help="Seconds per scene's parse."
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Sample scenes, parse them, compare with the sampled trees; timings per scene."""
    from ssgc.bench import bench_parse

    _check_method(method, "highs")
    result = bench_parse(
        load_grammar(grammar, allow_outside=allow_outside_files),
        scenes,
        seed,
        top,
        time_limit,
        method,
    )
    _print(result, as_json)


@bench_app.command("fit", short_help="Seconds per EM iteration.")
@_command
def bench_fit_cmd(
    grammar: GrammarArg,
    dataset: Annotated[str, typer.Argument(help="Scenes to fit to (anything ssg fit reads).")],
    iterations: Annotated[int, typer.Option("--iterations", min=1, help="EM iterations.")] = 2,
    top: Annotated[int, typer.Option("--top", min=1, help="Parse trees per scene.")] = 1,
    jobs: Annotated[int, typer.Option("--jobs", "-j", min=1, help="Processes parsing.")] = 1,
    max_concentration: Annotated[
        float,
        typer.Option(
            callback=lambda v: _in_range(v, "--max-concentration", 0.0, MAX_CONCENTRATION),
            help="As ssg fit's.",
        ),
    ] = 1e4,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    allow_outside_files: AllowOutside = False,
) -> None:
    """EM speed: seconds per iteration, split into the E-step (parsing) and the M-step."""
    from ssgc.bench import bench_fit

    result = bench_fit(
        str(grammar), dataset, iterations, top, jobs, max_concentration, allow_outside_files
    )
    _print(result, as_json)


def _print(result: dict, as_json: bool) -> None:
    """The whole result as JSON, or its summary as aligned lines."""
    if as_json:
        print(json.dumps(result, indent=1))
    else:
        for key, value in result["summary"].items():
            out.print(f"{key:>22}: {value}", markup=False, highlight=False)
