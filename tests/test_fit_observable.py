"""What the data cannot inform keeps its value (docs/fitting.md 4.1, issue: session-33 fit
report, finding 1): a rule whose child subtree can never hold an observed node says nothing
about its subtree's pose laws, nor about its own firing probability under an `independent` or
its count law under a `repeat`.  The parser puts such latent nodes at their modes, and fitting
to those poses collapsed their laws to the variance floor and the concentration cap."""

from __future__ import annotations

import numpy as np
import pytest
from test_fit import run_fit, scenes_of

from ssgc.compile import compile_text
from ssgc.fit.mstep import FitSettings, m_step
from ssgc.fit.observable import observable_rules, pose_observable_rules
from ssgc.sample.forward import sample_trees

# Repro A of the report: a Marker nobody observes, nothing below it.
MARKER = """\
grammar: marker
root: {type: Table}
types:
  Table:
    observed: true
    independent:
      - child: Cup
        p: 0.5
        translation: {world_normal: {mean: [0, 0, 0], variance: 0.1}}
      - child: Marker           # latent, nothing observed below it
        p: 0.5
        translation: {world_normal: {mean: [1, 0, 0], variance: 0.1}}
        rotation: {world_bingham: {concentration: 10}}
  Cup: {observed: true}
  Marker: {}
"""

MARKER_LINES = (
    "      - child: Marker           # latent, nothing observed below it\n"
    "        p: 0.5\n"
    "        translation: {world_normal: {mean: [1, 0, 0], variance: 0.1}}\n"
    "        rotation: {world_bingham: {concentration: 10}}\n"
)


def rule_named(grammar, name):
    return next(r.id for r in grammar.rules if grammar.rule_name(r.id) == name)


def test_a_latent_child_with_nothing_observed_below_keeps_its_laws(tmp_path):
    """Repro A: the Marker's p, variance and concentration went to 0.9999, 1e-6 and 10000;
    they are kept as written, while the Cup's are fitted."""
    _, scenes = scenes_of(MARKER, 40, seed=1)
    result = run_fit(tmp_path, MARKER, scenes, iterations=2, top=2, tol=0.0)
    assert MARKER_LINES in result.text
    cup = result.text.split("- child: Cup")[1].split("- child: Marker")[0]
    assert "p: 0.5\n" not in cup and "variance: 0.1}" not in cup  # fitted


def test_an_unobserved_subtree_leaves_the_log_evidence_as_it_is(tmp_path):
    """The Marker integrates to 1, so the grammar with it and the grammar without it have the
    same evidence for scenes of tables and cups.  The parser places it at its mode and counted
    its density there: +30.52 with it against -39.09 without (40 scenes, 1.74 nats each)."""
    without = MARKER.replace(MARKER_LINES, "")
    _, scenes = scenes_of(without, 40, seed=1)
    evidence = []
    for k, text in enumerate((MARKER, without)):
        (tmp_path / str(k)).mkdir()
        result = run_fit(tmp_path / str(k), text, scenes, iterations=1, top=4, tol=0.0)
        evidence.append(result.iterations[0]["log_evidence"])
    assert evidence[0] == pytest.approx(evidence[1], abs=1e-9)


def test_the_static_analysis_of_the_marker_grammar():
    g = compile_text(MARKER)
    assert observable_rules(g).tolist() == [True, False]


def test_m_step_on_complete_trees_keeps_what_no_observation_reaches():
    """The rule is kept however its latent nodes are placed: the check is static."""
    g = compile_text(MARKER)
    trees, _ = sample_trees(g, 200, 4)
    paths = {u.path for u in m_step(g, trees, np.ones(200), FitSettings())}
    marker = g.rules[rule_named(g, "Table[1]->Marker")]
    cup = g.rules[rule_named(g, "Table[0]->Cup")]
    assert marker.path not in paths and marker.translation.path not in paths
    assert marker.rotation.path not in paths
    assert cup.path in paths and cup.translation.path in paths


NESTED = """\
grammar: nested
root: {type: Root}
types:
  Root:
    observed: true
    and:
      - child: Box
        translation: {world_normal: {mean: [0, 0, 0], variance: 1.0}}
  Box:
    max_nesting: 1
    or:
      - child: Shelf            # a Box under the Shelf is blocked: the Shelf holds nothing
        p: 0.5
        translation: {world_normal_offset: {mean: [0, 0, 1], variance: 0.1}}
      - child: Cup
        p: 0.5
        translation: {world_normal_offset: {mean: [0, 0, 0], variance: 0.1}}
  Shelf:
    and:
      - child: Box
        translation: {world_normal_offset: {mean: [0, 0, 0], variance: 0.1}}
  Cup: {observed: true}
"""


def test_max_nesting_is_minded():
    """Box -> Shelf -> Box is blocked by max_nesting, so the Shelf never holds a Cup, though
    the type graph has a path from it to one."""
    g = compile_text(NESTED)
    seen = dict(zip([g.rule_name(r.id) for r in g.rules], observable_rules(g), strict=True))
    assert seen == {
        "Root[0]->Box": True,
        "Box[0]->Shelf": False,
        "Box[1]->Cup": True,
        "Shelf[0]->Box": False,
    }


