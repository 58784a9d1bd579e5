"""Rules blocked by `max_nesting` never fire (docs/grammar.md 3.4), in the parser as in the
sampler and the scorer: a blocked `repeat` produces nothing with probability 1 (its count law
is not consulted), a blocked `or` rule leaves the choice to the others, a blocked `independent`
rule contributes no factor.  Each parse must score its tree's log-probability (score_trees),
at least the sampled tree's, and an `optimal` parse the brute-force MAP, with every method and
both exact formulations (the pose-instantiated model and the equivalent-set model)."""

from __future__ import annotations

import numpy as np
import pytest
from bruteforce import enumerate_parses
from grammar_gen import sampled_scenes

from ssgc.compile import compile_text
from ssgc.parse.ip import SetReduction
from ssgc.parse.parser import REDUCTIONS, Parser
from ssgc.parse.supertree import build_supertree
from ssgc.score import score_trees
from ssgc.supertree_size import supertree_size

# The bug hunt's g15: T1's repeat is blocked at the second T1, and P(count = 0) = 0 there.
EXPLOSIVE = """
grammar: deep
root: T0
types:
  T0: {and: [{child: T1}]}
  T1: {max_nesting: 2, observed: true, repeat: {count: {probs: [0, 1]}, rule: {child: T1}}}
"""

# The bug hunt's g02b / g02c: the repeat under the second Tray is blocked.
STACK = """
grammar: blocked_stack
root: Base
types:
  Base:
    and: [{child: Tray}]
  Tray:
    observed: true
    max_nesting: 2
    independent:
      - {child: Stack, p: 0.7, translation: {offset: [0, 0, 0.06]}}
  Stack:
    repeat:
      count: {probs: PROBS}
      rule: {child: Tray}
"""

# Blocked children of an `or` and of an `and` under an `independent`.
KINDS = """
grammar: blocked_kinds
root: Base
types:
  Base:
    and: [{child: Tray}]
  Tray:
    observed: true
    max_nesting: 2
    independent:
      - {child: SubOr, p: 0.7, translation: {offset: [0, 0, 0.06]}}
      - {child: SubAnd, p: 0.6, translation: {offset: [0, 0, 0.07]}}
  SubOr:
    or: [{child: Tray, p: 3}, {child: Cap, p: 1}]
  SubAnd:
    and: [{child: Tray, translation: {offset: [0.1, 0, 0]}}]
  Cap: {observed: true}
"""

# A latent recursive type: the blocked repeat sits at a latent pose (the bound's path).
LATENT = """
grammar: latent_blocked
root: R
types:
  R: {and: [{child: L, translation: {world_normal: {mean: [0, 0, 0], variance: 0.01}}}]}
  L:
    max_nesting: 2
    and:
      - {child: A, translation: {world_normal_offset: {mean: [0.1, 0, 0], variance: 0.01}}}
      - {child: M}
  M:
    repeat:
      count: {probs: [0, 1]}
      rule: {child: L, translation: {world_normal_offset: {mean: [0, 0, 0.2], variance: 0.01}}}
  A: {observed: true}
"""

EXACT = {
    "explosive": EXPLOSIVE,
    "stack_never_empty": STACK.replace("PROBS", "[0, 1]"),
    "stack_maybe_empty": STACK.replace("PROBS", "[0.5, 0.5]"),
    "kinds": KINDS,
}
FORMULATIONS = {"posed": REDUCTIONS, "set": (SetReduction(),)}


@pytest.mark.parametrize("formulation", sorted(FORMULATIONS))
@pytest.mark.parametrize("method", ["ip", "micp"])
@pytest.mark.parametrize("name", sorted(EXACT))
def test_blocked_rules_parse_at_their_exact_score(name, method, formulation):
    """Was: `infeasible` for EXPLOSIVE, `optimal` below the sampled tree for the never-empty
    stack, and "parse score differs from the MILP objective" for the maybe-empty one: the
    parser charged a blocked repeat log P(count = 0)."""
    grammar = compile_text(EXACT[name])
    parser = Parser(grammar, method=method, reductions=FORMULATIONS[formulation])
    scenes = sampled_scenes(grammar, 8, seed=0, max_objects=6)
    assert scenes
    for scene in scenes:
        result = parser.parse(scene)
        assert result.status == "optimal", (scene.name, result.message)
        best = result.parses[0]
        assert best.score == pytest.approx(float(score_trees(grammar, best.tree)[0]), abs=1e-9)
        assert best.score >= scene.log_prob - 1e-9
        assert best.score == pytest.approx(enumerate_parses(grammar, scene)[0][0], abs=1e-7)


@pytest.mark.parametrize("method", ["ip", "micp"])
def test_a_blocked_repeat_at_a_latent_pose_costs_nothing(method):
    """The same at a latent pose (proposals, and `micp`'s bound): the sampled tree, whose
    second L's repeat is blocked, is matched or beaten, never certified below."""
    grammar = compile_text(LATENT)
    parser = Parser(grammar, method=method)
    scenes = sampled_scenes(grammar, 4, seed=0)
    assert scenes
    for scene in scenes:
        result = parser.parse(scene, time_limit=20)
        assert result.parses, (scene.name, result.status, result.message)
        best = result.parses[0]
        assert np.isfinite(best.score)
        assert best.score >= scene.log_prob - 1e-6 * max(1.0, abs(scene.log_prob))


