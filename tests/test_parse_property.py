"""The parser never says anything false about a scene sampled from a grammar (issue 11).

Over small random grammars of the whole language (tests/grammar_gen.py: every kind, every
translation and rotation law), each sampled scene is parsed with `ip` and `micp`, and
(tests/parse_profile.py `check_scene`):

- it is never `infeasible` (the tree it was sampled from explains it);
- it is never `optimal` with a score below the sampled tree's (a false certificate);
- where brute force can enumerate the grammar's trees, no parse scores above the MAP, and an
  `optimal` parse scores the MAP.

The parser may fail to *certify* (status `feasible`, or `no_parse` with its phase): that is
honest, and the long profile counts it.  Default run: a bounded number of grammars.  The long
profile (`-m slow`, SSG_PROFILE_GRAMMARS grammars, default 2000) prints its counts.
"""

from __future__ import annotations

import json
import os
from collections import Counter

import numpy as np
import pytest
from grammar_gen import compile_spec, grammars, sampled_scenes, to_yaml
from hypothesis import HealthCheck, example, given, settings
from parse_profile import brute_force_map, check_scene, run_profile

from ssgc.compile import compile_text
from ssgc.io.scene import Scene
from ssgc.parse.parser import Parser
from ssgc.score import score_trees

# The issue's first grammar: a latent `and` under a latent `and`, Normal laws.
LATENT_AND_CHAIN = """
grammar: latent_and_chain
root: {type: R}
types:
  R:
    and:
      - child: L
        translation: {world_normal: {mean: [0, 0, 0], variance: 0.01}}
  L:
    and:
      - child: X
        translation: {world_normal: {mean: [0, 0, 0], variance: 0.01}}
  X: {observed: true}
"""

# The reference implementation's test grammar: A -> B and C; B -> D (0.75) or E (0.25), both
# placed by world boxes, E by a world box offset of +-1 m from B; D -> G (p 0.5); C -> a
# geometric number of F; every rotation uniform.
REFERENCE_TEST = """
grammar: reference_test
root: A
types:
  A:
    and:
      - {child: B, translation: {world_box: {min: [0, 0, 0], max: [1, 1, 1]}}, rotation: uniform}
      - {child: C, translation: {world_box: {min: [0, 0, 0], max: [1, 1, 1]}}, rotation: uniform}
  B:
    or:
      - {child: D, p: 0.75, translation: OFF, rotation: uniform}
      - {child: E, p: 0.25, translation: OFF, rotation: uniform}
  D:
    observed: true
    independent:
      - {child: G, p: 0.5, translation: OFF, rotation: uniform}
  C:
    repeat:
      count: {geometric: {p: 0.2, max: 5, start: 0}}
      rule: {child: F, translation: OFF, rotation: uniform}
  E: {observed: true}
  F: {observed: true}
  G: {observed: true}
""".replace("OFF", "{world_box_offset: {min: [-1, -1, -1], max: [1, 1, 1]}}")
METHODS = ("ip", "micp")


def assert_honest(grammar, scenes, time_limit=None) -> Counter[str]:
    """No scene gets a false status from either method; returns the statuses per method."""
    counts: Counter[str] = Counter()
    for method in METHODS:
        parser = Parser(grammar, method=method)
        for scene in scenes:
            v = check_scene(grammar, parser, scene, time_limit, brute_force_map(grammar, scene))
            assert not v.false, (method, scene.name, v)
            counts[f"{method}:{v.status}"] += 1
    return counts


def assert_honest_on_samples(spec) -> None:  # type: ignore[no-untyped-def]
    """`assert_honest` on three scenes sampled from a generated grammar, naming it on failure."""
    grammar = compile_spec(spec)
    scenes = scored_as_sampled(grammar, sampled_scenes(grammar, 3, seed=0, max_objects=4))
    try:
        assert_honest(grammar, scenes, time_limit=5.0)
    except AssertionError as exc:
        raise AssertionError(f"{exc}\ngrammar:\n{to_yaml(spec)}") from None


def scored_as_sampled(grammar, scenes: list[Scene]) -> list[Scene]:  # type: ignore[no-untyped-def]
    """The scenes, after checking that the scorer scores each tree as the sampler drew it.  A
    parse's score is the scorer's (score_trees), so the parser's honesty rests on it.  They
    disagreed on an `or` whose unblocked rules all weigh 0 (test_parse_nesting.py)."""
    for scene in scenes:
        scored = float(score_trees(grammar, scene.tree)[0])
        assert np.isclose(scored, scene.log_prob, rtol=1e-9, atol=1e-9), (scored, scene.log_prob)
    return scenes


