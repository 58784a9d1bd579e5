"""`ssg explain` on latent nodes with poses of their own, clutter, rare rotations, and scenes
too small for a count law (docs/explain.md; the findings of session 35's bug hunt)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.explain import diagnose, explain, explain_tree, match_objects, pose_gains
from ssgc.io.scene import Scene, scene_from_tree
from ssgc.parse.parser import Parser
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees

RUNNER = CliRunner()


def scene_of(g, name: str, objects: list[tuple[str, list[float]]], quat=None) -> Scene:
    """A scene of (type, xyz) objects, all unturned unless `quat` gives their rotations."""
    types = np.array([g.type_ids[t] for t, _ in objects])
    xyz = np.array([x for _, x in objects], float)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(objects), 1)) if quat is None else np.asarray(quat)
    return Scene(name, types, xyz, q)


def by_index(e) -> dict:
    return {o.index: o for o in e.objects}


# -------------------------------------------- 1. empty latent nodes with a pose ---

TRAY = """
grammar: g9
root: {type: Table, pose: {xyz: [0, 0, 0]}}
types:
  Table:
    observed: true
    and:
      - child: Tray
        translation: {parent_normal_offset: {mean: [0, 0, 1.0], variance: 0.01}}
  Tray:
    repeat:
      count: {probs: [0.5, 0.5]}
      rule:
        child: Cup
        translation: {parent_normal_offset: {mean: [0, 0, 0], variance: 0.0004}}
  Cup: {observed: true}
"""

GROUPS = """
grammar: g5
root: {type: Table, pose: {xyz: [0, 0, 0]}}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0, COUNT]}
      rule:
        child: Group
        translation:
          parent_normal_offset: {mean: [0, 0, 1.0], variance: [0.01, 0.01, 0], pin: [z]}
        rotation: same
  Group:
    repeat:
      count: {probs: [GROUP]}
      rule:
        child: Cup
        translation:
          parent_normal_offset: {mean: [0, 0, 0], variance: [0.0004, 0.0004, 0], pin: [z]}
        rotation: same
  Cup: {observed: true}
"""


def groups(count: str = "0.5, 0.5", group: str = "0, 0.5, 0.5"):
    return compile_text(GROUPS.replace("COUNT", count).replace("GROUP", group))


def test_an_empty_latent_node_with_a_pose_counts_nothing(tmp_path):
    """The scorer integrates an unseen node's pose out (docs/conventions.md): its edge counts
    0, so it has no position reason, and the shares sum to −log p (log 2: the empty tray)."""
    g = compile_text(TRAY)
    scene = scene_of(g, "t9", [("Table", [0, 0, 0])])
    e = explain(g, scene)
    assert e.log_prob == pytest.approx(-np.log(2))
    assert sum(o.share for o in e.objects) == pytest.approx(np.log(2))
    assert [r.kind for r in e.objects[0].reasons] == ["count"]
    grammar, path = tmp_path / "g9.yaml", tmp_path / "t9.json"
    grammar.write_text(TRAY)
    path.write_text('{"name": "t9", "objects": [{"type": "Table", "pose": {"xyz": [0, 0, 0]}}]}')
    result = RUNNER.invoke(app, ["explain", str(path), "-g", str(grammar), "--json"])
    assert result.exit_code == 0, result.stderr
    assert json.loads(result.stdout)["scenes"][0]["neg_log_prob"] == pytest.approx(np.log(2))


def test_sampled_trees_with_empty_groups_explain_to_their_score():
    """Trees sampled from a grammar whose groups may hold nothing: every share sums to the
    scorer's −log p, and no unseen edge is a reason."""
    g = groups(count="0, 1", group="0.3, 0.35, 0.35")
    trees, _ = sample_trees(g, 40, 3)
    empty = 0
    for i in range(40):
        tree = trees.tree(i)
        scene = scene_from_tree(g, tree, f"s{i}")
        e = explain_tree(g, scene, tree)
        score = float(score_trees(g, tree)[0])
        assert sum(o.share for o in e.objects) + e.unattributed == pytest.approx(-score)
        group = np.flatnonzero(tree.type == g.type_ids["Group"])
        empty += int(np.sum(~np.isin(group, tree.parent)))
    assert empty > 0  # some sampled tree had an empty group


# ------------------------------------------------- 2. latent parents move along ---

