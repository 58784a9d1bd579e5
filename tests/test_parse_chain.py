"""A latent set placed relative to a latent parent (issue 11, `ssgc/parse/bound_chain.py`).

R → L1 → L2 → X: L1 and L2 are latent, L2 is placed relative to L1.  The bound used to count
L2's rule at its supremum (`decoupled`), so these scenes were never certified.  With the
chain lifted into L1's assignments the bound is the joint maximum over both latent poses.

The reference here is a brute force of its own: with isotropic Normal (or fixed) translations
and rotations that do not move the score, the MAP tree is the sampled structure with the
latent positions at the least-squares optimum of the chain (solved per axis below), scored by
the grammar's own scorer.  The bound must never be below it, and the parse must certify it.
"""

from __future__ import annotations

import numpy as np
import pytest
from grammar_gen import compile_spec, sampled_scenes
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as hs

from ssgc.compile import compile_text
from ssgc.parse.parser import Parser
from ssgc.score import score_trees

TOL = 1e-6

# translation laws of the chain's edges: (YAML, precision per axis, mean) — `same` has no
# precision (the child is at its parent's position)
LAWS = {
    "normal_offset": lambda mean, var: (
        {"world_normal_offset": {"mean": mean, "variance": var}},
        1.0 / var,
        mean,
    ),
    "parent_normal": lambda mean, var: (
        {"parent_normal_offset": {"mean": [0.0, 0.0, 0.0], "variance": var}},
        1.0 / var,
        [0.0, 0.0, 0.0],
    ),
    "same": lambda mean, var: ("same", None, [0.0, 0.0, 0.0]),
}
ROTATIONS = ("uniform", {"revolute": {"axis": [0, 0, 1]}}, {"revolute": {"axis": [1, 0, 0]}})


def chain_grammar(edges, rotations, copies: bool) -> tuple[str, list]:
    """The YAML of R → L1 → L2 → X with the given (law, mean, variance) per edge, and the
    edges' (precision, mean).  With `copies`, L1 holds a `repeat` of up to two L2."""
    made = [LAWS[law](mean, var) for law, mean, var in edges]
    rules = [
        {"child": child, "translation": t, "rotation": rot}
        for child, (t, _, _), rot in zip(("L1", "L2", "X"), made, rotations, strict=True)
    ]
    rules[0]["translation"] = {"world_normal": {"mean": edges[0][1], "variance": edges[0][2]}}
    l1 = (
        {"repeat": {"count": {"probs": [0.3, 0.4, 0.3]}, "rule": rules[1]}}
        if copies
        else {"and": [rules[1]]}
    )
    import yaml

    spec = {
        "grammar": "chain",
        "root": "R",
        "types": {
            "R": {"and": [rules[0]]},
            "L1": l1,
            "L2": {"and": [rules[2]]},
            "X": {"observed": True},
        },
    }
    return yaml.safe_dump(spec, default_flow_style=None), [(p, m) for _, p, m in made]


def least_squares_map(grammar, scene, edges) -> float:
    """The sampled tree with every latent position at the chain's least-squares optimum,
    scored by the grammar: the MAP of a chain whose rotations do not move the score.  Each
    L1 and its L2 children are one linear system (the same on every axis): minimise
    Σ prec (v·p + k)² over the unknown positions p."""
    tree = scene.tree
    names = [grammar.types[t].name for t in tree.type]
    xyz = tree.xyz.copy()
    (a1, m1), (a2, m2), (a3, m3) = edges
    for l1 in (i for i, t in enumerate(names) if t == "L1"):
        l2s = [i for i in range(len(names)) if tree.parent[i] == l1]
        # unknowns: L1, then each L2 (an L2 placed by `same` is L1 itself)
        index = {c: 0 if a2 is None else k + 1 for k, c in enumerate(l2s)}
        n = 1 + (0 if a2 is None else len(l2s))
        H, g = np.zeros((n, n)), np.zeros((n, 3))

        def add(v: np.ndarray, k: np.ndarray, prec: float, H=H, g=g) -> None:
            H += prec * np.outer(v, v)
            g -= prec * np.outer(v, k)

        v = np.zeros(n)
        v[0] = 1.0
        add(v, -(xyz[tree.parent[l1]] + np.asarray(m1)), a1)
        for c in l2s:
            if a2 is not None:
                v = np.zeros(n)
                v[index[c]], v[0] = 1.0, -1.0
                add(v, -np.asarray(m2, float), a2)
            (x,) = [i for i in range(len(names)) if tree.parent[i] == c]
            v = np.zeros(n)
            v[index[c]] = -1.0
            add(v, xyz[x] - np.asarray(m3, float), a3)
        sol = np.linalg.solve(H, g)
        xyz[l1] = sol[0]
        for c in l2s:
            xyz[c] = sol[index[c]]
    best = type(tree)(tree.scene, tree.type, tree.parent, tree.rule, xyz, tree.quat, 1)
    return float(score_trees(grammar, best)[0])


