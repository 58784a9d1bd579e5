"""Exports load in their real consumers, with every object where the scene puts it.

Each format is read back by the tool it is for (pydrake from the `drake` wheel, MuJoCo,
trimesh, usd-core: the `test` extra) and every object's position and rotation is compared
with the scene JSON.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAMMARS
from test_settle import GRAMMAR as DROP
from typer.testing import CliRunner

from ssgc.assets import load_shapes
from ssgc.cli.app import app
from ssgc.compile import compile_text, load_grammar
from ssgc.errors import GrammarError
from ssgc.geometry import quat_to_matrix
from ssgc.io.resume import MANIFEST
from ssgc.io.scene import scene_stem

runner = CliRunner()
DIMSUM = GRAMMARS / "dimsum_table.yaml"
N_SCENES = 3
TOL = 1e-6


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Sampled dimsum tables, with every format exported by `ssg sample --export`."""
    root = tmp_path_factory.mktemp("export")
    formats = [a for f in ("dmd", "sdf", "mjcf", "glb", "usd") for a in ("--export", f)]
    result = run("sample", DIMSUM, "-n", N_SCENES, "--seed", 3, "-o", root, "-q", *formats)
    assert result.exit_code == 0, result.output
    return root


def expected(root: Path, name: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Object id -> (position, rotation matrix) from the scene JSON."""
    doc = json.loads((root / f"{name}.json").read_text())
    return {
        f"{o['type']}_{i}": (np.array(o["pose"]["xyz"]), quat_to_matrix(o["pose"]["quat_wxyz"]))
        for i, o in enumerate(doc["objects"])
    }


def assert_same_poses(got: dict, want: dict) -> None:
    assert set(got) == set(want)
    for name, (xyz, rot) in want.items():
        np.testing.assert_allclose(got[name][0], xyz, atol=TOL, err_msg=name)
        np.testing.assert_allclose(got[name][1], rot, atol=TOL, err_msg=name)


def scene_names(root: Path) -> list[str]:
    names = sorted(p.stem for p in root.glob("*.json"))
    assert len(names) == N_SCENES
    return names


def drake_plant():  # type: ignore[no-untyped-def]
    """A MultibodyPlant with a SceneGraph, as users build one: a bare MultibodyPlant(0.0)
    skips every <visual> and <collision>, and missed that Drake refused each mesh's
    <drake:declare_convex/> where the exports put it."""
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    return AddMultibodyPlantSceneGraph(DiagramBuilder(), 0.0)  # (plant, scene_graph)


def drake_poses(plant, names) -> dict:  # type: ignore[no-untyped-def]
    context = plant.CreateDefaultContext()
    poses = {}
    for name in names:
        body = plant.GetBodyByName("body", plant.GetModelInstanceByName(name))
        pose = plant.EvalBodyPoseInWorld(context, body)
        poses[name] = (pose.translation(), pose.rotation().matrix())
    return poses


def test_drake_model_directives_load_into_a_plant(exported: Path) -> None:
    from pydrake.multibody.parsing import LoadModelDirectives, Parser, ProcessModelDirectives

    for name in scene_names(exported):
        plant, _ = drake_plant()
        parser = Parser(plant)
        parser.package_map().AddPackageXml(str(exported / "dmd" / "package.xml"))
        directives = LoadModelDirectives(str(exported / "dmd" / f"{name}.dmd.yaml"))
        ProcessModelDirectives(directives, plant, parser)
        plant.Finalize()
        want = expected(exported, name)
        assert_same_poses(drake_poses(plant, want), want)
        # Fixed objects are welded (no floating base), free ones float.
        for body_name in want:
            body = plant.GetBodyByName("body", plant.GetModelInstanceByName(body_name))
            assert body.is_floating_base_body() == (not body_name.startswith("Table")), body_name
            assert body.default_mass() > 0


def test_sdformat_world_loads_in_drakes_parser(exported: Path) -> None:
    from pydrake.multibody.parsing import Parser

    for name in scene_names(exported):
        plant, _ = drake_plant()
        Parser(plant).AddModels(str(exported / "sdf" / f"{name}.sdf"))
        plant.Finalize()
        want = expected(exported, name)
        assert_same_poses(drake_poses(plant, want), want)


def test_mjcf_compiles_in_mujoco_with_free_joints(exported: Path) -> None:
    import mujoco

    for name in scene_names(exported):
        model = mujoco.MjModel.from_xml_path(str(exported / "mjcf" / f"{name}.xml"))
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        want = expected(exported, name)
        got = {
            model.body(i).name: (data.xpos[i].copy(), data.xmat[i].reshape(3, 3).copy())
            for i in range(1, model.nbody)
        }
        assert_same_poses(got, want)
        free = {model.body(model.jnt_bodyid[j]).name for j in range(model.njnt)}
        assert free == {n for n in want if not n.startswith("Table")}
        assert model.jnt_type.tolist() == [mujoco.mjtJoint.mjJNT_FREE] * model.njnt


# test_settle's tray with a ball 2 cm into it, its block made a cylinder: primitives only.
PRIMITIVES = DROP.replace("box: {size: [0.1, 0.1, 0.08]}", "cylinder: {radius: 0.03, length: 0.08}")


def test_mjcf_primitives_are_visible_in_mujocos_viewer_and_still_collide(tmp_path: Path) -> None:
    """A primitive body had only its collision geom, in group 3, which MuJoCo's viewer hides
    (it shows groups 0-2): the table and trays were invisible. Each body now also has a visual
    geom (group 1, no contacts), as mesh bodies have."""
    import mujoco

    grammar = tmp_path / "prims.yaml"
    grammar.write_text(PRIMITIVES)
    out = tmp_path / "s"
    result = run("sample", grammar, "-n", 1, "--seed", 0, "-o", out, "-q", "--export", "mjcf")
    assert result.exit_code == 0, result.output
    model = mujoco.MjModel.from_xml_path(str(out / "mjcf" / "drop_000000.xml"))
    shown = mujoco.MjvOption().geomgroup
    collides = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
    for body in range(1, model.nbody):
        geoms = np.flatnonzero(model.geom_bodyid == body)
        visual = [g for g in geoms if shown[model.geom_group[g]] and not collides[g]]
        colliding = [g for g in geoms if model.geom_group[g] == 3 and collides[g]]
        name = model.body(body).name
        assert [model.geom(g).name for g in visual] == [f"{name}_visual"]
        assert [model.geom(g).name for g in colliding] == [f"{name}_geom"]
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    contacts = data.contact.geom[: data.ncon]
    assert len(contacts) > 0 and all(collides[g] for g in contacts.ravel())  # the ball's


def scene_pose(scene, node: str) -> tuple[np.ndarray, object]:  # type: ignore[no-untyped-def]
    """A glb node's world pose (glTF: +Y up) brought back to the scene's +Z up through the
    root node that turns one into the other (docs/export.md, glTF axes), and its geometry."""
    from ssgc.export.glb import ROOT_NAME, Z_UP_TO_Y_UP

    root, _ = scene.graph.get(ROOT_NAME)
    np.testing.assert_allclose(root, Z_UP_TO_Y_UP, atol=1e-12)
    matrix, geometry = scene.graph.get(node)
    return Z_UP_TO_Y_UP.T @ matrix, geometry


def test_glb_nodes_are_named_by_object_id_with_their_poses(exported: Path) -> None:
    import trimesh

    for name in scene_names(exported):
        scene = trimesh.load(str(exported / "glb" / f"{name}.glb"))
        want = expected(exported, name)
        got = {}
        for node in want:
            matrix, geometry = scene_pose(scene, node)
            got[node] = (matrix[:3, 3], matrix[:3, :3])
            assert geometry in scene.geometry
        assert_same_poses(got, want)


def test_usd_has_one_xform_per_object_with_its_pose(exported: Path) -> None:
    from pxr import Usd, UsdGeom, UsdPhysics

    for name in scene_names(exported):
        stage = Usd.Stage.Open(str(exported / "usd" / f"{name}.usda"))
        want = expected(exported, name)
        got = {}
        for prim in stage.GetPrimAtPath("/World").GetChildren():
            m = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0))
            got[prim.GetName()] = (m[3, :3], m[:3, :3].T)  # USD: row vectors
            rigid = prim.HasAPI(UsdPhysics.RigidBodyAPI)
            assert rigid == (not prim.GetName().startswith("Table"))
            assert len(prim.GetChildren()) == 1  # its geometry
        assert_same_poses(got, want)


def test_export_of_a_parse_result_and_a_directory(tmp_path: Path) -> None:
    """`ssg export` reads a directory of scenes and `ssg parse` output alike."""
    grammar = GRAMMARS / "sink.yaml"
    scenes = tmp_path / "scenes"
    assert run("sample", grammar, "-n", 2, "-o", scenes, "-q").exit_code == 0
    trees = [json.loads(p.read_text())["tree"] for p in sorted(scenes.glob("*.json"))]
    parsed = {
        "grammar": "sink",
        "scenes": [
            {"name": f"p{i}", "status": "optimal", "parses": [{"tree": t}]}
            for i, t in enumerate(trees)
        ],
    }
    (tmp_path / "parsed.json").write_text(json.dumps(parsed))
    for source in (scenes, tmp_path / "parsed.json"):
        out = tmp_path / "out" / source.name
        result = run("export", source, "-g", grammar, "-f", "mjcf", "-o", out, "-q")
        assert result.exit_code == 0, result.output
        assert len(list(out.glob("*.xml"))) == 2
    import mujoco

    for i, p in enumerate(sorted(scenes.glob("*.json"))):
        model = mujoco.MjModel.from_xml_path(str(tmp_path / "out" / "parsed.json" / f"p{i}.xml"))
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        objects = json.loads(p.read_text())["objects"]
        for k, o in enumerate(objects):
            xpos = data.xpos[model.body(f"{o['type']}_{k}").id]
            np.testing.assert_allclose(xpos, o["pose"]["xyz"], atol=TOL)


def test_unknown_format_and_unwritable_output_are_messages(tmp_path: Path) -> None:
    scenes = tmp_path / "s"
    assert run("sample", GRAMMARS / "gmm.yaml", "-n", 1, "-o", scenes, "-q").exit_code == 0
    result = run("export", scenes, "-g", GRAMMARS / "gmm.yaml", "-f", "obj", "-o", tmp_path / "o")
    assert result.exit_code == 1
    assert "unknown export format 'obj'; choose one of dmd, sdf, mjcf, glb, usd" in result.output
    (tmp_path / "file").write_text("")
    result = run(
        "export", scenes, "-g", GRAMMARS / "gmm.yaml", "-f", "glb", "-o", tmp_path / "file"
    )
    assert result.exit_code == 1 and "Traceback" not in result.output


def test_a_scene_with_a_very_long_name_exports_to_a_short_file_name(tmp_path: Path) -> None:
    """A 300-character name made `File name too long` (the name, its suffix and the temporary
    file's additions passed 255 bytes); the file is named by a cut stem and a hash."""
    scenes = tmp_path / "s"
    assert run("sample", GRAMMARS / "gmm.yaml", "-n", 1, "-o", scenes, "-q").exit_code == 0
    doc = json.loads(next(scenes.glob("*.json")).read_text())
    for name in ("x" * 300, "x" * 299 + "y"):
        (tmp_path / "long.json").write_text(json.dumps({**doc, "name": name}))
        args = ("export", tmp_path / "long.json", "-g", GRAMMARS / "gmm.yaml", "-f", "dmd")
        result = run(*args, "-o", tmp_path / "o", "-q")
        assert result.exit_code == 0, result.output
    files = sorted((tmp_path / "o").glob("*.dmd.yaml"))
    assert len(files) == 2  # the two names share their first 299 characters, not their file
    assert all(len(f.name) <= 120 and f.name.startswith("x" * 80) for f in files)
    assert scene_stem("a b") == "a_b"  # short names keep their stem


# ------------------------------------------------------------- geometry and mass ---

SHAPES = """
grammar: shapes
root: Tray
types:
  Tray:
    observed: true
    geometry: {{box: {{size: [0.4, 0.3, 0.02]}}}}
    body: {{static: true}}
    and:
      - {{child: Can, translation: {{offset: [0.1, 0, 0.07]}}}}
      - {{child: Cup, translation: {{offset: [-0.1, 0, 0.04]}}}}
  Can:
    observed: true
    geometry: {{cylinder: {{radius: 0.03, length: 0.12}}}}
    body: {{mass: 0.4}}
  Cup:
    observed: true
    geometry: {{mesh: {{file: {mesh}, scale: 2.0}}}}
    body: {{density: 500}}
"""


def shapes_grammar(tmp_path: Path, mesh: str = "cup.obj") -> Path:
    import trimesh

    trimesh.creation.box(extents=[0.1, 0.2, 0.05]).export(tmp_path / "cup.obj")
    path = tmp_path / "g.yaml"
    path.write_text(SHAPES.format(mesh=mesh))
    return path


def test_mass_and_inertia_from_primitives_and_meshes(tmp_path: Path) -> None:
    g = load_grammar(shapes_grammar(tmp_path))
    shapes = {s.type: s for s in load_shapes(g).values()}
    tray, can, cup = shapes["Tray"], shapes["Can"], shapes["Cup"]
    assert tray.static and not can.static
    assert tray.mass == pytest.approx(1000 * 0.4 * 0.3 * 0.02)
    np.testing.assert_allclose(
        np.diag(tray.inertia),
        tray.mass / 12 * np.array([0.3**2 + 0.02**2, 0.4**2 + 0.02**2, 0.4**2 + 0.3**2]),
    )
    assert can.mass == 0.4
    np.testing.assert_allclose(np.diag(can.inertia)[2], 0.4 * 0.03**2 / 2)
    # The mesh scaled by 2: a 0.2 x 0.4 x 0.1 box of density 500.
    assert cup.mass == pytest.approx(500 * 0.2 * 0.4 * 0.1)
    np.testing.assert_allclose(np.diag(cup.inertia)[0], cup.mass / 12 * (0.4**2 + 0.1**2))
    assert len(cup.collision) == 1 and cup.collision[0].is_convex


def test_each_mesh_file_is_read_once_for_the_shapes(tmp_path: Path, monkeypatch) -> None:
    """The check of every mesh and the shapes read each file once: a large mesh and its hull
    were read and computed twice per command."""
    import ssgc.assets

    read = []
    load = ssgc.assets._load_mesh
    monkeypatch.setattr(
        ssgc.assets, "_load_mesh", lambda path, scale: read.append(path) or load(path, scale)
    )
    g = load_grammar(shapes_grammar(tmp_path))
    shape = load_shapes(g, collision=False)[g.type_ids["Cup"]]
    assert [p.name for p in read] == ["cup.obj"]
    assert shape.mass == pytest.approx(500 * 0.2 * 0.4 * 0.1)


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        (None, "mesh file 'cup2.obj': not found"),
        (b"\x00\x01garbage", "mesh file 'cup2.obj': "),
        (b"", "mesh file 'cup2.obj': "),
    ],
)
def test_validate_locates_a_missing_or_unreadable_mesh(tmp_path, content, fragment) -> None:
    path = shapes_grammar(tmp_path, "cup2.obj")
    if content is not None:
        (tmp_path / "cup2.obj").write_bytes(content)
    result = run("validate", path)
    assert result.exit_code == 1
    assert f"{path}:18:" in result.output and fragment in result.output, result.output


