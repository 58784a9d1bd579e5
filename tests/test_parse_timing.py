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
from ssgc.io.journal import journal_path
from ssgc.io.scene import Scene, load_scenes, scene_from_tree
from ssgc.laws.base import POS_TOL
from ssgc.parse.parser import STEPS, Parser
from ssgc.parse.proposals import Candidates, _near_earlier
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
        i, j = _near_earlier(xyz, n_old)
    small = _near_earlier(xyz, n_old)  # every pair compared (the inputs are small)
    assert set(zip(*small, strict=True)) == set(zip(i.tolist(), j.tolist(), strict=True))
    assert set(zip(i.tolist(), j.tolist(), strict=True)) == _brute_near(xyz, n_old)


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
    scene = write_scene(tmp_path / "wide.json", grammar, wide_scene(grammar, 300))
    out = tmp_path / "out.json"
    result = run("parse", scene, "-g", grammar_path, "--time-limit", 0.02, "-q", "-o", out)
    assert result.exit_code == 4, result.output
    row = json.loads(out.read_text())["scenes"][0]
    assert (row["status"], row["phase"]) == ("no_parse", "time")
    assert row["timed_out_in"] in STEPS
    assert not journal_path(out).exists()


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
