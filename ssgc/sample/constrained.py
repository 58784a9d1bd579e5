"""`ssg sample --constraints`: scenes of P(T | constraints), reproducibly, by a chosen method.

Seeding: scenes are made in blocks of `BLOCK`; block b draws its candidates in attempts
k = 0, 1, ... sized by the block's own draws so far (`attempt_size`), attempt k with the generator
``default_rng([seed, b, k + 1, TAG])``, and scene b*BLOCK + j is the j-th candidate of block
b that satisfies the constraints.  So scene i depends only on the seed and i (and the
method), never on how many scenes were asked for, or on any time or try limit.  An attempt
holds at most as many candidates as fit the node store (`ssgc.sample.staged.largest_batch`);
one that overflows it anyway is drawn again, with the same generator and half the candidates.

Methods are registered in `METHODS` by name; each is one function drawing one attempt:
`rejection` (exact, `ssgc.sample.staged`), `rjmcmc` (exact in the limit of long chains,
`ssgc.sample.rjmcmc`), `hmc` (thesis 2.4.1, `ssgc.sample.hmc`) and `project` (thesis 2.4.2,
`ssgc.sample.project`), the last two biased.  The chain methods use smaller attempts
(`ATTEMPTS`): each candidate costs a chain.  `auto` picks per constraint kind (`choose_method`).
"""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint
from ssgc.errors import Diagnostic, SsgError
from ssgc.forked import ordered_map
from ssgc.ir import Grammar
from ssgc.sample.forward import TooLarge
from ssgc.sample.hmc import SETTINGS as HMC_SETTINGS
from ssgc.sample.hmc import hmc_batch
from ssgc.sample.project import project_batch
from ssgc.sample.rjmcmc import SETTINGS as RJ_SETTINGS
from ssgc.sample.rjmcmc import rjmcmc_batch
from ssgc.sample.staged import Outcome, OutOfTime, largest_batch, rejection_batch
from ssgc.tree import Trees

BLOCK = 256
TAG = 0x5C0C  # keeps constrained streams apart from forward sampling's ([seed, chunk])
FIRST_ATTEMPT = 1024
LARGEST_ATTEMPT = 65536

# (grammar, constraints, candidates, generator, deadline) -> the kept ones; may raise OutOfTime
Method = Callable[[Grammar, list[Constraint], int, np.random.Generator, float | None], Outcome]
METHODS: dict[str, Method] = {
    "rejection": rejection_batch,
    "rjmcmc": rjmcmc_batch,
    "hmc": hmc_batch,
    "project": project_batch,
}
# exact: every scene is a draw of P(T | C).  RJMCMC's stationary law is P(T | C), but a
# finite chain's final state only approaches it, so its scenes say "exact": false too.
EXACT = {"rejection": True, "rjmcmc": False, "hmc": False, "project": False}
# (first, largest) attempt, in candidates; chain methods run one chain per (kept) candidate
ATTEMPTS = {"rjmcmc": (256, 256), "hmc": (128, 8192), "project": (256, 1024)}
# `auto`'s choice per constraint kind: the fastest exact method measured on the bundled
# grammars (docs/constraints.md); a kind missing here would go to RJMCMC.
AUTO = {
    "count": "rejection",  # judged on the structure alone, before any pose is drawn
    "longest_chain": "rejection",
    "children": "rejection",
    "inside_box": "rejection",  # one array expression per batch
    "clearance": "rejection",
    "upright": "rejection",
    "non_penetration": "rejection",  # sink: 36% of candidates pass; chains call FCL far more
}


@dataclass(frozen=True)
class Spelling:
    """How messages name the try and time limits: `ssg sample`'s flags, or the arguments of
    the Python API (`ssgc.api.Grammar.sample`), whose users never typed a flag."""

    max_tries: str  # a format for the number of tries
    time_limit: str  # a format for the seconds


FLAGS = Spelling("--max-tries {:,}", "--time-limit {:g} s")
ARGUMENTS = Spelling("max_tries={}", "time_limit={:g}")


