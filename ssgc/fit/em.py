"""Approximate EM over a dataset of scenes (thesis 4.3): parse, weigh, update, repeat.

Each iteration parses every scene with the current grammar (top-N distinct trees, the
E-step), weighs each scene's trees by their posterior under the current parameters (the
softmax of their scores plus log c! per repeat node with c children: the parse score is that
of one ordered draw of the children, the scene is their set), and sets every parameter to its
weighted maximum-likelihood value (`ssgc.fit.mstep`, the M-step).  The new numbers are
written into the grammar's YAML text (`ssgc.fit.writeback`) and the next iteration compiles
that text: what the user gets is exactly the grammar the last iteration fitted.

The log-evidence reported per iteration is the thesis's estimate: for every scene, the
log-sum-exp of the same numbers over its top-N trees.  Where every pose is observed or fixed by
observed ones, it is a lower bound of the true log-evidence (only N trees are summed), so it is
comparable between iterations with the same N, not across N.  Latent positions touched only by
Normal laws are integrated out (the Laplace term of `ssgc.fit.laplace`), and subtrees that can
hold nothing observed are left out (they integrate to 1); where latent rotations, or latent
positions held by other laws, remain, a score is a density at the parser's values and the
estimate is no bound (docs/fitting.md sections 4.5 and 6).

Work is journalled (`FitJournal`): every parsed scene and every finished iteration is on disk
before the next starts, so `--resume` redoes nothing that was finished.  The results do not
depend on whether a run was interrupted: the M-step reads the trees back from the same
JSON records either way.
"""

from __future__ import annotations

import hashlib
import json
import math
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ssgc.compile import compile_text
from ssgc.errors import SsgError
from ssgc.fit.estep import parse_scenes
from ssgc.fit.laplace import hidden_nodes, latent_spread
from ssgc.fit.mstep import FitSettings, Ties, m_step, refuse_out_of_range
from ssgc.fit.posterior import McmcSettings, log_orders, posterior_e_step
from ssgc.fit.tails import has_tails, measure_tails, tail_updates
from ssgc.fit.writeback import (
    Loc,
    SharedValueConflict,
    apply_updates,
    shared_nodes,
    shared_with_kept,
    without_section,
)
from ssgc.io.journal import Journal, journal_path, scenes_digest
from ssgc.io.scene import Scene
from ssgc.ir import Grammar, Kind
from ssgc.laws.counts import GeometricCount
from ssgc.parse.parser import PROPOSAL_SHARE, Parser, SceneParses
from ssgc.score import node_terms
from ssgc.tree import Trees

# /2: scene records carry the parser's statuses of issue 11 (optimal only when certified,
# infeasible only when proven, no_parse with its phase); a /1 journal is refused on --resume.
FIT_JOURNAL_FORMAT = "ssgc.fit-journal/2"
DEADLINE_SHARE = 0.95  # of a time limit: the last parse and the output still take a moment
# The keys a pose law's fit may write (`fit` of ssgc/laws/position_normal.py, rotation_bingham.py)
POSE_KEYS = ("mean", "variance", "covariance", "mode", "concentration", "M", "Z")


@dataclass(frozen=True)
class FitOptions:
    """Everything that decides a fit's result (all of it goes in the journal's header, except
    `iterations` and `tol`, which only decide when to stop, and `jobs`)."""

    iterations: int = 10
    top: int = 10
    method: str = "auto"
    seed: int = 0
    tol: float = 1e-4  # nats per scene: stop when the log-evidence improves less
    jobs: int = 1  # worker processes for the E-step's parsing (the result is the same)
    estep: str = "topn"  # "topn": softmax over the top-N parses; "mcmc": posterior samples
    samples: int = 100  # --estep mcmc: rounds kept per scene chain (ssgc.fit.posterior)
    settings: FitSettings = field(default_factory=FitSettings)

    def __post_init__(self) -> None:
        """Out-of-range options are the caller's mistake, told before any work (`ssg fit`'s
        flags are bounded the same way by the CLI)."""
        checks = (
            ("iterations", self.iterations, self.iterations >= 1, "at least 1"),
            ("top", self.top, self.top >= 1, "at least 1"),
            ("jobs", self.jobs, self.jobs >= 1, "at least 1"),
            ("samples", self.samples, self.samples >= 1, "at least 1"),
            ("tol", self.tol, 0.0 <= self.tol < math.inf, "≥ 0 and finite"),
            ("estep", self.estep, self.estep in ("topn", "mcmc"), "'topn' or 'mcmc'"),
        )
        refuse_out_of_range(checks)


