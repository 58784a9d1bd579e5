"""Time limits in every phase of a parse (issue 11, item 3).

Default run: behaviour only — the step a limit cuts short is named, a scene cut short in the
proposals is `no_parse` with phase `time`, `-o` still gets a whole file, candidate poses are
deduplicated exactly as by comparing every pair.  `-m timing` (deselected by default): every
scene of random latent grammars and of the real sink scenes ends within 110% of its limit in
wall-clock time (the wide 1,000-object scene: tests/test_parse_status.py).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from latent_grammars import random_grammar
from test_parse_property import LATENT_AND_CHAIN
from test_parse_status import WIDE, run, wide_scene, write_scene

import ssgc.parse.parser as parser_module
import ssgc.parse.proposals as proposals
from ssgc.compile import compile_text, load_grammar
from ssgc.geometry import quat_angle
from ssgc.io.journal import journal_path
from ssgc.io.scene import Scene, load_scenes, scene_from_tree
from ssgc.laws.base import POS_TOL, ROT_TOL
from ssgc.parse.parser import STEPS, Parser
from ssgc.parse.posed import _first_distinct
from ssgc.parse.proposals import Candidates, near_earlier
from ssgc.sample.forward import sample_trees

ROOT = Path(__file__).resolve().parents[1]


def _brute_near(xyz: np.ndarray, n_old: int) -> set[tuple[int, int]]:
    new = xyz[n_old:]
    near = np.linalg.norm(xyz[:, None, :] - new[None, :, :], axis=2) <= POS_TOL
    earlier = np.arange(len(xyz))[:, None] < (n_old + np.arange(len(new)))[None, :]
    i, j = np.nonzero(near & earlier)
    return set(zip(i.tolist(), j.tolist(), strict=True))


@settings(max_examples=150, deadline=None)
@given(
    n_old=hs.integers(0, 12),
    n_new=hs.integers(1, 12),
    sites=hs.integers(1, 4),
    jitter=hs.sampled_from([0.0, 0.3, 1.0, 3.0]),
    flat=hs.booleans(),
    chunk=hs.sampled_from([1, 5, 1 << 20]),
    seed=hs.integers(0, 2**31),
)
def test_near_pairs_match_every_pair_compared(n_old, n_new, sites, jitter, flat, chunk, seed):
    """The sorted sweep finds exactly the pairs within POS_TOL that comparing every pair finds,
    also where poses repeat, sit within a few POS_TOL of each other, or share a coordinate,
    and whatever the chunk of pairs compared at once (the sweep is forced: small inputs
    compare every pair)."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(sites, 3))
    xyz = centres[rng.integers(0, sites, n_old + n_new)]
    xyz = xyz + rng.normal(size=xyz.shape) * POS_TOL * jitter
    if flat:
        xyz[:, 0] = 0.0
    with pytest.MonkeyPatch.context() as m:
        m.setattr(proposals, "NEAR_PAIRS_CHUNK", chunk)
        m.setattr(proposals, "ALL_PAIRS_UP_TO", 0)
        i, j = near_earlier(xyz, n_old)
    small = near_earlier(xyz, n_old)  # every pair compared (the inputs are small)
    assert set(zip(*small, strict=True)) == set(zip(i.tolist(), j.tolist(), strict=True))
    assert set(zip(i.tolist(), j.tolist(), strict=True)) == _brute_near(xyz, n_old)