def attempt_size(
    k: int,
    drawn: int = 0,
    kept: int = 0,
    first: int = FIRST_ATTEMPT,
    largest: int = LARGEST_ATTEMPT,
) -> int:
    """Candidates of a block's attempt k, after `drawn` candidates gave `kept` scenes in it.

    The first attempt is small (a constraint that most candidates meet needs no more); the
    next ones aim at the rest of a whole block at the acceptance seen so far (plus a quarter),
    at most 16**k times the first and `largest` in all.  The size depends on the
    block's own draws and never on how many scenes were asked for, so scene i still depends
    only on the seed and i; aiming at the block's end wastes less of the last attempt than
    doubling does (at 0.2% acceptance, about half of it)."""
    if k == 0 or drawn == 0:
        return first
    need = max(BLOCK - kept, 1)
    aim = int(np.ceil(1.25 * need * drawn / max(kept, 1)))
    return int(min(largest, first << min(4 * k, 16), max(first, aim)))


def select(grammar: Grammar, names: str | None) -> list[Constraint]:
    """The constraints `--constraints` names: `all`, or a comma-separated list of names."""
    if names is None:
        return []
    known = {c.name: c for c in grammar.constraints}
    if names.strip() == "all":
        if not known:
            raise SsgError.single(f"grammar '{grammar.name}' declares no constraints", grammar.file)
        return list(known.values())
    wanted = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in wanted if n not in known]
    if unknown or not wanted:
        have = ", ".join(known) or "none"
        raise SsgError.single(
            f"unknown constraint {', '.join(repr(n) for n in unknown) or '(empty list)'}; "
            f"this grammar declares: {have}",
            grammar.file,
        )
    return [known[n] for n in dict.fromkeys(wanted)]


def method_options(method: str, eps: float | None) -> dict[str, Any]:
    """The method's settings for a penalty scale ε given on the command line (HMC's penalty,
    RJMCMC's before a chain is first feasible); {} for the default."""
    if eps is None or method not in ("hmc", "rjmcmc"):
        return {}
    settings = HMC_SETTINGS if method == "hmc" else RJ_SETTINGS
    return {"settings": replace(settings, eps=eps)}


def choose_method(method: str, constraints: list[Constraint]) -> str:
    """`auto` picks per constraint kind (`AUTO`): rejection (exact) when it is every kind's
    choice, which it is for every built-in kind; else RJMCMC (one chain handles every kind,
    its stationary law is exact but a finite chain's scenes are not, and they say so)."""
    if method == "auto":
        picks = {AUTO.get(c.word, "rjmcmc") for c in constraints}
        return "rejection" if picks <= {"rejection"} else "rjmcmc"
    if method not in METHODS:
        raise SsgError.single(
            f"unknown sampling method '{method}'; expected auto or one of: {', '.join(METHODS)}"
        )
    return method


@dataclass
class Tally:
    """What the constraints did over a whole run (for the failure message and the bench)."""

    drawn: int = 0
    passed: int = 0  # candidates that met every constraint (the acceptance rate's numerator)
    kept: int = 0  # of those, the scenes of the run (a block's last attempt may pass more)
    evaluated: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    best: dict[str, float] = field(default_factory=dict)
    abandoned: int = 0  # attempts the time limit cut short (a chain method's can take minutes)

    def merge(self, other: Tally) -> None:
        """Add another tally (a block drawn by another process)."""
        self.drawn += other.drawn
        self.passed += other.passed
        self.kept += other.kept
        self.abandoned += other.abandoned
        for k in other.evaluated:
            self.evaluated[k] = self.evaluated.get(k, 0) + other.evaluated[k]
            self.rejected[k] = self.rejected.get(k, 0) + other.rejected[k]
            self.best[k] = max(self.best.get(k, -np.inf), other.best[k])

    def add(self, o: Outcome) -> None:
        self.drawn += o.drawn
        self.passed += o.trees.n_scenes
        self.kept += o.trees.n_scenes
        for k in o.evaluated:
            self.evaluated[k] = self.evaluated.get(k, 0) + o.evaluated[k]
            self.rejected[k] = self.rejected.get(k, 0) + o.rejected[k]
            self.best[k] = max(self.best.get(k, -np.inf), o.best[k])

    def report(self, judged: dict[str, str] | None = None) -> list[str]:
        """One line per constraint; `judged` names what each judged (candidates unless said:
        a chain method judges each of a chain's draws, several per candidate)."""
        judged = judged or {}
        lines = []
        for k in self.evaluated:
            if not self.evaluated[k]:
                continue  # "rejected 0 of the 0 chain draws": the run stopped before any
            best = self.best[k]
            closest = f"; the closest rejected came to {best:.4g}" if np.isfinite(best) else ""
            lines.append(
                f"constraint '{k}' rejected {self.rejected[k]:,} of the "
                f"{self.evaluated[k]:,} {judged.get(k, 'candidates')} it judged{closest}"
            )
        return lines