def test_mass_and_density_together_is_an_error() -> None:
    text = "grammar: g\nroot: A\ntypes:\n  A: {observed: true, body: {mass: 1, density: 2}}\n"
    with pytest.raises(GrammarError, match="give mass or density, not both"):
        compile_text(text)


def test_the_loading_snippets_of_export_md_run(tmp_path: Path, monkeypatch) -> None:
    """Each ```python block of docs/export.md loads the file it names."""
    text = (GRAMMARS.parent / "docs" / "export.md").read_text()
    snippets = [b.split("```", 1)[0] for b in text.split("```python\n")[1:]]
    assert len(snippets) == 5
    scenes = tmp_path / "scenes"
    assert run("sample", DIMSUM, "-n", 1, "--seed", 0, "-o", scenes, "-q").exit_code == 0
    for fmt in ("dmd", "sdf", "mjcf", "glb", "usd"):
        result = run("export", scenes, "-g", DIMSUM, "-f", fmt, "-o", tmp_path / "out" / fmt)
        assert result.exit_code == 0, result.output
    monkeypatch.chdir(tmp_path)
    for snippet in snippets:
        namespace: dict = {}
        exec(snippet, namespace)
        assert namespace.get("plant") or namespace.get("data") or namespace.get("pose") is not None


def test_revolve_dishes_load_as_meshes_in_drake_usd_and_gltf(tmp_path: Path) -> None:
    """The sink grammar's dishes are `revolve` shapes: each export writes them as meshes that
    pydrake (every object where the scene puts it), usd-core and trimesh read (MJCF is loaded
    in MuJoCo above)."""
    formats = [a for f in ("sdf", "glb", "usd") for a in ("--export", f)]
    sink = GRAMMARS / "sink.yaml"
    result = run("sample", sink, "-n", 1, "--seed", 0, "-o", tmp_path, "-q", *formats)
    assert result.exit_code == 0, result.output
    name = "sink_000000"
    want = expected(tmp_path, name)
    dishes = [k for k in want if not k.startswith("DishBin")]
    assert dishes
    from pydrake.multibody.parsing import Parser

    plant, _ = drake_plant()
    Parser(plant).AddModels(str(tmp_path / "sdf" / f"{name}.sdf"))
    plant.Finalize()
    assert_same_poses(drake_poses(plant, want), want)
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(tmp_path / "usd" / f"{name}.usda"))
    assert sum(p.IsA(UsdGeom.Mesh) for p in stage.Traverse()) >= len(dishes)
    import trimesh

    scene = trimesh.load(tmp_path / "glb" / f"{name}.glb")
    assert all(len(g.faces) > 0 for g in scene.geometry.values())
    assert set(dishes) <= set(scene.graph.nodes)


