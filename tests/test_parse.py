"""MAP parsing: the MILP against brute-force enumeration, top-N, real and sampled scenes."""

from __future__ import annotations

import json
import os
from dataclasses import replace

import numpy as np
import pytest
from bruteforce import enumerate_parses
from conftest import GRAMMARS, SINK_DATA
from test_bruteforce import REPEAT, ROUTES, SINGLES_PAIRS, trays

from ssgc.compile import compile_text, load_grammar
from ssgc.io.scene import Scene, read_sink_yaml, scene_from_tree
from ssgc.parse.highs import HighsSession
from ssgc.parse.ip import reduce_scene, set_model_size
from ssgc.parse.parser import Parser, tree_signature
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees

TINY = {"repeat": REPEAT, "routes": ROUTES, "singles_pairs": SINGLES_PAIRS}


def sampled_scenes(grammar, n, seed, max_objects):
    trees, logp = sample_trees(grammar, n, seed)
    out = []
    for i in range(n):
        scene = scene_from_tree(grammar, trees.tree(i), f"s{i}", float(logp[i]))
        if len(scene) <= max_objects:
            out.append(scene)
    return out


def tiny_grammars():
    yield from ((name, compile_text(text)) for name, text in TINY.items())
    yield "trays", trays(3)


@pytest.mark.parametrize(("name", "grammar"), list(tiny_grammars()))
def test_top_n_equals_brute_force_enumeration(name, grammar):
    parser = Parser(grammar)
    checked = 0
    for scene in sampled_scenes(grammar, 40, seed=3, max_objects=5):
        truth = enumerate_parses(grammar, scene)
        result = parser.parse(scene, top=len(truth) + 2)
        got = [p.score for p in result.parses]
        want = [s for s, _ in truth]
        assert len(got) == len(want), (name, scene.name)
        np.testing.assert_allclose(got, want, atol=1e-7)
        assert result.status == "optimal"
        checked += 1
    assert checked >= 10


def test_set_formulation_agrees_with_brute_force():
    """The equivalent-set MILP (thesis 3.5) finds the same optimum as enumeration."""
    grammar = compile_text(SINGLES_PAIRS)
    parser = Parser(grammar)
    for scene in sampled_scenes(grammar, 30, seed=5, max_objects=5):
        best = enumerate_parses(grammar, scene)[0][0]
        problem = reduce_scene(grammar, parser.supertree, scene)
        solution = HighsSession(problem.milp).solve()
        assert solution.status == "optimal"
        tree = problem.invert(solution.x)
        assert score_trees(grammar, tree)[0] == pytest.approx(solution.objective, abs=1e-7)
        assert solution.objective == pytest.approx(best, abs=1e-7)


def test_top_n_trees_are_distinct_and_ranked():
    grammar = load_grammar(GRAMMARS / "sink.yaml")
    parser = Parser(grammar)
    scene = max(read_sink_yaml(SINK_DATA, grammar)[:10], key=len)
    result = parser.parse(scene, top=10)
    assert len(result.parses) == 10
    keys = set()
    for p in result.parses:
        assert score_trees(grammar, p.tree)[0] == pytest.approx(p.score, abs=1e-9)
        assert sum(p.rule_log_probs) == pytest.approx(p.score, abs=1e-9)
        keys.add(tuple(map(tuple, np.round(np.c_[p.tree.type, p.tree.parent, p.tree.xyz], 9))))
    assert len(keys) == 10
    scores = [p.score for p in result.parses]
    assert scores == sorted(scores, reverse=True)


def test_every_real_sink_scene_parses_optimally():
    grammar = load_grammar(GRAMMARS / "sink.yaml")
    parser = Parser(grammar)
    scenes = read_sink_yaml(SINK_DATA, grammar)
    results = [parser.parse(s) for s in scenes]
    assert len(results) == 80
    assert all(r.status == "optimal" and r.parses[0].gap <= 1e-9 for r in results)
    assert max(len(s) for s in scenes) == 11  # the 10-object scenes (plus the bin) included


@pytest.mark.parametrize("grammar_file", ["singles_pairs_dependency.yaml", "sink.yaml"])
def test_sampled_scenes_match_or_beat_ground_truth(grammar_file):
    grammar = load_grammar(GRAMMARS / grammar_file)
    parser = Parser(grammar)
    scenes = sampled_scenes(grammar, 100, seed=11, max_objects=1000)
    for scene in scenes:
        best = parser.parse(scene).parses[0].score
        assert best >= scene.log_prob - 1e-6, scene.name


