"""The `ssg` command line: a thin typer layer over the `ssgc` API.

Every command runs inside `_user_errors`, which turns an `SsgError` (a user's mistake) into its
located messages on stderr and a non-zero exit code.  Anything else is a bug in ssgc: it is
reported in one paragraph (set SSG_DEBUG=1 for the traceback), still never a raw traceback.
"""

from __future__ import annotations

import json
import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from ssgc import __version__
from ssgc.assets import check_assets
from ssgc.bench import bench_sample
from ssgc.cli import render as render_cli
from ssgc.compile import load_grammar
from ssgc.errors import GrammarError, SsgError
from ssgc.inspect import grammar_summary
from ssgc.io.journal import journal_path
from ssgc.io.outputs import (
    ENVIRONMENT_ERRNOS,
    Output,
    check_directory,
    check_output,
    directory_lock,
    lock_outputs,
    write_output,
    write_output_text,
)
from ssgc.io.resume import prepare_sample_dir, run_manifest, scan_sampled, write_manifest
from ssgc.io.scene import dumps_scene, scene_from_tree
from ssgc.sample.forward import CHUNK, chunk_rng, sample_chunk

app = typer.Typer(
    name="ssg",
    help="Spatial scene grammars: validate, inspect, sample, parse and fit them.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Measure speed; prints JSON with --json.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

# Text is printed as it is: no emoji codes (rich would print `g.yaml:100:3` as `g.yaml💯3`)
# and no markup (a grammar named "[/]" in an `inspect` table title would be an error).
out = Console(soft_wrap=True, emoji=False, markup=False)
err = Console(stderr=True, soft_wrap=True, emoji=False, markup=False)
MAX_SHOWN_DIAGNOSTICS = 30


@contextmanager
def _user_errors() -> Iterator[None]:
    try:
        yield
    except SsgError as exc:
        _print_diagnostics(exc)
        raise typer.Exit(exc.exit_code) from None
    except KeyboardInterrupt:
        err.print("ssg: interrupted")
        raise typer.Exit(130) from None
    except (typer.Exit, typer.Abort):
        raise
    except BrokenPipeError:  # `ssg ... | head`: the reader is gone; end quietly, as Unix tools do
        _silence_stdout()
        raise typer.Exit(EXIT_PIPE) from None
    except OSError as exc:
        if exc.errno not in ENVIRONMENT_ERRNOS:
            raise _internal_error(exc) from None
        _print_diagnostics(_environment_error(exc))
        raise typer.Exit(1) from None
    except Exception as exc:  # a bug in ssgc, not the user's mistake
        raise _internal_error(exc) from None


EXIT_PIPE = 141  # what a shell reports for a command ended by SIGPIPE (128 + 13)


def _internal_error(exc: Exception) -> typer.Exit:
    if os.environ.get("SSG_DEBUG"):
        raise exc
    err.print(
        f"ssg: internal error: {type(exc).__name__}: {exc}. This is a bug in ssgc; "
        "please report it with the command you ran (SSG_DEBUG=1 shows the traceback).",
        markup=False,
        highlight=False,
    )
    return typer.Exit(70)


def _environment_error(exc: OSError) -> SsgError:
    """A full disk, an I/O error, a denied permission: the machine's fault, exit 1.  An error
    without a file name comes from writing standard output (every file ssgc writes is named by
    `ssgc.io.outputs`)."""
    if exc.filename is None:
        _silence_stdout()  # what is still buffered cannot be written either
        return SsgError.single(f"cannot write standard output: {exc.strerror}", "<stdout>")
    return SsgError.single(exc.strerror or str(exc), str(exc.filename))


def _silence_stdout() -> None:
    """Point standard output at /dev/null, so the flush at exit neither fails nor complains
    (Python prints "Exception ignored ... BrokenPipeError" otherwise)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, ValueError, OSError):
        return  # not a real file (in tests: typer's CliRunner)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


def _print_diagnostics(exc: SsgError) -> None:
    shown = exc.diagnostics[:MAX_SHOWN_DIAGNOSTICS]
    for d in shown:
        err.print(str(d), markup=False, highlight=False)
    hidden = len(exc.diagnostics) - len(shown)
    if hidden > 0:
        err.print(f"... and {hidden} more", markup=False, highlight=False)


def _command(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap a command body in the user-error handler (keeps typer's signature intact)."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with _user_errors():
            return fn(*args, **kwargs)

    return wrapper


def _version(value: bool) -> None:
    if value:
        out.print(f"ssg {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version, is_eager=True, help="Print the version and exit."
        ),
    ] = False,
) -> None:
    """Spatial scene grammar compiler."""


GrammarArg = Annotated[Path, typer.Argument(help="Grammar YAML file.", show_default=False)]
# Mesh and model files a grammar names must be in its directory unless the user allows others
# (docs/robustness.md): a grammar from elsewhere cannot point ssg at arbitrary files.
AllowOutside = Annotated[
    bool,
    typer.Option(
        "--allow-outside-files",
        help="Allow mesh and model files outside the grammar's directory.",
    ),
]


app.command("render")(_command(render_cli.render))  # docs/render.md


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


@app.command()
@_command
def sample(
    grammar: GrammarArg,
    n: Annotated[int, typer.Option("-n", "--num", min=0, help="Number of scenes.")] = 10,
    seed: Annotated[
        int, typer.Option("--seed", "-s", min=0, max=2**63 - 1, help="Random seed.")
    ] = 0,
    output: Annotated[Path, typer.Option("-o", "--output", help="Output directory.")] = Path(
        "scenes"
    ),
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="No progress bar or summary.")
    ] = False,
    resume: Annotated[
        bool,
        typer.Option(
            "--resume", help="Keep the complete scene files of an interrupted run; draw the rest."
        ),
    ] = False,
    overwrite: Annotated[
        bool,
        typer.Option("--overwrite", help="Delete another run's scenes in the output directory."),
    ] = False,
    allow_outside_files: AllowOutside = False,
    constraints: Annotated[
        str | None,
        typer.Option(help="Sample under constraints: all, or NAME,NAME (docs/constraints.md)."),
    ] = None,
    method: Annotated[str, typer.Option(help="With --constraints: auto | rejection.")] = "auto",
    max_tries: Annotated[
        int | None, typer.Option(min=1, help="With --constraints: stop after this many candidates.")
    ] = None,
    time_limit: Annotated[
        float | None, typer.Option(min=0.001, help="With --constraints: stop after these seconds.")
    ] = None,
    export: Annotated[
        list[str] | None,
        typer.Option("--export", help="Also write each scene in this format (into OUTPUT/FORMAT)."),
    ] = None,
    settle: Annotated[
        bool, typer.Option("--settle", help="Settle each scene in MuJoCo before writing it.")
    ] = False,
) -> None:
    """Draw N scenes; write one JSON file per scene (objects, full tree, log-probability).

    Scene i depends only on the seed and i, and `--resume` finishes an interrupted run with the
    files an uninterrupted one would write.  The directory's manifest records the run; a
    directory holding another run's scenes is refused unless `--overwrite`.
    With --constraints, scenes follow the grammar conditioned on them; when --max-tries or
    --time-limit run out first, the exit code is 2 and the scenes found so far are kept.
    """
    if resume and overwrite:
        raise SsgError.single(
            "--resume keeps a run's scenes and --overwrite deletes them: give one"
        )
    g = load_grammar(grammar, allow_outside=allow_outside_files)
    constrained = constraints is not None or (max_tries, time_limit) != (None, None)
    if constrained and (export or settle):
        raise SsgError.single("--export and --settle do not work with --constraints yet")
    check_directory(output)
    extras = _export.SampleExtras(g, export or [], settle, output) if export or settle else None
    width = max(6, len(str(max(n - 1, 0))))
    with directory_lock(output):
        manifest = run_manifest(g.name, grammar, seed, n, width)
        manifest.update(constraints=constraints, method=method if constrained else None)
        prepare_sample_dir(output, manifest, resume, overwrite)
        if constrained:
            from ssgc.cli.constrained import sample_constrained

            options = (constraints, method, max_tries, time_limit, resume)
            sample_constrained(
                g,
                n,
                seed,
                output,
                quiet,
                options,
                _safe_stem(g.name),
                lambda: _write_manifest(output, manifest),
            )
            _write_manifest(output, {**manifest, "complete": True})
            return
        _sample_into(g, output, n, seed, width, manifest, resume, quiet, extras)


def _sample_into(
    g: Any,
    output: Path,
    n: int,
    seed: int,
    width: int,
    manifest: dict,
    resume: bool,
    quiet: bool,
    extras: Any = None,
) -> None:
    """`ssg sample`'s work, once the directory is checked and locked."""
    first: Path | None = None  # the first and last file written, for the summary
    last: Path | None = None
    count = 0
    stem = _safe_stem(g.name)

    def name_of(index: int) -> str:
        return f"{stem}_{index:0{width}d}"

    have = scan_sampled(output, stem, name_of, n, g.name, seed) if resume else None
    _write_manifest(output, manifest)
    with _progress(quiet) as progress:
        task = progress.add_task("sampling", total=n)
        for chunk in range((n + CHUNK - 1) // CHUNK):
            lo, hi = chunk * CHUNK, min(n, (chunk + 1) * CHUNK)
            if have is not None and have.done[lo:hi].all():
                progress.advance(task, hi - lo)
                continue  # nothing missing: the chunk is not even drawn
            trees, logp = sample_chunk(g, chunk_rng(seed, chunk))
            if have is not None:
                have.check_same_draws(lo, logp[: hi - lo], name_of)
            for index in range(lo, hi):
                k = index - lo
                if have is not None and have.done[index]:
                    progress.advance(task)
                    continue
                name = name_of(index)
                scene = scene_from_tree(g, trees.tree(k), name, float(logp[k]))
                path = output / f"{name}.json"
                if extras is None:
                    text = dumps_scene(g, scene, seed=seed, index=index)
                    write_output_text(Output(path, path, "scene file"), text)
                else:
                    extras.write(scene, path, seed, index)
                first, last = first or path, path
                count += 1
                progress.advance(task)
    _write_manifest(output, {**manifest, "complete": True})
    if not quiet:
        where = (
            f"{first} … {last.name}"
            if first is not None and last is not None and count > 1
            else str(first or output)
        )
        summary = f"wrote {count} scene(s) of grammar '{g.name}' (seed {seed}) to {where}"
        if have is not None:
            summary += f"; kept {int(have.done.sum())} complete scene file(s)"
            if have.removed_temps:
                summary += f", removed {have.removed_temps} temporary file(s) of a killed run"
        if extras is not None and extras.unsettled:
            summary += f"; {extras.unsettled} scene(s) did not settle"
        out.print(summary, markup=False, highlight=False)


@app.command()
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
    if diagram is not None:  # docs/render.md
        return render_cli.diagram(grammar, diagram, allow_outside_files)
    g = load_grammar(grammar, allow_outside=allow_outside_files)
    summary = grammar_summary(g)
    if as_json:
        print(json.dumps(summary, indent=1))
        return
    types = Table(title=f"grammar '{g.name}': node types")
    for col in ("type", "kind", "observed", "rules", "choice"):
        types.add_column(col)
    for t in summary["types"]:
        types.add_row(
            t["name"], t["kind"], "yes" if t["observed"] else "", str(len(t["rules"])), t["choice"]
        )
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
    from ssgc.cli.explain import annotate
    from ssgc.io.journal import ParseJournal, journal_path, run_header, write_parse_output
    from ssgc.io.scene import load_scenes
    from ssgc.parse.parser import Parser, exit_code

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
    if code := exit_code(failed):
        raise typer.Exit(code)


def _summary(dest_: Output, text: str) -> None:
    """The closing line: on stdout, unless the output itself went there."""
    (err if dest_.stdout else out).print(text, markup=False, highlight=False)


def _note_discarded(journal: Any, quiet: bool) -> None:
    if journal.discarded and not quiet:
        err.print(
            f"note: starting again; the journal {journal.path} of an interrupted run is "
            "replaced (--resume continues it)",
            markup=False,
            highlight=False,
        )


def _check_method(method: str, solver: str) -> None:
    if method not in ("auto", "ip", "micp"):
        raise SsgError.single(f"--method must be auto, ip or micp, got '{method}'")
    if solver == "scip":
        raise SsgError.single(
            "--solver scip is not available in this build; HiGHS (the default) solves every "
            "parse model, including the latent-pose bound"
        )
    if solver != "highs":
        raise SsgError.single(f"--solver must be highs or scip, got '{solver}'")


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


class EStep(StrEnum):
    """`ssg fit --estep` (docs/fitting.md section 1)."""

    topn = "topn"
    mcmc = "mcmc"


@app.command()
@_command
def fit(
    scenes: Annotated[
        Path,
        typer.Argument(
            help="The dataset: a directory of scene JSON files, one scene JSON, or a "
            "sink-format YAML file.",
            show_default=False,
        ),
    ],
    grammar: Annotated[Path, typer.Option("-g", "--grammar", help="Grammar YAML to fit.")],
    output: Annotated[
        Path, typer.Option("-o", "--output", help="Write the fitted grammar YAML here.")
    ],
    iterations: Annotated[int, typer.Option(min=1, help="At most this many EM iterations.")] = 10,
    top: Annotated[
        int, typer.Option("--top", min=1, help="Parse trees per scene (the E-step's N).")
    ] = 10,
    method: Annotated[str, typer.Option(help="Parsing method: auto | ip | micp.")] = "auto",
    seed: Annotated[int, typer.Option("--seed", "-s", min=0, max=2**63 - 1)] = 0,
    estep: Annotated[
        EStep, typer.Option(help="topn: weigh the top-N parses; mcmc: sample the posterior.")
    ] = EStep.topn,
    samples: Annotated[
        int, typer.Option(min=1, help="--estep mcmc: sampled rounds per scene.")
    ] = 100,
    pseudocount: Annotated[
        float,
        typer.Option(
            min=0.0, help="Added to every possible outcome of a discrete law (0: plain MLE)."
        ),
    ] = 0.01,
    min_variance: Annotated[
        float, typer.Option(min=1e-300, help="Floor of fitted variances (m²).")
    ] = 1e-6,
    tol: Annotated[
        float,
        typer.Option(min=0.0, help="Stop when the log-evidence changes less (nats per scene)."),
    ] = 1e-4,
    time_limit: Annotated[
        float | None,
        typer.Option(
            "--time-limit",
            min=0.001,
            help="Seconds for the whole fit; then the last "
            "finished iteration's grammar is written.",
        ),
    ] = None,
    report: Annotated[
        Path | None, typer.Option("--report", help="Write per-iteration numbers (JSON) here.")
    ] = None,
    jobs: Annotated[
        int, typer.Option("--jobs", "-j", min=1, help="Processes parsing scenes (same result).")
    ] = 1,
    mmd: Annotated[
        int,
        typer.Option(
            "--mmd",
            min=0,
            help="Then compare N scenes sampled from the input and the fitted grammar with the "
            "dataset: MMD² per object type (0: skip).",
        ),
    ] = 0,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue an interrupted fit from its journal.")
    ] = False,
    allow_outside_files: AllowOutside = False,
) -> None:
    """Fit a grammar's parameters to a dataset of scenes by approximate EM (thesis ch. 4).

    Writes the grammar back with only the fitted numbers changed: comments, order and layout
    are kept.  Exit code 2 when some scene cannot be produced by the grammar.
    """
    from ssgc.compile import compile_text
    from ssgc.fit.em import (
        FitJournal,
        FitOptions,
        GrammarSource,
        fit_grammar,
        fit_header,
        report_json,
    )
    from ssgc.fit.metrics import compare_by_mmd
    from ssgc.fit.mstep import FitSettings
    from ssgc.io.scene import load_scenes
    from ssgc.yamlio import MAX_GRAMMAR_BYTES, read_text

    _check_method(method, "highs")
    # `-o` may be the grammar itself (an in-place update), never the dataset.
    dest = check_output(output, inputs=[grammar, scenes], in_place=[grammar])
    report_dest = None
    if report is not None:
        report_dest = check_output(report, "report", inputs=[grammar, scenes], others=[dest])
    if resume and dest.stream:
        raise SsgError.single("--resume needs -o FILE: the journal is kept next to it", dest.name)
    text = read_text(grammar, MAX_GRAMMAR_BYTES, "grammar file")

    source = GrammarSource(str(grammar), grammar.parent, allow_outside_files, str(scenes))
    g = compile_text(text, source.file, source.base_dir, source.allow_outside)
    items = load_scenes(scenes, g)
    if not items:
        raise SsgError.single("the dataset has no scenes", str(scenes))
    options = FitOptions(
        iterations=iterations,
        top=top,
        method=method,
        seed=seed,
        tol=tol,
        jobs=jobs,
        estep=estep.value,
        samples=samples,
        settings=FitSettings(pseudocount=pseudocount, min_variance=min_variance),
    )
    header = fit_header(text, scenes, items, options)
    with (
        lock_outputs([dest, report_dest]),
        _fit_journal_path(dest) as journal_file,
        FitJournal(journal_file, header, resume) as journal,
    ):
        _note_discarded(journal, quiet)
        for r in journal.reports:
            _print_iteration(r, quiet, resumed=True)
        with _progress(quiet) as progress:
            task = progress.add_task(
                f"iteration {journal.iteration}", total=len(items), completed=len(journal.scenes)
            )

            def on_iteration(r: dict[str, Any]) -> None:
                _print_iteration(r, quiet)
                progress.reset(task, description=f"iteration {r['iteration'] + 1}")

            result = fit_grammar(
                text,
                source,
                items,
                options,
                journal,
                time_limit=time_limit,
                on_scene=lambda: progress.advance(task),
                on_iteration=on_iteration,
            )
        if mmd:
            fitted = compile_text(result.text, source.file, source.base_dir, allow_outside_files)
            result.mmd = compare_by_mmd({"input": g, "fitted": fitted}, items, mmd, seed)
            _print_mmd(result.mmd, quiet)
        kept = None if dest.stream else journal.path
        write_output_text(dest, result.text, kept)
        if report_dest is not None:
            write_output_text(report_dest, report_json(result), kept)
        if result.status != "time_limit":
            journal.delete()
    if not quiet:
        _summary(dest, f"{result.message}; wrote {dest.name}")


@contextmanager
def _fit_journal_path(dest: Output) -> Iterator[Path]:
    """The fit journal's place: next to the output file, or, for a stream (which cannot be
    resumed), in a temporary directory removed at the end."""
    if not dest.stream:
        yield journal_path(dest.target)
        return
    with tempfile.TemporaryDirectory(prefix="ssg-fit-") as tmp:
        yield Path(tmp) / "fit.partial.jsonl"


def _print_mmd(mmd: dict[str, dict[str, float]], quiet: bool) -> None:
    if quiet:
        return
    names = sorted({name for per_type in mmd.values() for name in per_type})
    for name in names:
        values = ", ".join(
            f"{which} {per_type[name]:.4g}" for which, per_type in mmd.items() if name in per_type
        )
        err.print(f"MMD² {name}: {values}", markup=False, highlight=False)


def _print_iteration(r: dict[str, Any], quiet: bool, resumed: bool = False) -> None:
    if quiet:
        return
    line = (
        f"iteration {r['iteration']}: log-evidence {r['log_evidence']:.4f} "
        f"(mean best tree {r['mean_best_score']:.4f}), {r['scenes']} scene(s), "
        f"{r['trees']} tree(s)"
    )
    line += " (from the journal)" if resumed else f", {r['seconds']:.2f} s"
    err.print(line, markup=False, highlight=False)
    for s in r.get("skipped", []):
        err.print(f"  skipped {s}", markup=False, highlight=False)
    if "warning" in r.get("posterior", {}):
        err.print(f"  warning: {r['posterior']['warning']}", markup=False, highlight=False)


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


def _safe_stem(name: str) -> str:
    """A grammar name as a file-name stem: never a path, never hidden."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).lstrip(".")
    return stem or "scene"


def _write_manifest(directory: Path, manifest: dict) -> None:
    try:
        write_manifest(directory, manifest)
    except OSError as exc:
        raise SsgError.single(
            f"cannot write the manifest: {exc.strerror}", str(directory)
        ) from None


@contextmanager
def _progress(quiet: bool) -> Iterator[Progress]:
    progress = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=err,
        disable=quiet or not sys.stderr.isatty(),
        transient=True,
    )
    with progress:
        yield progress


# Commands in files of their own register themselves on `app` when imported.
from ssgc.cli import explain as _explain  # noqa: E402, F401  (registers `ssg explain`)
from ssgc.cli import export as _export  # noqa: E402
from ssgc.cli import settle as _settle  # noqa: E402, F401


def main() -> None:
    np.seterr(all="ignore")  # -inf log-probabilities are expected values, not warnings
    try:
        app()
        code: Any = 0
    except SystemExit as exc:
        code = exc.code
    sys.exit(_flush_stdout(code))


def _flush_stdout(code: Any) -> Any:
    """Write out what standard output still buffers before Python does it at exit, where a
    closed pipe or a full disk would only print "Exception ignored" and exit 120."""
    try:
        if sys.stdout is not None:
            sys.stdout.flush()
    except BrokenPipeError:
        _silence_stdout()
        return code or EXIT_PIPE
    except OSError as exc:
        _silence_stdout()
        _print_diagnostics(
            SsgError.single(f"cannot write standard output: {exc.strerror}", "<stdout>")
        )
        return code or 1
    return code


if __name__ == "__main__":
    # `python -m ssgc.cli.app`: run the importable module, on whose `app` the commands of
    # cli/export.py and cli/settle.py registered (not this __main__ copy's).
    from ssgc.cli.app import main as _real_main

    _real_main()