BARE = (
    "grammar: bare\nroot: L\ntypes:\n  L:\n    repeat:\n      count: {probs: [PROBS]}\n"
    "      rule:\n        child: A\n"
    "        translation: {world_normal: {mean: [0, 0, 1], variance: 0.01}}\n"
    "        rotation: uniform\n  A: {observed: true}\n"
)


@pytest.mark.parametrize("probs", ["0, 0, 1", "1"])
def test_glb_of_a_scene_without_geometry_has_its_posed_nodes(tmp_path: Path, probs: str) -> None:
    """Objects of types without geometry (or no object at all): trimesh refuses to export a
    scene without a mesh ('Can't export empty scenes!', an internal error of `ssg export`,
    found on generated grammars); the file now holds one posed empty node per object."""
    import trimesh

    grammar = tmp_path / "bare.yaml"
    grammar.write_text(BARE.replace("PROBS", probs))
    out = tmp_path / "s"
    result = run("sample", grammar, "-n", 1, "--seed", 0, "-o", out, "-q", "--export", "glb")
    assert result.exit_code == 0, result.output
    scene = trimesh.load(str(out / "glb" / "bare_000000.glb"))
    want = expected(out, "bare_000000")
    assert len(want) == (2 if probs == "0, 0, 1" else 0)
    got = {}
    for node in want:
        matrix, geometry = scene_pose(scene, node)
        assert geometry is None
        got[node] = (matrix[:3, 3], matrix[:3, :3])
    assert_same_poses(got, want)


