"""Objects pinned on a latent surface in its frame: the surface's tilt and height follow them.

A child's parent-frame Normal with a `pin` puts the child on a plane of its latent parent;
several such children lie on one plane, which fixes the parent's tilt, and a pinned world
axis of the parent's own rule fixes where on its line it stands.  Before, the hard-law poses
projected a set onto its children's planes and off its own pinned world axes (every pose
refused), a pose was solved from at most two children (the others off their planes), and
refinement kept the rotation the proposals gave (any turn moved a child off its pin): a
shelf with three or four boxes had no parse, with one or two it parsed 1.5–80 nats below its
sampled tree.  Now the hard laws turn the set so the planes are parallel and meet its own
pinned axes (`hard_laws._turn_pin_normals`, `_flat_axes`), solve from every pinned child of
a `repeat` at once (`proposals._many_pinned`), and refinement moves such a set on the planes
(`poses.PinPlanes`).
"""

from __future__ import annotations

import numpy as np
from grammar_text import grammar_from_text

import ssgc
from ssgc.geometry import quat_rotate
from ssgc.parse.hard_laws import nearest_unit_solution

SHELF = """\
grammar: shelf
root: Room
types:
  Room:
    and:
    - child: Shelf
      translation: {world_normal: {mean: [0, 0, 1.0], variance: [0.5, 0.5, 0.0], pin: [z]}}
      rotation: {world_bingham: {concentration: [50, 50, 0]}}
  Shelf:
    repeat:
      count: {probs: [0, 1, 1, 1, 1]}
      rule:
        child: Box
        translation: {parent_normal_offset: {mean: [0, 0, 0.05], variance: [0.1, 0.02, 0],
                      pin: [z]}}
        rotation: {parent_bingham: {concentration: [200, 200, 0]}}
  Box: {observed: true}
"""


# two such shelves of three boxes each: any three boxes lie on some plane, so the boxes of one
# shelf must be told from a mix (`proposals._near_trios`: the trios closest together first)
SHELVES = """\
grammar: shelves
root: Room
types:
  Room:
    repeat:
      count: {probs: [0, 0, 1]}
      rule:
        child: Shelf
        translation: {world_normal: {mean: [0, 0, 1.0], variance: [0.5, 0.5, 0.0], pin: [z]}}
        rotation: {world_bingham: {concentration: [50, 50, 0]}}
  Shelf:
    repeat:
      count: {probs: [0, 0, 0, 1]}
      rule:
        child: Box
        translation: {parent_normal_offset: {mean: [0, 0, 0.05], variance: [0.1, 0.02, 0],
                      pin: [z]}}
        rotation: {parent_bingham: {concentration: [200, 200, 0]}}
  Box: {observed: true}
"""


# a place setting pinned in height in its seat's frame, its plate pinned on it and turned by
# a revolute (the realistic-grammar hunt's dining table, reduced)
SETTING = """\
grammar: setting
root: {type: Seat}
types:
  Seat:
    and:
      - child: Setting
        translation: {parent_normal_offset: {mean: [0.25, 0, 0.76], variance: [0.002, 0.004, 0],
                      pin: [z]}}
        rotation: {parent_bingham: {concentration: [10000, 10000, 50]}}
  Setting:
    and:
      - child: Plate
        translation: {parent_normal_offset: {mean: [0, 0, 0.01], variance: [0.0004, 0.0004, 0],
                      pin: [z]}}
        rotation: {revolute: {axis: [0, 0, 1]}}
  Plate: {observed: true}
"""


def test_a_shelf_of_boxes_parses_to_its_sampled_tree(tmp_path):
    """Seed 7's four scenes hold 4, 1, 3 and 2 boxes, and parsed to no parse, −88, no parse,
    no parse; each now at least as high as the tree it was sampled from (the scenes of 1 and
    3 boxes here, for the default run's time; all four measured in 1e7e71d)."""
    g = grammar_from_text(tmp_path, SHELF)
    scenes = g.sample(4, seed=7)
    assert [len(s.types) for s in scenes] == [4, 1, 3, 2]
    for scene in scenes[1:3]:  # the planes in refinement (1 box) and the trios (3 boxes)
        result = ssgc.parse(g, scene, time_limit=120)
        assert result.status in ("optimal", "feasible"), result.status
        assert result.best.score >= scene.log_prob - 1e-6, (result.best.score, scene.log_prob)
        tree = result.best.tree.trees
        shelf = int(np.flatnonzero(tree.type == g.ir.type_id("Shelf"))[0])
        assert abs(tree.xyz[shelf, 2] - 1.0) <= 1e-9  # its own pinned height holds
        boxes = np.flatnonzero(tree.parent == shelf)  # and every box its pin in its frame
        inverse = np.broadcast_to(tree.quat[shelf] * [1.0, -1.0, -1.0, -1.0], (len(boxes), 4))
        local = quat_rotate(inverse, tree.xyz[boxes] - tree.xyz[shelf])
        np.testing.assert_allclose(local[:, 2], 0.05, atol=1e-6)


def test_two_shelves_of_three_boxes_parse_to_their_sampled_tree(tmp_path):
    """Before: no parse; with all candidate boxes at once, or in index order, trios mixing
    the shelves: 40–80 nats below."""
    g = grammar_from_text(tmp_path, SHELVES)
    for scene in g.sample(1, seed=7):
        assert len(scene.types) == 6
        result = ssgc.parse(g, scene, time_limit=120)
        assert result.status in ("optimal", "feasible"), result.status
        assert result.best.score >= scene.log_prob - 1e-6, (result.best.score, scene.log_prob)


def test_a_setting_pinned_in_its_seat_s_frame_follows_its_plate(tmp_path):
    """The setting's own pin is a plane in its parent's frame: the hard-law poses moved it
    onto its plate's plane and off its own (no parse in all four scenes), and refinement
    did not keep it there (scenes 1 and 3 below their sampled trees)."""
    g = grammar_from_text(tmp_path, SETTING)
    for scene in g.sample(4, seed=7)[1::2]:  # 1 and 3: below their sampled trees without
        result = ssgc.parse(g, scene, time_limit=60)
        assert result.status in ("optimal", "feasible"), result.status
        assert result.best.score >= scene.log_prob - 1e-6, (result.best.score, scene.log_prob)


def test_nearest_unit_solution_is_square_to_the_differences():
    """Three points on a tilted plane: the unit normal nearest a given one is the plane's."""
    normal = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(3, 3))
    pts -= np.outer(pts @ normal, normal)  # onto the plane through the origin
    d = pts[1:] - pts[0]
    got = nearest_unit_solution(d, np.zeros(2), np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(got[0], normal, atol=1e-9)
    np.testing.assert_allclose(got[1], -normal, atol=1e-9)
    # two points: the nearest unit vector square to their difference, from the given one
    one = nearest_unit_solution(d[:1], np.zeros(1), np.array([[0.0, 0.0, 1.0]]))[0]
    assert abs(one @ d[0]) <= 1e-9 and abs(np.linalg.norm(one) - 1.0) <= 1e-12
    # a difference in the means: n·d = delta
    shifted = nearest_unit_solution(d[:1], np.array([0.05]), np.array([[0.0, 0.0, 1.0]]))[0]
    assert abs(shifted @ d[0] - 0.05) <= 1e-9 and abs(np.linalg.norm(shifted) - 1.0) <= 1e-12