def check_chain(text: str, edges, scenes: int, seed: int) -> int:
    """Parse sampled scenes with `micp`: the bound is at or above the least-squares MAP (a
    brute force over the chain), and the parse is certified at it.  Returns the scenes
    checked."""
    grammar = compile_text(text)
    parser = Parser(grammar, method="micp")
    checked = 0
    for scene in sampled_scenes(grammar, scenes, seed, max_objects=3):
        best = least_squares_map(grammar, scene, edges)
        result = parser.parse(scene, time_limit=20)
        tol = TOL * max(1.0, abs(best))
        bound = result.extra.get("bound", np.nan)
        assert bound >= best - tol, (bound, best, text)
        assert result.status == "optimal", (result.status, result.message, text)
        assert result.parses[0].gap <= TOL
        assert result.parses[0].score == pytest.approx(best, rel=TOL, abs=TOL)
        checked += 1
    return checked


def test_chain_under_a_latent_parent_is_certified():
    """Fails on the bound without `bound_chain`: L2 (placed by a Normal relative to L1) was
    decoupled, its rule counted at its supremum, and no scene had a gap of 0."""
    text, edges = chain_grammar(
        [
            ("normal_offset", [0.0, 0.0, 0.0], 0.01),
            ("normal_offset", [0.3, 0.0, 0.0], 0.02),
            ("normal_offset", [0.0, 0.2, 0.0], 0.01),
        ],
        ("uniform", {"revolute": {"axis": [0, 0, 1]}}, "uniform"),
        copies=False,
    )
    assert check_chain(text, edges, 6, seed=3) >= 4


def test_repeat_of_latent_children_joined_by_same():
    """The profile's grammar 180: L1 holds a `repeat` of L2 at L1's own position (`same`)
    under a free revolute rotation.  Refinement cannot move L1 and L2 apart, so the tree comes
    from the chain's joint poses (`add_chain_poses`); the bound is exact."""
    text, edges = chain_grammar(
        [
            ("normal_offset", [1.0, 0.5, 0.0], 0.01),
            ("same", None, None),
            ("normal_offset", [0.0, 0.0, 0.0], 0.01),
        ],
        ({"revolute": {"axis": [0, 1, 1], "min": -0.4, "max": 0.7}}, ROTATIONS[1], "uniform"),
        copies=True,
    )
    assert check_chain(text, edges, 6, seed=180) >= 4


MEANS = ([0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [1.0, 0.5, 0.0])
edge = hs.tuples(
    hs.sampled_from(sorted(LAWS)), hs.sampled_from(MEANS), hs.sampled_from((0.01, 0.05))
)


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    l2=edge,
    x=edge.filter(lambda e: e[0] != "same"),
    # two revolute laws in a row hold L1's rotation only jointly through L2 (Paden-Kahan's
    # second subproblem): proposals may find no tree there (docs/parsing.md, what is left)
    rot=hs.tuples(hs.sampled_from(ROTATIONS), hs.sampled_from(ROTATIONS)).filter(
        lambda r: "uniform" in r
    ),
    copies=hs.booleans(),
    seed=hs.integers(0, 1000),
)
def test_chain_bound_is_the_least_squares_map(l2, x, rot, copies, seed):
    """Random chains: the bound is never below the brute-force (least-squares) MAP, and the
    parse certifies it."""
    text, edges = chain_grammar(
        [("normal_offset", [0.3, 0.0, 0.0], 0.02), l2, x], ("uniform", *rot), copies
    )
    check_chain(text, edges, 3, seed)