@dataclass
class FitResult:
    text: str  # the fitted grammar's YAML
    iterations: list[dict[str, Any]]  # one report per finished iteration
    status: str  # "converged", "iterations" (the limit was reached) or "time_limit"
    message: str = ""
    mmd: dict[str, dict[str, float]] | None = None  # grammar -> object type -> MMD² to the data
    tails: list[dict[str, Any]] = field(default_factory=list)  # measured (ssgc.fit.tails)
    noise_kept: list[str] = field(default_factory=list)  # `noise_kept_laws` of the grammar


class FitJournal(Journal):
    """The journal of `ssg fit -o`: per iteration, its parsed scenes, then its fitted grammar.

    Lines after the header, in this order for iterations 1, 2, ...::

        {"iteration": k, "index": 0, "scores": [...], "trees": [...]}   one per scene
        {"iteration": k, "grammar": "<fitted YAML>", "report": {...}}   the M-step's result
    """

    FORMAT = FIT_JOURNAL_FORMAT
    WHAT = "fit journal"

    def __init__(self, path: Path, header: dict[str, Any], resume: bool) -> None:
        self.iteration = 1  # the iteration under way
        self.scenes: list[dict[str, Any]] = []  # its finished scenes
        self.last_scenes: list[dict[str, Any]] = []  # the scenes of the last finished iteration
        self.text: str | None = None  # the last fitted grammar
        self.reports: list[dict[str, Any]] = []
        self.scene_count = int(header["scene_count"])
        super().__init__(path, header, resume)

    def accept(self, entry: Any, lineno: int) -> None:
        if not isinstance(entry, dict) or entry.get("iteration") != self.iteration:
            raise self.damaged(lineno, f"is not part of iteration {self.iteration}")
        if "grammar" in entry:
            if len(self.scenes) != self.scene_count:
                raise self.damaged(lineno, "ends an iteration before all its scenes")
            self._end_iteration(entry["grammar"], entry["report"])
        elif entry.get("index") == len(self.scenes) < self.scene_count:
            self.scenes.append(entry)
        else:
            raise self.damaged(lineno, f"is not the record of scene {len(self.scenes)}")

    def add_scene(self, record: dict[str, Any]) -> None:
        self.write_entry(record)
        self.scenes.append(record)

    def add_iteration(self, text: str, report: dict[str, Any]) -> None:
        self.write_entry({"iteration": self.iteration, "grammar": text, "report": report})
        self._end_iteration(text, report)

    def _end_iteration(self, text: str, report: dict[str, Any]) -> None:
        self.text = text
        self.reports.append(report)
        self.last_scenes, self.scenes = self.scenes, []
        self.iteration += 1

    def __enter__(self) -> FitJournal:
        return self


@contextmanager
def fit_journal_file(next_to: Path | None) -> Iterator[Path]:
    """Where a fit keeps its journal: next to the fitted grammar's file (so `--resume` finds
    it), or, without such a file (standard output, the Python API), in a temporary directory
    removed at the end."""
    if next_to is not None:
        yield journal_path(next_to)
        return
    with tempfile.TemporaryDirectory(prefix="ssg-fit-") as tmp:
        yield Path(tmp) / "fit.partial.jsonl"


def fit_header(
    grammar_text: str, scenes_path: Path, scenes: Sequence[Scene], options: FitOptions
) -> dict[str, Any]:
    """What makes two fits the same run: grammar, scenes, and every option but when to stop."""
    return {
        "journal": FIT_JOURNAL_FORMAT,
        "grammar_sha256": hashlib.sha256(grammar_text.encode()).hexdigest(),
        "scenes": str(scenes_path.resolve()),
        "scene_count": len(scenes),
        "scenes_sha256": scenes_digest(scenes),
        "top": options.top,
        "method": options.method,
        "seed": options.seed,
        "settings": asdict(options.settings),
        "estep": options.estep,
        "samples": options.samples,
    }


@dataclass(frozen=True)
class GrammarSource:
    """Where the grammar text came from, so each iteration compiles it like the original
    (and where the scenes came from, for messages)."""

    file: str
    base_dir: Path | None = None
    allow_outside: bool = False
    dataset: str = "<dataset>"  # where the scenes came from, for messages


