"""`ssg sample`: draw scenes into a directory, one JSON file per scene (docs/sampling.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

import ssgc.cli.app as cli_app
from ssgc.cli.app import AllowOutside, GrammarArg, _command, _progress, _safe_stem, app, out
from ssgc.compile import load_grammar
from ssgc.errors import SsgError
from ssgc.io.outputs import Output, check_directory, directory_lock, write_output_text
from ssgc.io.resume import prepare_sample_dir, run_manifest, scan_sampled, write_manifest
from ssgc.io.scene import dumps_scene, scene_from_tree
from ssgc.sample.forward import CHUNK, chunk_rng


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
    extras = None
    if export or settle:
        from ssgc.cli.export import SampleExtras

        extras = SampleExtras(g, export or [], settle, output)
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
            # looked up on cli.app, where tests count the chunks drawn
            trees, logp = cli_app.sample_chunk(g, chunk_rng(seed, chunk))
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


def _write_manifest(directory: Path, manifest: dict) -> None:
    try:
        write_manifest(directory, manifest)
    except OSError as exc:
        raise SsgError.single(
            f"cannot write the manifest: {exc.strerror}", str(directory)
        ) from None