# The profile's grammar 781: L2's rotation is L1's turned by a fixed offset, and L2's child
# sits at a parent-frame Normal offset, so L2's terms turn with L1's rotation (`_turning`);
# "free" is the same with L1's rotation uniform (the lifted term is then linear in R).
TURNING = """
grammar: turning
root: L0
types:
  A: {observed: true}
  B: {observed: true}
  L0:
    and:
      - child: L1
        translation: {world_normal: {mean: [0.3, -0.2, 0.1], variance: 0.01}}
        rotation: ROT
  L1:
    or:
      - child: L2
        p: 1.0
        translation: {world_normal_offset: {mean: [0.3, -0.2, 0.1], variance: 0.01}}
        rotation: {offset: {rpy_deg: [0, 90, 0]}}
  L2:
    independent:
      - child: B
        p: 1.0
        translation: {parent_normal_offset: {mean: [1.0, 0.5, 0.0], variance: 0.05}}
        rotation: {revolute: {axis: [1, 0, 0]}}
"""


@pytest.mark.parametrize(
    ("rotation", "certifies"),
    [("{offset: {rpy_deg: [20, 0, 45]}}", True), ("uniform", False)],
    ids=["pinned", "free"],
)
def test_child_turning_with_its_parent(rotation, certifies):
    """Pinned: every scene certified.  Free: B's revolute law holds L2's rotation to an arc,
    which the lift does not carry to L1 (a looser bound, still above every tree)."""
    grammar = compile_text(TURNING.replace("ROT", rotation))
    parser = Parser(grammar, method="micp")
    certified = 0
    for scene in sampled_scenes(grammar, 5, seed=781, max_objects=3):
        truth = float(scene.log_prob)
        result = parser.parse(scene, time_limit=20)
        tol = TOL * max(1.0, abs(truth))
        assert result.extra.get("bound", np.nan) >= truth - tol
        if result.status == "optimal":
            assert result.parses[0].score >= truth - tol
        certified += result.status == "optimal"
    assert certified == (5 if certifies else certified)


RELATIVE = ("same", "offset", "world_normal_offset", "parent_normal_offset", "world_box_offset")


def depth2_relative():
    """grammar_gen's family with L0 → L1 → L2 forced, L1 and L2 each entered by a rule
    relative to its parent; every other choice free.  Most draws have the profile's
    `depth2:relative` shape (18 of 30 drawn: a fixed rule can merge L1 or L2 into its parent's
    set)."""
    import grammar_gen as gg

    @hs.composite
    def strategy(draw):
        state = {"type": -1, "forced": None}

        def pick(what, options):
            if what == "latent":
                return 3
            if what == "kind":
                state["type"] += 1
                state["fresh"] = state["type"] < 2
            if what == "child" and state.get("fresh"):
                state["fresh"], state["forced"] = False, "translation"
                return f"L{state['type'] + 1}"
            if what == "translation" and state["forced"] == "translation":
                state["forced"] = None
                return draw(hs.sampled_from(RELATIVE), label="relative")
            return draw(hs.sampled_from(list(options)), label=what)

        return gg.make_spec(pick)

    return strategy()


def check_sound(grammar, scenes) -> None:
    """Each method: never `infeasible`, the bound at or above the sampled tree, a certified
    parse at or above it (parse_profile.check_scene's false answers, plus the bound)."""
    from parse_profile import check_scene

    for method in ("ip", "micp"):
        parser = Parser(grammar, method=method)
        for scene in scenes:
            v = check_scene(grammar, parser, scene, time_limit=10)
            assert not v.false, (method, v.false)
            bound = v.result.extra.get("bound", np.nan)
            assert not bound < v.truth - TOL * max(1.0, abs(v.truth)), (method, bound, v.truth)


@settings(max_examples=2, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spec=depth2_relative())
def test_depth2_relative_grammars_are_sound(spec):
    check_sound(compile_spec(spec), sampled_scenes(compile_spec(spec), 2, seed=0))


@pytest.mark.slow
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spec=depth2_relative())
def test_depth2_relative_grammars_are_sound_long(spec):
    check_sound(compile_spec(spec), sampled_scenes(compile_spec(spec), 5, seed=0))


