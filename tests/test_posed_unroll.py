"""The pose-instantiated model's array code against the plain loops it replaced, the `or`
alternatives it drops for a best-only parse, and the explanation's re-parse budget.

The unroll and the candidate poses must give the very same instances and poses, in the same
order, as the one-at-a-time loops of tests/posed_reference.py (then the models, being built
from them, are the same) on sampled scenes of every bundled grammar, the real sink scenes and
random latent grammars (whose bound restricts the unroll); dropping dominated alternatives must
keep the best score, its status and infeasibility; the explanation's re-parses must say when
their budget ran out.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from latent_grammars import random_grammar
from posed_reference import reference_candidates, reference_unroll

import ssgc.parse.posed as posed
from ssgc.compile import compile_text, load_grammar
from ssgc.explain import EXPLAIN_BUDGET_S, explain_tree
from ssgc.io.scene import Scene, load_scenes, scene_from_tree
from ssgc.ir import Grammar
from ssgc.parse.highs import HighsSession
from ssgc.parse.ip import UnparseableScene
from ssgc.parse.parser import Parser
from ssgc.sample.forward import sample_trees

ROOT = Path(__file__).resolve().parent.parent
GRAMMARS = sorted((ROOT / "grammars").glob("*.yaml"))
SINK_DATA = ROOT / "ssgc" / "data" / "sink" / "saved_scenes.yaml"
FIELDS = ("node", "parent", "slot", "cand_k", "top", "xyz", "quat")


def _sampled(grammar: Grammar, n: int, seed: int = 0) -> list[Scene]:
    trees, _ = sample_trees(grammar, n, seed)
    return [scene_from_tree(grammar, trees.tree(i), f"s{i}") for i in range(n)]


def _scenes(
    path: Path, grammar: Grammar, n: int = 3, real: tuple[int, ...] = (0, 8)
) -> list[Scene]:
    """Sampled scenes, and for the sink grammars some real ones."""
    scenes = _sampled(grammar, n)
    if path.name.startswith("sink"):
        data = load_scenes(SINK_DATA, grammar)
        scenes += [data[i] for i in real]
    return scenes


@contextmanager
def _checked_unroll() -> Iterator[list[int]]:
    """Every unroll made inside (also the bound's, with `restrict`) is compared with the
    reference loop; yields the list of instance counts compared."""
    seen: list[int] = []
    original = posed._Unroll.unroll

    def unroll(self: Any) -> posed.Unrolled:
        got = original(self)
        cand = posed.Candidates(self.cand_xyz, self.cand_quat)
        want = reference_unroll(self.g, self.st, cand, self.restrict or None)
        for f in FIELDS:
            assert np.array_equal(getattr(got, f), getattr(want, f)), f
        seen.append(len(got.node))
        return got

    posed._Unroll.unroll = unroll  # type: ignore[method-assign]
    try:
        yield seen
    finally:
        posed._Unroll.unroll = original  # type: ignore[method-assign]


def _check_loops(path: Path, scenes: list[Scene] | None = None) -> None:
    grammar = load_grammar(path)
    st = Parser(grammar).supertree
    for scene in scenes if scenes is not None else _scenes(path, grammar):
        cand = posed.candidate_poses(grammar, st, scene)
        ref = reference_candidates(grammar, st, scene)
        for got, want in zip(cand.xyz + cand.quat, ref.xyz + ref.quat, strict=True):
            assert got.shape == want.shape and np.array_equal(got, want)
        if posed.instance_count(st, cand) > 20_000:
            continue  # the reference loop takes seconds
        got = posed._Unroll(grammar, st, scene, cand).unroll()
        want = reference_unroll(grammar, st, cand)
        for f in FIELDS:
            assert np.array_equal(getattr(got, f), getattr(want, f)), (path.name, scene.name, f)


@pytest.mark.parametrize("path", GRAMMARS, ids=lambda p: p.stem)
def test_candidates_and_unroll_match_the_loops(path: Path) -> None:
    _check_loops(path)


@pytest.mark.slow
@pytest.mark.parametrize("path", GRAMMARS, ids=lambda p: p.stem)
def test_candidates_and_unroll_match_the_loops_long(path: Path) -> None:
    """50 sampled scenes of each grammar, and all 80 real ones of the sink grammars."""
    grammar = load_grammar(path)
    real = tuple(range(80)) if path.name.startswith("sink") else ()
    _check_loops(path, _scenes(path, grammar, 50, real))


def _check_restricted(seeds: range) -> None:
    with _checked_unroll() as seen:
        for seed in seeds:
            grammar = compile_text(random_grammar(seed))
            parser = Parser(grammar, method="micp")
            for scene in _sampled(grammar, 2, seed):
                parser.parse(scene, time_limit=10)
    assert len(seen) >= len(seeds)  # the check ran (the bound's unrolls included)


def test_restricted_unroll_matches_the_loop() -> None:
    """Latent grammars parsed with the bound unroll under `restrict` (and with proposals):
    every unroll of their parses equals the loop's."""
    _check_restricted(range(4))


@pytest.mark.slow
def test_restricted_unroll_matches_the_loop_long() -> None:
    _check_restricted(range(4, 100))


def _best_scores(grammar: Grammar, scene: Scene) -> tuple[float, float, int, int] | None:
    """The optimum of the full model and of the best-only one, and their sizes."""
    st = Parser(grammar).supertree
    cand = posed.candidate_poses(grammar, st, scene)
    if posed.instance_count(st, cand) > 3000:
        return None  # the full model of a large scene takes long to solve
    out = []
    for best_only in (False, True):
        try:
            problem = posed.reduce_posed(grammar, st, scene, cand, best_only=best_only)
        except UnparseableScene:
            out.append((float("-inf"), 0))
            continue
        sol = HighsSession(problem.milp).solve()
        out.append(
            (sol.objective if sol.x is not None else float("-inf"), problem.milp.shape["binaries"])
        )
    (full, n_full), (best, n_best) = out
    return full, best, n_full, n_best


def _check_best_only(path: Path, n: int) -> int:
    grammar = load_grammar(path)
    if Parser(grammar).has_latent:
        return 0  # the posed model of a latent grammar is over proposals: covered by parses
    compared = 0
    for scene in _sampled(grammar, n, seed=1):
        got = _best_scores(grammar, scene)
        if got is None:
            continue
        full, best, n_full, n_best = got
        assert best == pytest.approx(full, abs=1e-6), (path.name, scene.name)
        assert n_best <= n_full
        compared += 1
    return compared


@pytest.mark.parametrize("path", GRAMMARS, ids=lambda p: p.stem)
def test_best_only_keeps_the_optimum(path: Path) -> None:
    """Dropping dominated `or` alternatives never changes the optimum (nor feasibility)."""
    compared = _check_best_only(path, 4)
    assert compared > 0 or Parser(load_grammar(path)).has_latent


@pytest.mark.slow
@pytest.mark.parametrize("path", GRAMMARS, ids=lambda p: p.stem)
def test_best_only_keeps_the_optimum_long(path: Path) -> None:
    _check_best_only(path, 60)


def test_best_only_shrinks_sink_detailed() -> None:
    """In sink_detailed the dish's four placings under one `or` lead to the same terminal dish
    at the same pose: the best-only model keeps one of each such group."""
    grammar = load_grammar(ROOT / "grammars" / "sink_detailed.yaml")
    parser = Parser(grammar)
    scene = load_scenes(SINK_DATA, grammar)[8]
    cand = posed.candidate_poses(grammar, parser.supertree, scene)
    full = posed.reduce_posed(grammar, parser.supertree, scene, cand)
    best = posed.reduce_posed(grammar, parser.supertree, scene, cand, best_only=True)
    assert best.milp.shape["binaries"] < 0.6 * full.milp.shape["binaries"]


def test_explain_budget_is_reported() -> None:
    """An explanation's re-parses share one budget: with none left, the objects are ranked on
    their local repair and the status says so; with the default, every re-parse runs."""
    grammar = load_grammar(ROOT / "grammars" / "sink.yaml")
    parser = Parser(grammar)
    scene = load_scenes(SINK_DATA, grammar)[0]
    tree = parser.parse(scene).parses[0].tree
    full = explain_tree(grammar, scene, tree, parser)
    assert full.reparse is not None and full.reparse.status == "complete"
    assert full.reparse.budget_s == EXPLAIN_BUDGET_S and full.reparse.parsed > 0
    spent = explain_tree(grammar, scene, tree, parser, time_limit=0.0)
    assert spent.reparse is not None and spent.reparse.status == "budget_exhausted"
    assert spent.reparse.parsed == 0 and spent.reparse.skipped
    assert spent.to_json()["reparse"]["status"] == "budget_exhausted"
    assert "re-parse budget" in spent.text()
    local = {o.index: o.pose_gain for o in spent.objects}
    for o in full.objects:  # a re-parse can only add to the local repair's gain
        assert o.pose_gain >= local[o.index] - 1e-9


@settings(max_examples=40, deadline=None)
@given(hs.integers(0, 10_000), hs.integers(1, 30), hs.integers(0, 12))
def test_near_pairs_match_the_dense_distances(seed: int, n_objects: int, crowd: int) -> None:
    """`posed._near_pairs` (a k-d tree, 8 neighbours, dense where all 8 are near) finds the
    same (point, object) pairs within POS_TOL as the dense distance array it replaced, also
    where more than 8 objects share a spot."""
    from ssgc.parse.posed import _near_pairs
    from ssgc.rules import POS_TOL

    rng = np.random.default_rng(seed)
    objects = rng.uniform(-1, 1, (n_objects, 3))
    objects = np.vstack([objects, np.repeat(objects[:1], crowd, axis=0)])  # a crowded spot
    near = objects[rng.integers(len(objects), size=50)] + rng.normal(0, POS_TOL, (50, 3))
    points = np.vstack([near, rng.uniform(-1, 1, (50, 3))])
    got = set(zip(*_near_pairs(points, objects), strict=True))
    dense = np.linalg.norm(points[:, None] - objects[None], axis=2) <= POS_TOL
    assert got == set(zip(*np.nonzero(dense), strict=True))
