"""`ssg fit`: fit a grammar's parameters to a dataset by approximate EM (docs/fitting.md)."""

from __future__ import annotations

import os
import sys
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from ssgc.api import POSTERIOR_SAMPLES, fit_defaults, fit_options
from ssgc.cli.app import (
    AllowOutside,
    _check_method,
    _command,
    _in_range,
    _note_discarded,
    _progress,
    _summary,
    _warnings_about,
    app,
    err,
    finite_from,
)
from ssgc.cli.progress import SceneLines
from ssgc.errors import SsgError
from ssgc.fit.mstep import MAX_MIN_VARIANCE, MAX_PSEUDOCOUNT
from ssgc.io.journal import JournalWriteError, journal_path
from ssgc.io.outputs import Output, check_output, lock_outputs, lock_path, write_output_text
from ssgc.laws.rotation_bingham import MAX_CONCENTRATION

if TYPE_CHECKING:
    from ssgc.api import FitRun
    from ssgc.fit.em import FitResult as FitReport

DEFAULTS = fit_defaults()  # `ssgc.fit`'s: one place for the defaults of the API and the command


class EStep(StrEnum):
    """`ssg fit --estep` (docs/fitting.md section 1)."""

    topn = "topn"
    mcmc = "mcmc"


DEFAULT_ESTEP = EStep(DEFAULTS["estep"])