# Three grammars of the issue-11 profile (`python tests/parse_profile.py --seed 0`: grammar
# index, scenes `sampled_scenes(grammar, 10, index)`), each `decoupled` with a gap > 0.1 on
# main (894b760) and certified now, one per change in `bound_chain.py`:
# - 591: L2's rotation is L1's turned by a fixed offset, L1 on a revolute family, L2's child
#   at a fixed offset (turning with L2), L2 placed by an *anisotropic* world-offset Normal:
#   `_turning` now lifts it where L1 is held to an arc (the rotation search bounds it there).
# - 255: L2's own rule has a world Bingham rotation; the bound counted it, but the local search
#   of L2's poses left it out (`own_world_edge`), so the chain's poses scored far below.
# - 569: two latent L2 under each L1, placed by a parent-frame Bingham: the chain's poses now
#   put each at that Bingham's mode relative to its parent (`_at_rule_mode`), once per copy.
PROFILE_GRAMMARS = {
    591: """\
grammar: generated
root: L0
types:
  A: {observed: true}
  B: {observed: true}
  L0:
    and:
    - child: A
      translation:
        offset: [1.0, 0.5, 0.0]
      rotation: same
    - child: L1
      translation:
        offset: [1.0, 0.5, 0.0]
      rotation:
        revolute:
          axis: [1, 0, 0]
  L1:
    and:
    - child: L2
      translation:
        world_normal_offset:
          mean: [0.0, 0.0, 0.0]
          variance: [0.02, 0.01, 0.04]
      rotation:
        offset:
          rpy_deg: [0, 90, 0]
  L2:
    and:
    - child: B
      translation:
        offset: [1.0, 0.5, 0.0]
      rotation:
        revolute:
          axis: [0, 0, 1]
          min: -0.4
          max: 0.7
""",
    255: """\
grammar: generated
root: L0
types:
  A: {observed: true}
  B: {observed: true}
  L0:
    or:
    - child: L1
      translation: same
      rotation:
        world_bingham:
          mode:
            rpy_deg: [0, 0, 0]
          concentration: 20
      p: 3.0
  L1:
    independent:
    - child: L2
      translation: same
      rotation:
        world_bingham:
          mode:
            rpy_deg: [0, 90, 0]
          concentration: [100, 100, 0]
      p: 1.0
    - child: B
      translation:
        world_box:
          min: [0.19999999999999998, -0.30000000000000004, 0.0]
          max: [0.4, -0.1, 0.2]
      rotation:
        revolute:
          axis: [0, 1, 1]
      p: 0.6
  L2:
    and:
    - child: A
      translation:
        world_normal_offset:
          mean: [0.0, 0.0, 0.0]
          variance: 0.05
      rotation:
        revolute:
          axis: [1, 0, 0]
          min: -0.4
          max: 0.7
""",
    569: """\
grammar: generated
root: L0
types:
  A: {observed: true}
  B: {observed: true}
  L0:
    independent:
    - child: L1
      translation:
        parent_normal_offset:
          mean: [0.0, 0.0, 0.0]
          variance: 0.01
      rotation: uniform
      p: 0.3
    - child: L1
      translation:
        offset: [0.3, -0.2, 0.1]
      rotation:
        world_bingham:
          mode:
            rpy_deg: [0, 90, 0]
          concentration: 20
      p: 0.3
  L1:
    repeat:
      count:
        geometric: {p: 0.5, max: 2}
      rule:
        child: L2
        translation:
          world_normal_offset:
            mean: [0.3, -0.2, 0.1]
            variance: 0.01
        rotation:
          parent_bingham:
            mode:
              rpy_deg: [0, 90, 0]
            concentration: [100, 100, 0]
  L2:
    repeat:
      count:
        probs: [0.3, 0.4, 0.3]
      rule:
        child: B
        translation:
          world_normal:
            mean: [0.0, 0.0, 0.0]
            variance: [0.02, 0.01, 0.04]
        rotation:
          revolute:
            axis: [1, 0, 0]
            min: -0.4
            max: 0.7
""",
}


@pytest.mark.parametrize(
    ("index", "scenes"),
    [(591, ("s2",)), (255, ("s0",)), (569, ("s1",))],
    ids=["aniso_offset_on_arc", "world_bingham_own_rule", "bingham_mode_copies"],
)
def test_decoupled_profile_cases_certify(index, scenes):
    """Each of these scenes was `feasible` with a gap > 0.1 on main (591 s2: 1.34, 255 s0:
    1.82, 569 s1: 0.90, each a tree below the bound); now certified, at or above its sampled
    tree, with the bound at or above it too."""
    grammar = compile_text(PROFILE_GRAMMARS[index])
    parser = Parser(grammar, method="micp")
    by_name = {s.name: s for s in sampled_scenes(grammar, 10, seed=index)}
    for name in scenes:
        scene = by_name[name]
        truth = float(scene.log_prob)
        result = parser.parse(scene, time_limit=20)
        tol = TOL * max(1.0, abs(truth))
        assert result.extra.get("bound", np.nan) >= truth - tol, name
        assert result.status == "optimal", (name, result.status, result.parses[0].gap)
        assert result.parses[0].score >= truth - tol, name
