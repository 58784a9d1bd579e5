"""Sanity tests of the brute-force parser (tests/bruteforce.py) on tiny inline grammars.

Each test compares the enumerated parses with what can be worked out by hand: how many trees
explain a scene, and their log-probabilities written out term by term (count law, rule choice,
Normal densities, uniform rotations).  Sampled scenes of the singles/pairs dependency grammar
check that the tree that produced a scene is always among its parses.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from bruteforce import enumerate_parses
from scipy.spatial.transform import Rotation

from ssgc.compile import compile_text
from ssgc.geometry import quat_canonical, rpy_to_quat
from ssgc.io.scene import Scene, scene_from_tree
from ssgc.ir import Grammar
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees
from ssgc.tree import Trees

LOG_UNIFORM_SO3 = -math.log(math.pi**2)


def make_scene(grammar: Grammar, objects: list[tuple[str, list[float], list[float]]]) -> Scene:
    """A scene from (type name, xyz, rpy) triples."""
    types = np.array([grammar.type_id(name) for name, _, _ in objects], np.int64)
    xyz = np.array([p for _, p, _ in objects], float).reshape(-1, 3)
    quat = np.array([rpy_to_quat(np.array(r, float)) for _, _, r in objects]).reshape(-1, 4)
    return Scene("test", types, xyz, quat)


def tree_key(tree: Trees, i: int = 0) -> tuple:
    """Canonical key of a single tree, written independently of the enumerator: every node's
    children are sorted, poses rounded."""
    children = sorted(tree_key(tree, int(c)) for c in np.flatnonzero(tree.parent == i))
    return (
        int(tree.type[i]),
        int(tree.rule[i]),
        tuple(np.round(tree.xyz[i], 6) + 0.0),
        tuple(np.round(quat_canonical(tree.quat[i]), 6) + 0.0),
        tuple(children),
    )


def normal_logpdf(x: np.ndarray, mean: np.ndarray, var: np.ndarray) -> float:
    """Diagonal Normal log-density, written out."""
    x, mean, var = (np.broadcast_to(np.asarray(a, float), (3,)) for a in (x, mean, var))
    return float(np.sum(-0.5 * (x - mean) ** 2 / var - 0.5 * np.log(2 * math.pi * var)))


def check_parses(grammar: Grammar, parses: list[tuple[float, Trees]]) -> None:
    """Best first, distinct, finite, and each score is the scorer's."""
    scores = [s for s, _ in parses]
    assert scores == sorted(scores, reverse=True)
    assert all(np.isfinite(scores))
    keys = [tree_key(t) for _, t in parses]
    assert len(set(keys)) == len(keys)
    for s, t in parses:
        assert t.n_scenes == 1
        assert np.all(t.parent < np.arange(len(t)))
        assert s == pytest.approx(float(score_trees(grammar, t)[0]), abs=1e-12)


# ------------------------------------------------------------- 1. repeat of terminals ---

REPEAT = """
grammar: repeat_terminals
root:
  type: Root
  pose: {xyz: [0.5, -0.2, 0.1], rpy: [0.0, 0.0, 0.3]}
types:
  Root:
    observed: true
    repeat:
      count: {probs: [0.1, 0.2, 0.3, 0.4]}
      rule:
        child: Object
        translation: {world_normal_offset: {mean: [0.0, 0.0, 1.0], variance: [0.5, 0.2, 0.1]}}
        rotation: uniform
  Object:
    observed: true
"""

OBJECTS = [
    ([0.7, 0.1, 1.2], [0.1, 0.2, 0.3]),
    ([0.1, -0.4, 0.9], [1.0, -0.5, 2.0]),
    ([0.9, 0.3, 1.4], [0.0, 0.0, -1.0]),
    ([0.4, -0.1, 0.8], [0.3, 0.3, 0.3]),
]


def repeat_score(k: int, positions: list[list[float]]) -> float:
    root = np.array([0.5, -0.2, 0.1])
    total = math.log([0.1, 0.2, 0.3, 0.4][k])
    for x in positions:
        total += normal_logpdf(np.array(x) - root, [0.0, 0.0, 1.0], [0.5, 0.2, 0.1])
        total += LOG_UNIFORM_SO3
    return total


