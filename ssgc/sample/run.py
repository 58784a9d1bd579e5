"""Scenes drawn in order and named, in memory or into a directory: `ssg sample`'s loop.

Both ways of sampling (forward, `ssgc.sample.forward`; under constraints,
`ssgc.sample.constrained`) draw scene i from the seed and i alone, so a run is a sequence of
numbered scenes, each named `STEM_INDEX` (the grammar's name made a safe file stem, the index
zero-padded to `index_width(n)`).  `draw_scenes` yields them; `sample_to_directory` writes
them one JSON file each, under the directory's lock and manifest (`ssgc.io.resume`), and with
`resume` keeps the complete files of an interrupted run and draws only the chunks missing one.
The `ssg sample` command and the Python API (`ssgc.api.Grammar.sample`) both call these.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.dsl import MAX_COORDINATE
from ssgc.errors import Diagnostic, SsgError
from ssgc.io.atomic import remove_stale_temps_below
from ssgc.io.outputs import Output, check_directory, directory_lock, write_output_text
from ssgc.io.resume import (
    SampledScenes,
    clear_old_run,
    prepare_sample_dir,
    run_manifest,
    scan_sampled,
    write_manifest,
)
from ssgc.io.scene import Scene, dumps_scene, scene_from_tree, scene_stem
from ssgc.ir import Grammar
from ssgc.sample import forward
from ssgc.sample.constrained import (
    BLOCK,
    FLAGS,
    Spelling,
    Tally,
    Unmet,
    choose_method,
    method_options,
    sample_blocks,
    scene_metadata,
    select,
)
from ssgc.tree import Trees

# What a run does with each scene it draws: (scene, its file, seed, index, metadata).
SceneWriter = Callable[[Scene, Path, int, int, dict[str, Any] | None], None]
Progress = Callable[[int], None]  # called with the number of scenes just finished


def index_width(n: int) -> int:
    """Digits of the zero-padded index in scene names: at least 6, so names sort by index."""
    return max(6, len(str(max(n - 1, 0))))


@dataclass(frozen=True)
class Drawn:
    """Scene `index` of a run, and what its file records about how it was sampled."""

    index: int
    scene: Scene
    metadata: dict[str, Any] | None = None


@dataclass
class Plan:
    """How a run samples: forward, or under the chosen constraints by a method.  `asked` is
    the options as given (`--constraints`, `--method`), which the run's manifest records."""

    constraints: list[Any] = field(default_factory=list)
    method: str | None = None  # the method chosen (never `auto`); None: forward sampling
    asked: tuple[str | None, str | None] = (None, None)
    max_tries: int | None = None
    time_limit: float | None = None
    jobs: int = 1  # processes drawing constrained blocks (the same scenes for any number)
    eps: float | None = None  # the penalty scale of hmc and rjmcmc; None: the method's default
    tally: Tally = field(default_factory=Tally)
    spelling: Spelling = FLAGS  # how messages name the limits: flags, or the API's arguments

    @property
    def constrained(self) -> bool:
        return self.method is not None


def plan_sampling(
    grammar: Grammar,
    constraints: str | None = None,
    method: str = "auto",
    max_tries: int | None = None,
    time_limit: float | None = None,
    jobs: int = 1,
    penalty_eps: float | None = None,
    spelling: Spelling = FLAGS,
) -> Plan:
    """Check the sampling options: `constraints` is `all` or `NAME,NAME`; a try or time
    limit only bounds constrained sampling, so it needs constraints.  `spelling`: how the
    run's messages name its limits."""
    if constraints is None:
        if (max_tries, time_limit) != (None, None):
            raise SsgError.single("--max-tries and --time-limit need --constraints (all, or names)")
        if method != "auto" or penalty_eps is not None or jobs != 1:  # they were ignored
            raise SsgError.single(
                "--method, --penalty-eps and --jobs need --constraints (all, or names)"
            )
        return Plan()
    chosen = select(grammar, constraints)
    chosen_method = choose_method(method, chosen)
    asked = (constraints, method)
    return Plan(
        chosen, chosen_method, asked, max_tries, time_limit, jobs, penalty_eps, spelling=spelling
    )


def draw_scenes(
    grammar: Grammar,
    n: int,
    seed: int,
    plan: Plan | None = None,
    have: SampledScenes | None = None,
    progress: Progress | None = None,
) -> Iterator[Drawn]:
    """Scenes 0..n-1 in order, named as `ssg sample` names them.  With `have` (a resumed
    run's complete files), the scenes it holds are skipped, and chunks without a missing scene
    are not even drawn.  Constrained sampling raises `Unmet` when its try or time budget runs
    out, after yielding the scenes found by then."""
    plan = plan or Plan()
    stem, width = scene_stem(grammar.name), index_width(n)

    def name_of(index: int) -> str:
        return f"{stem}_{index:0{width}d}"

    if plan.constrained:
        yield from _constrained(grammar, n, seed, plan, name_of, have, progress)
    else:
        yield from _forward(grammar, n, seed, name_of, have, progress)