def fit_grammar(
    text: str,
    source: GrammarSource,
    scenes: Sequence[Scene],
    options: FitOptions,
    journal: FitJournal,
    time_limit: float | None = None,
    on_scene: Callable[[], None] | None = None,
    on_iteration: Callable[[dict[str, Any]], None] | None = None,
    on_tails: Callable[[], None] | None = None,
) -> FitResult:
    """Run EM from `text` (or from where `journal` stopped) and return the fitted grammar.
    `on_tails` is called when the EM is over and the physical tails are measured (seconds
    of work after the last iteration's report: a progress bar would show a next one)."""
    result = _em(
        text, source, scenes, options, journal, time_limit, on_scene, on_iteration, on_tails
    )
    result.noise_kept = noise_kept_laws(text, source)
    return result


def noise_kept_laws(text: str, source: GrammarSource) -> list[str]:
    """Where the pose laws are that the fit keeps as written only because the `observation`
    section's noise made them (docs/grammar.md section 9): those that fit in the grammar
    without that section and do not in the grammar of observed scenes.  Said once per fit
    (docs/fitting.md): users read "fitted" and find them unchanged."""
    grammar = compile_text(text, source.file, source.base_dir, source.allow_outside)
    if grammar.observation is None:
        return []
    plain_text = without_section(text, "observation")
    try:
        plain = compile_text(plain_text, source.file, source.base_dir, source.allow_outside)
    except SsgError:  # the file's types need the section (clutter names): no plain grammar
        return []
    fits = {p.path for r in plain.rules for p in (r.translation, r.rotation) if p.fits}
    kept = {p.path for r in grammar.rules for p in (r.translation, r.rotation) if not p.fits}
    return [".".join(str(k) for k in path) for path in sorted(fits & kept, key=str)]


def _em(
    text: str,
    source: GrammarSource,
    scenes: Sequence[Scene],
    options: FitOptions,
    journal: FitJournal,
    time_limit: float | None,
    on_scene: Callable[[], None] | None,
    on_iteration: Callable[[dict[str, Any]], None] | None,
    on_tails: Callable[[], None] | None,
) -> FitResult:
    """`fit_grammar`'s iterations."""
    t0 = time.monotonic()
    deadline = None if time_limit is None else t0 + DEADLINE_SHARE * time_limit
    current = journal.text or text
    grammar = compile_text(current, source.file, source.base_dir, source.allow_outside)
    ties = parameter_ties(grammar, current, source.file)  # aliases survive every write-back
    while True:
        stop = _stop_reason(journal.reports, options, len(scenes))
        if stop:
            return _with_tails(
                FitResult(current, journal.reports, *stop), grammar, journal, scenes, on_tails
            )
        if deadline is not None and time.monotonic() >= deadline:
            return _with_tails(
                _out_of_time(current, journal.reports), grammar, journal, scenes, on_tails
            )
        started = time.monotonic()
        parser = Parser(grammar, method=options.method, seed=options.seed)
        start = len(journal.scenes)
        for parsed in parse_scenes(parser, scenes, start, options.top, deadline, options.jobs):
            if parsed.limit is not None and _cut_short(parsed.result, parsed.limit):
                return _with_tails(
                    _out_of_time(current, journal.reports), grammar, journal, scenes, on_tails
                )
            assert parsed.result is not None
            record = _scene_record(journal.iteration, parsed.index, parsed.result, source.dataset)
            journal.add_scene(record)
            if on_scene is not None:
                on_scene()
        trees, weights, report = _weigh(grammar, journal.scenes, journal.iteration)
        if options.estep == "mcmc":
            sampled = _posterior(grammar, journal, options, ties, deadline)
            if sampled is None:  # resumed, the journalled parses give the same chains
                return _with_tails(
                    _out_of_time(current, journal.reports), grammar, journal, scenes, on_tails
                )
            trees, weights, report["posterior"] = sampled
            report["trees"] = len(weights)
        m_started = time.monotonic()
        updates = m_step(grammar, trees, weights, options.settings, ties)
        try:
            current = apply_updates(current, updates, source.file)
        except SharedValueConflict as exc:
            raise SsgError.single(
                f"{exc}; ssg fit cannot give one YAML node two values: write the parameters "
                "out where they differ, or mark them `fixed: true`",
                source.file,
            ) from None
        grammar = compile_text(current, source.file, source.base_dir, source.allow_outside)
        report["seconds"] = round(time.monotonic() - started, 6)
        report["mstep_seconds"] = round(time.monotonic() - m_started, 6)
        journal.add_iteration(current, report)
        if on_iteration is not None:
            on_iteration(report)