def test_max_nesting_two_reaches_the_cup():
    g = compile_text(NESTED.replace("max_nesting: 1", "max_nesting: 2"))
    assert observable_rules(g).all()


def test_the_synthetic_types_of_an_observation_model():
    """Noise on the observed root moves its rules to a latent `~node:Table`, and clutter adds a
    new root and a set: the Marker's rule is still the one that reaches nothing observed."""
    text = MARKER + (
        "observation:\n"
        "  noise: {Table: {position: 0.01}}\n"
        "  clutter: {region: {min: [-1, -1, -1], max: [1, 1, 1]}, rates: {Sponge: 0.1}}\n"
    )
    g = compile_text(text)
    seen = observable_rules(g)
    assert not seen[rule_named(g, "~node:Table[1]->Marker")]
    assert np.sum(~seen) == 1


REPEAT = """\
grammar: repeat_of_latent
root: {type: Table}
types:
  Table:
    observed: true
    and:
      - child: Cups
      - child: Markers
  Cups:
    repeat:
      count: {probs: [0.5, 0.5]}
      rule:
        child: Cup
        translation: {world_normal: {mean: [0, 0, 0], variance: 0.1}}
  Markers:
    repeat:
      count: {probs: [0.25, 0.25, 0.5]}
      rule:
        child: Marker
        translation: {world_normal: {mean: [1, 0, 0], variance: 0.1}}
  Cup: {observed: true}
  Marker: {}
"""


def test_the_count_law_of_a_repeat_of_an_unobservable_rule_is_kept(tmp_path):
    _, scenes = scenes_of(REPEAT, 30, seed=2)
    result = run_fit(tmp_path, REPEAT, scenes, iterations=1, top=3)
    assert "count: {probs: [0.25, 0.25, 0.5]}" in result.text
    assert "translation: {world_normal: {mean: [1, 0, 0], variance: 0.1}}" in result.text
    assert "count: {probs: [0.5, 0.5]}" not in result.text  # the Cups' count is fitted


CHOICE = """\
grammar: choice
root: {type: Table}
types:
  Table:
    observed: true
    and:
      - child: Thing
  Thing:
    or:
      - {child: Cup, p: 0.5}
      - {child: MarkerA, p: 0.1}
      - {child: MarkerB, p: 0.4}
  Cup: {observed: true}
  MarkerA: {}
  MarkerB: {}
"""


def test_or_weights_keep_the_split_among_unobservable_options():
    """A scene without the Cup is evidence for the Markers together, so the `or` is fitted;
    which Marker it was, no scene says: they share their fitted mass as 0.1 : 0.4."""
    g = compile_text(CHOICE)
    trees, _ = sample_trees(g, 400, 7)
    fitted = {u.path: u.values["p"] for u in m_step(g, trees, np.ones(400), FitSettings())}
    p = [fitted[g.rules[r].path] for r in g.types[g.type_ids["Thing"]].rules]
    assert abs(p[0] - 0.5) < 0.1 and p[0] != 0.5
    assert p[2] / p[1] == pytest.approx(4.0, rel=1e-12)
    assert sum(p) == pytest.approx(1.0, rel=1e-12)


# The fit hunt of session 36: a latent Group whose Cup is placed in world coordinates.
GROUP = """\
grammar: latpin
root: Table
types:
  Table:
    observed: true
    and:
      - child: Group
        translation: {world_normal_offset: {mean: [0.3, 0, 0], variance: 0.05, pin: [z]}}
        rotation: {world_bingham: {concentration: 10}}
  Group:
    and:
      - child: Cup
        translation: {world_normal: {mean: [0.5, 0, 0], variance: 0.01}}
        rotation: ROTATION
  Cup: {observed: true}
"""
GROUP_LAWS = (
    "        translation: {world_normal_offset: {mean: [0.3, 0, 0], variance: 0.05, pin: [z]}}\n"
    "        rotation: {world_bingham: {concentration: 10}}\n"
)


def test_a_latent_pose_that_moves_nothing_observed_keeps_its_laws(tmp_path):
    """The Cup's position is in world coordinates and its rotation too, so where the Group is
    and how it is turned change nothing observed.  With its z pinned (no Laplace spread), its
    variance went from 0.05 to 1e-6 in two iterations, and its concentration to the cap."""
    text = GROUP.replace("ROTATION", "{world_bingham: {concentration: 50}}")
    _, scenes = scenes_of(text, 50, seed=1)
    result = run_fit(tmp_path, text, scenes, iterations=2, top=1, tol=0.0)
    assert GROUP_LAWS in result.text
    assert "variance: 0.01}" not in result.text and "concentration: 50}" not in result.text


def test_which_poses_move_an_observed_pose():
    """A parent-frame rotation of the Cup reads the Group's rotation, not its position; a
    rotation in world coordinates reads neither."""
    g = compile_text(GROUP.replace("ROTATION", "{parent_bingham: {concentration: 50}}"))
    position, rotation = pose_observable_rules(g)
    assert position.tolist() == [False, True] and rotation.tolist() == [True, True]
    g = compile_text(GROUP.replace("ROTATION", "{world_bingham: {concentration: 50}}"))
    position, rotation = pose_observable_rules(g)
    assert position.tolist() == [False, True] and rotation.tolist() == [False, True]
