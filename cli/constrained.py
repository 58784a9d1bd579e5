"""`ssg sample --constraints`: the body of the sample command when constraints are asked for.

Kept apart from `cli/app.py` so that the sampling methods can grow without touching it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ssgc.errors import Diagnostic, SsgError
from ssgc.io.atomic import write_text_atomic
from ssgc.io.scene import dumps_scene, scene_from_tree
from ssgc.ir import Grammar
from ssgc.sample.constrained import (
    BLOCK,
    Tally,
    Unmet,
    choose_method,
    method_options,
    sample_blocks,
    scene_metadata,
    select,
)


def sample_constrained(
    g: Grammar,
    n: int,
    seed: int,
    output: Path,
    quiet: bool,
    options: Any,
    stem: str,
    before_first_write: Callable[[], None],
) -> None:
    """Write the scenes; `before_first_write` records the run (its manifest) before the first
    scene file, so a run that finds no scene leaves the directory as it was."""
    from ssgc.cli.app import _progress, err, out

    names, method, max_tries, time_limit, resume, eps = options
    if names is None:
        raise SsgError.single("--max-tries and --time-limit need --constraints (all, or names)")
    if resume:
        raise SsgError.single("--resume is not supported with --constraints yet")
    chosen = select(g, names)
    asked, method = method, choose_method(method, chosen)
    width = max(6, len(str(max(n - 1, 0))))
    names_ = [c.name for c in chosen]
    tally = Tally()
    written = 0
    if not quiet:
        kinds = ", ".join(f"{c.name} ({c.kind})" for c in chosen)
        why = " (auto: chosen per constraint kind, docs/constraints.md)" if asked == "auto" else ""
        err.print(f"sampling under {kinds} by {method}{why}", markup=False, highlight=False)
    try:
        with _progress(quiet) as progress:
            task = progress.add_task("sampling (constrained)", total=n)
            blocks = sample_blocks(
                g,
                chosen,
                n,
                seed,
                method,
                max_tries,
                time_limit,
                tally,
                lambda k: progress.advance(task, k),
                method_options(method, eps),
            )
            for block in blocks:
                first = block.index * BLOCK
                for k in range(block.trees.n_scenes):
                    index = first + k
                    name = f"{stem}_{index:0{width}d}"
                    scene = scene_from_tree(g, block.trees.tree(k), name, float(block.logp[k]))
                    meta = scene_metadata(method, names_, block.margins, k, block.chain)
                    text = dumps_scene(g, scene, seed=seed, index=index, metadata=meta)
                    if not written:
                        before_first_write()
                    write_text_atomic(output / f"{name}.json", text)
                    written += 1
    except Unmet as exc:
        if written:
            exc.diagnostics.append(
                Diagnostic(f"kept the {written} complete scene file(s) found", str(output))
            )
        raise
    if not quiet:
        rate = tally.kept / tally.drawn if tally.drawn else 0.0
        out.print(
            f"wrote {written} scene(s) of grammar '{g.name}' (seed {seed}, {method}) to {output}; "
            f"{tally.drawn:,} candidates, {rate:.3%} accepted",
            markup=False,
            highlight=False,
        )