def test_scene_the_grammar_cannot_produce_names_the_objects():
    grammar = load_grammar(GRAMMARS / "sink.yaml")
    bowl = grammar.type_id("BowlBradshaw7Qt")
    scene = Scene(
        "odd",
        np.array([grammar.root, bowl, bowl]),
        np.array([[0.5, 0, 0], [0.5, 0, 0.1], [0.5, 0, 0.1]]),
        np.tile([1.0, 0, 0, 0], (3, 1)),
    )
    parser = Parser(grammar)
    assert parser.parse(scene).status == "optimal"  # a bowl in a bowl is fine
    gmm = load_grammar(GRAMMARS / "gmm.yaml")
    point = gmm.type_id("Point")
    two_points = Scene(
        "two", np.array([point, point]), np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1))
    )
    result = Parser(gmm).parse(two_points)
    assert result.status == "infeasible" and not result.parses
    assert "scene 'two' has more objects than any tree of the grammar can hold" in result.message
    assert "2 Point (at most 1)" in result.message
    cup = grammar.type_id("MugColeHardwareClassicBlue")
    no_bin = Scene(
        "floating",
        np.array([grammar.root, cup]),
        np.array([[0.5, 0, 0], [9, 9, 9]]),
        np.tile([1.0, 0, 0, 0], (2, 1)),
    )
    result = parser.parse(no_bin)
    assert result.status == "optimal"  # far away is unlikely, not impossible
    root_elsewhere = Scene(
        "moved", np.array([grammar.root]), np.array([[0.0, 0, 0]]), np.tile([1.0, 0, 0, 0], (1, 1))
    )
    result = parser.parse(root_elsewhere)
    assert result.status == "infeasible"
    assert "objects the grammar cannot place: 0 (DishBin)" in result.message


CHAIN = """
grammar: chain
root: {type: Table, pose: {xyz: [0, 0, 0.4], rpy_deg: [0, 0, 30]}}
types:
  Table:
    observed: true
    and:
      - child: Edge
        translation: {offset: [0.5, 0.0, 0.3]}
        rotation: {offset: {rpy_deg: [0, 0, 90]}}
  Edge:
    and:
      - child: Seat
        translation: {offset: [0.2, 0.1, 0.0]}
        rotation: {offset: {rpy_deg: [0, 0, 180]}}
  Seat:
    repeat:
      count: {probs: [0.2, 0.5, 0.3]}
      rule:
        child: Cup
        translation: {parent_normal_offset: {mean: [0.1, 0.0, 0.0], variance: 0.01, pin: [z]}}
        rotation: {revolute: {axis: [0, 0, 1], min: -1.0, max: 1.0}}
  Cup: {observed: true}
"""


def test_chained_fixed_offsets_match_brute_force():
    """Poses through two fixed, rotated offsets (the dimsum place settings' shape)."""
    grammar = compile_text(CHAIN)
    parser = Parser(grammar)
    scenes = sampled_scenes(grammar, 30, seed=2, max_objects=10)
    for scene in scenes:
        truth = [s for s, _ in enumerate_parses(grammar, scene)]
        got = [p.score for p in parser.parse(scene, top=5).parses]
        np.testing.assert_allclose(got, truth[:5], atol=1e-7)
        assert got[0] >= scene.log_prob - 1e-6


def test_dimsum_sampled_scenes_match_or_beat_ground_truth():
    grammar = load_grammar(GRAMMARS / "dimsum_table.yaml")
    parser = Parser(grammar)
    for scene in sampled_scenes(grammar, 60, seed=4, max_objects=12):
        result = parser.parse(scene)
        assert result.status == "optimal", (scene.name, result.message)
        assert result.parses[0].score >= scene.log_prob - 1e-6, scene.name


def test_scene_with_more_objects_than_any_tree_is_refused_before_modelling():
    grammar = load_grammar(GRAMMARS / "sink.yaml")
    parser = Parser(grammar)
    trees, _ = sample_trees(grammar, 2000, 8)
    scenes = [scene_from_tree(grammar, trees.tree(i), f"s{i}", 0.0) for i in range(2000)]
    counts = np.stack([np.bincount(s.types, minlength=len(grammar.types)) for s in scenes])
    assert np.all(counts <= parser.capacity[:-1])  # sampled trees never exceed it
    assert max(len(s) for s in scenes) <= parser.capacity[-1]
    pile = [o for s in scenes for o in range(1, len(s))]  # every non-bin object, many scenes
    big = Scene(
        "pile",
        np.r_[grammar.root, np.concatenate([s.types[1:] for s in scenes])],
        np.vstack([[0.5, 0, 0], *[s.xyz[1:] for s in scenes]]),
        np.vstack([[1.0, 0, 0, 0], *[s.quat[1:] for s in scenes]]),
    )
    assert len(big) == len(pile) + 1 > parser.capacity[-1]
    result = parser.parse(big)
    assert result.status == "infeasible" and result.model["variables"] == 0
    assert "more objects than any tree of the grammar can hold" in result.message
    assert f"{len(big)} objects in all (at most {parser.capacity[-1]})" in result.message