def _forward(
    grammar: Grammar,
    n: int,
    seed: int,
    name_of: Callable[[int], str],
    have: SampledScenes | None,
    progress: Progress | None,
) -> Iterator[Drawn]:
    step = progress or (lambda k: None)
    for chunk in range((n + forward.CHUNK - 1) // forward.CHUNK):
        lo, hi = chunk * forward.CHUNK, min(n, (chunk + 1) * forward.CHUNK)
        if have is not None and have.done[lo:hi].all():
            step(hi - lo)
            continue  # nothing missing: the chunk is not even drawn
        trees, logp = forward.sample_chunk(grammar, forward.chunk_rng(seed, chunk))
        if have is not None:
            have.check_same_draws(lo, logp[: hi - lo], name_of)
        check_within_limit(grammar, trees, hi - lo, lo, name_of)
        for index in range(lo, hi):
            k = index - lo
            if have is None or not have.done[index]:
                scene = scene_from_tree(grammar, trees.tree(k), name_of(index), float(logp[k]))
                yield Drawn(index, scene)
            step(1)


def _constrained(
    grammar: Grammar,
    n: int,
    seed: int,
    plan: Plan,
    name_of: Callable[[int], str],
    have: SampledScenes | None,
    progress: Progress | None,
) -> Iterator[Drawn]:
    assert plan.method is not None
    step = progress or (lambda k: None)
    names = [c.name for c in plan.constraints]
    every = range((n + BLOCK - 1) // BLOCK)  # lazy: `-n` may be 10**12 with a try limit
    todo, skipped = (every, 0) if have is None else _blocks_missing(have.done, n)
    step(skipped)  # the scenes of the blocks a resumed run has whole
    blocks = sample_blocks(
        grammar,
        plan.constraints,
        n,
        seed,
        plan.method,
        plan.max_tries,
        plan.time_limit,
        plan.tally,
        None,
        plan.jobs,
        todo,
        method_options(plan.method, plan.eps),
        plan.spelling,
    )
    for block in blocks:
        first = block.index * BLOCK
        if have is not None:
            have.check_same_draws(first, block.logp, name_of)
        check_within_limit(grammar, block.trees, block.trees.n_scenes, first, name_of)
        for k in range(block.trees.n_scenes):
            index = first + k
            if have is None or not have.done[index]:
                tree = block.trees.tree(k)
                scene = scene_from_tree(grammar, tree, name_of(index), float(block.logp[k]))
                meta = scene_metadata(plan.method, names, block.margins, k, block.chain)
                yield Drawn(index, scene, meta)
            step(1)


def _blocks_missing(done: NDArray[np.bool_], n: int) -> tuple[Sequence[int], int]:
    """(the blocks that miss a scene of a resumed run, how many scenes the other blocks hold):
    one array expression over the run's `done` flags (n of them, read already), where a list
    and a set of every block made `-n 10**12` run out of memory before any scene was drawn."""
    count = (n + BLOCK - 1) // BLOCK
    padded = np.ones(count * BLOCK, bool)  # the last block's missing tail counts as done
    padded[:n] = done[:n]
    full = padded.reshape(count, BLOCK).all(axis=1)
    in_full = np.repeat(full, BLOCK)[:n]
    return np.flatnonzero(~full).tolist(), int(np.count_nonzero(in_full))


class BeyondLimit(SsgError):
    """A drawn scene has a node beyond the 1,000 km every scene reader accepts."""


def check_within_limit(
    grammar: Grammar, trees: Trees, count: int, first: int, name_of: Callable[[int], str]
) -> None:
    """Refuse a batch of drawn scenes (the first `count` trees of `trees`, scenes `first`...)
    if a node of one lies beyond `dsl.MAX_COORDINATE` on an axis, before any of them is
    written or returned: every scene reader refuses such a pose, so the file would be one no
    command reads.  The grammar's constants are within the limit (`ssgc.dsl`), but a spread (a
    variance of 1e14 m²) or offsets added along a chain can carry a node beyond it; no bound on
    the variances at validate time could exclude that (a Normal has no edge, and chains add
    up), so this is checked here, on the poses themselves.  The first such scene is named,
    with the node's type and coordinate."""
    with np.errstate(invalid="ignore"):
        far = ~(np.abs(trees.xyz) <= MAX_COORDINATE) & (trees.scene < count)[:, None]
    if not far.any():
        return
    nodes = np.flatnonzero(far.any(axis=1))
    node = int(nodes[np.argmin(trees.scene[nodes])])  # of the first scene that has one
    axis = int(np.argmax(np.where(far[node], np.abs(trees.xyz[node]), -1.0)))  # its farthest
    t = grammar.types[int(trees.type[node])]
    what = "object" if t.observed else "node"
    raise BeyondLimit.single(
        f"scene {name_of(first + int(trees.scene[node]))}: {what} {t.name} was drawn at "
        f"{'xyz'[axis]} = {trees.xyz[node, axis]:g} m, beyond the "
        f"{MAX_COORDINATE / 1000:,.0f} km from the origin (on each axis) that scene files may "
        "hold; no command would read it, so it is not written. The grammar's spreads or "
        "chained offsets reach that far: narrow them",
        grammar.file,
    )


@dataclass
class SampleRun:
    """What `sample_to_directory` did, for the summary line."""

    directory: Path
    written: int = 0
    first: Path | None = None  # the first and last file written
    last: Path | None = None
    resumed: bool = False  # an interrupted run was continued
    kept: int = 0  # complete scene files of that run, kept
    removed_temps: int = 0  # temporary files of a killed run, deleted (resume)


def sample_to_directory(
    grammar: Grammar,
    grammar_file: Path,
    output: Path,
    n: int,
    seed: int = 0,
    plan: Plan | None = None,
    resume: bool = False,
    overwrite: bool = False,
    write: SceneWriter | None = None,
    progress: Progress | None = None,
    subdirs: Sequence[str] = (),
    settled: bool = False,
) -> SampleRun:
    """Write scenes 0..n-1 into `output`, one JSON file each, under the directory's lock.

    The directory's manifest records the run; a directory holding another run's scenes is
    refused unless `overwrite`, and `resume` keeps the complete files of this same run.
    `write` replaces the plain scene file (`ssg sample --settle`, `--export`), writing the
    scene file last; `subdirs` are the directories it also writes into, cleaned of a killed
    run's temporary files on `resume`.  The formats of `subdirs` and `settled` (the scenes
    written are settled ones) are part of the run: a directory is never a mixture.  The
    manifest is written (and an overwritten run deleted) when the first scene is ready, so a
    run that finds none (or is stopped before) leaves the directory as it was; on `Unmet` the
    scenes found are kept.
    """
    if resume and overwrite:
        raise SsgError.single(
            "--resume keeps a run's scenes and --overwrite deletes them: give one"
        )
    plan = plan or Plan()
    check_directory(output)
    write = write or _scene_file_writer(grammar)
    with directory_lock(output):
        manifest = run_manifest(grammar.name, grammar_file, seed, n, index_width(n))
        manifest.update(constraints=plan.asked[0], method=plan.asked[1])
        manifest.update(settle=settled, export=sorted(subdirs))
        old = prepare_sample_dir(output, manifest, resume, overwrite)
        run = SampleRun(output)
        have = _resumed(grammar, output, n, seed, subdirs, run) if resume else None
        try:
            for drawn in draw_scenes(grammar, n, seed, plan, have, progress):
                if not run.written:  # a scene is ready: only now is the old run deleted
                    _begin(output, manifest, old)
                path = output / f"{drawn.scene.name}.json"
                write(drawn.scene, path, seed, drawn.index, drawn.metadata)
                run.first, run.last = run.first or path, path
                run.written += 1
        except (Unmet, BeyondLimit) as exc:
            if run.written:
                note = f"kept the {run.written} complete scene file(s) found"
                exc.diagnostics.append(Diagnostic(note, str(output)))
            raise
        if not run.written and old is not None:  # `-n 0 --overwrite`: the old run goes too
            clear_old_run(output, old)
        _write_manifest(output, {**manifest, "complete": True})
    return run


def _resumed(
    grammar: Grammar, output: Path, n: int, seed: int, subdirs: Sequence[str], run: SampleRun
) -> SampledScenes:
    """The complete scene files of the interrupted run, noted in `run`; the temporary files it
    left are deleted, in its scene writer's subdirectories (`--export`'s OUTPUT/FORMAT/) too."""
    stem, width = scene_stem(grammar.name), index_width(n)
    have = scan_sampled(output, stem, lambda i: f"{stem}_{i:0{width}d}", n, grammar.name, seed)
    below = sum(remove_stale_temps_below(output / d) for d in subdirs)
    run.resumed, run.kept = True, int(have.done.sum())
    run.removed_temps = have.removed_temps + below
    return have


def _begin(output: Path, manifest: dict[str, Any], old: list[str] | None) -> None:
    """Before the run's first scene file: delete the run `--overwrite` replaces, then record
    this run (with no scene written, a stopped run changes nothing in the directory)."""
    if old is not None:
        clear_old_run(output, old)
    _write_manifest(output, manifest)


def _scene_file_writer(grammar: Grammar) -> SceneWriter:
    def write(
        scene: Scene, path: Path, seed: int, index: int, metadata: dict[str, Any] | None
    ) -> None:
        text = dumps_scene(grammar, scene, seed=seed, index=index, metadata=metadata)
        write_output_text(Output(path, path, "scene file"), text)

    return write


def _write_manifest(directory: Path, manifest: dict[str, Any]) -> None:
    try:
        write_manifest(directory, manifest)
    except OSError as exc:
        raise SsgError.single(
            f"cannot write the manifest: {exc.strerror}", str(directory)
        ) from None
