"""MAP parsing of scenes: top-N distinct parse trees with their scores and certificates.

`Parser.parse` makes candidate poses for every equivalent set (observed, proposed, or the
bound's assignments), reduces the scene to a MILP through the first reduction that accepts it
(`ssgc.parse.reduction`: the assignment, pose-instantiated or equivalent-set model), solves it
in a solver session (`ssgc.parse.milp.Session`, HiGHS by default), maps each solution back to
a tree, re-scores the tree with the grammar's scorer (the score reported is that one, and it
must equal the MILP objective), then excludes the tree with a no-good cut on the binaries that
define it and solves again for the next one.
"""

from __future__ import annotations

import gc
import hashlib
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ssgc.errors import SsgError
from ssgc.geometry import quat_canonical
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.parse.bound import (
    AssignmentReduction,
    SetBound,
    add_assignment_poses,
    assignment_problem,
    certify_only,
    set_bounds,
)
from ssgc.parse.bound_chain import add_chain_poses
from ssgc.parse.clock import OutOfTime, check_deadline, past
from ssgc.parse.highs import HighsSession
from ssgc.parse.ip import SetReduction, UnparseableScene
from ssgc.parse.milp import Milp, Session
from ssgc.parse.posed import PosedProblem, PosedReduction, candidate_poses, fit_instances
from ssgc.parse.poses import free_blocks, refine_tree
from ssgc.parse.proposals import Candidates, add_hard_poses, add_proposals, latent_sets
from ssgc.parse.reduction import ModelTooLarge, Problem, Reduction, Request, choose
from ssgc.parse.supertree import Supertree, build_supertree, max_observed
from ssgc.score import node_terms, score_trees
from ssgc.tree import Trees

SCORE_TOL = 1e-6
GAP_TOL = 1e-6  # a relative gap at most this is a certificate (status `optimal`)
# How far a found tree may score above the bound before the bound is taken as wrong, not
# short by rounding: trees may lean into the scorer's POS_TOL slack (a few 1e-6 nats; grammar
# 373 of the profile: 2.6e-6 above its exact bound), which the bound is raised to cover.
BOUND_SHORTFALL = 1e-4
METHODS = ("auto", "ip", "micp")
PROPOSAL_SHARE = 0.3  # of a time limit, for making and optimising pose proposals
DEADLINE_SHARE = 0.9  # of a time limit, when every step must have stopped
REDUCTIONS = (AssignmentReduction(), PosedReduction(), SetReduction())  # first that accepts

# What a scene's (and a parse's) status says; docs/parsing.md "Statuses".
OPTIMAL = "optimal"  # a certificate: no tree scores higher (relative gap <= GAP_TOL)
FEASIBLE = "feasible"  # a real tree with its exact score, not proven best (gap or null)
INFEASIBLE = "infeasible"  # proven: no tree of the grammar explains the scene
NO_PARSE = "no_parse"  # no tree found, and not proven that none exists: see `phase`
ERROR = "error"  # the solver failed
STATUSES = (OPTIMAL, FEASIBLE, INFEASIBLE, NO_PARSE, ERROR)
# Why a scene is `no_parse`: the step that gave up.
PHASES = ("proposals", "instance_limit", "time")
# The steps a time limit can cut short (`timed_out_in`).
STEPS = ("proposals", "build", "solve", "refine", "bound")
# Exit codes of `ssg parse` and `ssg explain` (docs/robustness.md): the first that applies.
EXIT_ERROR = 1  # the solver failed on some scene
EXIT_INFEASIBLE = 2  # some scene has no tree under the grammar: proven
EXIT_NO_PARSE = 3  # some scene has no parse found (proposals, instance limit): not proven
EXIT_TIME = 4  # some scene has no parse because its --time-limit ran out


@dataclass
class Parse:
    tree: Trees
    score: float
    status: str  # optimal (certified) or feasible
    gap: float
    objective: float
    rule_log_probs: list[float]  # per node: log p(pose | parent) + log P(its fired rules)


@dataclass
class SceneParses:
    name: str
    parses: list[Parse]
    timing: dict[str, float]
    model: dict[str, int]
    status: str  # one of STATUSES
    message: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    phase: str = ""  # for no_parse: the step that gave up (PHASES)
    timed_out_in: str = ""  # the step the time limit cut short (STEPS), if any