def _with_tails(
    result: FitResult,
    grammar: Grammar,
    journal: FitJournal,
    scenes: Sequence[Scene],
    on_tails: Callable[[], None] | None = None,
) -> FitResult:
    """The fitted grammar with the physical tails of `ssg explain` measured on the last
    iteration's best parses (`ssgc.fit.tails`), where its constraints have such tails.  Done
    once, after the last M-step, so it changes no fitted law; a function of the journal, so
    `--resume` gives the same.  `on_tails` is called only when there is something to
    measure, so a grammar without such constraints is not announced as measuring them."""
    if not journal.last_scenes or not has_tails(grammar):
        return result
    if on_tails is not None:
        on_tails()
    best = [
        _tree_from_json(r["trees"][int(np.argmax(r["scores"]))]) if r["scores"] else None
        for r in journal.last_scenes
    ]
    measured = measure_tails(grammar, scenes, best)
    updates = tail_updates(grammar, measured)
    if not updates:
        return result
    result.tails = [m.to_json() for m in measured]
    try:  # a constraint body or a tail shared through a YAML alias cannot take two tails
        result.text = apply_updates(result.text, updates, grammar.file)
    except SharedValueConflict as exc:
        result.message += f"; the measured tails of ssg explain were not written: {exc}"
    return result


def parameter_ties(grammar: Grammar, text: str, file: str) -> Ties:
    """Which rules share a pose law through YAML aliases (fitted once, on all their edges).

    A discrete law (an `or` or `independent` rule's `p`, a count law) reached through an
    alias would get one value per use, which one YAML node cannot hold: that is refused, and
    so is one shared with a `fixed` type's law, which fitting the other use would change.  So
    is any fitted value (a list, a number) that is one YAML node with a value the fit keeps as
    written, such as the root's pose or a `fixed` law: the write would show there too.
    """
    owner: dict[tuple[str | int, ...], tuple[str, int]] = {}
    for r in grammar.rules:
        for part in (r.translation, r.rotation):
            if part.fits:
                owner[part.path] = (part.part, r.id)
    for t in grammar.types:
        if t.synthetic:  # added by `observation` (clutter): no YAML node of its own
            continue
        kind = "kept" if t.fixed else "discrete"
        if t.kind in (Kind.OR, Kind.INDEPENDENT):
            owner.update({grammar.rules[r].path: (kind, r) for r in t.rules})
        elif t.kind == Kind.REPEAT:
            owner[(*t.path, "repeat", "count")] = (kind, -1)
    ties = Ties.none(grammar)
    for group in shared_nodes(text, list(owner), file):
        kinds = {owner[path][0] for path in group}
        if kinds == {"kept"}:
            continue  # written by nobody
        if kinds != {"translation"} and kinds != {"rotation"}:
            raise SsgError.single(_shared_discrete_message(group, "kept" in kinds), file)
        rules = [owner[path][1] for path in group]
        table = ties.translation if kinds == {"translation"} else ties.rotation
        table[rules] = min(rules)
    kept = shared_with_kept(text, fitted_places(grammar))
    if kept is not None:
        raise SsgError.single(
            _shared_kept_message(kept.fitted, kept.kept), file, kept.line, kept.column
        )
    return ties


def fitted_places(grammar: Grammar) -> list[tuple[Loc, str]]:
    """Every (mapping path, key) at which the fit may write a number, by the M-step's rules
    (`ssgc.fit.mstep`): the pose laws that fit, and the discrete laws of types not `fixed`
    (an `independent` rule only where 0 < p < 1)."""
    places: list[tuple[Loc, str]] = []
    for r in grammar.rules:
        for part in (r.translation, r.rotation):
            if part.fits:
                places += [(part.path, key) for key in POSE_KEYS]
    for t in grammar.types:
        if t.fixed or t.synthetic:
            continue
        if t.kind == Kind.OR:
            places += [(grammar.rules[r].path, "p") for r in t.rules]
        elif t.kind == Kind.INDEPENDENT:
            places += [
                (grammar.rules[r].path, "p")
                for r, p in zip(t.rules, t.probs, strict=True)
                if 0 < p < 1
            ]
        elif t.kind == Kind.REPEAT and isinstance(t.count, GeometricCount):
            places.append(((*t.count.path, "geometric"), "p"))
        elif t.kind == Kind.REPEAT and t.count is not None:
            places.append((t.count.path, "probs"))
    return places