# T1's only unblocked rule weighs 0 once its T1 rule is blocked (at the first T1).
ZERO_MASS_OR = """
grammar: zero_mass_or
root: T0
types:
  T0: {and: [{child: T1}]}
  T1: {max_nesting: 1, observed: true, or: [{child: T1, p: 1}, {child: A, p: 0}]}
  A: {observed: true}
"""


@pytest.mark.parametrize("formulation", sorted(FORMULATIONS))
@pytest.mark.parametrize("method", ["ip", "micp"])
def test_an_or_whose_unblocked_rules_weigh_nothing_makes_nothing(method, formulation):
    """Was ZeroDivisionError (an internal error of `ssg parse`): the `or` renormalised over
    its unblocked rules divided by their weight, 0.  Then the parser followed the scorer,
    which gave every choice of such a node -inf, and called the sampled scene infeasible.  A
    rule of weight 0 never fires, so the node makes nothing with probability 1 (as the
    sampler draws it): the sampled tree is the only one, of probability 1."""
    grammar = compile_text(ZERO_MASS_OR)
    scene = sampled_scenes(grammar, 1, seed=0)[0]
    truth = float(score_trees(grammar, scene.tree)[0])
    assert truth == pytest.approx(0.0)
    result = Parser(grammar, method=method, reductions=FORMULATIONS[formulation]).parse(scene)
    assert result.status == "optimal", result.message
    assert result.parses[0].score == pytest.approx(truth, abs=1e-9)


def test_the_scorer_scores_a_zero_mass_or_as_the_sampler_draws_it():
    """The sampler gives ZERO_MASS_OR's T1 no child (probability 1: a rule of weight 0
    never fires, so the node is as one whose every rule is blocked); the scorer gave that tree
    -inf (0/0 after renormalising), and the parser called the sampled scene infeasible."""
    grammar = compile_text(ZERO_MASS_OR)
    scene = sampled_scenes(grammar, 1, seed=0)[0]
    assert len(scene.tree.type) == 2  # T0, T1: T1's rule of T1 is blocked, its A weighs 0
    assert float(score_trees(grammar, scene.tree)[0]) == pytest.approx(scene.log_prob)


# Found by the generated grammars (`rare`): two copies of a latent node whose latent child
# ends its chain, here a recursive `or` blocked at its third level; NO_NESTING is the same
# shape without max_nesting (a latent terminal).  Every term is a density above 1, so the
# MAP tree has both copies.
BINGHAM = "{world_bingham: {mode: {rpy_deg: [20, 0, 45]}, concentration: [100, 100, 0]}}"
BOX = "{world_box: {min: [-0.1, -0.1, -0.1], max: [0.1, 0.1, 0.1]}}"
TWO_COPIES = f"""
grammar: two_latent_copies
root: L0
types:
  L0:
    observed: true
    repeat:
      count: {{probs: [0, 0.5, 0.5]}}
      rule: {{child: L1, translation: {BOX}, rotation: same}}
  L1: {{max_nesting: 3, or: [{{child: L1, p: 2, translation: same, rotation: {BINGHAM}}}]}}
"""
NO_NESTING = f"""
grammar: two_latent_copies_no_nesting
root: L0
types:
  L0: {{repeat: {{count: {{probs: [0, 0.5, 0.5]}}, rule: {{child: L1, translation: {BOX}}}}}}}
  L1: {{and: [{{child: L2, translation: same, rotation: {BINGHAM}}}]}}
  L2: {{}}
"""


@pytest.mark.parametrize("method", ["ip", "micp"])
@pytest.mark.parametrize("text", [TWO_COPIES, NO_NESTING], ids=["nesting", "terminal"])
def test_two_copies_of_one_latent_assignment_are_counted(method, text):
    """Was `optimal` at one copy's score, below the sampled two-copy tree (12.07 against
    8.77 for TWO_COPIES): the bound repeated a `repeat`'s childless assignments once per
    copy, but not one naming only a lifted latent child, and the model over proposals had
    one candidate pose for the two copies.  Nothing here is observed but the root, so every
    latent pose is integrated out (`ssgc.score`): one copy and two score log 0.5 alike, and
    the parse is certified at that score (it was 12.07, each density above 1 counted)."""
    grammar = compile_text(text)
    scene = sampled_scenes(grammar, 1, seed=0)[0]
    result = Parser(grammar, method=method).parse(scene, time_limit=30)
    assert result.parses, result.message
    best = result.parses[0]
    assert best.score >= scene.log_prob - 1e-6 * max(1.0, abs(scene.log_prob))
    assert best.score == pytest.approx(np.log(0.5), abs=1e-9)
    assert result.status == "optimal"
    l1 = grammar.type_ids["L1"]
    assert np.count_nonzero((best.tree.type == l1) & (best.tree.parent == 0)) in (1, 2)


def test_rules_that_never_fire_are_left_out_of_the_supertree_and_its_count():
    """`ssg inspect`'s count is the supertree the parser builds; neither holds a rule of weight
    or probability 0 (they used to: ZERO_MASS_OR's A, and here the `independent` B)."""
    text = ZERO_MASS_OR.replace(
        "A: {observed: true}",
        "A: {observed: true}\n  B: {observed: true}\n  I: {independent: [{child: B, p: 0}]}",
    ).replace("{child: A, p: 0}]}", "{child: A, p: 0}, {child: I, p: 2}]}")
    grammar = compile_text(text)
    tree = build_supertree(grammar)
    names = sorted(grammar.types[t].name for t in tree.type)
    assert names == ["I", "T0", "T1"]
    assert supertree_size(grammar) == len(tree)
