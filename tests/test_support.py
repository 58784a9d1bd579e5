"""A geometry's `origin` in the grammar language, the container's floor and walls
(`inside_box` with `geometry: true`), and the physical reasons of `ssg explain`: floating, and
going through a floor or a wall (ssgc/support.py, docs/explain.md)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from ssgc.assets import load_shapes
from ssgc.cli.app import app
from ssgc.compile import compile_text, load_grammar
from ssgc.constraints.penetration import NonPenetration
from ssgc.constraints.pose import InsideBox
from ssgc.constraints.shapes import extents_of, frame_extents
from ssgc.explain import explain_tree, match_objects
from ssgc.export.glb import Z_UP_TO_Y_UP
from ssgc.geometry import axis_angle_to_quat, quat_rotate, quat_to_matrix
from ssgc.io.scene import Scene
from ssgc.parse.parser import Parser
from ssgc.support import findings

runner = CliRunner()

# A bin with plates on its floor and mugs on the plates; every dish's frame is at its base.
BIN = """
grammar: tub
root: {type: Tub, pose: {xyz: [0, 0, 0]}}
types:
  Tub:
    observed: true
    geometry: {box: {size: [0.6, 0.6, 0.3]}, origin: [0, 0, 0.15]}
    repeat:
      count: {probs: [0, 0.3, 0.4, 0.3]}
      rule:
        child: Plate
        translation: {world_normal_offset: {mean: [0, 0, 0], variance: [0.01, 0.01, 1], pin: [z]}}
        rotation: {world_bingham: {concentration: [300, 300, 0]}}
  Plate:
    observed: true
    geometry: {cylinder: {radius: 0.1, length: 0.02}, origin: [0, 0, 0.01]}
    repeat:
      count: {probs: [0.5, 0.5]}
      rule:
        child: Mug
        translation:
          parent_normal_offset: {mean: [0, 0, 0.02], variance: [0.001, 0.001, 1], pin: [z]}
        rotation: {world_bingham: {concentration: [300, 300, 0]}}
  Mug:
    observed: true
    geometry: {cylinder: {radius: 0.04, length: 0.1}, origin: [0, 0, 0.05]}
constraints:
  apart:
    non_penetration: {types: [Plate, Mug]}
  in_tub:
    inside_box:
      types: [Plate, Mug]
      frame: Tub
      min: [-0.3, -0.3, 0.0]
      max: [0.3, 0.3, null]
      geometry: true
"""
UP = np.array([1.0, 0, 0, 0])
FLIP = axis_angle_to_quat(np.array([1.0, 0, 0]), np.pi)


@pytest.fixture(scope="module")
def tub():
    return compile_text(BIN, "tub.yaml")


def tub_scene(g, moves=None) -> Scene:
    """Tub #0; plates #1 (at x -0.15) and #2 (x 0.15); mug #3 on plate #1."""
    xyz = np.array([[0, 0, 0], [-0.15, 0, 0], [0.15, 0, 0], [-0.15, 0, 0.02]], float)
    quat = np.tile(UP, (4, 1))
    for o, (dx, q) in (moves or {}).items():
        xyz[o] += dx
        quat[o] = q
    types = np.array([g.type_ids[n] for n in ("Tub", "Plate", "Plate", "Mug")])
    return Scene("tub", types, xyz, quat)


def explained(g, scene):
    parser = Parser(g)
    tree = parser.parse(scene, top=1).parses[0].tree
    return explain_tree(g, scene, tree, parser), match_objects(g, scene, tree), tree


# ------------------------------------------------------------------ the language ---