@pytest.mark.parametrize("k", [0, 1, 2, 3])
@pytest.mark.parametrize("root_object", [True, False])
def test_repeat_has_one_parse_with_hand_score(k: int, root_object: bool) -> None:
    g = compile_text(REPEAT)
    objects = [("Object", x, r) for x, r in OBJECTS[:k]]
    if root_object:  # listed last, to make sure the root is looked for anywhere
        objects.append(("Root", [0.5, -0.2, 0.1], [0.0, 0.0, 0.3]))
    parses = enumerate_parses(g, make_scene(g, objects))
    check_parses(g, parses)
    assert len(parses) == 1
    score, tree = parses[0]
    assert score == pytest.approx(repeat_score(k, [x for x, _ in OBJECTS[:k]]), abs=1e-9)
    assert len(tree) == k + 1
    assert list(tree.type) == [g.type_id("Root")] + [g.type_id("Object")] * k


def test_repeat_impossible_scenes() -> None:
    g = compile_text(REPEAT)
    four = [("Object", x, r) for x, r in OBJECTS]
    assert enumerate_parses(g, make_scene(g, four)) == []  # more copies than the count allows
    misplaced_root = [("Root", [0.5, -0.2, 0.2], [0.0, 0.0, 0.3]), *four[:2]]
    assert enumerate_parses(g, make_scene(g, misplaced_root)) == []
    two_roots = [("Root", [0.5, -0.2, 0.1], [0.0, 0.0, 0.3])] * 2
    assert enumerate_parses(g, make_scene(g, two_roots)) == []


def test_identical_objects_are_one_parse() -> None:
    g = compile_text(REPEAT)
    x, r = OBJECTS[0]
    parses = enumerate_parses(g, make_scene(g, [("Object", x, r), ("Object", x, r)]))
    assert len(parses) == 1
    assert parses[0][0] == pytest.approx(repeat_score(2, [x, x]), abs=1e-9)


# ------------------------------------------------------- 2. or of two latent routes ---

ROUTES = """
grammar: two_routes
root: Root
types:
  Root:
    observed: true
    or:
      - child: A
        p: 0.25
        translation: {world_normal: {mean: [1.0, 0.0, 0.0], variance: 0.5}}
        rotation: uniform
      - child: B
        p: 0.75
        translation: {world_normal: {mean: [0.0, 1.0, 0.0], variance: [0.3, 0.4, 0.2]}}
        rotation: uniform
  A:
    and:
      - child: Thing
  B:
    and:
      - child: Thing
        translation: {offset: [0.0, 0.0, 0.2]}
        rotation: {offset: {rpy: [0.0, 0.0, 0.5]}}
  Thing:
    observed: true
"""


@pytest.mark.parametrize("root_object", [True, False])
def test_or_of_latent_routes(root_object: bool) -> None:
    g = compile_text(ROUTES)
    x, rpy = np.array([0.4, 0.6, -0.1]), [0.3, -0.2, 1.0]
    objects = [("Thing", list(x), rpy)]
    if root_object:
        objects.insert(0, ("Root", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]))
    parses = enumerate_parses(g, make_scene(g, objects))
    check_parses(g, parses)
    assert len(parses) == 2

    # Via A: A sits on the Thing.  Via B: B = Thing ⊕ offset⁻¹ (scipy as an independent check).
    score_a = math.log(0.25) + normal_logpdf(x, [1.0, 0.0, 0.0], [0.5] * 3) + LOG_UNIFORM_SO3
    r_thing = Rotation.from_euler("xyz", rpy)
    r_b = r_thing * Rotation.from_euler("xyz", [0.0, 0.0, 0.5]).inv()
    x_b = x - r_b.apply([0.0, 0.0, 0.2])
    score_b = math.log(0.75) + normal_logpdf(x_b, [0.0, 1.0, 0.0], [0.3, 0.4, 0.2])
    score_b += LOG_UNIFORM_SO3
    by_route = {g.types[int(t.type[1])].name: (s, t) for s, t in parses}
    assert set(by_route) == {"A", "B"}
    assert by_route["A"][0] == pytest.approx(score_a, abs=1e-9)
    assert by_route["B"][0] == pytest.approx(score_b, abs=1e-9)
    b_tree = by_route["B"][1]
    assert np.allclose(b_tree.xyz[1], x_b, atol=1e-12)
    q_b = r_b.as_quat()[[3, 0, 1, 2]]
    assert abs(float(np.dot(b_tree.quat[1], q_b))) == pytest.approx(1.0, abs=1e-12)
    # The scene's density sums the two routes: a mixture written out by hand.
    total = np.logaddexp(*[s for s, _ in parses])
    mixture = 0.25 * math.exp(normal_logpdf(x, [1.0, 0.0, 0.0], [0.5] * 3))
    mixture += 0.75 * math.exp(normal_logpdf(x_b, [0.0, 1.0, 0.0], [0.3, 0.4, 0.2]))
    assert total == pytest.approx(math.log(mixture) + LOG_UNIFORM_SO3, abs=1e-9)