@app.command(short_help="Fit a grammar's numbers to scenes (EM).")
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
    iterations: Annotated[
        int, typer.Option(min=1, help="At most this many EM iterations.")
    ] = DEFAULTS["iterations"],
    top: Annotated[
        int, typer.Option("--top", min=1, help="Parse trees per scene (the E-step's N).")
    ] = DEFAULTS["top"],
    method: Annotated[str, typer.Option(help="Parsing method: auto | ip | micp.")] = DEFAULTS[
        "method"
    ],
    seed: Annotated[
        int,
        typer.Option(
            "--seed",
            "-s",
            min=0,
            max=2**63 - 1,
            help="Seed of everything random: pose proposals, mcmc chains, --mmd and --plot "
            "samples.",
        ),
    ] = DEFAULTS["seed"],
    estep: Annotated[
        EStep, typer.Option(help="topn: weigh the top-N parses; mcmc: sample the posterior.")
    ] = DEFAULT_ESTEP,
    samples: Annotated[
        int | None,
        typer.Option(
            min=1,
            show_default=False,
            help=f"--estep mcmc: rounds kept per scene, {POSTERIOR_SAMPLES} unless given "
            "(after S/2 of burn-in).",
        ),
    ] = None,
    pseudocount: Annotated[
        float,
        typer.Option(
            callback=finite_from(0.0, MAX_PSEUDOCOUNT),
            help="Added to every possible outcome of a discrete law (0: plain MLE; at most "
            f"{MAX_PSEUDOCOUNT:g}).",
        ),
    ] = DEFAULTS["pseudocount"],
    min_variance: Annotated[
        float,
        typer.Option(
            callback=lambda v: _in_range(v, "--min-variance", 0.0, MAX_MIN_VARIANCE),
            help="Floor of fitted variances (m², 0 < v ≤ 1e6).",
        ),
    ] = DEFAULTS["min_variance"],
    max_concentration: Annotated[
        float,
        typer.Option(
            callback=lambda v: _in_range(v, "--max-concentration", 0.0, MAX_CONCENTRATION),
            help="Ceiling of fitted Bingham concentrations (0 < c ≤ 10000: a spread of about "
            "√(2/c) rad).",
        ),
    ] = DEFAULTS["max_concentration"],
    tol: Annotated[
        float,
        typer.Option(
            callback=finite_from(0.0),
            help="Stop when the log-evidence changes less (nats per scene).",
        ),
    ] = DEFAULTS["tol"],
    time_limit: Annotated[
        float | None,
        typer.Option(
            "--time-limit",
            callback=finite_from(0.001),
            help="Seconds for the EM loop (not loading, --mmd, --plot or writing); then the "
            "last finished iteration's grammar is written.",
        ),
    ] = None,
    report: Annotated[
        Path | None, typer.Option("--report", help="Write per-iteration numbers (JSON) here.")
    ] = None,
    jobs: Annotated[
        int, typer.Option("--jobs", "-j", min=1, help="Processes parsing scenes (same result).")
    ] = DEFAULTS["jobs"],
    mmd: Annotated[
        int,
        typer.Option(
            "--mmd",
            min=0,
            help="Then compare N scenes sampled from the input and the fitted grammar with the "
            "dataset: MMD² per object type (0: skip).",
        ),
    ] = 0,
    plot: Annotated[
        Path | None,
        typer.Option(
            "--plot",
            help="Draw log-evidence per iteration, count histograms and positions of the data "
            "against samples into this directory (PNG).",
        ),
    ] = None,
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
    from ssgc.api import Grammar, load_grammar, open_fit
    from ssgc.fit.em import report_json
    from ssgc.fit.metrics import compare_by_mmd
    from ssgc.io.scene import load_scenes

    _check_method(method, "highs")
    options = fit_options(  # told before any work
        iterations=iterations,
        top=top,
        method=method,
        seed=seed,
        tol=tol,
        estep=estep.value,
        samples=samples,
        pseudocount=pseudocount,
        min_variance=min_variance,
        max_concentration=max_concentration,
        jobs=jobs,
    )
    # `-o` may be the grammar itself (an in-place update), never the dataset.
    dest = check_output(output, inputs=[grammar, scenes], in_place=[grammar])
    report_dest = None
    if report is not None:
        report_dest = check_output(report, "report", inputs=[grammar, scenes], others=[dest])
    plots = None
    if plot is not None:
        from ssgc.render.fit import check_plot_outputs, require_matplotlib

        require_matplotlib()
        plots = check_plot_outputs(plot, [grammar, scenes], [dest, report_dest])
    _refuse_side_files(dest, [o for o in (report_dest, *(plots or [])) if o is not None])
    if resume and dest.stream:
        raise SsgError.single("--resume needs -o FILE: the journal is kept next to it", dest.name)
    g = load_grammar(grammar, allow_outside=allow_outside_files)
    items = load_scenes(scenes, g.ir)
    with (
        lock_outputs([dest, report_dest, *(plots or [])]),
        open_fit(g, items, scenes, options, None if dest.stream else dest.target, resume) as run,
    ):
        journal = run.journal
        try:
            result = _run_with_progress(run, len(items), time_limit, quiet)
        except JournalWriteError:
            raise  # its finished work is kept for --resume, as the message says
        except SsgError:  # the grammar or a scene: a resumed run would stop the same way
            journal.delete()
            raise
        fitted: Grammar | None = None
        if mmd or plots is not None:
            fitted = run.fitted(result)
        if mmd and fitted is not None:
            result.mmd = compare_by_mmd({"input": g.ir, "fitted": fitted.ir}, items, mmd, seed)
            _print_mmd(result.mmd, quiet)
        if plots is not None and fitted is not None:
            from ssgc.render.fit import plot_fit

            with _warnings_about(grammar):  # the pictures' names are the grammar's types
                plot_fit(plots, result.iterations, items, fitted.ir, g.ir, seed)
        # -o last: when it is the grammar itself, a run stopped before (in the plots) leaves
        # the grammar and its journal as they were, so --resume finishes it
        kept = None if dest.stream else journal.path
        if report_dest is not None:
            write_output_text(report_dest, report_json(result), kept)
        write_output_text(dest, _with_bom_of(grammar, result.text), kept)
        if result.status != "time_limit":
            journal.delete()
    if not quiet:
        _note_noise_kept(result.noise_kept)
        _summary(dest, f"{result.message}; wrote {dest.name}")