class Parser:
    """Parses scenes with one grammar; the supertree is built once and reused.

    For grammars with latent poses, the MILP chooses among proposed poses
    (`ssgc.parse.proposals`); each tree it returns is then refined with its structure fixed
    (`ssgc.parse.poses`), and the refined poses are fed back as proposals until the MILP finds
    nothing better than the refined tree (at most MAX_ROUNDS times).

    Statuses are claims, each backed by a proof or not made: `optimal` needs a certificate
    (HiGHS's optimum of a *complete* model — one holding every tree of the grammar at its
    exact score — or the assignment bound within GAP_TOL); `infeasible` needs a proof (a count
    the grammar cannot hold, or a complete model with no solution).  Anything else is
    `feasible` (a tree, not proven best) or `no_parse` (none found, not proven absent).
    """

    MAX_ROUNDS = 4

    def __init__(
        self,
        grammar: Grammar,
        method: str = "auto",
        seed: int = 0,
        session: Callable[[Milp, float | None], Session] = HighsSession,
        reductions: tuple[Reduction, ...] = REDUCTIONS,
    ) -> None:
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.grammar = grammar
        self.method = method
        self.seed = seed
        self.session = session
        self.reductions = reductions
        self.supertree: Supertree = build_supertree(grammar)
        self.latent = latent_sets(self.supertree)
        self.capacity = max_observed(grammar, self.supertree)

    @property
    def has_latent(self) -> bool:
        return bool(np.any(self.latent))

    def parse(
        self,
        scene: Scene,
        top: int = 1,
        time_limit: float | None = None,
        imply_root: bool = False,
    ) -> SceneParses:
        """The top parses of one scene; `time_limit` (seconds) bounds everything it does.
        `imply_root`: a scene without the root the grammar requires still parses, the root
        implied at its pose (the diagnosis sets a misplaced root aside this way)."""
        if time_limit is None or not gc.isenabled():
            return self._parse(scene, top, time_limit, imply_root)
        # A full garbage collection of a large heap can pause for a tenth of a second, a
        # fifth of a short limit; reference counting still frees what one parse discards.
        gc.disable()
        try:
            return self._parse(scene, top, time_limit, imply_root)
        finally:
            gc.enable()

    def _parse(
        self, scene: Scene, top: int, time_limit: float | None, imply_root: bool = False
    ) -> SceneParses:
        t0 = time.perf_counter()
        # the last steps after a deadline check (a vectorised pass, HiGHS's exit) take a moment
        deadline = None if time_limit is None else t0 + DEADLINE_SHARE * time_limit
        step, complete = "capacity", not self.has_latent
        cand: Candidates | None = None
        bounds: dict[int, SetBound] | None = None
        run: _Run | None = None
        propose_s = 0.0
        try:
            self.check_capacity(scene, imply_root)
            step = "build"  # the poses the objects imply: part of every model
            cand = candidate_poses(self.grammar, self.supertree, scene, deadline)
            step = "proposals"
            # proposals get part of a time limit; the MILP needs the rest
            bounds = self.latent_candidates(
                cand, None if time_limit is None else t0 + PROPOSAL_SHARE * time_limit, deadline
            )
            propose_s = time.perf_counter() - t0
            check_deadline(deadline)
            step = "build"
            request = self.request(scene, cand, bounds, deadline, best_only=top == 1)
            reduction = self._choose(request)
            complete = self.complete(reduction, request)
            problem = reduction.apply(request)[1]
        except UnparseableScene as exc:
            if step == "capacity" or (step == "build" and complete):  # a proof
                return _failed(scene, INFEASIBLE, exc, t0)
            if cand is not None and step == "build":  # no tree among the latent candidates
                run = self._retry_hard(scene, cand, bounds, deadline, top)
            if run is None and past(deadline):  # the hard-law poses ran out of time
                message = f"scene '{scene.name}': time limit reached in the proposals step"
                return _failed(scene, NO_PARSE, SsgError.single(message), t0, "time", "proposals")
            if run is None:
                return _failed(scene, NO_PARSE, exc, t0, "proposals")
        except OutOfTime:
            step = "build" if step == "capacity" else step
            message = f"scene '{scene.name}': time limit reached in the {step} step"
            return _failed(scene, NO_PARSE, SsgError.single(message), t0, "time", step)
        except ModelTooLarge as exc:
            return _failed(scene, NO_PARSE, exc, t0, "instance_limit")
        # With a bound, the best tree is certified before the time goes on more trees: asked
        # for three under a time limit, the first lost its certificate to the search for
        # the others (`--top 3 --time-limit 5`: feasible, where `--top 1` was optimal).
        first = 1 if bounds is not None else top
        if run is None:
            run = _Run(self, scene, problem, cand, bounds, deadline, complete)
            run.solve(first)
        if not run.parses and run.status == NO_PARSE and run.phase == "proposals":
            run = self._retry_hard(scene, cand, bounds, deadline, first) or run
            if not run.parses and past(deadline):
                run.timed_out_in = run.timed_out_in or "proposals"
        if bounds is not None and run.parses:
            run.certify()
            if top > len(run.parses) and not run.timed_out_in:
                run.solve(top)
                run.recertify()
        elif self.has_latent and not complete:
            run.message = (
                run.message or "no upper bound for this grammar's shape: the gap is unknown"
            )
        proposals_cut = self.has_latent and propose_s >= PROPOSAL_SHARE * (time_limit or np.inf)
        if proposals_cut and not run.timed_out_in:
            run.timed_out_in = "proposals"  # proposals were cut short: fewer of them
        run.settle()
        total_s = time.perf_counter() - t0
        return SceneParses(
            name=scene.name,
            parses=sorted(run.parses, key=lambda p: -p.score),
            status=run.status,
            message=run.message,
            timing={
                "build_s": run.build_s,
                "solve_s": run.solve_s,
                "total_s": total_s,
                "propose_s": propose_s,
                "refine_s": run.refine_s,
                "bound_s": run.bound_s,
            },
            model=run.problem.milp.shape,
            extra={"raw_score": run.raw_score, "bound": run.bound},
            phase=run.phase,
            timed_out_in=run.timed_out_in,
        )

    def _retry_hard(
        self,
        scene: Scene,
        cand: Candidates,
        bounds: dict[int, SetBound] | None,
        deadline: float | None,
        top: int,
    ) -> _Run | None:
        """When no tree was found among the latent candidates, add the poses that satisfy the
        hard laws exactly (`ssgc.parse.proposals.add_hard_poses`) and solve again over the
        proposals (the assignment model of `micp` names only its assignments' poses, so it
        is left for the model over proposals, the bound still certifying).  None when that
        model has no tree either (or the clock ran out)."""
        g, st = self.grammar, self.supertree
        if bounds is not None and not certify_only(bounds) and self.method != "ip":
            self._propose(cand, bounds, deadline)  # not made yet: micp built from assignments
        add_hard_poses(g, st, cand, deadline)
        request = Request(g, st, scene, cand, True, None, deadline)
        try:
            problem = self._choose(request).apply(request)[1]
        except (UnparseableScene, OutOfTime, ModelTooLarge):
            return None
        run = _Run(self, scene, problem, cand, bounds, deadline, False)
        run.over_proposals = True
        run.solve(top)
        return run if run.parses else None

    def complete(self, reduction: Reduction, request: Request) -> bool:
        """Whether the model the reduction builds holds every tree of the grammar for the
        scene at its exact score, so that its infeasibility is a proof and its optimum a
        certificate: true for grammars without latent poses (every pose is implied by the
        objects), and for a reduction that says so (`complete = True`)."""
        return not request.latent or bool(getattr(reduction, "complete", False))

    def check_capacity(self, scene: Scene, imply_root: bool = False) -> None:
        """Refuse, before any model is built, a scene with more objects (of one type, or in
        all) than any tree of the grammar can hold, or without the root the grammar requires."""
        counts = np.bincount(scene.types, minlength=len(self.grammar.types))
        need = self.grammar.required_root
        if need is not None and counts[need] == 0 and not imply_root:
            raise UnparseableScene.single(missing_root(self.grammar, scene.name), exit_code=2)
        over = np.flatnonzero(counts > self.capacity[:-1])
        parts = [
            f"{counts[t]} {self.grammar.types[t].name} (at most {self.capacity[t]})" for t in over
        ]
        if len(scene) > self.capacity[-1]:
            parts.append(f"{len(scene)} objects in all (at most {self.capacity[-1]})")
        if parts:
            raise UnparseableScene.single(
                f"scene '{scene.name}' has more objects than any tree of the grammar can hold: "
                + ", ".join(parts),
                exit_code=2,
            )

    def candidates(
        self, scene: Scene, deadline: float | None = None
    ) -> tuple[Candidates, dict[int, SetBound] | None]:
        """Candidate poses per set: implied by the objects; for latent sets, the best pose of
        every assignment of children (`micp`, when the grammar's shape allows the bound) or
        proposals (`ip`, and any other shape)."""
        cand = candidate_poses(self.grammar, self.supertree, scene)
        return cand, self.latent_candidates(cand, deadline)

    def latent_candidates(
        self, cand: Candidates, deadline: float | None = None, stop: float | None = None
    ) -> dict[int, SetBound] | None:
        """Add the latent sets' candidate poses to `cand` (optimising them until `deadline`):
        the bound's assignments (`micp` when the grammar's shape allows it), else proposals.
        The bounds are returned whenever the shape allows them: `ip` (and `micp` with
        `certify_only` bounds) parses over the proposals and uses them only to certify its
        refined tree.  Past `stop` (the parse's own deadline) it raises OutOfTime."""
        g, st = self.grammar, self.supertree
        if not self.has_latent:
            return None
        bounds = set_bounds(g, st, cand, deadline)
        check_deadline(stop)
        if self.method != "ip" and bounds is not None and not certify_only(bounds):
            return bounds
        self._propose(cand, bounds, deadline, stop)
        return bounds

    def _propose(
        self,
        cand: Candidates,
        bounds: dict[int, SetBound] | None,
        deadline: float | None,
        stop: float | None = None,
    ) -> None:
        """Proposals for the latent sets, plus the bound's assignment and chain poses when
        there is a bound (they only certify; their poses join the proposals)."""
        g, st = self.grammar, self.supertree
        add_proposals(g, st, cand, np.random.default_rng(self.seed), deadline, stop)
        if bounds is not None:
            add_assignment_poses(cand, bounds)
            add_chain_poses(g, st, cand, bounds)
            _repeat_empty_poses(cand, bounds)

    def reduce(
        self,
        scene: Scene,
        cand: Candidates | None = None,
        bounds: dict[int, SetBound] | None = None,
        deadline: float | None = None,
    ) -> Problem:
        """The scene reduced by the first reduction of the chain that accepts it (the
        assignment model with bounds; else the pose-instantiated model when it is small
        enough; else, for grammars without latent poses, the equivalent-set model)."""
        if cand is None:
            cand, bounds = self.candidates(scene)
        request = self.request(scene, cand, bounds, deadline)
        return self._choose(request).apply(request)[1]

    def _choose(self, request: Request) -> Reduction:
        """The first reduction that accepts the request; for a latent grammar whose model
        over proposals would pass the instance limit, after dropping proposals until it fits
        (`fit_instances`: sound, the model over proposals is not complete anyway)."""
        try:
            return choose(self.reductions, request)
        except ModelTooLarge:
            if not self.has_latent or not fit_instances(self.supertree, request.cand, self.latent):
                raise
            return choose(self.reductions, request)

    def request(
        self,
        scene: Scene,
        cand: Candidates,
        bounds: dict[int, SetBound] | None,
        deadline: float | None,
        best_only: bool = False,
    ) -> Request:
        if self.method == "ip":
            bounds = None  # the bounds only certify: the model is over the proposals
        return Request(
            self.grammar, self.supertree, scene, cand, self.has_latent, bounds, deadline, best_only
        )

    def open_session(self, milp: Milp, time_limit: float | None = None) -> Session:
        """The one place a solver session is made (HiGHS unless the parser was given another)."""
        return self.session(milp, time_limit)

    def read(
        self,
        problem: Problem,
        x: np.ndarray,
        objective: float,
        status: str,
        gap: float,
    ) -> Parse:
        """The tree a solution encodes, re-scored; it must score the MILP objective."""
        tree = problem.invert(x)
        parse = self.scored(tree, status, gap, objective)
        if not abs(parse.score - objective) <= SCORE_TOL * max(1.0, abs(objective)):
            raise RuntimeError(
                f"parse score {parse.score} differs from the MILP objective {objective}"
            )
        return parse

    def scored(self, tree: Trees, status: str, gap: float, objective: float) -> Parse:
        score = float(score_trees(self.grammar, tree, marginal=True)[0])
        terms = node_terms(self.grammar, tree, marginal=True)
        return Parse(
            tree=tree,
            score=score,
            status=status,
            gap=gap,
            objective=objective,
            rule_log_probs=(terms.edge + terms.choice).tolist(),
        )