@dataclass
class Block:
    """The scenes of one block, in order: trees, log-probabilities and margins."""

    index: int
    trees: Trees
    logp: NDArray[np.float64]
    margins: dict[str, NDArray[np.float64]]
    chain: dict[str, NDArray[np.float64]] = field(default_factory=dict)  # MCMC statistics


class Unmet(SsgError):
    """The try or time budget ran out before the scenes were found (exit 2)."""


def sample_blocks(
    grammar: Grammar,
    constraints: list[Constraint],
    n: int,
    seed: int,
    method: str = "rejection",
    max_tries: int | None = None,
    time_limit: float | None = None,
    tally: Tally | None = None,
    progress: Callable[[int], None] | None = None,
    jobs: int = 1,
    blocks: Sequence[int] | None = None,
    options: dict[str, Any] | None = None,
    spelling: Spelling = FLAGS,
) -> Iterator[Block]:
    """Yield the blocks of scenes 0..n-1 (or only the blocks numbered in `blocks`, e.g. those
    `--resume` still needs), in order.  With `jobs` > 1, blocks are drawn by that many forked
    processes; a block's scenes are the same for any `jobs`.

    Raises `Unmet` when `max_tries` candidates (counted over all processes) or `time_limit`
    seconds are spent first (tries are checked between attempts, time also between an
    attempt's stages); the scenes found by then in the first unfinished block are yielded
    first, as a last, shorter block, after every block before it.  `options` are keyword
    arguments of the method (`method_options`); `spelling` how messages name the limits.
    A constraint that the fixed root fails on its own raises `SsgError` (exit 2) at once
    (`check_root`)."""
    check_root(grammar, constraints)
    tally = tally if tally is not None else Tally()
    deadline = None if time_limit is None else time.monotonic() + time_limit
    todo = range((n + BLOCK - 1) // BLOCK) if blocks is None else blocks  # never a list of all
    shared = _counter(jobs > 1 and len(todo) > 1)
    limits = _Limits(max_tries, time_limit, deadline, shared, spelling)
    batch = largest_batch(grammar)
    work = _BlockWork(grammar, constraints, n, seed, method, limits, options or {}, batch)
    results = ordered_map(functools.partial(_draw_block, work), todo, jobs)
    for done in results:
        tally.merge(done.tally)
        if done.block is not None:
            if progress is not None:
                progress(done.block.trees.n_scenes)
            yield done.block
        if done.limit is not None:
            _count_stopped(results, tally, jobs)
            raise _unmet(grammar, tally, n, done.limit, _judged(constraints, method))


def _count_stopped(results: Iterator[_Done], tally: Tally, jobs: int) -> None:
    """Add to `tally` the candidates of the blocks after the one that hit the run's limit:
    they stop at the same (shared) limit, their candidates count in the report, their scenes
    are not written (the files stay a prefix of the run).  Blocks start in order, at most
    `jobs` at a time, so once `jobs` blocks in a row drew nothing (they started after the
    limit was reached) every later one starts after it too: the rest are not called, where
    calling each one made `-n 10**12 --max-tries 100` run for hours after its last scene."""
    idle = 0
    for later in results:
        if later.tally.drawn == 0 and later.tally.abandoned == 0:
            idle += 1
            if idle >= jobs:
                return
            continue
        idle = 0
        tally.merge(later.tally)
        tally.kept -= later.block.trees.n_scenes if later.block is not None else 0


@dataclass
class _Limits:
    max_tries: int | None
    time_limit: float | None
    deadline: float | None
    drawn: Any  # candidates drawn by every process: a shared multiprocessing.Value or a _Count
    spelling: Spelling = FLAGS

    def hit(self) -> str | None:
        if self.max_tries is not None and self.drawn.value >= self.max_tries:
            return self.spelling.max_tries.format(self.max_tries)
        if self.deadline is not None and time.monotonic() > self.deadline:
            return self.out_of_time()
        return None

    def out_of_time(self) -> str:
        return self.spelling.time_limit.format(self.time_limit)


class _Count:
    """A candidate counter for one process (the shape of a multiprocessing.Value)."""

    def __init__(self) -> None:
        self.value = 0

    def get_lock(self) -> contextlib.nullcontext[None]:
        return contextlib.nullcontext()


def _counter(shared: bool) -> Any:
    if shared:
        return multiprocessing.get_context("fork").Value("q", 0)
    return _Count()


@dataclass
class _BlockWork:
    grammar: Grammar
    constraints: list[Constraint]
    n: int
    seed: int
    method: str
    limits: _Limits
    options: dict[str, Any]
    batch: int | None = None  # the most candidates an attempt draws (None: no bound known)


@dataclass
class _Done:
    """A block's result: its scenes (None if it found none), what the constraints did, and
    the limit that stopped it (None if it is complete)."""

    block: Block | None
    tally: Tally
    limit: str | None


def _draw_block(work: _BlockWork, b: int) -> _Done:
    """Scenes b*BLOCK ... of the run, by attempts k = 0, 1, ... seeded by (seed, b, k).

    An attempt draws at most `work.batch` candidates, as many as the node store holds; an
    attempt that overflows it anyway (`TooLarge`: sizes spread, the proposals of
    `ssgc.sample.proposals` draw larger trees than P(T)) is drawn again with half as many,
    and so are the block's later attempts.  What a block draws still depends only on the
    seed and b.  Only a single candidate too large for the store is an error."""
    draw = functools.partial(METHODS[work.method], **work.options)
    first, largest = ATTEMPTS.get(work.method, (FIRST_ATTEMPT, LARGEST_ATTEMPT))
    limits = work.limits
    want = min(BLOCK, work.n - b * BLOCK)
    tally = Tally()
    got: list[Outcome] = []
    have = 0
    k = 0
    limit = None
    cap = work.batch
    while have < want:
        limit = limits.hit()
        if limit is not None:
            break
        rng = np.random.default_rng([int(work.seed) & 0xFFFFFFFFFFFFFFFF, b, k + 1, TAG])
        size = attempt_size(k, tally.drawn, have, first, largest)
        size = size if cap is None else min(size, cap)
        try:
            o = draw(work.grammar, work.constraints, size, rng, limits.deadline)
        except OutOfTime:  # the attempt is abandoned: the scenes found before it stand
            limit = limits.out_of_time()
            tally.abandoned += 1
            break
        except TooLarge:
            if size == 1:
                raise  # "one scene would hold more than ... nodes"
            cap = size // 2  # attempt k again, with fewer candidates
            continue
        with limits.drawn.get_lock():
            limits.drawn.value += o.drawn
        o = only_holding(o)
        tally.add(o)
        if o.trees.n_scenes:
            got.append(o)
        have += o.trees.n_scenes
        k += 1
    tally.kept = min(have, want)  # the last attempt's scenes beyond the block are not kept
    block = _block(b, got, min(have, want)) if have else None
    return _Done(block, tally, limit if have < want else None)


def only_holding(o: Outcome) -> Outcome:
    """The outcome without the scenes on which some final margin fails (counted as that
    constraint's rejections).  Every method judges its candidates itself; this is the last
    word whatever the method: a scene is written only if every chosen constraint holds on
    it (a staged sampler that skipped the root's terms once wrote scenes with margin -0.125)."""
    ok = np.ones(o.trees.n_scenes, bool)
    for m in o.margins.values():
        ok &= m >= 0
    if np.all(ok):
        return o
    rejected, best = dict(o.rejected), dict(o.best)
    for name, m in o.margins.items():
        bad = ~(m >= 0)
        rejected[name] += int(np.count_nonzero(bad))
        if np.any(bad):
            best[name] = max(best[name], float(np.max(m[bad])))
    kept: dict[str, Any] = {
        "trees": o.trees.select(ok),
        "logp": o.logp[ok],
        "margins": {k: v[ok] for k, v in o.margins.items()},
        "rejected": rejected,
        "best": best,
    }
    chain = getattr(o, "chain", None)
    if chain is not None:
        kept["chain"] = {k: v[ok] for k, v in chain.items()}
    return replace(o, **kept)


def check_root(grammar: Grammar, constraints: list[Constraint]) -> None:
    """Refuse, before drawing anything, the progressive pose constraints that the root fails
    on its own.  The root's pose is fixed (`root: pose`) and such a margin is a minimum over
    terms, which more nodes can only lower (what the staged sampler's partial judgements rest
    on): no tree can satisfy it, and sampling would only run out of tries."""
    root = Trees(
        scene=np.zeros(1, np.int64),
        type=np.full(1, grammar.root, np.int64),
        parent=np.full(1, -1, np.int64),
        rule=np.full(1, -1, np.int64),
        xyz=np.asarray(grammar.root_xyz, float)[None, :],
        quat=np.asarray(grammar.root_quat, float)[None, :],
        n_scenes=1,
    )
    name = grammar.types[grammar.root].name
    lines = []
    for c in constraints:
        if c.kind != "pose" or not c.progressive:
            continue
        m = float(c.margin(root)[0])
        if not m >= 0:
            by = f" (margin {m:.4g})" if np.isfinite(m) else ""
            lines.append(
                f"constraint '{c.name}' can never hold: the root '{name}' fails it on its "
                f"own{by}, and the grammar's `root:` fixes its pose"
            )
    if lines:
        raise SsgError([Diagnostic(line, grammar.file) for line in lines], exit_code=2)


def _block(index: int, outcomes: list[Outcome], want: int) -> Block:
    trees = Trees.concatenate([o.trees for o in outcomes])
    logp = np.concatenate([o.logp for o in outcomes])[:want]
    names = outcomes[0].margins.keys()
    margins = {k: np.concatenate([o.margins[k] for o in outcomes])[:want] for k in names}
    stats = [getattr(o, "chain", {}) for o in outcomes]
    chain = {k: np.concatenate([s[k] for s in stats])[:want] for k in stats[0]}
    if trees.n_scenes > want:
        trees = trees.first(want)
    return Block(index, trees, logp, margins, chain)


# What a method judges a pose constraint on (structural ones are judged on the candidates).
POSE_JUDGED = {"rjmcmc": "chain draws", "hmc": "chain draws", "project": "projected candidates"}


def _judged(constraints: list[Constraint], method: str) -> dict[str, str]:
    return {
        c.name: POSE_JUDGED[method]
        for c in constraints
        if c.kind == "pose" and method in POSE_JUDGED
    }


def _unmet(grammar: Grammar, tally: Tally, n: int, limit: str, judged: dict[str, str]) -> Unmet:
    found = f"found {tally.kept:,} of the {n:,} requested scene(s) satisfying the constraints"
    if tally.drawn:
        head = f"{found} after {tally.drawn:,} candidates ({limit})"
    elif tally.abandoned:  # work was done (a chain method's attempt can take many seconds)
        head = f"{found}: no attempt finished within the limit ({limit})"
    else:
        head = f"{found} before the first candidate ({limit})"
    lines = [head, *tally.report(judged)]
    return Unmet([Diagnostic(line, grammar.file) for line in lines], exit_code=2)


def scene_metadata(
    method: str,
    names: list[str],
    margins: dict[str, NDArray],  # type: ignore[type-arg]
    k: int,
    chain: dict[str, NDArray] | None = None,  # type: ignore[type-arg]
) -> dict:  # type: ignore[type-arg]
    """What a scene file records about how it was sampled: method, each margin and, for the
    chain methods, the chain's statistics (acceptance rates, step size, ...)."""
    sampler: dict = {"method": method, "exact": EXACT.get(method, False)}  # type: ignore[type-arg]
    if chain:
        sampler["chain"] = {name: float(v[k]) for name, v in chain.items()}
    return {
        "sampler": sampler,
        "constraints": {
            name: (float(margins[name][k]) if np.isfinite(margins[name][k]) else None)
            for name in names
        },
    }
