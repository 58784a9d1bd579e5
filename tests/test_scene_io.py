"""Scene files: the JSON format, tree round trips, and the real sink dataset."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from conftest import SINK_DATA
from scipy.spatial.transform import Rotation

from ssgc.errors import SceneError
from ssgc.io.scene import (
    dumps_scene,
    load_scenes,
    parse_scene_text,
    read_sink_yaml,
    scene_from_tree,
)
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees


def test_sink_dataset_reads_all_80_scenes(sink):
    scenes = read_sink_yaml(SINK_DATA, sink)
    assert len(scenes) == 80
    # 406 objects (plate 128, cup 139, bowl 139) plus the bin of each scene.
    assert sum(len(s) for s in scenes) == 406 + 80
    bin_id = sink.type_id("DishBin")
    assert all(int((s.types == bin_id).sum()) == 1 for s in scenes)
    sizes = np.bincount([len(s) - 1 for s in scenes])
    assert sizes[10] == 4 and sizes.max() == 16  # histogram of the reference report


def test_sink_rpy_is_drakes_fixed_axis_convention(sink):
    scene = read_sink_yaml(SINK_DATA, sink)[0]
    rpy = [-0.004306018339555129, 0.014380971273873657, -2.7679342144005084]
    expected = Rotation.from_euler("xyz", rpy).as_quat()  # extrinsic x-y-z = Rz Ry Rx
    q = scene.quat[1]
    assert np.allclose(np.abs(np.dot(q, np.roll(expected, 1))), 1.0, atol=1e-12)


def test_sink_unknown_model_is_a_located_error(sink, tmp_path):
    text = SINK_DATA.read_text().replace("Ecoforms_Plate_S20Avocado", "Mystery_Plate", 1)
    path = tmp_path / "scenes.yaml"
    path.write_text(text)
    with pytest.raises(SceneError) as exc:
        read_sink_yaml(path, sink)
    d = exc.value.diagnostics[0]
    assert d.line is not None and "Mystery_Plate" in d.message
    assert "no observed type has model" in d.message


def test_sampled_scene_round_trips_and_rescores(sink):
    trees, logp = sample_trees(sink, 20, seed=5)
    for i in range(20):
        scene = scene_from_tree(sink, trees.tree(i), f"s{i}", float(logp[i]))
        text = dumps_scene(sink, scene, seed=5, index=i)
        back = parse_scene_text(text, f"s{i}.json", sink)
        assert back.tree is not None
        assert score_trees(sink, back.tree)[0] == pytest.approx(logp[i], abs=1e-9)
        assert back.log_prob == logp[i]
        np.testing.assert_array_equal(back.types, scene.types)
        np.testing.assert_allclose(back.xyz, scene.xyz, atol=0)


def test_rpy_input_and_default_name(sink, tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(
        json.dumps(
            {
                "objects": [
                    {"type": "DishBin", "pose": {"xyz": [0.5, 0, 0], "rpy": [0, 0, 0]}},
                    {
                        "type": "MugColeHardwareClassicBlue",
                        "pose": {"xyz": [0.5, 0, 0.1], "rpy": [0, 0, 1.0]},
                    },
                ]
            }
        )
    )
    [scene] = load_scenes(path, sink)
    assert scene.name == "mine"
    assert np.allclose(scene.quat[1], [np.cos(0.5), 0, 0, np.sin(0.5)])


@pytest.mark.parametrize(
    ("text", "line", "fragment"),
    [
        (
            '{"objects": [\n  {"type": "Nope", "pose": {"xyz": [0, 0, 0]}}]}',
            2,
            "'Nope', which is not a type",
        ),
        ('{"objects": [\n  {"type": "Object", "pose": {"xyz": [0, 0, 0]}}]}', 2, "is not observed"),
        (
            '{"objects": [{"type": "DishBin",\n'
            ' "pose": {"xyz": [0, 0, 0], "quat_wxyz": [1, 1, 0, 0]}}]}',
            2,
            "unit norm",
        ),
        ('{"objects": [{"type": "DishBin",\n "pose": {"xyz": [0, 0]}}]}', 2, "at least 3"),
        (
            '{"objects": [{"type": "DishBin",\n "pose": {"xyz": [0, 0, 0]}, "typo": 1}]}',
            2,
            "unknown key 'typo'",
        ),
        ('{"objects": [\n  {"type": "DishBin",', 2, "invalid JSON"),
        ('{"objects": [{"type": "DishBin",\n "pose": {"xyz": [0, 0, NaN]}}]}', 2, "finite"),
        (  # a float64 step is 2e-6 m there: sampled scenes were proven infeasible
            '{"objects": [{"type": "DishBin",\n "pose": {"xyz": [1e10, 0, 0]}}]}',
            2,
            "within 1,000 km of the origin",
        ),
    ],
)
def test_bad_scenes_give_located_errors(sink, text, line, fragment):
    with pytest.raises(SceneError) as exc:
        parse_scene_text(text, "bad.json", sink)
    d = exc.value.diagnostics[0]
    assert fragment in d.message, d
    assert d.file == "bad.json" and d.line == line


def test_duplicate_json_key_is_located(sink):
    with pytest.raises(SceneError) as exc:
        parse_scene_text('{"objects": [],\n "objects": []}', "d.json", sink)
    d = exc.value.diagnostics[0]
    assert d.message == "invalid JSON: duplicate key 'objects'" and (d.line, d.column) == (2, 2)


def _sampled_doc(grammar: Any) -> dict[str, Any]:
    trees, logp = sample_trees(grammar, 1, seed=0)
    return json.loads(
        dumps_scene(grammar, scene_from_tree(grammar, trees.tree(0), "t", float(logp[0])))
    )


def test_objects_must_match_the_tree(sink):
    doc = _sampled_doc(sink)
    doc["objects"][-1]["pose"]["xyz"][0] += 0.5
    with pytest.raises(SceneError, match="observed nodes of `tree`"):
        parse_scene_text(json.dumps(doc), "t.json", sink)


def test_an_edited_object_is_named_with_the_way_out(sink):
    """A user who moves one object of a sampled scene learns which object disagrees with the
    tree and that deleting the tree lets the scene be parsed; the scene then reads."""
    doc = _sampled_doc(sink)
    k = len(doc["objects"]) - 1
    doc["objects"][k]["pose"]["xyz"][2] += 0.01
    text = json.dumps(doc, indent=1)
    with pytest.raises(SceneError) as exc:
        parse_scene_text(text, "t.json", sink)
    (d,) = exc.value.diagnostics
    name = doc["objects"][k]["type"]
    assert f"object {k} ({name}) is not at the pose of its node" in d.message
    assert "delete `tree`" in d.message
    starts = [n + 1 for n, line in enumerate(text.splitlines()) if line == "  {"]  # objects
    assert d.line == starts[k]
    del doc["tree"]
    scene = parse_scene_text(json.dumps(doc), "t.json", sink)
    assert scene.xyz[k, 2] == pytest.approx(doc["objects"][k]["pose"]["xyz"][2])


def test_objects_of_another_type_or_number_than_the_tree_are_named(sink):
    doc = _sampled_doc(sink)
    removed = json.loads(json.dumps(doc))
    removed["objects"].pop()
    with pytest.raises(SceneError, match=r"observed node\(s\), `objects` lists"):
        parse_scene_text(json.dumps(removed), "t.json", sink)
    k = len(doc["objects"]) - 1
    other = "DishBin" if doc["objects"][k]["type"] != "DishBin" else "Plate"
    doc["objects"][k]["type"] = other
    with pytest.raises(SceneError, match=f"object {k} is a {other}, its node"):
        parse_scene_text(json.dumps(doc), "t.json", sink)


def test_tree_with_wrong_rule_index_is_rejected(sink):
    trees, logp = sample_trees(sink, 1, seed=0)
    doc = json.loads(dumps_scene(sink, scene_from_tree(sink, trees.tree(0), "t", float(logp[0]))))
    doc["tree"]["nodes"][1]["rule"] = 7
    with pytest.raises(SceneError, match="has 1 rule"):
        parse_scene_text(json.dumps(doc), "t.json", sink)


@pytest.mark.parametrize(
    "field, value, fragment", [("type", "Objekt", "unknown type"), ("id", 9, "node ids")]
)
def test_a_node_with_a_bad_type_or_id_is_the_one_error(sink, field, value, fragment):
    """Its children's rules are not checked against a type it does not have: one error, at it."""
    doc = _sampled_doc(sink)
    nodes = doc["tree"]["nodes"]
    first = len(sink.types[0].rules)  # what a node wrongly taken as type 0 would allow
    k = next(n["parent"] for n in nodes if n.get("parent") and n["rule"] >= first)
    nodes[k][field] = value
    with pytest.raises(SceneError) as exc:
        parse_scene_text(json.dumps(doc), "t.json", sink)
    (d,) = exc.value.diagnostics
    assert fragment in d.message