SLOTS = """
grammar: g4
root: {type: Table, pose: {xyz: [0, 0, 0]}}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0, 0.5, 0.5]}
      rule:
        child: Slot
        translation:
          parent_normal_offset:
            mean: [0, 0, 1.0]
            covariance: [[0.04, 0.03, 0], [0.03, 0.09, 0], [0, 0, 0]]
            pin: [z]
        rotation: same
  Slot:
    or:
      - child: Cup
        p: 0.6
        translation: same
        rotation: {parent_bingham: {concentration: [100, 100, 0]}}
      - child: Cup
        p: 0.4
        translation: {offset: [0, 0, 0.1]}
        rotation: {revolute: {axis: [0, 0, 1], min: 0, max: 1.5707963267948966}}
  Cup: {observed: true}
"""


def slots_far(g) -> Scene:
    """Cup #1 1 m off the table's mode (m² = 33.3 under the slot's covariance)."""
    yaw = np.pi / 4
    turned = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
    quat = [[1.0, 0, 0, 0], [1.0, 0, 0, 0], turned]
    objects = [("Table", [0, 0, 0]), ("Cup", [1.0, 0, 1.0]), ("Cup", [-0.1, 0.2, 1.1])]
    return scene_of(g, "g4far", objects, quat)


def groups_far(g) -> Scene:
    """Cup #1 alone in a group 0.6 m off the table's mode (5.8σ), two cups 2σ apart."""
    objects = [("Table", [0, 0, 0]), ("Cup", [0.6, 0, 1.0])]
    objects += [("Cup", [0, 0.04, 1.0]), ("Cup", [0, -0.04, 1.0])]
    return scene_of(g, "g5t", objects)


def local_gain(g, scene: Scene, o: int) -> float:
    """Object o's pose gain on the scene's best tree, without re-parses; it never claims more
    than moving the object can give: the scene with object o at its repaired pose parses at
    least that much better."""
    parser = Parser(g)
    best = parser.parse(scene, top=1).parses[0]
    fix = pose_gains(g, best.tree, match_objects(g, scene, best.tree))[o]
    if not fix.poses:  # no move raises the score
        return fix.gain
    xyz, quat = scene.xyz.copy(), scene.quat.copy()
    xyz[o], quat[o] = fix.poses[0]
    better = parser.parse(replace(scene, xyz=xyz, quat=quat), top=1).parses[0].score
    assert better - best.score >= fix.gain - 1e-6
    return fix.gain


def test_a_cup_whose_latent_slot_is_misplaced_gains_the_slots_move():
    """The slot places its cup at its own position (`translation: same`): moving the cup
    alone is impossible, so the slot moves with it, and the cup gains m²/2 ≈ 16.7 nats."""
    g = compile_text(SLOTS)
    assert local_gain(g, slots_far(g), 1) == pytest.approx(33.3 / 2, abs=0.2)
    e = explain(g, slots_far(g))
    assert by_index(e)[1].pose_gain == pytest.approx(33.3 / 2, abs=0.2)
    assert e.objects[0].index == 1


def test_a_cup_alone_in_a_misplaced_group_ranks_first():
    """Cup #1 is 5.8σ off where the table places its group: moving it (its group along) to
    the mode gains the group's edge (≈ 16.8) and then its own (≈ 0.7), above the 2σ cups;
    parsed again with the cup moved, the scene gains more (its groups rearranged)."""
    g = groups()
    gain = local_gain(g, groups_far(g), 1)
    assert 16.8 < gain < 17.6
    e = explain(g, groups_far(g))
    assert by_index(e)[1].pose_gain >= gain
    assert e.objects[0].index == 1
    assert all(o.unusual < 4 for o in e.objects[1:])


def test_a_cup_of_a_shared_group_gets_its_own_edge_not_its_groups():
    """Two cups share a group that the table placed far off (14.5 nats): moving one cup
    cannot fix the group (the other cup holds it there), so neither cup gains that much."""
    g = groups(count="1")
    objects = [("Table", [0, 0, 0]), ("Cup", [0.6, 0.02, 1.0]), ("Cup", [0.6, -0.02, 1.0])]
    assert local_gain(g, scene_of(g, "shared", objects), 1) < 1.0
    e = explain(g, scene_of(g, "shared", objects))
    assert all(o.pose_gain < 2.0 for o in e.objects)


# ---------------------------------------------------------------- 3. clutter ---