def _shared_kept_message(fitted: str, kept: str) -> str:
    return (
        f"{fitted} is one YAML node with {kept} (an anchor and its aliases, or a `<<` merge), "
        "which ssg fit must keep as written (the root's pose, a `fixed` law, or a value it "
        "never fits), so fitting the one would change the other; write the value out at each "
        "place"
    )


def _shared_discrete_message(group: list[tuple[str | int, ...]], with_fixed: bool) -> str:
    where = ", ".join(".".join(str(k) for k in path) for path in group)
    if with_fixed:
        return (
            f"{where} are one YAML node (an anchor and its aliases) and a type marked "
            "`fixed: true` uses it, so fitting the others would change the fixed one too; "
            "write them out, or mark every type that uses it `fixed: true`"
        )
    return (
        f"{where} are one YAML node (an anchor and its aliases), so ssg fit cannot give "
        "them separate values; write them out, or mark the types `fixed: true`"
    )


def _stop_reason(
    reports: list[dict[str, Any]], options: FitOptions, n_scenes: int
) -> tuple[str, str] | None:
    done = len(reports)
    if done >= 2:
        gain = (reports[-1]["log_evidence"] - reports[-2]["log_evidence"]) / max(n_scenes, 1)
        if abs(gain) < options.tol:
            return "converged", (
                f"converged after {done} iterations: the log-evidence changed by "
                f"{gain:.3g} nats per scene (tolerance {options.tol:g})"
            )
    if done >= options.iterations:
        return "iterations", f"stopped after {done} iterations (--iterations)"
    return None


def _cut_short(result: SceneParses | None, limit: float) -> bool:
    """Whether the time limit may have changed this scene's parse.

    The parser gives pose proposals a share of its limit (PROPOSAL_SHARE); a parse that ran
    that long may have had fewer of them than an unlimited one, so it is not journalled: a
    resumed fit must give what an uninterrupted one gives.
    """
    if result is None:
        return True
    return bool(result.timed_out_in) or result.timing["total_s"] >= PROPOSAL_SHARE * limit


def _out_of_time(text: str, reports: list[dict[str, Any]]) -> FitResult:
    done = len(reports)
    what = (
        f"the grammar of iteration {done}"
        if done
        else "the input grammar, unchanged (no iteration finished)"
    )
    return FitResult(
        text,
        reports,
        "time_limit",
        f"time limit reached during iteration {done + 1}; the output is {what}",
    )


def _scene_record(iteration: int, index: int, result: SceneParses, dataset: str) -> dict[str, Any]:
    """One parsed scene as the journal keeps it; a scene proven infeasible stops the fit, one
    without a parse found (no_parse: not proven) is kept and skipped by the M-step."""
    if result.status == "infeasible":
        raise SsgError.single(
            f"scene '{result.name}' cannot be explained by the grammar: {result.message}",
            dataset,
            exit_code=2,
        )
    return {
        "iteration": iteration,
        "index": index,
        "name": result.name,
        "status": result.status,
        "phase": result.phase,
        "message": result.message,
        "scores": [p.score for p in result.parses],
        "trees": [_tree_json(p.tree) for p in result.parses],
    }


def _tree_json(tree: Trees) -> dict[str, list[Any]]:
    """A tree as plain lists: exact (JSON keeps every float64), and rule ids stay valid
    because fitting never changes the grammar's structure."""
    return {
        "type": tree.type.tolist(),
        "parent": tree.parent.tolist(),
        "rule": tree.rule.tolist(),
        "xyz": tree.xyz.tolist(),
        "quat": tree.quat.tolist(),
    }


def _hidden_terms(grammar: Grammar, trees: Trees) -> np.ndarray:
    """Per tree, the score terms of its nodes in subtrees that can hold nothing observed
    (`ssgc.fit.observable`).  Summed over every such subtree they give 1, so a tree's weight
    leaves them out, as the M-step does: the parser places an unobserved subtree at its mode
    and counts its density there, which lifted the log-evidence by 1.74 nats per scene for a
    marker of variance 0.1 and weighed trees with it above trees without."""
    hidden = hidden_nodes(grammar, trees)
    if not hidden.any():
        return np.zeros(trees.n_scenes)
    terms = node_terms(grammar, trees)
    own = (terms.edge + terms.choice)[hidden]
    return np.bincount(trees.scene[hidden], own, minlength=trees.n_scenes)