class _Run:
    """One scene's solve loop: the refinement rounds (latent grammars), then top-N by cuts.

    Parses are read as `feasible`; `settle` makes a parse `optimal` only with its
    certificate, and names the scene's status from what was found and proven."""

    def __init__(
        self,
        parser: Parser,
        scene: Scene,
        problem: Problem,
        cand: Candidates,
        bounds: dict[int, SetBound] | None,
        deadline: float | None,
        complete: bool,
    ) -> None:
        self.p, self.scene, self.problem, self.cand = parser, scene, problem, cand
        self.bounds = bounds
        self.deadline = deadline
        self.complete = complete  # the MILP holds every tree at its exact score
        self.parses: list[Parse] = []
        self.certified: set[int] = set()  # ids of parses with a certificate
        self.seen: set[tuple] = set()
        self.status, self.message = FEASIBLE, ""
        self.phase, self.timed_out_in = "", ""
        self.build_s = problem.build_s
        self.solve_s = 0.0
        self.rounds = 0
        self.refine_s = 0.0
        self.raw_score = float("nan")  # the first MILP tree's score, before any refinement
        self.bound = float("nan")  # an upper bound on the MAP score, when one is known
        self.bound_s = 0.0
        self.over_proposals = False  # a `micp` retry over proposals (`Parser._retry_hard`)
        self.pending: Parse | None = None  # a refined tree while its rebuilt model solves
        self.session = parser.open_session(problem.milp)

    @property
    def _assignment_model(self) -> bool:
        """Whether the MILP is the assignment model (its latent poses are each assignment's
        best already), not the model over proposals whose trees are refined."""
        if self.over_proposals:
            return False
        return self.p.method != "ip" and self.bounds is not None and not certify_only(self.bounds)

    def _solve_once(self):  # type: ignore[no-untyped-def]
        if self.deadline is not None:
            left = self.deadline - time.perf_counter()
            if left <= 0:
                return None
            self.session.set_time_limit(left)
        sol = self.session.solve()
        self.solve_s += sol.solve_s
        return sol

    def solve(self, top: int) -> None:
        tries = 0
        while len(self.parses) < top:
            if tries >= 20 * top:  # each solve found another encoding of a tree found
                self.message = (
                    f"only {len(self.parses)} distinct tree(s) found in {tries} solves "
                    "(the others were trees already found, their interchangeable objects or "
                    "latent nodes in other places); more may exist"
                )
                return
            tries += 1
            sol = self._solve_once()
            if sol is None or (sol.x is None and sol.status == "time_limit"):
                self.timed_out_in = "solve"
                self._keep_pending()
                self.message = _why(self.scene, "time_limit", "", len(self.parses), top)
                return
            if sol.x is None:
                self._no_more(sol, top)
                return
            parse = self.p.read(self.problem, sol.x, sol.objective, FEASIBLE, sol.gap)
            if not self.parses and np.isnan(self.raw_score):
                self.raw_score = parse.score
            certified = self.complete and sol.status == "optimal" and sol.gap <= GAP_TOL
            if self.p.has_latent and not self._assignment_model:
                parse = self._refined(parse, sol)
                if parse is None:
                    continue  # the MILP was rebuilt with better proposals: solve again
            key = tree_signature(self.p.grammar, parse.tree)
            if key not in self.seen:
                self.seen.add(key)
                self.parses.append(parse)
                if certified and (not self.p.has_latent or parse.score >= parse.objective):
                    self.certified.add(id(parse))
            if sol.status != "optimal":
                self.timed_out_in = "solve" if sol.status == "time_limit" else ""
                if sol.status != "time_limit":
                    self.status, self.message = ERROR, _why(self.scene, sol.status, sol.message)
                return
            _exclude(self.session, self.problem, sol.x)

    def _keep_pending(self) -> None:
        """A refined tree whose rebuilt model ran out of time is still a tree: keep it."""
        if not self.parses and self.pending is not None:
            self.parses.append(self.pending)
            self.seen.add(tree_signature(self.p.grammar, self.pending.tree))

    def _no_more(self, sol, top: int) -> None:  # type: ignore[no-untyped-def]
        """The MILP has no (further) solution: a proof when the model is complete."""
        self._keep_pending()
        if sol.status != "infeasible":
            self.status, self.message = ERROR, _why(self.scene, sol.status, sol.message)
        elif self.parses:  # no more trees: say so (--top N asked for more)
            exists = "exist" if self.complete else "found"
            self.message = f"only {len(self.parses)} distinct tree(s) {exists}"
        elif self.complete:
            self.status, self.message = INFEASIBLE, _why(self.scene, "infeasible", "")
        else:
            self.status, self.phase = NO_PARSE, "proposals"
            self.message = (
                f"scene '{self.scene.name}': no parse found among the proposed latent poses "
                "(not proven: a tree may exist at poses not proposed)"
            )

    def settle(self) -> None:
        """Each parse's status from its certificate, and the scene's from its best parse."""
        if self.status == NO_PARSE and self.timed_out_in == "proposals":
            self.phase = "time"  # more time, more proposals: the clock gave up, not them
        if not self.parses and self.status == FEASIBLE:  # the loop ended without a tree
            self.status, self.phase = NO_PARSE, "time" if self.timed_out_in else "proposals"
        for p in self.parses:
            p.status = OPTIMAL if id(p) in self.certified else FEASIBLE
            if not self.complete and self.bounds is None:
                p.gap = float("nan")  # the gap of a model over proposals proves nothing
        if self.parses and self.status != ERROR:
            best = max(self.parses, key=lambda p: p.score)
            self.status = best.status
        if self.timed_out_in and self.parses and not self.message:
            self.message = f"time limit reached in the {self.timed_out_in} step"

    def certify(self) -> None:
        """Bound the MAP score from above (`ssgc.parse.bound`) and give the best parse its gap;
        within GAP_TOL, the best parse is certified.

        A time limit during the bound's MILP still leaves a valid bound (HiGHS's dual bound).
        """
        g, st = self.p.grammar, self.p.supertree
        t0 = time.perf_counter()
        assert self.bounds is not None
        best = max(self.parses, key=lambda p: p.score)
        best.gap = float("nan")  # only the bound gives this model's parses a gap
        for p in self.parses:
            p.gap = float("nan")
        if self.deadline is not None and self.deadline - t0 < self.build_s:
            self.message = "time limit reached before the bound: the gap is unknown"
            self.timed_out_in = "bound"
            return
        try:
            problem = assignment_problem(
                g, st, self.scene, self.cand, self.bounds, upper=True, deadline=self.deadline
            )
        except OutOfTime:
            self.message = "time limit reached before the bound: the gap is unknown"
            self.timed_out_in = "bound"
            return
        except UnparseableScene:  # a tree exists, so the bound's model missed it: no bound
            self.message = "the bound's model holds no tree of this scene: the gap is unknown"
            return
        session = self.p.open_session(problem.milp)
        if self.deadline is not None:
            session.set_time_limit(max(self.deadline - time.perf_counter(), 1e-3))
        sol = session.solve()
        self.bound_s = time.perf_counter() - t0
        self.solve_s += sol.solve_s
        if sol.status == "time_limit":
            self.timed_out_in = "bound"
        upper = sol.objective if sol.status == "optimal" else sol.bound
        if not np.isfinite(upper):
            return
        if (best.score - upper) / max(1.0, abs(best.score)) > BOUND_SHORTFALL:
            # every tree scores at most the bound: one clearly above it proves the bound's
            # model incomplete here (a latent pose its rows do not cover): no certificate
            self.message = "the bound fell below a tree's score: the gap is unknown"
            return
        self.bound = float(upper)
        if (self.bound - best.score) / max(1.0, abs(best.score)) > GAP_TOL:
            best = self._polished(best)
        self.bound = max(self.bound, best.score)
        best.gap = (self.bound - best.score) / max(1.0, abs(best.score))
        if best.gap <= GAP_TOL:
            self.certified.add(id(best))

    def recertify(self) -> None:
        """After more trees were found: the certificate, if any, goes to the best of them,
        against the bound `certify` computed (it holds for every tree)."""
        if not np.isfinite(self.bound):
            return
        self.certified.clear()
        best = max(self.parses, key=lambda p: p.score)
        if (best.score - self.bound) / max(1.0, abs(best.score)) > BOUND_SHORTFALL:
            self.message = "the bound fell below a tree's score: the gap is unknown"
            self.bound = float("nan")
            for p in self.parses:
                p.gap = float("nan")
            return
        for p in self.parses:
            p.gap = (max(self.bound, p.score) - p.score) / max(1.0, abs(p.score))
        if best.gap <= GAP_TOL:
            self.certified.add(id(best))

    def _polished(self, best: Parse) -> Parse:
        """The best parse with its latent poses moved to a local maximum of the exact score
        (`refine_tree`, with the structure fixed), when that scores higher; it replaces the
        parse in the list.

        Why: `micp`'s trees sit at each assignment's polished pose, which stops a little short
        of the optimum where a box face or several terms meet; a gap left by that is closed
        by the last step uphill, at the cost of one refinement, only for an uncertified tree."""
        if past(self.deadline):
            return best
        t0 = time.perf_counter()
        tree = refine_tree(self.p.grammar, best.tree, deadline=self.deadline)
        self.refine_s += time.perf_counter() - t0
        polished = self.p.scored(tree, best.status, float("nan"), best.objective)
        if not polished.score > best.score:
            return best
        self.parses[self.parses.index(best)] = polished
        return polished

    def _refined(self, parse: Parse, sol) -> Parse | None:  # type: ignore[no-untyped-def]
        """The parse with its latent poses refined; None when the refined poses were added as
        proposals and the MILP rebuilt (only while looking for the first tree)."""
        g = self.p.grammar
        t0 = time.perf_counter()
        tree = refine_tree(g, parse.tree, deadline=self.deadline)
        self.refine_s += time.perf_counter() - t0
        if self.deadline is not None and time.perf_counter() >= self.deadline:
            self.timed_out_in = self.timed_out_in or "refine"
        refined = self.p.scored(tree, parse.status, float("nan"), parse.objective)
        if refined.score < parse.score:
            refined = replace(parse, gap=float("nan"))  # refinement cannot lose: keep it
        improved = refined.score > parse.score + SCORE_TOL * max(1.0, abs(parse.score))
        if self.parses or not improved or self.rounds >= Parser.MAX_ROUNDS:
            return refined
        self.rounds += 1
        self.pending = refined  # the tree so far, should the rebuilt model run out of time
        self._add_refined_poses(sol.x, tree)
        t0 = time.perf_counter()
        try:
            self.problem = self.p.reduce(self.scene, self.cand, deadline=self.deadline)
        except OutOfTime:
            self.timed_out_in = self.timed_out_in or "build"
            return refined
        except ModelTooLarge:  # the refined poses do not fit: keep the refined tree
            return refined
        self.session = self.p.open_session(self.problem.milp)
        self.build_s += time.perf_counter() - t0
        return None

    def _add_refined_poses(self, x: np.ndarray, tree: Trees) -> None:
        """Offer every refined latent pose to the latent sets of the same type and rule."""
        st = self.p.supertree
        problem = self.problem
        assert isinstance(problem, PosedProblem)
        nodes = problem.st_node[problem.active(x)]
        _, tops = free_blocks(self.p.grammar, tree)
        for i in tops:
            n = nodes[i]
            same = (
                self.p.latent
                & (st.type[st.set_top] == st.type[n])
                & (st.rule[st.set_top] == st.rule[n])
            )
            for e in np.flatnonzero(same):
                self.cand.add(int(e), tree.xyz[i], tree.quat[i])