CLUTTER = """
grammar: g1
root: {type: Table, pose: {xyz: [0, 0, 0]}}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0.1, 0.5, 0.4]}
      rule:
        child: Mug
        translation:
          parent_normal_offset: {mean: [0, 0, 1.0], variance: [0.01, 0.04, 0.09]}
        rotation: {world_bingham: {mode: {rpy_deg: [0, 0, 0]}, concentration: [50, 50, 0]}}
  Mug:
    observed: true
  Spoon: {observed: true}
observation:
  clutter:
    region: {min: [-1, -1, 0], max: [1, 1, 2]}
    rates: {Spoon: 0.1}
"""


def clutter_scene(g) -> Scene:
    objects = [("Table", [0, 0, 0]), ("Mug", [0.05, 0, 1]), ("Mug", [0.25, 0.1, 1.1])]
    objects += [("Spoon", [0.3, 0, 1]), ("Spoon", [-0.5, 0.2, 0.4]), ("Spoon", [0.7, -0.3, 1.5])]
    return scene_of(g, "clut3", objects)


def test_the_clutter_count_goes_to_the_clutter_objects():
    """Without noise the table shares the root's pose with the clutter set; the count of
    clutter objects is still theirs (docs/explain.md, "Unexplained objects")."""
    g = compile_text(CLUTTER)
    e = explain(g, clutter_scene(g))
    objects = by_index(e)
    count = [(o.index, r) for o in e.objects for r in o.reasons if r.rule == "~clutter"]
    assert sorted(i for i, r in count if r.kind == "count") == [3, 4, 5]
    for i in (3, 4, 5):
        assert objects[i].unexplained
        part = next(r for r in objects[i].reasons if r.kind == "count")
        assert part.share == pytest.approx(-part.log_prob / 3)
        position = next(r for r in objects[i].reasons if r.kind == "position")
        assert "Table" not in position.text
    assert not any("clutter" in r.rule for r in objects[0].reasons)
    assert objects[0].unusual < 1.0
    assert sum(o.share for o in e.objects) == pytest.approx(-e.log_prob)


# ---------------------------------------------------------- 4. rare rotations ---

SHELF = """
grammar: kitchen_shelf
root:
  type: Shelf
  pose: {xyz: [1.0, 0.0, 1.2], rpy_deg: [0, 0, 90]}
types:
  Shelf:
    observed: true
    repeat:
      count: {geometric: {p: 0.4, max: 4}}
      rule:
        child: Mug
        translation:
          parent_normal_offset: {mean: [0, 0, 0.06], variance: [0.003, 0.04, 0], pin: [z]}
        rotation: {revolute: {axis: [0, 0, 1]}}
  Mug:
    observed: true
    independent:
      - child: Spoon
        p: 0.3
        translation: {offset: [0, 0, 0.07]}
        rotation: {parent_bingham: {mode: {rpy_deg: [20, 0, 0]}, concentration: [100, 100, 0]}}
  Spoon:
    or:
      - {child: Teaspoon, p: 0.7}
      - {child: SoupSpoon, p: 0.3}
  Teaspoon: {observed: true}
  SoupSpoon: {observed: true}
"""
SHELF_SPOONS = {  # the teaspoon's rotation in the scenes of the bug hunt
    "ty40": [0.6123724356957947, -0.1227878039689728, 0.35355339059327373, 0.696364240320019],
    "tx180": [-0.1227878039689728, 0.696364240320019, 0.6963642403200189, -0.12278780396897278],
}


def shelf_scene(g, name: str) -> Scene:
    half = np.sqrt(0.5)
    objects = [("Shelf", [1.0, 0.0, 1.2]), ("Mug", [0.8, 0.1, 1.26]), ("Mug", [1.0, 0.0, 1.26])]
    objects += [("Teaspoon", [1.0, 0.0, 1.33])]
    quat = [[half, 0, 0, half], [0.5, 0, 0, np.sqrt(0.75)], [half, 0, 0, half]]
    return scene_of(g, name, objects, [*quat, SHELF_SPOONS[name]])


def spoon_rotation(e):
    spoon = by_index(e)[3]
    return next(r for r in spoon.reasons if r.kind == "rotation")