def test_origin_is_read_and_defaults_to_the_frame(tub) -> None:
    assert tub.types[tub.type_ids["Mug"]].geometry.origin == [0.0, 0.0, 0.05]
    g = compile_text(BIN.replace(", origin: [0, 0, 0.05]", ""), "tub.yaml")
    assert g.types[g.type_ids["Mug"]].geometry.origin == [0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    "bad, where, says",
    [
        ("origin: [0, 0, 0.05]}", "origin: [0, 0]}", "origin: must have at least 3 items"),
        ("origin: [0, 0, 0.05]}", "origin: [0, 0, .nan]}", "origin[2]: must be a finite number"),
        ("{cylinder: {radius: 0.04, length: 0.1}, ", "{", "expected a geometry: one of box"),
        ("origin: [0, 0, 0.05]}", "origin: [0, 0, 0.05], spin: 1}", "unknown key 'spin'"),
        ("      geometry: true\n", "      geometry: true\n      keep_out: true\n", "not both"),
    ],
)
def test_bad_origins_are_located_messages(tmp_path: Path, bad, where, says) -> None:
    path = tmp_path / "g.yaml"
    path.write_text(BIN.replace(bad, where, 1))
    result = runner.invoke(app, ["validate", str(path)])
    assert result.exit_code != 0
    assert says in result.output
    assert f"{path}:" in result.output and "Traceback" not in result.output