def test_set_model_size_estimate_counts_its_edge_variables():
    grammar = load_grammar(GRAMMARS / "sink.yaml")
    parser = Parser(grammar)
    for scene in sorted(read_sink_yaml(SINK_DATA, grammar), key=len)[-3:]:
        cand, _ = parser.candidates(scene)
        milp = reduce_scene(grammar, parser.supertree, scene).milp
        assert set_model_size(parser.supertree, cand) == int(np.sum(~milp.integer))


def test_a_tree_thousands_of_levels_deep_gets_a_flat_signature():
    """Found by fuzzing `ssg fit`: top-N parsing keyed trees by nested tuples, and hashing
    one 2,800 levels deep exhausted Python's recursion limit."""
    n = 200
    lines = ["grammar: deep", "root: T0", "types:"]
    for i in range(n):
        bound = "max_nesting: 14, " if i == 43 else ""
        child = f"T{i + 1}" if i + 1 < n else "T1"
        lines.append(f"  T{i}: {{{bound}observed: true, and: [{{child: {child}}}]}}")
    grammar = compile_text("\n".join(lines) + "\n")
    trees, _ = sample_trees(grammar, 1, 0)
    assert len(trees) > 2500
    key = tree_signature(grammar, trees)
    assert key in {key} and key == tree_signature(grammar, trees.tree(0))
    moved = replace(trees, xyz=trees.xyz + np.eye(3)[0] * (np.arange(len(trees)) == 700)[:, None])
    assert tree_signature(grammar, moved) != key  # an observed node's pose is part of it


def test_a_grammar_without_rules_parses_its_empty_scenes():
    """Found by fuzzing `ssg fit`: a grammar of one latent terminal root has no rule tables,
    and scoring its one-node tree indexed into them (an internal error in parse and fit)."""
    grammar = compile_text("grammar: g\nroot: R\ntypes: {R: {}}\n")
    scene = sampled_scenes(grammar, 1, seed=0, max_objects=10)[0]
    assert len(scene) == 0
    result = Parser(grammar).parse(scene, top=2)
    assert result.status == "optimal" and [p.score for p in result.parses] == [0.0]
    assert len(result.parses[0].tree) == 1  # the root, always in the tree


def test_the_highs_banner_never_reaches_standard_output(
    monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """highspy 1.16 prints "Running HiGHS ..." to the C standard output while `Highs()` is
    built, before its log can be turned off, and `ssg parse` writes its JSON there (a fresh
    `pip install .` got 1.16 and printed invalid JSON).  A Highs that writes its banner both
    straight to the file descriptor and through C's buffered stdio stands in for it here."""
    import ctypes

    import ssgc
    from ssgc.parse import highs

    libc = ctypes.CDLL(None)

    class Loud(highs.highspy.Highs):  # type: ignore[misc, name-defined]
        def __init__(self) -> None:
            os.write(1, b"Running HiGHS (unbuffered)\n")
            libc.printf(b"Running HiGHS (buffered)\n")
            super().__init__()

    monkeypatch.setattr(highs.highspy, "Highs", Loud)
    g = ssgc.load_grammar(GRAMMARS / "gmm.yaml")
    scene = g.sample(1, seed=0)[0]
    print("before", flush=True)
    assert highs.quiet_highs().getOptionValue("output_flag")[1] is False
    result = ssgc.parse(g, scene)
    libc.fflush(None)
    print("after", flush=True)
    assert result.best is not None
    assert capfd.readouterr().out == "before\nafter\n"


def test_objects_at_one_pose_are_parsed_as_two():
    """Two mugs (or discs) at exactly one pose were one candidate: the scene was proven
    infeasible, and with a bowl beside them a worse tree was certified optimal."""
    from ssgc.compile import load_grammar
    from ssgc.io.scene import parse_scene_text
    from ssgc.parse.parser import Parser

    g = load_grammar(GRAMMARS / "sink.yaml")
    mug = "MugColeHardwareClassicBlue"
    bowl = next(t.name for t in g.types if t.observed and "Bowl" in t.name)

    def scene(mugs, with_bowl):
        objects = [{"type": "DishBin", "pose": {"xyz": [0.5, 0, 0]}}]
        objects += [{"type": mug, "pose": {"xyz": [0.5, 0, z]}} for z in mugs]
        if with_bowl:
            objects.append({"type": bowl, "pose": {"xyz": [0.5, 0.2, 0.1]}})
        return parse_scene_text(json.dumps({"objects": objects}), "s.json", g)

    for method in ("ip", "micp"):
        parser = Parser(g, method=method)
        for with_bowl in (False, True):
            same = parser.parse(scene([0.1, 0.1], with_bowl))
            near = parser.parse(scene([0.1, 0.1 + 2e-6], with_bowl))
            assert same.status == near.status == "optimal", (method, with_bowl, same.status)
            assert same.parses[0].score == pytest.approx(near.parses[0].score, abs=1e-4)