@pytest.mark.parametrize("command", [["export", "-f", "glb"], ["settle"]])
def test_a_parse_output_with_explanations_is_read_as_one(
    tmp_path: Path, command: list[str]
) -> None:
    """`ssg parse --explain` puts "objects" early in the file (the explanation's); the output
    was then taken for a scene file: "unknown key 'scenes'"."""
    grammar = GRAMMARS / "gmm.yaml"
    assert run("sample", grammar, "-n", 1, "-o", tmp_path / "s", "-q").exit_code == 0
    parsed = tmp_path / "p.json"
    scene = tmp_path / "s" / "gmm_000000.json"
    assert run("parse", scene, "-g", grammar, "--explain", "-o", parsed, "-q").exit_code == 0
    result = run(*command, parsed, "-g", grammar, "-o", tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert len(list((tmp_path / "out").iterdir())) == 1


CLASH = """grammar: clash
root: {type: Table, pose: {xyz: [0, 0, 0.4]}}
types:
  Table:
    observed: true
    geometry: {box: {size: [1, 1, 0.8]}}
    body: {static: true}
    and:
      - {child: Cup, translation: {offset: [0, 0, 0.5]}}
      - {child: Cup_collision_0, translation: {offset: [0.3, 0, 0.6]}}
      - {child: world, translation: {offset: [-0.3, 0, 0.6]}}
      - {child: _empty, translation: {offset: [-0.3, 0.2, 0.6]}}
      - {child: __model__, translation: {offset: [0.3, 0.2, 0.6]}}
      - {child: Mark, translation: {offset: [-0.3, -0.2, 0.6]}}
  Cup: {observed: true, geometry: {mesh: {file: cube.obj}}}
  Cup_collision_0: {observed: true, geometry: {mesh: {file: ball.obj}}}
  world: {observed: true, geometry: {sphere: {radius: 0.05}}}
  _empty: {observed: true, geometry: {box: {size: [0.2, 0.2, 0.2]}}}
  __model__: {observed: true, geometry: {box: {size: [0.1, 0.1, 0.1]}}}
  Mark: {observed: true}
"""


def clash_scenes(tmp_path: Path, text: str = CLASH) -> tuple[Path, Path]:
    import trimesh

    tmp_path.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box([0.05] * 3).export(tmp_path / "cube.obj")
    trimesh.creation.icosphere(radius=0.1).export(tmp_path / "ball.obj")
    grammar = tmp_path / "g.yaml"
    grammar.write_text(text)
    scenes = tmp_path / "scenes"
    assert run("sample", grammar, "-n", 1, "-o", scenes, "-q").exit_code == 0
    return grammar, scenes


def test_type_names_that_look_like_export_file_names_keep_their_own_shapes(tmp_path: Path):
    """A type `Cup_collision_0` shared a file with Cup's first convex piece (MuJoCo refused the
    repeated mesh name; Drake took the ball for the cube), a type `_empty` had its model
    replaced by the one of objects without geometry, and types `world` and `__model__` wrote
    model names SDFormat reserves (Drake refused them)."""
    import mujoco
    from pydrake.multibody.parsing import LoadModelDirectives, Parser, ProcessModelDirectives

    grammar, scenes = clash_scenes(tmp_path)
    for fmt in ("dmd", "sdf", "mjcf"):
        result = run("export", scenes, "-g", grammar, "-f", fmt, "-o", tmp_path / fmt, "-q")
        assert result.exit_code == 0, result.output
    mujoco.MjModel.from_xml_path(str(next((tmp_path / "mjcf").glob("*.xml"))))
    masses = {  # of density 1000: a 5 cm cube, a 10 cm ball (icosphere), a 20 cm box
        "Cup_1": 0.125,
        "Cup_collision_0_2": 4.15,
        "_empty_4": 8.0,
    }
    plant, _ = drake_plant()
    parser = Parser(plant)
    parser.package_map().AddPackageXml(str(tmp_path / "dmd" / "package.xml"))
    directives = LoadModelDirectives(str(next((tmp_path / "dmd").glob("*.dmd.yaml"))))
    ProcessModelDirectives(directives, plant, parser)
    sdf_plant, _ = drake_plant()
    Parser(sdf_plant).AddModels(str(next((tmp_path / "sdf").glob("*.sdf"))))
    for p in (plant, sdf_plant):
        for name, mass in masses.items():
            body = p.GetBodyByName("body", p.GetModelInstanceByName(name))
            assert body.default_mass() == pytest.approx(mass, rel=0.01), name
    import trimesh

    cube_piece = trimesh.load(tmp_path / "sdf" / "meshes" / "Cup.collision.0.obj")
    np.testing.assert_allclose(cube_piece.extents, [0.05] * 3, rtol=1e-6)


def test_a_scene_named_as_sdformat_reserves_loads_in_drake(tmp_path: Path) -> None:
    """`<world name="world">` (a scene called `world`, or `__x__`) was refused by Drake."""
    from pydrake.multibody.parsing import Parser

    grammar, _ = clash_scenes(tmp_path)
    for name in ("world", "__model__"):
        scene = tmp_path / f"{name}.json"
        objects = [{"type": "Table", "pose": {"xyz": [0, 0, 0.4]}}]
        scene.write_text(json.dumps({"name": name, "objects": objects}))
        out = tmp_path / f"sdf_{name}"
        assert run("export", scene, "-g", grammar, "-f", "sdf", "-o", out, "-q").exit_code == 0
        plant, _ = drake_plant()
        Parser(plant).AddModels(str(next(out.glob("*.sdf"))))
        assert plant.HasModelInstanceNamed("Table_0")


def test_an_export_does_not_change_the_shared_files_of_scenes_already_there(tmp_path: Path):
    """Scenes of another grammar exported into the same directory replaced the first ones'
    meshes (their Cup became a ball) without a word.  Now nothing is written; the same
    grammar's scenes can still be exported there again."""
    first = tmp_path / "first"
    grammar, scenes = clash_scenes(first)
    other_grammar, other_scenes = clash_scenes(
        tmp_path / "other", CLASH.replace("clash", "other").replace("cube.obj", "ball.obj")
    )
    out = tmp_path / "out"
    for fmt in ("sdf", "dmd", "mjcf"):
        assert run("export", scenes, "-g", grammar, "-f", fmt, "-o", out / fmt).exit_code == 0
        before = {p: p.read_bytes() for p in (out / fmt).rglob("*") if p.is_file()}
        result = run("export", other_scenes, "-g", other_grammar, "-f", fmt, "-o", out / fmt)
        assert result.exit_code == 1, result.output
        assert "Cup.obj: error: already holds a different version" in result.output
        after = {p: p.read_bytes() for p in (out / fmt).rglob("*") if p.is_file()}
        assert after == before
        assert run("export", scenes, "-g", grammar, "-f", fmt, "-o", out / fmt).exit_code == 0


WRAP = """grammar: m
root: Tray
types:
  Tray:
    observed: true
    geometry: {box: {size: [1.0, 1.0, 0.02]}}
    body: {static: true}
    and:
      - {child: Thing, translation: {offset: [0, 0, 0.06]}}
  Thing: {observed: true, geometry: GEOMETRY, body: BODY}
"""


def wrapped(tmp_path: Path, geometry: str, body: str = "{}") -> Path:
    tmp_path.mkdir(parents=True, exist_ok=True)
    grammar = tmp_path / "g.yaml"
    grammar.write_text(WRAP.replace("GEOMETRY", geometry).replace("BODY", body))
    return grammar


@pytest.mark.parametrize(
    "obj",
    [
        "v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n",  # a flat square
        "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n",  # one triangle
        "v 0 0 0\nv 0.1 0 0\nv 0.2 0 0\nf 1 2 3\n",  # points on a line
    ],
)
def test_a_mesh_that_encloses_no_volume_is_a_located_error(tmp_path: Path, obj: str) -> None:
    """NaN masses in SDF and DMD, and internal errors (LinAlgError, QhullError) elsewhere."""
    (tmp_path / "flat.obj").write_text(obj)
    grammar = wrapped(tmp_path, "{mesh: {file: flat.obj}}")
    result = run("validate", grammar)
    assert result.exit_code == 1 and "encloses no volume" in result.output, result.output
    assert f"{grammar}:10:" in result.output


def test_a_cube_wound_both_ways_has_a_cubes_mass(tmp_path: Path) -> None:
    """Two faces turned the other way: mass 0.5 instead of 1, and an inertia MuJoCo refused."""
    import trimesh

    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    faces = box.faces.copy()
    faces[:2] = faces[:2, ::-1]
    trimesh.Trimesh(box.vertices, faces, process=False).export(tmp_path / "mixed.obj")
    g = load_grammar(wrapped(tmp_path, "{mesh: {file: mixed.obj}}"))
    shape = load_shapes(g, collision=False)[g.type_ids["Thing"]]
    assert shape.mass == pytest.approx(1.0)
    np.testing.assert_allclose(shape.com, 0, atol=1e-9)


@pytest.mark.parametrize(
    ("body", "fmt"),
    [
        ("{density: 1.0e306}", "sdf"),  # overflows float64: inf
        ("{density: 1.0e300}", "usd"),  # float32 inf in USD; Drake: "not physically valid"
        ("{density: 1.0e-300}", "usd"),  # float32 0 in USD: "no mass given"
        ("{mass: 1.0e-40}", "mjcf"),
    ],
)
def test_a_mass_simulators_cannot_hold_is_a_message(tmp_path: Path, body: str, fmt: str) -> None:
    grammar = wrapped(tmp_path, "{box: {size: [10, 10, 10]}}", body)
    scenes = tmp_path / "s"
    assert run("sample", grammar, "-n", 1, "-o", scenes, "-q").exit_code == 0
    result = run("export", scenes, "-g", grammar, "-f", fmt, "-o", tmp_path / "e")
    assert result.exit_code == 1 and "32-bit floats" in result.output, result.output
    assert not (tmp_path / "e").exists()


def test_extreme_but_storable_masses_load_in_drake_and_usd(tmp_path: Path) -> None:
    """The edges of the range that `_check_storable` lets through are files the consumers read
    with the mass written."""
    from pxr import Usd, UsdPhysics
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    for density in (1.0e-30, 1.0e30):
        grammar = wrapped(tmp_path, "{box: {size: [0.1, 0.1, 0.1]}}", f"{{density: {density}}}")
        scenes, out = tmp_path / f"s{density}", tmp_path / f"e{density}"
        assert run("sample", grammar, "-n", 1, "-o", scenes, "-q").exit_code == 0
        for fmt in ("sdf", "usd"):
            assert run("export", scenes, "-g", grammar, "-f", fmt, "-o", out / fmt).exit_code == 0
        plant = MultibodyPlant(0.0)
        Parser(plant).AddModels(str(next((out / "sdf").glob("*.sdf"))))
        plant.Finalize()
        stage = Usd.Stage.Open(str(next((out / "usd").glob("*.usd*"))))
        masses = [
            UsdPhysics.MassAPI(p).GetMassAttr().Get()
            for p in stage.Traverse()
            if p.HasAPI(UsdPhysics.MassAPI)
        ]
        assert masses and all(m == pytest.approx(density * 1e-3, rel=1e-6) for m in masses)


def test_an_empty_scene_loads_as_drake_model_directives(tmp_path: Path) -> None:
    """`directives:` alone is null, which LoadModelDirectives refuses."""
    from pydrake.multibody.parsing import LoadModelDirectives

    grammar = wrapped(tmp_path, "{sphere: {radius: 0.1}}")
    scene = tmp_path / "empty.json"
    scene.write_text(json.dumps({"name": "empty", "objects": []}))
    assert run("export", scene, "-g", grammar, "-f", "dmd", "-o", tmp_path / "e").exit_code == 0
    LoadModelDirectives(str(tmp_path / "e" / "empty.dmd.yaml"))


def test_a_grain_of_a_tenth_of_a_millimetre_loads_in_mujoco(tmp_path: Path) -> None:
    """Its inertia (2e-18) is below MuJoCo's least: the MJCF did not load, and `ssg settle`
    stopped part way through a run."""
    import mujoco

    grammar = wrapped(tmp_path, "{box: {size: [0.0001, 0.0001, 0.0001]}}")
    scenes = tmp_path / "s"
    assert run("sample", grammar, "-n", 1, "-o", scenes, "-q").exit_code == 0
    assert run("export", scenes, "-g", grammar, "-f", "mjcf", "-o", tmp_path / "e").exit_code == 0
    model = mujoco.MjModel.from_xml_path(str(next((tmp_path / "e").glob("*.xml"))))
    assert model.body_mass[-1] == pytest.approx(1e-9)  # its own mass, above the floor
    assert run("settle", scenes, "-g", grammar, "-o", tmp_path / "st", "-q").exit_code == 0


@pytest.mark.parametrize(
    "profile, like",
    [  # pinched to a point at (0.03, 0.01): two rings; a spur out and back along the floor
        (
            "[[0,0],[0.02,0],[0.03,0.01],[0.04,0],[0.05,0],[0.05,0.02],[0.04,0.02],"
            "[0.03,0.01],[0.02,0.02],[0,0.02]]",
            None,
        ),
        (
            "[[0,0],[0.05,0],[0.08,0],[0.05,0],[0.05,0.02],[0,0.02]]",
            "[[0,0],[0.05,0],[0.05,0.02],[0,0.02]]",
        ),
    ],
)
def test_a_revolve_that_touches_itself_weighs_what_it_encloses(tmp_path, profile, like):
    """trimesh calls such a surface no volume, and its hull was 32% and 72% too heavy."""
    g = load_grammar(wrapped(tmp_path, f"{{revolve: {{profile: {profile}}}}}"))
    shape = load_shapes(g, collision=False)[g.type_ids["Thing"]]
    if like is None:  # Pappus over the 32-gon: the cylinder less the two triangles' rings
        expected = float(shape.mesh.volume) * 1000  # its own closed surface's volume
        assert expected < 0.8 * float(shape.mesh.convex_hull.volume) * 1000
    else:
        plain = load_grammar(wrapped(tmp_path / "plain", f"{{revolve: {{profile: {like}}}}}"))
        expected = load_shapes(plain, collision=False)[plain.type_ids["Thing"]].mass
    assert shape.mass == pytest.approx(expected, rel=1e-9)
    assert shape.com[2] == pytest.approx(0.01, abs=1e-9)


# A mesh (scaled, moved by `origin`), a revolve and a cylinder (both moved by `origin`), on a
# fixed tray: every kind of geometry Drake reads, each placed off its frame.
PLACED = """grammar: placed
root: {type: Tray, pose: {xyz: [0.1, -0.2, 0.3], rpy_deg: [0, 0, 30]}}
types:
  Tray:
    observed: true
    geometry: {box: {size: [1.0, 1.0, 0.02]}, origin: [0.01, 0.02, -0.01]}
    body: {static: true}
    and:
      - {child: Brick, translation: {offset: [0.2, 0, 0.1]}, rotation: uniform}
      - {child: Dish, translation: {offset: [-0.2, 0, 0.1]}, rotation: uniform}
      - {child: Can, translation: {offset: [0, 0.2, 0.1]}, rotation: uniform}
  Brick:
    observed: true
    geometry: {mesh: {file: brick.obj, scale: [1, 2, 1]}, origin: [0.01, 0.02, 0.03]}
  Dish:
    observed: true
    geometry:
      revolve:
        profile: [[0, 0], [0.05, 0], [0.08, 0.03], [0.075, 0.03], [0.045, 0.005], [0, 0.005]]
      origin: [0, 0.01, -0.01]
  Can: {observed: true, geometry: {cylinder: {radius: 0.03, length: 0.1}, origin: [0, 0, 0.05]}}
"""


def drake_loaded(root: Path, fmt: str, name: str):  # type: ignore[no-untyped-def]
    """The `fmt` (sdf or dmd) export of scene `name` in a plant with a SceneGraph."""
    from pydrake.multibody.parsing import LoadModelDirectives, Parser, ProcessModelDirectives

    plant, scene_graph = drake_plant()
    parser = Parser(plant)
    if fmt == "sdf":
        parser.AddModels(str(root / "sdf" / f"{name}.sdf"))
    else:
        parser.package_map().AddPackageXml(str(root / "dmd" / "package.xml"))
        directives = LoadModelDirectives(str(root / "dmd" / f"{name}.dmd.yaml"))
        ProcessModelDirectives(directives, plant, parser)
    plant.Finalize()
    return plant, scene_graph.model_inspector()


@pytest.mark.parametrize("fmt", ["sdf", "dmd"])
def test_meshes_and_revolves_load_in_a_plant_with_a_scene_graph(tmp_path: Path, fmt) -> None:
    """Drake refused every sdf and dmd export with a mesh or a revolve once the plant had a
    SceneGraph ("Unsupported SDFormat element in collision: drake:declare_convex"): the mark
    stood after </geometry>, and Drake takes it only inside <mesh>.  Now each loads, every
    object where the scene puts it, each geometry where its origin puts it (a mesh's OBJ is
    already placed), each convex piece a Convex, each body of the mass ssgc computes."""
    import trimesh
    from pydrake.geometry import Convex

    trimesh.creation.box(extents=[0.1, 0.05, 0.04]).export(tmp_path / "brick.obj")
    grammar = tmp_path / "g.yaml"
    grammar.write_text(PLACED)
    result = run("sample", grammar, "-n", 1, "--seed", 4, "-o", tmp_path, "-q", "--export", fmt)
    assert result.exit_code == 0, result.output
    name = "placed_000000"
    want = expected(tmp_path, name)
    plant, inspector = drake_loaded(tmp_path, fmt, name)
    assert_same_poses(drake_poses(plant, want), want)
    g = load_grammar(grammar)
    shapes = {s.type: s for s in load_shapes(g).values()}
    for obj in want:
        shape = shapes[obj.rsplit("_", 1)[0]]
        body = plant.GetBodyByName("body", plant.GetModelInstanceByName(obj))
        assert body.default_mass() == pytest.approx(shape.mass, rel=1e-9), obj
        visual = plant.GetVisualGeometriesForBody(body)
        collision = plant.GetCollisionGeometriesForBody(body)
        assert (len(visual), len(collision)) == (1, max(1, len(shape.collision))), obj
        at = np.zeros(3) if shape.kind == "mesh" else np.array(shape.origin)
        for gid in [*visual, *collision]:
            np.testing.assert_allclose(inspector.GetPoseInFrame(gid).translation(), at, atol=TOL)
        convex = [isinstance(inspector.GetShape(i), Convex) for i in collision]
        assert convex == [shape.kind == "mesh"] * len(collision), obj


def test_two_crossed_flat_quads_load_in_mujoco_and_settle(tmp_path: Path) -> None:
    """Their hull has a volume (validation accepts them), but MuJoCo refused the MJCF: "mesh
    volume is too small ... Try setting inertia to shell", and `sample --settle` exited 1
    with an incomplete run.  The mesh assets' own inertia (unused: the body's is the
    <inertial>) is now a shell's."""
    import mujoco

    quads = "v -0.05 0 -0.05\nv 0.05 0 -0.05\nv 0.05 0 0.05\nv -0.05 0 0.05\n"
    quads += "v 0 -0.05 -0.05\nv 0 0.05 -0.05\nv 0 0.05 0.05\nv 0 -0.05 0.05\n"
    (tmp_path / "cross.obj").write_text(quads + "f 1 2 3\nf 1 3 4\nf 5 6 7\nf 5 7 8\n")
    grammar = wrapped(tmp_path, "{mesh: {file: cross.obj}}")
    assert run("validate", grammar).exit_code == 0
    result = run("sample", grammar, "-n", 1, "-o", tmp_path / "s", "-q", "--export", "mjcf")
    assert result.exit_code == 0, result.output
    model = mujoco.MjModel.from_xml_path(str(next((tmp_path / "s" / "mjcf").glob("*.xml"))))
    shape = load_shapes(load_grammar(grammar))[1]
    assert model.body_mass[-1] == pytest.approx(shape.mass)
    result = run("sample", grammar, "-n", 1, "-o", tmp_path / "st", "-q", "--settle")
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "st" / MANIFEST).read_text())["complete"] is True


