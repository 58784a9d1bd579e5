"""`--top N`: distinct trees, and an honest word when fewer than N were found.

Found by a hunt of top-N parsing: two planks crossed at one place (yaw +30° and −30°) were one
tree to `tree_signature`, which keyed rotations on |q| per component; and a search that ran out
of solves on copies of one tree returned fewer trees than asked with no message.
"""

from __future__ import annotations

import numpy as np
import pytest
from bruteforce import enumerate_parses

from ssgc.compile import compile_text
from ssgc.io.scene import Scene
from ssgc.parse.parser import Parser

CROSS = """
grammar: cross
root: {type: Table}
types:
  Table:
    observed: true
    independent:
      - child: Plank
        p: 0.6
        translation: {world_normal: {mean: [0, 0, 0.1], variance: 0.05}}
        rotation: {world_bingham: {concentration: 5, mode: {rpy_deg: [0, 0, 20]}}}
      - child: Plank
        p: 0.5
        translation: {world_normal: {mean: [0, 0, 0.1], variance: 0.05}}
        rotation: {world_bingham: {concentration: 5, mode: {rpy_deg: [0, 0, -20]}}}
  Plank: {observed: true}
"""

CHAIN = """
grammar: chain
root: {type: Table}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0, 0.5, 0.5]}
      rule: {child: Slot, translation: {world_normal: {mean: [0, 0, 1], variance: 0.1}}}
  Slot:
    or:
      - {child: Cup, p: 0.5, translation: same}
      - child: Ghost
        p: 0.5
        translation: {world_normal_offset: {mean: [0, 0, 0.2], variance: 0.02}}
  Cup: {observed: true}
  Ghost:
    repeat:
      count: {probs: [0.5, 0.5]}
      rule: {child: Marker, translation: {world_normal_offset: {mean: [0, 0, 0.1], variance: 0.01}}}
  Marker: {}
"""


def _scene(grammar, objects) -> Scene:  # type: ignore[no-untyped-def]
    types = np.array([grammar.type_ids[t] for t, _, _ in objects])
    xyz = np.array([p for _, p, _ in objects], float)
    quat = np.array([q for *_, q in objects], float)
    return Scene("s", types, xyz, quat)


@pytest.mark.parametrize("method", ["ip", "micp"])
def test_two_objects_at_one_place_turned_apart_are_two_trees(method: str) -> None:
    grammar = compile_text(CROSS)
    half = np.radians(30) / 2
    turned = [[np.cos(half), 0, 0, s * np.sin(half)] for s in (1, -1)]
    scene = _scene(
        grammar,
        [("Table", [0, 0, 0], [1, 0, 0, 0])] + [("Plank", [0, 0, 0.1], q) for q in turned],
    )
    truth = [score for score, _ in enumerate_parses(grammar, scene)]
    assert len(truth) == 2 and truth[0] - truth[1] > 1.0  # 3.1293 and 1.4192
    result = Parser(grammar, method=method).parse(scene, top=5)
    assert [p.score for p in result.parses] == pytest.approx(truth, abs=1e-6)
    assert result.message == "only 2 distinct tree(s) exist"


def test_fewer_trees_than_asked_are_said_to_be_fewer() -> None:
    grammar = compile_text(CHAIN)
    cup = [0.14073440928249964, -0.07244124844067044, 0.7272472945865112]
    scene = _scene(grammar, [("Table", [0, 0, 0], [1, 0, 0, 0]), ("Cup", cup, [1, 0, 0, 0])])
    result = Parser(grammar).parse(scene, top=3)
    assert result.parses[0].status == "optimal"
    if len(result.parses) < 3:
        assert "distinct tree(s)" in result.message and "found" in result.message
    scores = [p.score for p in result.parses]
    assert scores == sorted(scores, reverse=True)


def test_unseen_nodes_at_other_poses_are_not_new_trees() -> None:
    """A slot that holds a marker or a ghost is unseen: its pose is integrated out, so the
    same tree has it at any candidate, and each solve found one more copy (2 of 3 trees in
    60 solves, 48 s).  The three best trees of a one-cup scene, by hand: the cup alone (S),
    and a second slot holding a marker (S + log 0.3) or an empty ghost (S + log 0.1)."""
    from test_unseen_nodes import MIXOR

    grammar = compile_text(MIXOR)
    cup = [0.14073440928249964, -0.07244124844067044, 0.7272472945865112]
    scene = _scene(grammar, [("Table", [0, 0, 0], [1, 0, 0, 0]), ("Cup", cup, [1, 0, 0, 0])])
    result = Parser(grammar).parse(scene, top=3)
    best = result.parses[0].score
    expected = [best, best + np.log(0.3), best + np.log(0.2 * 0.5)]
    assert [p.score for p in result.parses] == pytest.approx(expected, abs=1e-6)
    assert result.parses[0].status == "optimal"
