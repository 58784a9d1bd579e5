"""Unseen nodes: latent nodes with nothing observed at or below them (`ssgc.score`).

Their poses are integrated out of a tree's score, exactly (every pose law is normalised), so
a parse never gains by adding an empty latent node at the mode of a tight law.  Under Eq. 2.1
as written it did: with nothing but the table observed, `mixor` below was parsed as two slots
with a marker each (score 9.88: each marker's density at its mode is e^5.8), though one slot
with one marker is 3.3 times as probable as two (0.15 against 0.045).
"""

from __future__ import annotations

import numpy as np
import pytest

import ssgc
from ssgc.compile import compile_text
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees, seen_nodes, unseen_edges

MIXOR = """\
grammar: mixor
root: {type: Table}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0, 0.5, 0.5]}
      rule:
        child: Slot
        translation: {world_normal: {mean: [0, 0, 1], variance: 0.1}}
  Slot:
    or:
      - {child: Cup, p: 0.5, translation: same}
      - child: Marker
        p: 0.3
        translation: {world_normal_offset: {mean: [0, 0, 0.1], variance: 0.01}}
        rotation: {world_bingham: {concentration: 10}}
      - child: Ghost
        p: 0.2
        translation: {world_normal_offset: {mean: [0, 0, 0.2], variance: 0.02}}
  Cup: {observed: true}
  Marker: {}
  Ghost:
    repeat:
      count: {probs: [0.5, 0.5]}
      rule:
        child: Marker
        translation: {world_normal_offset: {mean: [0, 0, 0.1], variance: 0.01}}
"""


@pytest.fixture(scope="module")
def mixor(tmp_path_factory: pytest.TempPathFactory) -> ssgc.Grammar:
    path = tmp_path_factory.mktemp("unseen") / "mixor.yaml"
    path.write_text(MIXOR)
    return ssgc.load_grammar(path)


def test_unseen_poses_are_integrated_out_of_the_score(mixor: ssgc.Grammar) -> None:
    g = mixor.ir
    trees, logp = sample_trees(g, 400, 7)
    np.testing.assert_allclose(score_trees(g, trees), logp, rtol=0, atol=1e-9)
    joint = score_trees(g, trees, marginal=False)
    np.testing.assert_allclose(joint - unseen_edges(g, trees), logp, rtol=0, atol=1e-9)
    marker = g.type_id("Marker")
    assert np.any(trees.type == marker) and not np.any(seen_nodes(g, trees)[trees.type == marker])
    moved = trees.select(np.ones(trees.n_scenes, bool))
    moved.xyz[trees.type == marker] += [0.3, -0.2, 0.5]  # anywhere: nothing shows it
    np.testing.assert_allclose(score_trees(g, moved), logp, rtol=0, atol=1e-9)
    assert np.any(score_trees(g, moved, marginal=False) != joint)


def _map_score(scene: ssgc.Scene) -> float:
    """The MAP tree's score by hand: a slot per cup at the cup (its world Normal's density
    there), each other slot unseen at its likeliest choice, a Marker (0.3 against a Ghost's
    0.2); two slots at most."""
    cups = scene.xyz[np.array(scene.types) == "Cup"].reshape(-1, 3)
    k = len(cups)
    d2 = np.sum((cups - [0.0, 0.0, 1.0]) ** 2, axis=1)
    per_cup = np.log(0.5) - 1.5 * np.log(2 * np.pi * 0.1) - d2 / (2 * 0.1)
    return max(np.log(0.5) + per_cup.sum() + (c - k) * np.log(0.3) for c in (1, 2) if c >= k)


@pytest.mark.parametrize("method", ["auto", "ip", "micp"])
def test_the_parse_adds_no_empty_slot(mixor: ssgc.Grammar, method: str) -> None:
    scenes = mixor.sample(12, seed=5)
    cups = {s.types.count("Cup") for s in scenes}
    assert cups == {0, 1, 2}  # every kind of scene is checked
    for scene in scenes:
        result = ssgc.parse(mixor, scene, method=method)
        best = result.parses[0]
        assert best.score == pytest.approx(_map_score(scene), abs=1e-6), scene.name
        assert best.score >= scene.log_prob - 1e-9
        slots = sum(t == "Slot" for t in best.tree.types)
        assert slots == max(1, scene.types.count("Cup"))
        assert result.status == "optimal"


def test_the_score_of_a_tree_with_nothing_latent_is_unchanged() -> None:
    g = compile_text(MIXOR.replace("p: 0.3", "p: 0").replace("p: 0.2", "p: 0"))
    trees, logp = sample_trees(g, 50, 1)
    assert seen_nodes(g, trees)[trees.type != g.type_id("Table")].all()
    np.testing.assert_allclose(score_trees(g, trees, marginal=False), logp, rtol=0, atol=1e-9)


NEST_UNSEEN = """
grammar: nest_unseen
root: R
types:
  R:
    and:
      - {child: A, translation: same, rotation: same}
  A:
    observed: true
    max_nesting: 1
    and:
      - child: L
        translation: {world_normal: {mean: [0, 0, 0], variance: 0.01}}
  L:
    and:
      - {child: A, translation: same, rotation: same}
"""


def test_a_node_emptied_by_max_nesting_is_unseen_when_sampled() -> None:
    """L's one rule, to A, is blocked by A's `max_nesting` below the first A: that L holds
    nothing, and its pose is integrated out.  The sampler's shortcut (`score._maybe_unseen`)
    ignored nesting bounds, took L as always holding an A, and the scenes' `log_prob` kept
    L's density (3.93 here) while every tree of this grammar has probability 1 (session-35
    parse hunt)."""
    g = compile_text(NEST_UNSEEN)
    trees, logp = sample_trees(g, 20, 0)
    assert (~seen_nodes(g, trees)).sum() == 20  # one empty L per tree
    np.testing.assert_allclose(logp, 0.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(score_trees(g, trees), logp, rtol=0, atol=1e-12)
