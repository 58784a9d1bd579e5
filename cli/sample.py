"""`ssg sample`: draw scenes into a directory, one JSON file per scene (docs/scenes.md).

The loop (chunks, resume, names, manifest) is `ssgc.sample.run.sample_to_directory`; this
module reads the flags, draws the progress bar and prints the summary.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssgc.cli.app import (
    AllowOutside,
    GrammarArg,
    _command,
    _progress,
    app,
    err,
    finite_from,
    out,
)
from ssgc.compile import load_grammar
from ssgc.sample.constrained import METHODS
from ssgc.sample.run import Plan, SampleRun, plan_sampling, sample_to_directory


@app.command(short_help="Draw scenes, one JSON file each.")
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
    method: Annotated[
        str, typer.Option(help=f"With --constraints: auto | {' | '.join(METHODS)}.")
    ] = "auto",
    max_tries: Annotated[
        int | None,
        typer.Option(
            min=1,
            help="With --constraints: stop once this many candidates are drawn (checked "
            "between attempts, which draw many at once).",
        ),
    ] = None,
    time_limit: Annotated[
        float | None,
        typer.Option(
            callback=finite_from(0.001), help="With --constraints: stop after these seconds."
        ),
    ] = None,
    penalty_eps: Annotated[
        float | None,
        typer.Option(
            callback=finite_from(1e-9),
            help="With --constraints, hmc, rjmcmc: the penalty's ε in m (default 1e-3).",
        ),
    ] = None,
    export: Annotated[
        list[str] | None,
        typer.Option(
            "--export",
            metavar="<format>",
            help="Also write each scene in this format (into OUTPUT/FORMAT); repeatable.",
        ),
    ] = None,
    settle: Annotated[
        bool,
        typer.Option(
            "--settle",
            help="Settle each scene in MuJoCo before writing it (exit 2 if one does not).",
        ),
    ] = False,
    jobs: Annotated[
        int,
        typer.Option(
            "--jobs", "-j", min=1, help="With --constraints: processes drawing (same scenes)."
        ),
    ] = 1,
) -> None:
    """Draw N scenes; write one JSON file per scene (objects, full tree, log-probability).

    Scene i depends only on the seed and i, and `--resume` finishes an interrupted run with the
    files an uninterrupted one would write.  The directory's manifest records the run; a
    directory holding another run's scenes is refused unless `--overwrite`.
    With --constraints, scenes follow the grammar conditioned on them; when --max-tries or
    --time-limit run out first, the exit code is 2 and the scenes found so far are kept.
    """
    g = load_grammar(grammar, allow_outside=allow_outside_files)
    plan = plan_sampling(g, constraints, method, max_tries, time_limit, jobs, penalty_eps)
    extras = None
    if export or settle:
        from ssgc.cli.export import SampleExtras

        extras = SampleExtras(g, export or [], settle, output)
    if plan.constrained and not quiet:
        kinds = ", ".join(f"{c.name} ({c.kind})" for c in plan.constraints)
        jobs_note = f", {jobs} processes" if jobs > 1 else ""
        why = " (auto: chosen per constraint kind, docs/constraints.md)" if method == "auto" else ""
        line = f"sampling under {kinds} by {plan.method}{why}{jobs_note}"
        err.print(line, markup=False, highlight=False)
    with _progress(quiet) as progress:
        task = progress.add_task(
            "sampling (constrained)" if plan.constrained else "sampling", total=n
        )
        run = sample_to_directory(
            g,
            grammar,
            output,
            n,
            seed,
            plan,
            resume,
            overwrite,
            write=None if extras is None else extras.write,
            progress=lambda k: progress.advance(task, k),
            subdirs=[] if extras is None else extras.formats,
            settled=settle,
        )
    unsettled = 0 if extras is None else extras.unsettled
    if not quiet:
        out.print(_summary(g.name, seed, run, plan, unsettled), markup=False, highlight=False)
    if unsettled:  # as `ssg settle`: exit 2, the scenes are written all the same
        if quiet:
            err.print(f"{unsettled} scene(s) did not settle", markup=False, highlight=False)
        raise typer.Exit(2)


def _summary(name: str, seed: int, run: SampleRun, plan: Plan, unsettled: int) -> str:
    """The closing line: how many scenes went where, and what a resume kept."""
    if plan.constrained:
        tally = plan.tally
        rate = tally.passed / tally.drawn if tally.drawn else 0.0
        # HMC gives several draws per chain, so a candidate can give several scenes
        share = f"{rate:.3%} accepted" if rate <= 1 else f"{rate:.2f} scenes per candidate"
        summary = (
            f"wrote {run.written} scene(s) of grammar '{name}' (seed {seed}, {plan.method}) to "
            f"{run.directory}; {tally.drawn:,} candidates, {share}"
        )
    else:
        first, last = run.first, run.last
        where = (
            f"{first} … {last.name}"
            if first is not None and last is not None and run.written > 1
            else str(first or run.directory)
        )
        summary = f"wrote {run.written} scene(s) of grammar '{name}' (seed {seed}) to {where}"
    if run.resumed:
        summary += f"; kept {run.kept} complete scene file(s)"
        if run.removed_temps:
            summary += f", removed {run.removed_temps} temporary file(s) of a killed run"
    if unsettled:
        summary += f"; {unsettled} scene(s) did not settle"
    return summary
