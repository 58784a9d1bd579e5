"""MAP parsing of scenes: top-N distinct parse trees with their scores and certificates.

`parse_scene` reduces a scene to a MILP (`ssgc.parse.ip`), solves it with HiGHS, maps each
solution back to a tree, re-scores the tree with the grammar's scorer (the score reported is
that one, and it must equal the MILP objective), then excludes the tree with a no-good cut on
the binaries that define it and solves again for the next one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ssgc.errors import SsgError
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.parse.ip import ParseProblem, UnparseableScene, reduce_scene
from ssgc.parse.milp import HighsSession
from ssgc.parse.posed import PosedProblem, TooLarge, reduce_posed
from ssgc.parse.supertree import Supertree, build_supertree
from ssgc.score import node_terms, score_trees
from ssgc.tree import Trees

SCORE_TOL = 1e-6


@dataclass
class Parse:
    tree: Trees
    score: float
    status: str
    gap: float
    objective: float
    rule_log_probs: list[float]  # per node: log p(pose | parent) + log P(its fired rules)


@dataclass
class SceneParses:
    name: str
    parses: list[Parse]
    timing: dict[str, float]
    model: dict[str, int]
    status: str
    message: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


class Parser:
    """Parses scenes with one grammar; the supertree is built once and reused."""

    def __init__(self, grammar: Grammar) -> None:
        self.grammar = grammar
        self.supertree: Supertree = build_supertree(grammar)

    def parse(self, scene: Scene, top: int = 1, time_limit: float | None = None) -> SceneParses:
        t0 = time.perf_counter()
        try:
            problem = self.reduce(scene)
        except UnparseableScene as exc:
            return SceneParses(
                name=scene.name,
                parses=[],
                status="infeasible",
                message="; ".join(d.message for d in exc.diagnostics),
                timing={
                    "build_s": time.perf_counter() - t0,
                    "solve_s": 0.0,
                    "total_s": time.perf_counter() - t0,
                },
                model={"variables": 0, "binaries": 0, "rows": 0, "nonzeros": 0},
            )
        session = HighsSession(problem.milp, time_limit)
        build_s = time.perf_counter() - t0
        parses: list[Parse] = []
        solve_s = 0.0
        status, message = "optimal", ""
        while len(parses) < top:
            if time_limit is not None:
                left = time_limit - (time.perf_counter() - t0)
                if left <= 0:
                    status = "time_limit"
                    break
                session.set_time_limit(left)
            sol = session.solve()
            solve_s += sol.solve_s
            if sol.x is None:
                if not parses or sol.status != "infeasible":
                    status, message = sol.status, _why(scene, sol.status, sol.message)
                break  # infeasible after at least one parse: no more trees
            parses.append(self._read(problem, sol.x, sol.objective, sol.status, sol.gap))
            if sol.status != "optimal":
                status = sol.status
                break
            _exclude(session, problem, sol.x)
        total_s = time.perf_counter() - t0
        return SceneParses(
            name=scene.name,
            parses=parses,
            status=status,
            message=message,
            timing={"build_s": build_s, "solve_s": solve_s, "total_s": total_s},
            model=problem.milp.shape,
        )

    def reduce(self, scene: Scene) -> ParseProblem | PosedProblem:
        """The pose-instantiated model when every pose is observed and it is small enough,
        else the equivalent-set model (which also reports grammars with latent poses)."""
        st = self.supertree
        latent = ~st.always_observed
        latent[st.set_of[0]] = False
        if np.any(latent):
            names = sorted(
                {self.grammar.types[st.type[st.set_top[e]]].name for e in np.flatnonzero(latent)}
            )
            raise SsgError.single(
                "this grammar has latent poses (types " + ", ".join(names) + " are never "
                "observed nor tied to an observed node by fixed rules); the IP parser does not "
                "yet propose poses for them",
                self.grammar.file,
            )
        try:
            return reduce_posed(self.grammar, st, scene)
        except TooLarge:
            return reduce_scene(self.grammar, st, scene)

    def _read(
        self,
        problem: ParseProblem | PosedProblem,
        x: np.ndarray,
        objective: float,
        status: str,
        gap: float,
    ) -> Parse:
        tree = problem.invert(x)
        score = float(score_trees(self.grammar, tree)[0])
        if not abs(score - objective) <= SCORE_TOL * max(1.0, abs(objective)):
            raise RuntimeError(f"parse score {score} differs from the MILP objective {objective}")
        terms = node_terms(self.grammar, tree)
        return Parse(
            tree=tree,
            score=score,
            status=status,
            gap=gap,
            objective=objective,
            rule_log_probs=(terms.edge + terms.choice).tolist(),
        )


def _why(scene: Scene, status: str, solver_message: str) -> str:
    if status == "infeasible":
        return (
            f"scene '{scene.name}': no tree of the grammar explains all {len(scene)} objects "
            "together (each can be placed, but not all at once: too many for the grammar's "
            "count bounds or recursion depth?)"
        )
    if status == "time_limit":
        return f"scene '{scene.name}': time limit reached before a parse was found"
    return f"scene '{scene.name}': solver failure ({solver_message})"


def _exclude(session: HighsSession, problem: ParseProblem | PosedProblem, x: np.ndarray) -> None:
    """No-good cut: at least one tree-defining binary must change."""
    cols = problem.structural
    on = x[cols] > 0.5
    coefs = np.where(on, 1.0, -1.0)
    session.add_cut(cols, coefs, -np.inf, float(on.sum()) - 1.0)


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
    if result.message:
        out["message"] = result.message
    return out