def _repeat_empty_poses(cand: Candidates, bounds: dict[int, SetBound]) -> None:
    """Give a latent set its childless assignment's pose once per copy of its `repeat`, and
    the pose of every assignment the bound repeats (one naming only latent children).

    The model over proposals gives each candidate pose of a `repeat`'s child set to at most
    one copy, so two childless latent copies (each best at its rule's mode) could not both sit
    at that pose, while the bound counts them both (its `_copies_apart` repeats the row): the
    tree found would fall short of the bound.  Candidates.add would merge the repeats, so they
    are appended as they are."""
    for e, sb in bounds.items():
        empty = np.flatnonzero(np.all(sb.assignment < 0, axis=1))
        extra = np.union1d(empty[1:], _repeated_rows(sb))
        if len(extra):
            cand.xyz[e] = np.vstack([cand.xyz[e], sb.xyz[extra]])
            cand.quat[e] = np.vstack([cand.quat[e], sb.quat[extra]])


def _repeated_rows(sb: SetBound) -> np.ndarray:
    """The rows of a bound that repeat an earlier row (assignment and pose): the copies
    `_copies_apart` made of an assignment naming no object."""
    key = np.column_stack([sb.assignment, sb.xyz, sb.quat])
    if not len(key):
        return np.zeros(0, np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.setdiff1d(np.arange(len(key)), first)


def tree_signature(grammar: Grammar, tree: Trees) -> bytes:
    """What makes two parse trees different: types, rules, and the poses of nodes tied to
    observations, but not the poses of latent nodes (two refinements of one structure are one
    tree).

    Each node gets a digest of its own part and its children's sorted digests (children are
    unordered), built bottom-up: a flat key even for a tree thousands of levels deep, where
    nested tuples would exhaust Python's recursion limit when hashed or compared.
    """
    top, tops = free_blocks(grammar, tree)
    latent = np.isin(top, tops)
    keys: list[bytes] = [b""] * len(tree)
    kids: list[list[bytes]] = [[] for _ in range(len(tree))]
    for i in range(len(tree) - 1, -1, -1):  # children first
        # q and -q are one rotation: the sign-canonical quaternion, not |q| per component,
        # which made yaw +30° and -30° one key (two planks crossed at one place: one tree)
        rounded = np.round(np.r_[tree.xyz[i], quat_canonical(tree.quat[i])], 6) + 0.0
        pose = () if latent[i] else tuple(rounded.tolist())
        own = repr((int(tree.type[i]), int(tree.rule[i]), pose)).encode()
        keys[i] = hashlib.blake2b(own + b"".join(sorted(kids[i])), digest_size=20).digest()
        if tree.parent[i] >= 0:
            kids[tree.parent[i]].append(keys[i])
    return keys[0] if keys else b""


def _failed(
    scene: Scene, status: str, exc: SsgError, t0: float, phase: str = "", step: str = ""
) -> SceneParses:
    """A scene without a parse: proven `infeasible`, or `no_parse` with the phase that gave
    up (and, for a time limit, the step it cut short)."""
    elapsed = time.perf_counter() - t0
    message = "; ".join(d.message for d in exc.diagnostics)
    if status == NO_PARSE and phase == "proposals":  # the model's reason is no proof: drop it
        message = (
            f"scene '{scene.name}': no parse found among the proposed latent poses "
            "(not proven: a tree may exist at poses not proposed)"
        )
    elif status == NO_PARSE and phase == "instance_limit":
        message = f"no parse: {message} (not proven that no tree exists)"
    return SceneParses(
        name=scene.name,
        parses=[],
        status=status,
        message=message,
        timing={"build_s": elapsed, "solve_s": 0.0, "total_s": elapsed},
        model={"variables": 0, "binaries": 0, "rows": 0, "nonzeros": 0},
        phase=phase,
        timed_out_in=step,
    )


def _why(scene: Scene, status: str, solver_message: str, found: int = 0, top: int = 1) -> str:
    if status == "infeasible":
        return (
            f"scene '{scene.name}': no tree of the grammar explains all {len(scene)} objects "
            "together (each can be placed, but not all at once: too many for the grammar's "
            "count bounds or recursion depth?)"
        )
    if status == "time_limit" and not found:
        return (
            f"scene '{scene.name}': time limit reached in the solve step before a parse was found"
        )
    if status == "time_limit":
        return f"time limit reached in the solve step after {found} of {top} parse(s)"
    return f"scene '{scene.name}': solver failure ({solver_message})"


def _exclude(session: Session, problem: Problem, x: np.ndarray) -> None:
    """No-good cut: at least one tree-defining binary must change."""
    cols = problem.structural
    on = x[cols] > 0.5
    coefs = np.where(on, 1.0, -1.0)
    session.add_cut(cols, coefs, -np.inf, float(on.sum()) - 1.0)


def exit_code(rows: Iterable[Mapping[str, Any]]) -> int:
    """The exit code of a run from its scenes' `status` and `phase` (0: every scene has a
    parse).  A proven answer outranks an unproven one: error, infeasible, no_parse, time."""
    codes = {0}
    for r in rows:
        status, phase = r.get("status"), r.get("phase")
        if status == ERROR:
            codes.add(EXIT_ERROR)
        elif status == INFEASIBLE:
            codes.add(EXIT_INFEASIBLE)
        elif status == NO_PARSE:
            codes.add(EXIT_TIME if phase == "time" else EXIT_NO_PARSE)
    return min(codes - {0}, default=0)


def result_to_json(grammar: Grammar, result: SceneParses) -> dict[str, Any]:
    """One scene of `ssg parse` output: always the same shape, parses best first."""
    from ssgc.io.scene import tree_to_json

    parses = []
    for p in result.parses:
        tree = p.tree
        rules = [
            {
                "node": i,
                "rule": grammar.rule_name(int(tree.rule[i])) if tree.rule[i] >= 0 else None,
                "log_prob": float(p.rule_log_probs[i]),
            }
            for i in range(len(tree))
        ]
        parses.append(
            {
                "score": p.score,
                "status": p.status,
                "gap": p.gap if np.isfinite(p.gap) else None,
                "tree": tree_to_json(grammar, tree),
                "rules": rules,
            }
        )
    out: dict[str, Any] = {
        "name": result.name,
        "status": result.status,
        "parses": parses,
        "timing": {k: round(v, 6) for k, v in result.timing.items()},
        "model": {k: result.model[k] for k in ("variables", "binaries", "rows")},
    }
    bound = result.extra.get("bound", float("nan"))
    if np.isfinite(bound):
        out["bound"] = bound
    if result.phase:
        out["phase"] = result.phase
    if result.timed_out_in:
        out["timed_out_in"] = result.timed_out_in
    if result.message:
        out["message"] = result.message
    return out


def missing_root(grammar: Grammar, scene_name: str) -> str:
    """Why a scene without its grammar's required root has no tree."""
    assert grammar.required_root is not None
    name = grammar.types[grammar.required_root].name
    why = f"`root: {{required: true}}` in {grammar.file}"
    if grammar.root != grammar.required_root:
        why = (
            f"with the `observation` section of {grammar.file}, an observed root is an object "
            "of every scene, never implied"
        )
    return f"scene '{scene_name}' has no {name}: every scene of this grammar shows its root ({why})"
