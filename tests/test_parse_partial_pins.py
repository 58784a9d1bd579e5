"""A latent set whose position is partly pinned (`pin:` on some axes of a Normal law, the
others free): the parser must place it at its best position, on its pins, and certify it.

Found by a fit hunt (session 36): a `Cluster` under `world_normal` with `pin: [z]` and two
Points at Normal offsets was left at a proposal (the mean of the objects and the root, score
0.46, `feasible`, gap 4.95), 4.7 nats below its closed-form best (-0.178, 0.631, 0) at 5.17;
`--method ip` gave -14.97.  The relaxation dropped the pinned axis (its point mass), so the
relaxation's pose sat off the pin, where the density is -inf, and the exact polish could not
step onto it.  Pinned axes are now planes of the relaxation (`_LocalBounds.plane`) and bounds
of the polish (`poses._pin_limits`).

Every expected score is a closed form: the weighted least-squares position on the pins' plane
(a unit Normal prior on the free axes of the set's own law, Normal offsets of variance 0.01
to its two Points), for both ways of assigning the Points, scored by the grammar's scorer."""

from __future__ import annotations

import numpy as np
import pytest

from ssgc.compile import compile_text
from ssgc.geometry import quat_to_matrix, rpy_to_quat
from ssgc.io.scene import Scene
from ssgc.parse.parser import Parser
from ssgc.parse.poses import refine_tree
from ssgc.score import score_trees
from ssgc.tree import Trees

GRAMMAR = """
grammar: partial_pin
root: {type: Root, pose: {xyz: XYZ, rpy_deg: RPY}}
types:
  Root:
    observed: true
    repeat:
      count: {probs: [0, 0.5, 0.5]}
      rule:
        child: Cluster
        translation: {LAW: {mean: [0, 0, 0], variance: 1.0PIN}}
  Cluster:
    and:
      - child: Point
        translation: {world_normal_offset: {mean: [0.2, 0, 0], variance: 0.01KID}}
      - child: Point
        translation: {world_normal_offset: {mean: [-0.2, 0, 0], variance: 0.01KID}}
  Point: {observed: true}
"""
MEANS = np.array([[0.2, 0.0, 0.0], [-0.2, 0.0, 0.0]])
# the scene of the hunt (/work/s36/fit/pinparse/s.json)
HUNT = [[0.012, 0.645, -0.014], [-0.37, 0.624, -0.084]]


def grammar_text(
    law: str, pin: str | None, child_pin: str | None = None, xyz=(0, 0, 0), rpy=(0, 0, 0)
) -> str:
    """The grammar, its root at (xyz, rpy in radians)."""
    text = GRAMMAR.replace("LAW", law).replace("PIN", f", pin: {pin}" if pin else "")
    text = text.replace("XYZ", str(list(xyz))).replace("RPY", str(np.degrees(rpy).tolist()))
    return text.replace("KID", f", pin: {child_pin}" if child_pin else "")


def make_scene(grammar, root_xyz, root_rpy, points) -> Scene:  # type: ignore[no-untyped-def]
    types = [grammar.type_id("Root")] + [grammar.type_id("Point")] * len(points)
    xyz = np.array([root_xyz, *points], float)
    # every rotation is `same` (the default): the root's
    quat = np.tile(rpy_to_quat(np.asarray(root_rpy, float)), (len(xyz), 1))
    return Scene("s", np.array(types, np.int64), xyz, quat)


def closed_form(origin, turn, pinned, points, child_z=None):  # type: ignore[no-untyped-def]
    """The best Cluster position for the Points in this order (the first at +0.2 in x):
    t = origin + turn u, u ~ N(0, I) on the law's free axes, 0 on its pinned ones; a Point
    pinned in z by its own rule (`child_z`) fixes t_z instead."""
    if child_z is not None:  # a world Normal without pins: z is the Points', x and y free
        origin, A = np.array([0.0, 0.0, child_z]), np.eye(3)[:, :2]
    else:
        A = turn[:, [a not in pinned for a in "xyz"]]  # the directions t may move in
    r = np.array(points) - MEANS - origin
    s = 100.0 * np.sum(r @ A, axis=0) / (1.0 + 200.0)  # the prior's mean: the origin
    return origin + A @ s


def best_tree_score(grammar, tree: Trees, origin, turn, pinned, child_z=None):  # type: ignore[no-untyped-def]
    """The closed-form best over both assignments of the Points, by the grammar's scorer,
    and its Cluster position: the parse's tree with its Points (in either order) and its
    Cluster moved there."""
    cluster = int(np.flatnonzero(tree.type == grammar.type_id("Cluster"))[0])
    kids = np.flatnonzero(tree.parent == cluster)
    kids = kids[np.argsort(tree.rule[kids])]  # rule 0 (+0.2) first
    best = (-np.inf, None)
    for order in (kids, kids[::-1]):
        points = tree.xyz[order]
        t = closed_form(origin, turn, pinned, points, child_z)
        xyz = tree.xyz.copy()
        xyz[kids] = points
        xyz[cluster] = t
        moved = Trees(tree.scene, tree.type, tree.parent, tree.rule, xyz, tree.quat, 1)
        score = float(score_trees(grammar, moved, marginal=True)[0])
        best = max(best, (score, tuple(t)), key=lambda b: b[0])
    return best