def test_a_box_a_nanometre_thin_loads_in_mujoco_with_its_own_inertia(tmp_path: Path) -> None:
    """Its largest principal moment is the sum of the other two, and rounding put it one float
    step above: MuJoCo refused the MJCF ("inertia must satisfy A + B >= C").  Lowered by that
    step, not balanced (`balanceinertia` sets all three to their mean, 21% to 330% off)."""
    import mujoco

    grammar = wrapped(tmp_path, "{box: {size: [0.3, 0.7, 1.0e-9]}}")
    scenes = tmp_path / "s"
    assert run("sample", grammar, "-n", 1, "-o", scenes, "-q").exit_code == 0
    assert run("export", scenes, "-g", grammar, "-f", "mjcf", "-o", tmp_path / "e").exit_code == 0
    model = mujoco.MjModel.from_xml_path(str(next((tmp_path / "e").glob("*.xml"))))
    shape = load_shapes(load_grammar(grammar))[1]
    np.testing.assert_allclose(
        np.sort(model.body_inertia[-1]), np.sort(np.diag(shape.inertia)), rtol=1e-15
    )


@pytest.mark.parametrize("scale", ["1.0e-6", "1.0e-3", "1000"])
def test_a_scaled_box_is_a_box_at_any_size(tmp_path: Path, scale: str) -> None:
    """Scaled by 1e-6 a 0.1 m box was refused as "encloses no volume" (trimesh merged its
    points), as were scales of 1e15 and 1e20 (its integer rounding overflowed); now the
    test and the mass are computed at unit size: the box has a box's mass at any scale."""
    import trimesh

    trimesh.creation.box(extents=[0.1, 0.05, 0.03]).export(tmp_path / "box.obj")
    grammar = wrapped(tmp_path, f"{{mesh: {{file: box.obj, scale: {scale}}}}}")
    result = run("validate", grammar)
    assert result.exit_code == 0, result.output
    g = load_grammar(grammar)
    shape = load_shapes(g, collision=False)[g.type_ids["Thing"]]
    s = float(scale)
    assert shape.mass == pytest.approx(1000 * 0.1 * 0.05 * 0.03 * s**3, rel=1e-9)
    np.testing.assert_allclose(
        np.diag(shape.inertia),
        shape.mass / 12 * s**2 * np.array([0.05**2 + 0.03**2, 0.1**2 + 0.03**2, 0.1**2 + 0.05**2]),
        rtol=1e-9,
    )