def test_moved_object_scores_lower_and_impossible_pose_scores_minus_inf(sink):
    trees, _ = sample_trees(sink, 50, seed=1)
    tree = trees.tree(int(np.argmax([len(trees.tree(i)) for i in range(50)])))
    base = score_trees(sink, tree)[0]
    moved = type(tree)(
        **{
            **tree.__dict__,
            "xyz": tree.xyz + np.where(np.arange(len(tree))[:, None] == 1, 5.0, 0.0),
        }
    )
    # Node 1 hangs off the bin by a Normal offset: far away is much less likely, but possible.
    assert score_trees(sink, moved)[0] < base - 10
    # A child of an `or` with `same` translation moved by 1 cm is impossible.
    same_child = int(np.flatnonzero(tree.parent == 1)[0])
    xyz = tree.xyz.copy()
    xyz[same_child] += 0.01
    broken = type(tree)(**{**tree.__dict__, "xyz": xyz})
    assert score_trees(sink, broken)[0] == -np.inf


def test_a_tree_of_no_nodes_is_impossible_and_says_why(sink):
    """Every scene has the grammar's root: a tree with no nodes summed to log p = 0
    (probability 1) and had no reason to give."""
    from ssgc.score import explain

    scene = parse_scene_text('{"objects": [], "tree": {"nodes": []}}', "t.json", sink)
    assert score_trees(sink, scene.tree)[0] == -np.inf
    assert explain(sink, scene.tree) == [
        "the tree has 0 roots; a scene's tree has one, the grammar's root"
    ]
    assert explain(sink, sample_trees(sink, 1, seed=0)[0]) == []