def test_a_rare_rotation_gets_its_tail_not_zero():
    """A teaspoon tilted 40° off a [100, 100, 0] Bingham's circle of modes: P(a draw is no
    more likely) ≈ 8.3e-6 (10⁷ draws), beyond the plain Monte Carlo's 4000 draws."""
    g = compile_text(SHELF)
    r = spoon_rotation(explain(g, shelf_scene(g, "ty40")))
    assert r.percentile == pytest.approx(8.3e-6, rel=0.1)
    assert not r.percentile_bound
    assert "0.0008% likely" in r.text


def test_the_least_likely_rotation_gets_an_honest_bound(tmp_path):
    """Upside down is the law's least likely rotation: no draw is rarer, so the percentile is
    the bound exp(log p)·π² (the volume of SO(3)), said as such in the text and the JSON."""
    g = compile_text(SHELF)
    e = explain(g, shelf_scene(g, "tx180"))
    r = spoon_rotation(e)
    assert r.percentile_bound
    assert r.percentile == pytest.approx(np.exp(r.log_prob) * np.pi**2, rel=1e-9)
    assert 0 < r.percentile < 1e-40
    assert "< 3.7e-40% likely" in r.text
    doc = e.to_json()["objects"][0]["reasons"]
    assert next(x for x in doc if x["kind"] == "rotation")["percentile_bound"] is True


# ---------------------------------------------------------------- 5. diagnose ---

AT_LEAST_ONE = """
grammar: g6
root: {type: Table, pose: {xyz: [0, 0, 0]}}
types:
  Table:
    observed: true
    repeat:
      count: {geometric: {p: 0.5, max: 3, start: 1}}
      rule:
        child: Mug
        translation:
          parent_normal_offset: {mean: [0, 0, 1.0], variance: [0.01, 0.04, 0.09]}
        rotation: {world_bingham: {mode: {rpy_deg: [0, 0, 0]}, concentration: [50, 50, 0]}}
  Mug:
    observed: true
"""


def test_a_scene_too_small_for_a_count_law_names_the_law():
    g = compile_text(AT_LEAST_ONE)
    d = diagnose(g, scene_of(g, "one", [("Table", [0, 0, 0])]))
    assert "Table #0" in d.message
    assert "Table holds at least 1 Mug (its count law), and the scene has none" in d.message
    assert d.reasons[0] == ["Table holds at least 1 Mug (its count law), and the scene has none"]


PLATES = """
grammar: g7
root: {type: Table, pose: {xyz: [0, 0, 0]}}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0.5, 0.5]}
      rule:
        child: Plate
        translation:
          parent_normal_offset: {mean: [0, 0, 1.0], variance: [0.04, 0.04, 0], pin: [z]}
        rotation: same
  Plate:
    observed: true
    or:
      - child: Mug
        p: 0.7
        translation:
          parent_normal_offset: {mean: [0, 0, 0.02], variance: [0.0004, 0.0004, 0], pin: [z]}
        rotation: same
      - child: Spoon
        p: 0.3
        translation:
          parent_normal_offset: {mean: [0, 0, 0.01], variance: [0.0004, 0.0004, 0], pin: [z]}
        rotation: same
  Mug: {observed: true}
  Spoon: {observed: true}
"""


def test_a_child_off_a_removed_parent_is_named_with_its_pinned_axis():
    """Plate and spoon go together; the spoon is 1 cm above its pinned height over the plate,
    which is the reason, not "no Plate among the other objects"."""
    g = compile_text(PLATES)
    objects = [("Table", [0, 0, 0]), ("Plate", [0.2, 0, 1.0]), ("Spoon", [0.2, 0, 1.02])]
    d = diagnose(g, scene_of(g, "g7t", objects))
    assert d.objects == [1, 2]
    assert d.reasons[2][0] == "Plate[1]->Spoon from Plate #1: pinned axis z off by +0.01 m"
    assert "Hint: poses from a sensor are never exact" in d.message


# ------------------------------------------------- 6. validate and clutter types ---


def test_a_type_made_only_by_clutter_is_reachable():
    assert not [w for w in compile_text(CLUTTER).warnings if "unreachable" in w.message]


def test_validate_keeps_warning_about_a_truly_unreachable_type(tmp_path: Path):
    text = CLUTTER.replace("  Spoon: {observed: true}", "  Spoon: {observed: true}\n  Fork: {}")
    warnings = [w.message for w in compile_text(text).warnings]
    assert warnings == ["type 'Fork' is unreachable from the root"]