def test_or_produces_exactly_one_thing() -> None:
    g = compile_text(ROUTES)
    assert enumerate_parses(g, make_scene(g, [])) == []
    two = [("Thing", [0.1, 0.2, 0.3], [0, 0, 0]), ("Thing", [0.5, 0.2, 0.3], [0, 0, 1])]
    assert enumerate_parses(g, make_scene(g, two)) == []


# ------------------------------------------------------------- 3. singles and pairs ---

SINGLES_PAIRS = """
grammar: singles_pairs
root:
  type: Root
  pose: {xyz: [0.0, 0.0, 0.0]}
types:
  Root:
    observed: true
    independent:
      - {child: Singles, p: 0.7}
      - {child: Pairs, p: 0.6}
  Singles:
    repeat:
      count: {geometric: {p: 0.5, max: 4, start: 1}}
      rule:
        child: Object
        translation: {world_normal: {mean: [0.0, 0.0, 1.0], variance: [1.0, 1.0, 0.25]}}
        rotation: {world_bingham: {concentration: [20.0, 20.0, 0.5]}}
  Pairs:
    repeat:
      count: {geometric: {p: 0.5, max: 3, start: 1}}
      rule:
        child: Pair
        translation: {world_normal: {mean: [0.0, 0.0, 1.0], variance: [1.0, 1.0, 0.25]}}
        rotation: {world_bingham: {concentration: [20.0, 20.0, 0.5]}}
  Pair:
    and:
      - {child: Object, translation: same, rotation: same}
      - child: Object
        translation: {parent_normal_offset: {mean: [-0.3, -0.5, 0.0], variance: 0.01}}
        rotation: {parent_bingham: {concentration: 50.0}}
  Object:
    observed: true
"""