@pytest.mark.parametrize("scale", ["1.0e15", "1.0e20", "1.0e200"])
def test_a_mesh_scaled_beyond_the_scene_is_one_message(tmp_path: Path, scale: str) -> None:
    """1e200 was an internal error (OverflowError in size**3, exit 70); 1e15 and 1e20 said
    "encloses no volume" of a solid box."""
    import trimesh

    trimesh.creation.box(extents=[0.1, 0.05, 0.03]).export(tmp_path / "box.obj")
    grammar = wrapped(tmp_path, f"{{mesh: {{file: box.obj, scale: {scale}}}}}")
    result = run("validate", grammar)
    assert result.exit_code == 1, result.output
    assert f"{grammar}:10:" in result.output and "m across once scaled" in result.output
    assert "encloses no volume" not in result.output and "internal error" not in result.output


@pytest.mark.parametrize("scale", ["0", ".nan", "-1"])
def test_a_bad_mesh_scale_is_one_error(tmp_path: Path, scale: str) -> None:
    """A scale of 0 or NaN printed the scale's error and "encloses no volume" for one mistake."""
    import trimesh

    trimesh.creation.box(extents=[0.1, 0.05, 0.03]).export(tmp_path / "box.obj")
    grammar = wrapped(tmp_path, f"{{mesh: {{file: box.obj, scale: {scale}}}}}")
    result = run("validate", grammar)
    assert result.exit_code == 1, result.output
    assert result.output.count("error:") == 1 and "scale" in result.output, result.output