@settings(max_examples=100, deadline=None)
@given(
    n=hs.integers(0, 40),
    sites=hs.integers(1, 4),
    jitter=hs.sampled_from([0.0, 0.3, 1.0, 3.0]),
    turns=hs.integers(1, 3),
    nodes=hs.integers(1, 3),
    objects=hs.integers(1, 6),
    held=hs.booleans(),
    seed=hs.integers(0, 2**31),
)
def test_first_distinct_poses_match_every_pair_compared(
    n, sites, jitter, turns, nodes, objects, held, seed
):
    """The implied poses a set keeps (`candidate_poses`), exactly as comparing every pair
    says.  Where every instance holds an observed node (`held`): a pose is the r-th of its
    node among the poses within both tolerances of it, and is kept unless an earlier pose of
    another node within them is the r-th of its own; so two objects at one pose through one
    node get two candidates, and an object of another node there shares one.  Otherwise a
    pose is kept unless an earlier one within them is the same object's."""
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(sites, 3))[rng.integers(0, sites, n)]
    xyz = xyz + rng.normal(size=xyz.shape) * POS_TOL * jitter
    quat = np.eye(4)[rng.integers(0, turns, n)]
    node = np.sort(rng.integers(0, nodes, n))  # poses come in node order
    obj = rng.integers(0, objects, n)
    keep = _first_distinct(xyz, quat, obj, node if held else None, None)
    close = np.linalg.norm(xyz[:, None] - xyz[None], axis=2) <= POS_TOL
    same = close & (quat_angle(quat[:, None], quat[None]) <= ROT_TOL)
    one_node = node[:, None] == node[None]
    rank = [int((same[:j, j] & one_node[:j, j]).sum()) for j in range(n)]

    def shares(i: int, j: int) -> bool:
        if held:
            return bool(same[i, j] and not one_node[i, j] and rank[i] == rank[j])
        return bool(same[i, j] and obj[i] == obj[j])

    expected = [j for j in range(n) if not any(shares(i, j) for i in range(j))]
    assert keep.tolist() == expected


def test_candidates_add_skips_repeats_only():
    c = Candidates([np.zeros((0, 3))], [np.zeros((0, 4))])
    q = np.tile([1.0, 0, 0, 0], (3, 1))
    c.add(0, np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0.5 * POS_TOL]]), q)
    assert len(c.xyz[0]) == 2  # the third is the first within POS_TOL
    turned = np.array([[0.0, 1.0, 0, 0]])  # same position, another rotation: kept
    c.add(0, np.zeros((1, 3)), turned)
    c.add(0, np.array([[1.0, 0, 0]]), q[:1])  # a repeat of an old pose: skipped
    assert len(c.xyz[0]) == 3


def test_time_limit_in_the_proposals_says_so(monkeypatch):
    """A limit that runs out while latent poses are proposed: `no_parse`, phase `time`, step
    `proposals` — not a parse of half the proposals, and not `infeasible`."""
    real = parser_module.set_bounds

    def slow_bounds(*args, **kwargs):
        time.sleep(0.06)  # past the parse's deadline (90% of 0.05 s)
        return real(*args, **kwargs)

    monkeypatch.setattr(parser_module, "set_bounds", slow_bounds)
    grammar = compile_text(LATENT_AND_CHAIN)
    x = grammar.type_ids["X"]
    scene = Scene("one", np.array([x]), np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]))
    for method in ("ip", "micp"):
        result = Parser(grammar, method=method).parse(scene, time_limit=0.05)
        assert (result.status, result.phase, result.timed_out_in) == (
            "no_parse",
            "time",
            "proposals",
        ), (method, result.message)
        assert not result.parses and "proposals" in result.message


def test_time_limit_with_output_file_writes_a_whole_file(tmp_path):
    """`-o` under a limit that cuts a scene short: exit 4, a complete JSON file with the
    scene's status and step, and no journal left behind."""
    grammar_path = tmp_path / "wide.yaml"
    grammar_path.write_text(WIDE)
    grammar = compile_text(WIDE)
    scene = write_scene(tmp_path / "wide.json", grammar, wide_scene(grammar, 1000))
    out = tmp_path / "out.json"
    result = run("parse", scene, "-g", grammar_path, "--time-limit", 0.001, "-q", "-o", out)
    assert result.exit_code == 4, result.output
    row = json.loads(out.read_text())["scenes"][0]
    assert (row["status"], row["phase"]) == ("no_parse", "time")
    assert row["timed_out_in"] in STEPS
    assert not journal_path(out).exists()


def test_hard_law_poses_stop_within_a_set_at_the_deadline(monkeypatch):
    """`add_hard_poses` checks the deadline between a set's combinations of children, not only
    between sets: one set's combinations took up to 0.06 s of CPU, which let a 0.5 s parse of
    random latent grammar 6 end at 0.56-0.64 s (pytest -m timing).  With the clock passing
    the deadline at the first solved combination, one combination's parent poses are all that
    is solved, where the set has many more."""
    from ssgc.parse import hard_laws
    from ssgc.parse.posed import candidate_poses

    grammar = compile_text(random_grammar(6))
    trees, _ = sample_trees(grammar, 5, 6)
    scene = scene_from_tree(grammar, trees.tree(1), "s1")
    st = Parser(grammar).supertree
    solve, calls, late = hard_laws.hard_poses, [], []

    def counted(*args, **kwargs):
        calls.append(1)
        late.append(True)  # from now on the clock reads past the deadline
        return solve(*args, **kwargs)

    monkeypatch.setattr(hard_laws, "hard_poses", counted)
    proposals.add_hard_poses(grammar, st, candidate_poses(grammar, st, scene))
    unbounded = len(calls)
    calls.clear()
    late.clear()
    monkeypatch.setattr(time, "perf_counter", lambda: 1e9 if late else 0.0)
    proposals.add_hard_poses(grammar, st, candidate_poses(grammar, st, scene), deadline=1.0)
    assert unbounded > proposals.HARD_PARENTS_EACH + 1
    assert 1 <= len(calls) <= proposals.HARD_PARENTS_EACH + 1