# A `repeat` blocked by `max_nesting` (the second L1's) whose count law has P(0) = 0: was
# `infeasible` with both methods (the parser charged the blocked repeat log P(0)).
BLOCKED_REPEAT = {
    "grammar": "generated",
    "root": "L0",
    "types": {
        "A": {"observed": True},
        "B": {"observed": True},
        "L0": {"and": [{"child": "L1", "translation": "same", "rotation": "same"}]},
        "L1": {
            "max_nesting": 2,
            "observed": True,
            "repeat": {
                "count": {"probs": [0, 1]},
                "rule": {"child": "L1", "translation": {"offset": [0, 0, 0.1]}, "rotation": "same"},
            },
        },
    },
}


@settings(
    max_examples=10,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(spec=grammars(rare=True))
@example(spec=BLOCKED_REPEAT)
def test_sampled_scenes_get_no_false_status(spec):
    assert_honest_on_samples(spec)


@settings(
    max_examples=8,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(spec=grammars(extras=True, rare=True))
def test_scenes_with_noise_and_clutter_get_no_false_status(spec):
    """The same over grammars with an `observation` section (noise on every observed type,
    clutter objects) and pose constraints (which parsing does not read, but the compiled
    grammar carries): the scenes sampled from the grammar of what is observed, clutter
    objects included, are parsed as honestly."""
    assert_honest_on_samples(spec)


def test_latent_and_chain_scenes_are_never_called_infeasible():
    grammar = compile_text(LATENT_AND_CHAIN)
    assert_honest(grammar, sampled_scenes(grammar, 8, seed=1))


def test_reference_test_grammar_sampled_scenes_get_no_false_status():
    grammar = compile_text(REFERENCE_TEST)
    assert_honest(grammar, sampled_scenes(grammar, 8, seed=2, max_objects=4))


def _e_scene(grammar, xyz):
    e = grammar.type_ids["E"]
    return Scene("E", np.array([e]), np.array([xyz], float), np.array([[1.0, 0, 0, 0]]))


@pytest.mark.parametrize("xyz", [[1.8, 0.2, 0.2], [1.5, 0.5, 0.5]])
@pytest.mark.parametrize("method", METHODS)
def test_reference_e_scene_is_not_called_infeasible(method, xyz):
    """B anywhere in [0.8, 1] x [0, 1] x [0, 1] explains E at (1.8, 0.2, 0.2): never
    infeasible; every tree of this scene has the same score (uniform boxes), so a parse must
    score exactly that, and `optimal` is then true.  C holds nothing observed: its pose is
    integrated out of the score (`ssgc.score`)."""
    grammar = compile_text(REFERENCE_TEST)
    p0 = 0.2 / (1 - 0.8**6)  # the geometric count law at 0, truncated at 5
    # or-rule, E's box offset, no F, and two uniform rotations (B, E)
    only = np.log(0.25) - np.log(8.0) + np.log(p0) - 2 * np.log(np.pi**2)
    result = Parser(grammar, method=method).parse(_e_scene(grammar, xyz))
    assert result.status in ("optimal", "feasible", "no_parse"), result.message
    if result.parses:
        assert result.parses[0].score == pytest.approx(only, abs=1e-9)
    else:
        assert result.phase in ("proposals", "instance_limit", "time"), result
        assert "not proven" in result.message or result.phase == "time"


@pytest.mark.slow
def test_long_profile_has_no_false_answers():
    """Thousands of random grammars (SSG_PROFILE_GRAMMARS, default 2000), ten scenes each, both
    methods: prints the counts; every answer must be true."""
    n = int(os.environ.get("SSG_PROFILE_GRAMMARS", "2000"))
    report = run_profile(n, 10, seed=int(os.environ.get("SSG_PROFILE_SEED", "0")))
    print(json.dumps({k: v for k, v in report.items() if k != "false_examples"}, indent=1))
    assert report["false_answers"] == 0, report["false_examples"]


MICP_CERTIFIED_FLOOR = 0.975  # measured 98.05% (1961 of 2000); a little room for time limits


@pytest.mark.slow
def test_micp_certifies_the_profile_grammars():
    """`micp` on the 200-grammar profile (seed 0, 2,000 scene parses): no false answer, and
    at least the share certified measured once the bound handled optional members, meeting
    revolute laws, isotropic rotations and offset pins (docs/parsing.md, "Why `micp` does not
    certify"): a floor against regressions of the bound."""
    report = run_profile(200, 10, seed=0, methods=("micp",))
    print(json.dumps(report["micp_causes"]))
    assert report["false_answers"] == 0, report["false_examples"]
    certified = report["counts"].get("micp:certified", 0) / report["scene_parses"]
    assert certified >= MICP_CERTIFIED_FLOOR, report["micp_causes"]


@pytest.mark.slow
@pytest.mark.parametrize("text", [LATENT_AND_CHAIN, REFERENCE_TEST])
def test_issue_grammars_thousand_scenes_no_false_status(text):
    grammar = compile_text(text)
    scenes = sampled_scenes(grammar, 1000, seed=3, max_objects=8)
    print(grammar.name, len(scenes), "scenes", dict(sorted(assert_honest(grammar, scenes).items())))