def test_a_geometry_origin_is_bounded_as_a_pose_is(tmp_path: Path) -> None:
    """An origin of [1e300, 0, 0] validated, and the USD export wrote a centre of mass of
    (inf, 0, 0) (float32)."""
    grammar = wrapped(tmp_path, "{box: {size: [0.1, 0.1, 0.1]}, origin: [1.0e300, 0, 0]}")
    result = run("validate", grammar)
    assert result.exit_code == 1, result.output
    assert "geometry.origin: a position must lie within 1,000 km" in result.output
    near = wrapped(tmp_path / "near", "{box: {size: [0.1, 0.1, 0.1]}, origin: [1.0e6, 0, 0]}")
    assert run("validate", near).exit_code == 0


def test_sample_export_glb_does_not_need_coacd(tmp_path: Path, monkeypatch) -> None:
    """glTF carries no collision geometry: `ssg export -f glb` never decomposed meshes, but
    `ssg sample --export glb` did, and exited 1 "needs coacd" without it."""
    import sys

    import trimesh

    trimesh.creation.box(extents=[0.1, 0.05, 0.03]).export(tmp_path / "box.obj")
    grammar = wrapped(tmp_path, "{mesh: {file: box.obj}}", "{collision: decomposition}")
    monkeypatch.setitem(sys.modules, "coacd", None)  # `import coacd` raises ImportError
    result = run("sample", grammar, "-n", 1, "-o", tmp_path / "s", "-q", "--export", "glb")
    assert result.exit_code == 0, result.output
    assert len(list((tmp_path / "s" / "glb").glob("*.glb"))) == 1
    result = run("sample", grammar, "-n", 1, "-o", tmp_path / "m", "-q", "--export", "mjcf")
    assert result.exit_code == 1 and "needs coacd" in result.output, result.output