def _weigh(
    grammar: Grammar, records: list[dict[str, Any]], iteration: int
) -> tuple[Trees, np.ndarray, dict[str, Any]]:
    """All trees as one batch, each weighted by its posterior within its scene; the report.

    A tree's log-posterior (up to the scene's constant) is its parse score plus `log_orders`
    (log c! per repeat node with c children): the parser scores one ordered draw of the
    children, the scene is their set (`ssgc.fit.posterior.log_orders`).  Trees with free latent
    positions (`ssgc.fit.laplace`) also get ½ log det(2πΣ) of those positions' Gaussian
    posterior: the Laplace approximation of the tree's probability with them integrated out,
    rather than at their best values.  The log-evidence is
    that of the set, the log-sum-exp of the same numbers.
    """
    batches, per_scene, skipped = [], [], []
    for r in records:
        if not r["scores"]:
            skipped.append(f"{r['name']}: {r['status']}: {r['message']}")
            continue
        per_scene.append(len(r["scores"]))
        batches += [_tree_from_json(t) for t in r["trees"]]
    if not batches:
        raise SsgError.single("no scene could be parsed, so there is nothing to fit to")
    trees = Trees.concatenate(batches)
    raw = np.concatenate([np.asarray(r["scores"], float) for r in records if r["scores"]])
    scores = raw + log_orders(grammar, trees) - _hidden_terms(grammar, trees)
    spread = latent_spread(grammar, trees)
    if spread.any:  # free latent positions integrated out (Laplace): docs/fitting.md 4.5
        scores = scores + spread.log_volume
    scene = np.repeat(np.arange(len(per_scene)), per_scene)
    best = np.full(len(per_scene), -np.inf)
    np.maximum.at(best, scene, scores)
    shifted = np.exp(scores - best[scene])
    lse = best + np.log(np.bincount(scene, shifted, minlength=len(per_scene)))
    report = {
        "iteration": iteration,
        "log_evidence": float(np.sum(lse)),
        "mean_best_score": float(np.mean(best)),
        "scenes": len(per_scene),
        "trees": len(batches),
        "skipped": skipped,
        # optimal: the best tree is certified; feasible: a tree, not proven best
        "statuses": dict(sorted(Counter(str(r["status"]) for r in records).items())),
    }
    return trees, np.exp(scores - lse[scene]), report


def _posterior(
    grammar: Grammar, journal: FitJournal, options: FitOptions, ties: Ties, deadline: float | None
) -> tuple[Trees, np.ndarray, dict[str, Any]] | None:
    """The MCMC E-step (`ssgc.fit.posterior`), from the journalled top-N parses: a function of
    the journal and the seed, so `--resume` and `--jobs` do not change it."""
    scene_trees = [[_tree_from_json(t) for t in r["trees"]] for r in journal.scenes if r["trees"]]
    mcmc = McmcSettings(samples=options.samples, burn_in=options.samples // 2)
    return posterior_e_step(
        grammar,
        scene_trees,
        mcmc,
        options.settings,
        ties,
        options.seed,
        journal.iteration,
        deadline=deadline,
    )


def _tree_from_json(t: dict[str, list[Any]]) -> Trees:
    n = len(t["type"])
    return Trees(
        scene=np.zeros(n, np.int64),
        type=np.asarray(t["type"], np.int64),
        parent=np.asarray(t["parent"], np.int64),
        rule=np.asarray(t["rule"], np.int64),
        xyz=np.asarray(t["xyz"], float).reshape(n, 3),
        quat=np.asarray(t["quat"], float).reshape(n, 4),
        n_scenes=1,
    )


def report_json(result: FitResult) -> str:
    """The `--report` file: every iteration's numbers and how the fit ended.  `tails` is
    always there (`[]` when none were written, docs/fitting.md section 11), so that a script
    reads it without first asking whether the grammar has such constraints; `mmd` only with
    `--mmd`, which the user asked for; `kept_for_noise` only when the `observation` noise made
    laws the fit keeps (`noise_kept_laws`)."""
    doc: dict[str, Any] = {
        "status": result.status,
        "message": result.message,
        "iterations": result.iterations,
    }
    if result.mmd is not None:
        doc["mmd"] = result.mmd
    doc["tails"] = result.tails
    if result.noise_kept:
        doc["kept_for_noise"] = result.noise_kept
    return json.dumps(doc, indent=1) + "\n"