def test_a_scene_with_no_object_and_its_tree_reads():
    """A grammar can make a scene without objects (a latent root, no child): its file, with
    the tree, reads back (the check that objects match the tree broadcast (0, 3) against
    (0,) and failed with a ValueError; found by `ssg parse` of generated grammars)."""
    from ssgc.compile import compile_text

    g = compile_text(
        "grammar: empty\nroot: L\ntypes:\n  L:\n    repeat:\n      count: {probs: [1.0]}\n"
        "      rule: {child: A}\n  A: {observed: true}\n"
    )
    trees, logp = sample_trees(g, 1, seed=0)
    text = dumps_scene(g, scene_from_tree(g, trees.tree(0), "t", float(logp[0])))
    scene = parse_scene_text(text, "t.json", g)
    assert len(scene) == 0 and scene.tree is not None


def test_a_root_far_from_the_origin_is_refused_and_one_at_the_limit_is_not():
    from ssgc.compile import compile_text
    from ssgc.errors import GrammarError

    text = "grammar: far\nroot: {type: R, pose: {xyz: [%s, 0, 0]}}\ntypes:\n  R: {observed: true}\n"
    compile_text(text % "1e6", "far.yaml")
    with pytest.raises(GrammarError) as info:
        compile_text(text % "-1.5e6", "far.yaml")
    assert "within 1,000 km of the origin" in str(info.value)
    assert info.value.diagnostics[0].line == 2
