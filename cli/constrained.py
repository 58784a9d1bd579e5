"""`ssg sample --constraints`: the body of the sample command when constraints are asked for.

Kept apart from `cli/app.py` so that the sampling methods can grow without touching it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ssgc.errors import Diagnostic, SsgError
from ssgc.io.outputs import Output, write_output_text
from ssgc.io.resume import SampledScenes, scan_sampled
from ssgc.io.scene import dumps_scene, scene_from_tree
from ssgc.ir import Grammar
from ssgc.sample.constrained import (
    BLOCK,
    Tally,
    Unmet,
    choose_method,
    sample_blocks,
    scene_metadata,
    select,
)


@dataclass
class ConstrainedOptions:
    """The sample command's options that constrained sampling reads."""

    names: str | None
    method: str = "auto"
    max_tries: int | None = None
    time_limit: float | None = None
    resume: bool = False
    jobs: int = 1
    extras: Any = None  # cli.export.SampleExtras for --export / --settle, or None


def sample_constrained(
    g: Grammar,
    n: int,
    seed: int,
    output: Path,
    quiet: bool,
    options: ConstrainedOptions,
    stem: str,
    before_first_write: Callable[[], None],
) -> None:
    """Write the scenes; `before_first_write` records the run (its manifest) before the first
    scene file, so a run that finds no scene leaves the directory as it was.  With `resume`,
    complete scene files are kept and blocks whose scenes are all there are not drawn."""
    from ssgc.cli.app import _progress, err, out

    o = options
    if o.names is None:
        raise SsgError.single("--max-tries and --time-limit need --constraints (all, or names)")
    chosen = select(g, o.names)
    method = choose_method(o.method, chosen)
    width = max(6, len(str(max(n - 1, 0))))
    names_ = [c.name for c in chosen]

    def name_of(index: int) -> str:
        return f"{stem}_{index:0{width}d}"

    have = scan_sampled(output, stem, name_of, n, g.name, seed) if o.resume else None
    todo = _blocks_to_draw(n, have)
    tally = Tally()
    written = 0
    if not quiet:
        kinds = ", ".join(f"{c.name} ({c.kind})" for c in chosen)
        jobs = f", {o.jobs} processes" if o.jobs > 1 else ""
        err.print(f"sampling under {kinds} by {method}{jobs}", markup=False, highlight=False)
    try:
        with _progress(quiet) as progress:
            task = progress.add_task("sampling (constrained)", total=n)
            if have is not None:
                progress.advance(task, int(have.done.sum()))
            blocks = sample_blocks(
                g,
                chosen,
                n,
                seed,
                method,
                o.max_tries,
                o.time_limit,
                tally,
                None,
                o.jobs,
                todo,
            )
            for block in blocks:
                first = block.index * BLOCK
                if have is not None:
                    have.check_same_draws(first, block.logp, name_of)
                for k in range(block.trees.n_scenes):
                    index = first + k
                    if have is not None and have.done[index]:
                        continue
                    name = name_of(index)
                    scene = scene_from_tree(g, block.trees.tree(k), name, float(block.logp[k]))
                    meta = scene_metadata(method, names_, block.margins, k)
                    if not written:
                        before_first_write()
                    path = output / f"{name}.json"
                    if o.extras is None:
                        text = dumps_scene(g, scene, seed=seed, index=index, metadata=meta)
                        write_output_text(Output(path, path, "scene file"), text)
                    else:
                        o.extras.write(scene, path, seed, index, meta)
                    written += 1
                    progress.advance(task)
    except Unmet as exc:
        if written:
            exc.diagnostics.append(
                Diagnostic(f"kept the {written} complete scene file(s) found", str(output))
            )
        raise
    if not quiet:
        rate = tally.kept / tally.drawn if tally.drawn else 0.0
        summary = (
            f"wrote {written} scene(s) of grammar '{g.name}' (seed {seed}, {method}) to "
            f"{output}; {tally.drawn:,} candidates, {rate:.3%} accepted"
        )
        if have is not None:
            summary += f"; kept {int(have.done.sum())} complete scene file(s)"
        if o.extras is not None and o.extras.unsettled:
            summary += f"; {o.extras.unsettled} scene(s) did not settle"
        out.print(summary, markup=False, highlight=False)


def _blocks_to_draw(n: int, have: SampledScenes | None) -> list[int]:
    """The blocks with a scene still to write (all of them without --resume)."""
    blocks = range((n + BLOCK - 1) // BLOCK)
    if have is None:
        return list(blocks)
    return [b for b in blocks if not have.done[b * BLOCK : (b + 1) * BLOCK].all()]