def test_the_revolute_search_stops_at_the_deadline_within_its_first_grid(monkeypatch):
    """The bound's search along revolute arcs checks the deadline at every grid point: its
    first grid (48 angles over every row) ran unchecked, 0.3 s of CPU past a 0.5 s parse's
    proposal deadline (random latent grammar 10, scene s4).  With the clock passing the
    deadline at the search's first evaluation, it evaluates one grid point, where a grid has
    48."""
    import ssgc.parse.bound as bound
    from ssgc.parse.posed import candidate_poses

    grammar = compile_text(random_grammar(10))
    trees, _ = sample_trees(grammar, 5, 10)
    scene = scene_from_tree(grammar, trees.tree(4), "s4")
    st = Parser(grammar).supertree
    search, values = bound._revolute_search, bound._owned_values
    inside, counts, late = [], [], []

    def counted_search(*args, **kwargs):
        inside.append(1)
        counts.append(0)
        try:
            return search(*args, **kwargs)
        finally:
            inside.pop()

    def counted_values(*args, **kwargs):
        if inside:
            counts[-1] += 1
            late.append(True)  # the clock reads past the deadline from the first one on
        return values(*args, **kwargs)

    monkeypatch.setattr(bound, "_revolute_search", counted_search)
    monkeypatch.setattr(bound, "_owned_values", counted_values)
    bound.set_bounds(grammar, st, candidate_poses(grammar, st, scene))
    assert counts and max(counts) > bound.REVOLUTE_GRID  # unbounded: whole grids
    counts.clear()
    late.clear()
    monkeypatch.setattr(time, "perf_counter", lambda: 1e9 if late else 0.0)
    bound.set_bounds(grammar, st, candidate_poses(grammar, st, scene), deadline=1.0)
    assert counts and max(counts) <= 3  # the pose it starts from, one grid point's two


# -- wall-clock checks (pytest -m timing; run them on a quiet machine) ------------------------


def _within(parser: Parser, scene: Scene, limit: float) -> tuple[float, float, str]:
    wall, cpu = time.perf_counter(), time.process_time()
    result = parser.parse(scene, time_limit=limit)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return wall, cpu, f"{result.status}/{result.phase}/{result.timed_out_in}"


def _assert_limits(runs: list[tuple[float, float, str]], limit: float) -> None:
    late = [r for r in runs if r[0] > 1.1 * limit]
    print(f"{len(runs)} parses, wall max {max(r[0] for r in runs):.3f} s", file=sys.stderr)
    assert not late, late


@pytest.mark.timing
@pytest.mark.parametrize("method", ["ip", "micp"])
def test_latent_grammars_stop_in_time(method):
    """Random latent grammars (tests/latent_grammars.py), five sampled scenes each, at 0.5 s."""
    runs = []
    for seed in range(60):
        grammar = compile_text(random_grammar(seed))
        parser = Parser(grammar, method=method)
        trees, _ = sample_trees(grammar, 5, seed)
        for i in range(5):
            scene = scene_from_tree(grammar, trees.tree(i), f"s{i}")
            if 0 < len(scene) <= 8:
                runs.append(_within(parser, scene, 0.5))
    _assert_limits(runs, 0.5)


@pytest.mark.timing
def test_sink_detailed_real_scenes_stop_in_time():
    grammar = load_grammar(ROOT / "grammars" / "sink_detailed.yaml")
    parser = Parser(grammar)
    scenes = load_scenes(ROOT / "ssgc" / "data" / "sink" / "saved_scenes.yaml", grammar)
    _assert_limits([_within(parser, s, 0.5) for s in scenes], 0.5)