def _side_files(dest: Output, others: list[Output]) -> list[tuple[str, str]]:
    """The files the fit writes and removes beside its outputs, as real paths with what they
    are: the journal next to -o (kept for --resume) and each output's lock `.NAME.lock`."""
    sides = [] if dest.stream else [(journal_path(dest.target), "the fit's journal")]
    for out in (dest, *others):
        if not out.stream:
            sides.append((lock_path(out.target), f"the lock file of the {out.what}"))
    return [(os.path.realpath(path), what) for path, what in sides]


def _refuse_side_files(dest: Output, others: list[Output]) -> None:
    """Refuse, before any work, an output that is one of `_side_files`: the fit would write it
    and then delete or overwrite it (a --report onto the journal was gone after exit 0)."""
    sides = _side_files(dest, others)
    for out in (dest, *others):
        for path, what in sides:
            if not out.stream and os.path.realpath(out.target) == path:
                raise SsgError.single(
                    f"the {out.what} is {what}, which ssg fit writes and removes itself; "
                    "give another name",
                    out.name,
                )


def _note_noise_kept(places: list[str]) -> None:
    """One line when the `observation` noise made laws the fit keeps as written."""
    if places:
        err.print(
            f"note: {len(places)} pose law(s) kept as written because the observation noise "
            f"made them ({', '.join(places)}): fit the grammar without `observation` to fit "
            "them (docs/fitting.md)",
            markup=False,
            highlight=False,
        )


def _with_bom_of(grammar: Path, text: str) -> str:
    """`text` with the byte-order mark the grammar file starts with, if any: the grammar is
    read without it, and the fitted file is the same file with new numbers."""
    with open(grammar, "rb") as f:
        return "\ufeff" + text if f.read(3) == b"\xef\xbb\xbf" else text


def _run_with_progress(
    run: FitRun, n_scenes: int, time_limit: float | None, quiet: bool
) -> FitReport:
    """Run the fit with a progress bar per iteration (one line per scene when stderr is not a
    terminal), after saying what a resumed journal already holds."""
    journal = run.journal
    _note_discarded(journal, quiet)
    for r in journal.reports:
        _print_iteration(r, quiet, resumed=True)
    with _progress(quiet) as progress:
        task = progress.add_task(
            f"iteration {journal.iteration}", total=n_scenes, completed=len(journal.scenes)
        )
        lines = SceneLines(err, n_scenes, not quiet and not sys.stderr.isatty())
        lines.start(journal.iteration, len(journal.scenes))

        def on_scene() -> None:
            progress.advance(task)
            lines.scene()

        def on_iteration(r: dict[str, Any]) -> None:
            _print_iteration(r, quiet)
            progress.reset(task, description=f"iteration {r['iteration'] + 1}")
            lines.start(r["iteration"] + 1, 0)

        def on_tails() -> None:  # after the last report: not a next iteration's bar
            what = "measuring overlaps and support (the tails of ssg explain)"
            progress.reset(task, description=what, total=None)
            lines.say(what)

        return run.fit(time_limit, on_scene=on_scene, on_iteration=on_iteration, on_tails=on_tails)


def _print_mmd(mmd: dict[str, dict[str, float]], quiet: bool) -> None:
    if quiet:
        return
    names = sorted({name for per_type in mmd.values() for name in per_type})
    for name in names:
        values = ", ".join(
            f"{which} {per_type[name]:.4g}" for which, per_type in mmd.items() if name in per_type
        )
        err.print(f"MMD² {name}: {values}", markup=False, highlight=False)
    if any(v < 0 for per_type in mmd.values() for v in per_type.values()):
        err.print(
            "note: MMD² is estimated without bias, so where the sampled and the data poses "
            "cannot be told apart it comes out near 0, and below 0 as often as above: a "
            "negative value means no measurable difference at this sample size",
            markup=False,
            highlight=False,
        )


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