def test_a_container_box_needs_geometry(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    path.write_text(
        BIN.replace(
            "    geometry: {cylinder: {radius: 0.04, length: 0.1}, origin: [0, 0, 0.05]}\n", ""
        )
    )
    result = runner.invoke(app, ["validate", str(path)])
    assert result.exit_code != 0 and "'Mug' has no geometry to keep inside" in result.output


# --------------------------------------------------------- where geometry is placed ---


def test_extents_of_a_turned_base_anchored_cylinder(tub) -> None:
    ext = extents_of([t.geometry for t in tub.types])
    mug = tub.type_ids["Mug"]
    quats = np.array([UP, FLIP, axis_angle_to_quat(np.array([0, 1.0, 0]), np.pi / 2)])
    lo, hi = frame_extents(ext, np.full(3, mug), quat_to_matrix(quats))
    np.testing.assert_allclose(lo[:, 2], [0.0, -0.1, -0.04], atol=1e-12)  # up, flipped, lying
    np.testing.assert_allclose(hi[:, 2], [0.1, 0.0, 0.04], atol=1e-12)
    np.testing.assert_allclose(hi[2, 0], 0.1, atol=1e-12)  # lying along x from its base


def test_non_penetration_places_the_geometry_at_its_origin(tub) -> None:
    """A mug standing on a plate touches it; with centred cylinders it would sink into it."""
    scene = tub_scene(tub)
    batch = SimpleNamespace(
        xyz=scene.xyz,
        quat=scene.quat,
        type=scene.types,
        scene=np.zeros(4, np.int64),
        parent=np.full(4, -1),
        n_scenes=1,
    )

    def depth(g) -> float:
        check = next(c for c in g.constraints if isinstance(c, NonPenetration))
        i, j, dist = check.pair_distances(batch)
        pairs = zip(i.tolist(), j.tolist(), strict=True)
        return dict(zip(pairs, dist.tolist(), strict=True))[(1, 3)]

    assert abs(depth(tub)) < 1e-6  # resting: touching, not overlapping
    assert depth(compile_text(BIN.replace(", origin: [0, 0, 0.05]", ""), "tub.yaml")) < -0.02


def test_the_container_box_judges_the_whole_geometry(tub) -> None:
    box = next(c for c in tub.constraints if isinstance(c, InsideBox))
    parser = Parser(tub)
    for moves, inside in (
        ({}, True),
        ({2: ([0, 0, 0], FLIP)}, False),  # a flipped plate reaches 2 cm below its base
        ({2: ([0.1, 0, 0], UP)}, False),  # its rim goes 5 cm through the wall at x = 0.3
    ):
        scene = tub_scene(tub, moves)
        tree = parser.parse(scene, top=1).parses[0].tree
        assert (box.margin(tree)[0] >= 0) == inside


def export_one(tmp_path: Path, fmt: str) -> tuple[Path, Scene]:
    import json

    path = tmp_path / "g.yaml"
    path.write_text(BIN)
    g = load_grammar(path)
    q = axis_angle_to_quat(np.array([0, 1.0, 0]), np.pi / 2)
    scene = {
        "objects": [
            {"type": "Tub", "pose": {"xyz": [0, 0, 0]}},
            {"type": "Mug", "pose": {"xyz": [0.1, 0.2, 0.3], "quat_wxyz": q.tolist()}},
        ]
    }
    (tmp_path / "s.json").write_text(json.dumps(scene))
    out = tmp_path / fmt
    result = runner.invoke(
        app, ["export", str(tmp_path / "s.json"), "-g", str(path), "-f", fmt, "-o", str(out), "-q"]
    )
    assert result.exit_code == 0, result.output
    xyz = np.array([[0, 0, 0], [0.1, 0.2, 0.3]])
    return out, Scene("s", np.array([g.type_ids["Tub"], g.type_ids["Mug"]]), xyz, np.array([UP, q]))


def mug_centre(scene: Scene) -> np.ndarray:
    return scene.xyz[1] + quat_rotate(scene.quat[1], np.array([0, 0, 0.05]))  # at 0.15, 0.2, 0.3


def test_mujoco_puts_the_geometry_at_its_origin(tmp_path: Path) -> None:
    mujoco = pytest.importorskip("mujoco")
    out, scene = export_one(tmp_path, "mjcf")
    model = mujoco.MjModel.from_xml_path(str(next(out.glob("*.xml"))))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    np.testing.assert_allclose(
        data.geom_xpos[model.geom("Mug_1_geom").id], mug_centre(scene), atol=1e-9
    )
    np.testing.assert_allclose(data.geom_xpos[model.geom("Tub_0_geom").id], [0, 0, 0.15], atol=1e-9)


def test_drake_puts_the_geometry_at_its_origin(tmp_path: Path) -> None:
    pytest.importorskip("pydrake")
    from pydrake.multibody.parsing import Parser as DrakeParser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    out, _ = export_one(tmp_path, "sdf")
    builder = DiagramBuilder()
    plant, graph = AddMultibodyPlantSceneGraph(builder, 0.0)
    DrakeParser(plant).AddModels(str(next(out.glob("*.sdf"))))
    plant.Finalize()
    body = plant.GetBodyByName("body", plant.GetModelInstanceByName("Mug_1"))
    (geometry,) = plant.GetCollisionGeometriesForBody(body)
    at = graph.model_inspector().GetPoseInFrame(geometry).translation()
    np.testing.assert_allclose(at, [0, 0, 0.05], atol=1e-9)  # in the body's frame


def test_usd_and_gltf_put_the_geometry_at_its_origin(tmp_path: Path) -> None:
    pytest.importorskip("pxr")
    import trimesh
    from pxr import Usd, UsdGeom

    out, scene = export_one(tmp_path, "usd")
    stage = Usd.Stage.Open(str(next(out.glob("*.usda"))))
    m = np.array(
        UsdGeom.Xformable(
            stage.GetPrimAtPath("/World/Mug_1/geometry")
        ).ComputeLocalToWorldTransform(0)
    )
    np.testing.assert_allclose(m[3, :3], mug_centre(scene), atol=1e-9)
    out, scene = export_one(tmp_path, "glb")
    glb = trimesh.load(str(next(out.glob("*.glb"))))
    matrix, name = glb.graph.get("Mug_1")
    matrix = Z_UP_TO_Y_UP.T @ matrix  # glTF is +Y up: back to the scene's +Z up
    centre = matrix[:3, :3] @ glb.geometry[name].bounds.mean(axis=0) + matrix[:3, 3]
    np.testing.assert_allclose(centre, mug_centre(scene), atol=1e-6)


def test_shapes_carry_the_origin_into_mass_properties(tub) -> None:
    shapes = {s.type: s for s in load_shapes(tub).values()}
    np.testing.assert_allclose(shapes["Mug"].com, [0, 0, 0.05])
    np.testing.assert_allclose(shapes["Mug"].mesh.bounds[:, 2], [0.0, 0.1], atol=1e-9)


# -------------------------------------------------------------- physical reasons ---


def kinds_of(e, o: int) -> set[str]:
    return {r.kind for r in next(x for x in e.objects if x.index == o).reasons}


def test_a_settled_scene_has_no_physical_reason(tub) -> None:
    e, obj, tree = explained(tub, tub_scene(tub))
    assert findings(tub, tub_scene(tub), tree, obj) == []
    assert all(x.support == 0 for x in e.objects)


def test_a_mug_moved_off_its_plate_floats(tub) -> None:
    scene = tub_scene(tub, {3: ([0.0, 0.2, 0.0], UP)})  # still 2 cm up, over the empty floor
    e, _, _ = explained(tub, scene)
    mug = next(x for x in e.objects if x.index == 3)
    assert "floats" in kinds_of(e, 3) and mug.support > 0
    (reason,) = [r for r in mug.reasons if r.kind == "floats"]
    assert reason.text == "floats 2.0 cm above anything under it (in_tub)"
    assert e.objects[0].index == 3


def test_a_plate_turned_over_goes_through_the_floor(tub) -> None:
    scene = tub_scene(tub, {2: ([0, 0, 0], FLIP)})
    e, _, _ = explained(tub, scene)
    (reason,) = [r for r in next(x for x in e.objects if x.index == 2).reasons if r.kind == "floor"]
    assert reason.text == "goes 2.0 cm through the floor of Tub #0 (in_tub)"
    assert kinds_of(e, 1) & {"floor", "wall", "floats"} == set()


def test_a_plate_pushed_into_the_wall_goes_through_it(tub) -> None:
    scene = tub_scene(tub, {2: ([0.1, 0, 0], UP)})
    e, _, _ = explained(tub, scene)
    (reason,) = [r for r in next(x for x in e.objects if x.index == 2).reasons if r.kind == "wall"]
    assert reason.text == "goes 5.0 cm through a wall of Tub #0 (in_tub)"


def test_render_and_view_draw_the_geometry_at_its_origin(tub) -> None:
    from ssgc.render.scene import geometry_of
    from ssgc.view.page import _shapes

    vertices, _ = geometry_of(tub)["Mug"]
    np.testing.assert_allclose([vertices[:, 2].min(), vertices[:, 2].max()], [0.0, 0.1])
    drawn = np.array(_shapes(tub, ["Mug"])["Mug"]["vertices"])
    np.testing.assert_allclose([drawn[:, 2].min(), drawn[:, 2].max()], [0.0, 0.1], atol=1e-5)


PILE = """
grammar: pile
root: Bin
types:
  Bin:
    observed: true
    geometry: {tray: {size: [0.6, 0.6, 0.2], wall: 0.01}, origin: [0, 0, 0.1]}
    repeat:
      count: {probs: [1, 1, 1, 1, 1]}
      rule:
        child: Cyl
        translation: {world_box_offset: {min: [-0.3, -0.3, 0.0], max: [0.3, 0.3, 0.3]}}
        rotation: uniform
  Cyl:
    observed: true
    geometry: {cylinder: {radius: 0.05, length: 0.1}, origin: [0, 0, 0.05]}
constraints:
  apart: {non_penetration: {types: [Cyl]}}
  inbox:
    inside_box:
      types: [Cyl]
      frame: Bin
      min: [-0.29, -0.29, 0.01]
      max: [0.29, 0.29, null]
      geometry: true
"""


def test_a_float_over_a_far_object_is_its_true_distance() -> None:
    """A cylinder standing above one lying on the floor (the constraint hunt's scene): beyond
    the constraint's screen its bounding-sphere gap, a lower bound, was taken for the
    distance, so lifting it from 0.22 to 0.25 m turned a float of 16.1 cm into 5.7 cm."""
    g = compile_text(PILE, "pile.yaml")
    lying = axis_angle_to_quat(np.array([0.0, 1.0, 0.0]), np.pi / 2)
    floats = []
    for z in (0.2, 0.25, 0.3):
        xyz = np.array([[0, 0, 0], [0, 0, 0.04], [0.15, -0.15, z]], float)
        quat = np.array([UP, lying, UP])
        types = np.array([g.type_ids[n] for n in ("Bin", "Cyl", "Cyl")])
        e, _, _ = explained(g, Scene("pile", types, xyz, quat))
        reasons = next(x for x in e.objects if x.index == 2).reasons
        (reason,) = [r for r in reasons if r.kind == "floats"]
        floats.append(float(reason.text.split()[1]))
    assert floats == pytest.approx([14.4, 18.7, 23.2], abs=0.06)