def n_singles_pairs_parses(m: int) -> int:
    """m objects: j ordered pairs (leader, wingman) and m - 2j singles, for every j."""
    return sum(
        math.factorial(m) // (math.factorial(m - 2 * j) * math.factorial(j))
        for j in range(m // 2 + 1)
    )


def test_two_objects_are_two_singles_or_a_pair_either_way() -> None:
    g = compile_text(SINGLES_PAIRS)
    objects = [
        ("Root", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
        ("Object", [0.2, -0.1, 1.0], [0.0, 0.0, 0.4]),
        ("Object", [-0.2, -0.5, 0.9], [0.05, 0.0, 0.3]),
    ]
    parses = enumerate_parses(g, make_scene(g, objects))
    check_parses(g, parses)
    assert n_singles_pairs_parses(2) == 3
    assert len(parses) == 3
    names = [sorted(g.types[int(t)].name for t in tree.type) for _, tree in parses]
    singles = ["Object", "Object", "Root", "Singles"]
    pair = ["Object", "Object", "Pair", "Pairs", "Root"]
    assert sorted(names) == sorted([singles, pair, pair])
    # The two pairs differ by which object leads: the Pair sits on its leader.
    leaders = set()
    for _, tree in parses:
        pair_nodes = np.flatnonzero(tree.type == g.type_id("Pair"))
        if len(pair_nodes):
            leaders.add(tuple(np.round(tree.xyz[pair_nodes[0]], 9)))
    assert leaders == {(0.2, -0.1, 1.0), (-0.2, -0.5, 0.9)}


def test_sampled_trees_are_among_the_parses() -> None:
    g = compile_text(SINGLES_PAIRS)
    trees, logp = sample_trees(g, 60, seed=3)
    checked = 0
    sizes = set()
    for i in range(trees.n_scenes):
        tree = trees.tree(i)
        scene = scene_from_tree(g, tree, f"s{i}")
        m = len(scene) - 1  # the Root is observed too
        if m > 4:
            continue
        parses = enumerate_parses(g, scene)
        check_parses(g, parses)
        assert len(parses) == n_singles_pairs_parses(m)
        truth = float(score_trees(g, tree)[0])
        assert truth == pytest.approx(float(logp[i]), abs=1e-9)
        match = [s for s, t in parses if tree_key(t) == tree_key(tree)]
        assert len(match) == 1
        assert match[0] == pytest.approx(truth, abs=1e-9)
        sizes.add(m)
        checked += 1
        if checked == 20:
            break
    assert checked == 20
    assert sizes >= {1, 2, 3}


# -------------------------------------------------------------- 4. stacks of trays ---

TRAYS = """
grammar: trays
root: Table
types:
  Table:
    observed: true
    and:
      - child: Tray
        translation: {world_normal_offset: {mean: [0.0, 0.0, 0.5], variance: 0.01}}
        rotation: same
  Tray:
    observed: true
    max_nesting: NESTING
    or:
      - {child: Stop, p: 0.4}
      - child: Tray
        p: 0.6
        translation: TRAY_TRANSLATION
        rotation: same
  Stop: {}
"""
NORMAL_TRAY = "{parent_normal_offset: {mean: [0.0, 0.0, 0.1], variance: 0.0004}}"
FIXED_TRAY = "{offset: [0.0, 0.0, 0.1]}"
TRAY_XYZ = [[0.01, 0.0, 0.5], [0.0, 0.02, 0.61], [-0.01, 0.0, 0.7]]


def trays(nesting: int, translation: str = NORMAL_TRAY) -> Grammar:
    text = TRAYS.replace("NESTING", str(nesting)).replace("TRAY_TRANSLATION", translation)
    return compile_text(text)


def tray_scene(g: Grammar, xyz: list[list[float]]) -> Scene:
    table = [("Table", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])]
    return make_scene(g, table + [("Tray", x, [0.0, 0.0, 0.0]) for x in xyz])


@pytest.mark.parametrize(("nesting", "n_trays", "expected"), [(3, 3, 6), (3, 2, 2), (2, 3, 0)])
def test_tray_stacks(nesting: int, n_trays: int, expected: int) -> None:
    g = trays(nesting)
    parses = enumerate_parses(g, tray_scene(g, TRAY_XYZ[:n_trays]))
    check_parses(g, parses)
    assert len(parses) == expected  # every order of the trays is a chain


def test_full_stack_is_blocked_and_stops_for_sure() -> None:
    x = np.array(TRAY_XYZ)
    table_edge = normal_logpdf(x[0], [0.0, 0.0, 0.5], [0.01] * 3)
    tray_edges = sum(normal_logpdf(x[k + 1] - x[k], [0.0, 0.0, 0.1], [0.0004] * 3) for k in (0, 1))
    # nesting 3: the top tray may not hold another, so its `or` gives Stop probability 1
    best = enumerate_parses(trays(3), tray_scene(trays(3), TRAY_XYZ))[0]
    assert best[0] == pytest.approx(table_edge + 2 * math.log(0.6) + tray_edges, abs=1e-9)
    assert len(best[1]) == 5 and best[1].type[-1] == trays(3).type_id("Stop")
    # nesting 4: the top tray chooses to stop, with probability 0.4
    loose = enumerate_parses(trays(4), tray_scene(trays(4), TRAY_XYZ))
    assert len(loose) == 6
    expected = table_edge + 2 * math.log(0.6) + math.log(0.4) + tray_edges
    assert loose[0][0] == pytest.approx(expected, abs=1e-9)


def test_fixed_offset_stack_is_one_group() -> None:
    g = trays(3, FIXED_TRAY)
    exact = [[0.01, 0.0, 0.5], [0.01, 0.0, 0.6], [0.01, 0.0, 0.7]]
    # listed top first: the head's pose is back-computed through a chain of fixed offsets
    parses = enumerate_parses(g, tray_scene(g, exact[::-1]))
    check_parses(g, parses)
    assert len(parses) == 1
    score, tree = parses[0]
    assert score == pytest.approx(
        normal_logpdf(np.array(exact[0]), [0.0, 0.0, 0.5], [0.01] * 3) + 2 * math.log(0.6)
    )
    assert np.allclose(tree.xyz[1:4], exact, atol=1e-12)
    off = [[0.01, 0.0, 0.5], [0.01, 0.0, 0.6], [0.01, 0.0, 0.75]]
    assert enumerate_parses(g, tray_scene(g, off)) == []


# ------------------------------------------------------------------- out of scope ---


def test_free_latent_group_is_not_implemented() -> None:
    g = compile_text(
        """
grammar: free_latent
root: Root
types:
  Root:
    observed: true
    and:
      - child: Hidden
        translation: {world_normal: {mean: [0.0, 0.0, 0.0], variance: 1.0}}
        rotation: uniform
  Hidden: {}
"""
    )
    with pytest.raises(NotImplementedError, match="Hidden"):
        enumerate_parses(g, make_scene(g, []))