def test_the_hunts_cluster_pinned_in_z_is_placed_at_its_best_position():
    grammar = compile_text(grammar_text("world_normal", "[z]"))
    scene = make_scene(grammar, [0, 0, 0], [0, 0, 0], HUNT)
    for method in ("auto", "micp", "ip"):
        result = Parser(grammar, method=method).parse(scene, time_limit=20)
        parse = result.parses[0]
        score, t = best_tree_score(grammar, parse.tree, np.zeros(3), np.eye(3), "z")
        assert score == pytest.approx(5.1729, abs=1e-3)
        assert np.allclose(t, [-0.1781, 0.6313, 0.0], atol=1e-3)
        cluster = parse.tree.xyz[parse.tree.type == grammar.type_id("Cluster")][0]
        assert np.allclose(cluster, t, atol=1e-5), (method, cluster)
        assert parse.score == pytest.approx(score, abs=1e-6), method
        assert result.status == "optimal", (method, result.status, parse.gap)


CASES = [
    # (law, pin, root xyz, root rpy): a pin in the world or in the root's turned frame
    ("world_normal", "[z]", [0.1, -0.2, 0.05], [0.0, 0.0, 0.0]),
    ("world_normal", "[x]", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    ("world_normal", "[y]", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    ("world_normal_offset", "[z]", [0.1, -0.2, 0.05], [0.0, 0.0, 0.7]),
    ("parent_normal_offset", "[z]", [0.1, -0.2, 0.05], [0.0, 0.0, 0.7]),  # a world axis still
    ("parent_normal_offset", "[y]", [0.1, -0.2, 0.05], [0.0, 0.0, 0.4]),  # across x and y
    ("parent_normal_offset", "[z]", [0.1, -0.2, 0.05], [0.5, -0.2, 0.3]),  # a tilted plane
]


@pytest.mark.parametrize(("law", "pin", "root_xyz", "root_rpy"), CASES)
def test_a_latent_set_with_a_partly_pinned_own_law_is_certified_at_its_best(
    law, pin, root_xyz, root_rpy
):
    grammar = compile_text(grammar_text(law, pin, None, root_xyz, root_rpy))
    origin = np.zeros(3) if law == "world_normal" else np.array(root_xyz, float)
    turn = np.eye(3)
    if law == "parent_normal_offset":
        turn = quat_to_matrix(rpy_to_quat(np.array(root_rpy, float)))
    rng = np.random.default_rng(7)
    held = np.array([a in pin for a in "xyz"])
    true = origin + turn @ np.where(held, 0.0, [0.3, -0.2, 0.25])  # on the pins' plane
    points = true + MEANS + rng.normal(0.0, 0.05, (2, 3))
    scene = make_scene(grammar, root_xyz, root_rpy, points)
    for method in ("auto", "ip"):
        result = Parser(grammar, method=method).parse(scene, time_limit=20)
        parse = result.parses[0]
        score, t = best_tree_score(grammar, parse.tree, origin, turn, pin)
        assert np.isfinite(score)
        cluster = parse.tree.xyz[parse.tree.type == grammar.type_id("Cluster")][0]
        assert np.allclose(cluster, t, atol=1e-5), (method, cluster, t)
        assert parse.score == pytest.approx(score, abs=1e-6), (method, parse.score, score)
        assert result.status == "optimal", (method, result.status, parse.gap)


def test_points_pinned_in_z_below_a_latent_set_fix_its_height():
    """The child's law pins z: the set's height is the Points' (less the mean), its x and y
    the least-squares position; certified."""
    grammar = compile_text(grammar_text("world_normal", None, "[z]"))
    points = [[0.31, 0.52, 0.4], [-0.05, 0.61, 0.4]]
    scene = make_scene(grammar, [0, 0, 0], [0, 0, 0], points)
    for method in ("auto", "ip"):
        result = Parser(grammar, method=method).parse(scene, time_limit=20)
        parse = result.parses[0]
        score, _ = best_tree_score(grammar, parse.tree, None, None, "", child_z=0.4)
        assert np.isfinite(score)
        assert parse.score == pytest.approx(score, abs=1e-6), (method, parse.score, score)
        assert result.status == "optimal", (method, result.status, parse.gap)


@pytest.mark.parametrize(
    ("law", "pin", "root_rpy"),
    [("world_normal", "[z]", [0, 0, 0]), ("parent_normal_offset", "[x]", [0, 0, np.pi / 2])],
)
def test_refinement_moves_a_partly_pinned_set_along_its_pins(law, pin, root_rpy):
    """The exact polish (`refine_tree`, what `ip` and an uncertified tree get) holds a pinned
    axis as a bound and moves the free ones: from a pose on the pins it reaches the closed
    form (it stayed put: every step left the pinned plane, where the density is -inf)."""
    grammar = compile_text(grammar_text(law, pin, None, (0, 0, 0), root_rpy))
    scene = make_scene(
        grammar, [0, 0, 0], root_rpy, HUNT if pin == "[z]" else [[0.3, 0.1, 0.5], [-0.1, 0.2, 0.45]]
    )
    parse = Parser(grammar).parse(scene, time_limit=20).parses[0]
    turn = quat_to_matrix(rpy_to_quat(np.array(root_rpy, float)))
    best, t = best_tree_score(grammar, parse.tree, np.zeros(3), turn, pin)
    assert parse.score == pytest.approx(best, abs=1e-6)
    cluster = parse.tree.type == grammar.type_id("Cluster")
    xyz = parse.tree.xyz.copy()
    xyz[cluster] = 0.0  # the root's position: on the pins
    tree = parse.tree
    start = Trees(tree.scene, tree.type, tree.parent, tree.rule, xyz, tree.quat, 1)
    refined = refine_tree(grammar, start)
    assert np.allclose(refined.xyz[cluster][0], t, atol=1e-4)
    score = float(score_trees(grammar, refined, marginal=True)[0])
    assert score == pytest.approx(parse.score, abs=1e-6)
