"""Geometry as simulators see it: a revolve's collision is its own solid (a cup rests in a bowl
without being thrown out), cut exactly into convex pieces without coacd."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from ssgc.assets import load_shapes, profile_trapezoids, revolve_pieces, revolve_sectors
from ssgc.cli.app import app
from ssgc.compile import compile_text, load_grammar
from ssgc.constraints.revolved import Revolved
from ssgc.io.scene import read_scene_file

runner = CliRunner()

# grammars/sink_detailed.yaml's BowlBradshaw7Qt (15 cm rim, inner floor at 5 mm) and
# MugThresholdBeadWhite (4.5 cm rim, 11.5 cm tall).
BOWL = (
    "[[0.0, 0.0], [0.085, 0.0], [0.107, 0.026], [0.119, 0.051], [0.128, 0.077], [0.136, 0.103], "
    "[0.143, 0.128], [0.15, 0.154], [0.146, 0.154], [0.139, 0.129], [0.132, 0.104], "
    "[0.124, 0.08], [0.115, 0.055], [0.103, 0.03], [0.081, 0.005], [0.0, 0.005]]"
)
MUG = "[[0.0, 0.0], [0.04, 0.0], [0.045, 0.115], [0.041, 0.115], [0.036, 0.005], [0.0, 0.005]]"
PLATE = "[[0.0, 0.0], [0.07, 0.0], [0.11, 0.028], [0.102, 0.028], [0.062, 0.01], [0.0, 0.01]]"
POINTED = "[[0, 0], [0.1, 0], [0.15, 0.05], [0.09, 0.005], [0, 0.005]]"  # a rim of no width
LENS = "[[0, -0.1], [0.05, -0.08], [0.1, 0], [0.05, 0.08], [0, 0.1]]"  # on the axis top and bottom

# A bowl on the floor with a mug standing on its inner floor (5 mm up), off centre.
CUP_IN_BOWL = f"""
grammar: cup_in_bowl
root: Bowl
types:
  Bowl:
    observed: true
    geometry: {{revolve: {{profile: {BOWL}}}}}
    BODY
    and:
      - {{child: Mug, translation: {{offset: [0.02, 0.0, 0.005]}}}}
  Mug:
    observed: true
    geometry: {{revolve: {{profile: {MUG}}}}}
"""


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


def settled_moves(tmp_path: Path, body: str) -> tuple[np.ndarray, dict]:
    """How far each object of the cup-in-bowl scene moves under `ssg settle`, and its report
    (`settled`: whether it came to rest)."""
    grammar = tmp_path / "g.yaml"
    grammar.write_text(CUP_IN_BOWL.replace("BODY", body))
    scenes, out, report = tmp_path / "s", tmp_path / "settled", tmp_path / "r.json"
    assert run("sample", grammar, "-n", 1, "--seed", 0, "-o", scenes, "-q").exit_code == 0
    result = run("settle", scenes, "-g", grammar, "-o", out, "--report", report, "-q")
    g = load_grammar(grammar)
    before = read_scene_file(scenes / "cup_in_bowl_000000.json", g)
    after = read_scene_file(out / "cup_in_bowl_000000.json", g)
    (r,) = json.loads(report.read_text())["scenes"]
    assert result.exit_code == (0 if r["settled"] else 2), result.output
    return np.linalg.norm(after.xyz - before.xyz, axis=1), r


def test_a_cup_resting_in_a_bowl_stays_in_it_when_settled(tmp_path: Path) -> None:
    """A revolve collided as its convex hull: the mug stood inside the bowl's collision solid,
    and settling pushed it out over the rim (moved 15 cm).  It now collides as its own solid,
    cut into convex pieces: the mug stays on the bowl's inner floor."""
    moved, report = settled_moves(tmp_path, "body: {}")
    assert report["settled"]
    assert report["penetration_before"] < 1e-3  # nothing overlaps: the cavity is empty
    assert moved[1] < 0.005, moved  # the mug
    assert moved[0] < 0.005, moved  # the bowl


def test_a_revolve_with_collision_hull_collides_as_its_hull(tmp_path: Path) -> None:
    """`collision: hull` keeps its meaning for a revolve: one convex piece, cavity filled (for
    dishes nothing rests in, a cheaper collision): the two are pushed apart."""
    moved, _ = settled_moves(tmp_path, "body: {collision: hull}")
    assert max(moved) > 0.05, moved  # the bowl is pushed off the mug, or the mug out of it


@pytest.mark.parametrize("profile", [BOWL, MUG, PLATE, POINTED, LENS])
def test_the_pieces_tile_the_solid_and_leave_the_cavity_empty(profile: str) -> None:
    """Each piece is convex, the pieces hold the volume of the solid's mesh of as many sections
    (its chords), every point of the solid deeper than the chord error is in a piece and no
    point farther than that outside it (in the bowl's cavity) is."""
    rz = np.array(json.loads(profile), float)
    pieces = revolve_pieces(rz)
    k = revolve_sectors(float(rz[:, 0].max()))
    vertices, faces = Revolved(rz).mesh(k)
    assert all(p.is_convex and p.volume > 0 for p in pieces)
    volume = sum(p.volume for p in pieces)
    assert volume == pytest.approx(abs(trimesh.Trimesh(vertices, faces).volume), rel=1e-9)
    points = np.random.default_rng(0).uniform(vertices.min(0), vertices.max(0), (20000, 3))
    depth = Revolved(rz).signed_distance(points)
    inside = np.zeros(len(points), bool)
    for p in pieces:  # inside a convex piece: behind every face's plane
        offsets = np.einsum("ij,ij->i", p.face_normals, p.triangles[:, 0])
        inside |= np.all(points @ p.face_normals.T <= offsets + 1e-12, axis=1)
    chord = 0.0011  # m: the chord error, 1 mm, and rounding
    assert inside[depth < -chord].all()
    assert not inside[depth > chord].any()


def test_sectors_keep_the_chords_within_a_millimetre() -> None:
    """28 sectors for the 15 cm bowl (a chord 0.9 mm inside its rim), 16 at least."""
    assert revolve_sectors(0.15) == 28
    assert 0.15 * (1 - np.cos(np.pi / 28)) <= 1e-3 < 0.15 * (1 - np.cos(np.pi / 27))
    assert revolve_sectors(0.045) == 16
    assert revolve_sectors(1e-6) == 16 and revolve_sectors(100.0) == 64


def test_a_dish_wall_is_one_trapezoid_per_straight_stretch() -> None:
    """The mug's profile is its base (on the axis) and one wall: two trapezoids."""
    trapezoids, on_axis = profile_trapezoids(json.loads(MUG))
    foot = 0.04 + 0.005 * 0.005 / 0.115  # the outer wall's r at the inner floor's height
    want = [[0.0, 0.04, 0.0, foot, 0.0, 0.005], [0.036, foot, 0.041, 0.045, 0.005, 0.115]]
    np.testing.assert_allclose(trapezoids, want, atol=1e-12)
    assert on_axis.tolist() == [True, False]


def _shapes(tmp_path: Path, body: str = "{}"):  # type: ignore[no-untyped-def]
    text = CUP_IN_BOWL.replace("BODY", f"body: {body}")
    g = compile_text(text, str(tmp_path / "g.yaml"))
    return g, {s.type: s for s in load_shapes(g).values()}


def test_a_revolve_collides_as_exact_pieces_by_default_and_as_its_hull_when_asked(tmp_path):
    _, shapes = _shapes(tmp_path)
    assert shapes["Bowl"].exact_pieces and len(shapes["Bowl"].collision) == 1 + 11 * 28
    assert shapes["Mug"].exact_pieces and len(shapes["Mug"].collision) == 1 + 16
    _, shapes = _shapes(tmp_path, "{collision: hull}")
    assert not shapes["Bowl"].exact_pieces and len(shapes["Bowl"].collision) == 1


def test_placed_revolve_pieces_sit_at_the_geometry_origin(tmp_path: Path) -> None:
    text = CUP_IN_BOWL.replace("BODY", "body: {}").replace(
        f"{{revolve: {{profile: {MUG}}}}}", f"{{revolve: {{profile: {MUG}}}, origin: [0, 0, 0.1]}}"
    )
    g = compile_text(text, str(tmp_path / "g.yaml"))
    mug = {s.type: s for s in load_shapes(g).values()}["Mug"]
    low = min(float(p.vertices[:, 2].min()) for p in mug.collision)
    assert low == pytest.approx(0.1) and mug.mesh.bounds[0, 2] == pytest.approx(0.1)


def test_every_simulator_format_carries_the_pieces(tmp_path: Path) -> None:
    """MJCF inline (no file per piece), SDFormat one convex OBJ per piece (Drake loads them),
    USD one collider Mesh per piece under ID/collision, the visual mesh colliding with nothing."""
    import mujoco
    from pxr import Usd, UsdPhysics
    from pydrake.geometry import Convex
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    grammar = tmp_path / "g.yaml"
    grammar.write_text(CUP_IN_BOWL.replace("BODY", "body: {}"))
    formats = [a for f in ("mjcf", "sdf", "usd") for a in ("--export", f)]
    result = run("sample", grammar, "-n", 1, "--seed", 0, "-o", tmp_path / "s", "-q", *formats)
    assert result.exit_code == 0, result.output
    name, pieces = "cup_in_bowl_000000", {"Bowl_0": 309, "Mug_1": 17}
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "s" / "mjcf" / f"{name}.xml"))
    for body, n in pieces.items():
        in_body = model.geom_bodyid == model.body(body).id
        assert np.count_nonzero(in_body & (model.geom_group == 3)) == n
    assert not list((tmp_path / "s" / "mjcf" / "meshes").glob("*.collision.*"))
    assert len(list((tmp_path / "s" / "sdf" / "meshes").glob("Bowl.collision.*.obj"))) == 309
    plant, scene_graph = AddMultibodyPlantSceneGraph(DiagramBuilder(), 0.0)
    Parser(plant).AddModels(str(tmp_path / "s" / "sdf" / f"{name}.sdf"))
    plant.Finalize()
    inspector = scene_graph.model_inspector()
    for body, n in pieces.items():
        ids = plant.GetCollisionGeometriesForBody(
            plant.GetBodyByName("body", plant.GetModelInstanceByName(body))
        )
        assert len(ids) == n and all(isinstance(inspector.GetShape(i), Convex) for i in ids)
    stage = Usd.Stage.Open(str(tmp_path / "s" / "usd" / f"{name}.usda"))
    for body, n in pieces.items():
        visual = stage.GetPrimAtPath(f"/World/{body}/geometry")
        assert not visual.HasAPI(UsdPhysics.CollisionAPI)
        colliders = stage.GetPrimAtPath(f"/World/{body}/collision").GetChildren()
        assert len(colliders) == n and all(p.HasAPI(UsdPhysics.CollisionAPI) for p in colliders)


# ------------------------------------------------------------------------------ tray ---

TRAY = """
grammar: bin
root: Bin
types:
  Bin:
    observed: true
    geometry: {tray: {size: [0.4, 0.3, 0.12], wall: 0.01}, origin: [0, 0, 0.06]}
    body: {static: true}
    and:
      - {child: Mug, translation: {offset: [0.1, 0.05, 0.01]}}
  Mug:
    observed: true
    geometry: {revolve: {profile: MUG}}
"""


def tray_grammar(tmp_path: Path, text: str = TRAY) -> Path:
    path = tmp_path / "bin.yaml"
    path.write_text(text.replace("MUG", MUG))
    return path


def test_a_tray_weighs_its_floor_and_walls(tmp_path: Path) -> None:
    """Volume, centre of mass and inertia in closed form (its five boxes), as trimesh finds
    them on its closed surface; the surface is watertight and faces outwards."""
    g = load_grammar(tray_grammar(tmp_path, TRAY.replace("{static: true}", "{density: 1000}")))
    tray = {s.type: s for s in load_shapes(g).values()}["Bin"]
    assert tray.kind == "tray" and len(tray.boxes) == 5 and tray.collision == ()
    volume = 0.4 * 0.3 * 0.12 - 0.38 * 0.28 * 0.11
    assert tray.mass == pytest.approx(1000 * volume)
    mesh = tray.mesh
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(volume)
    np.testing.assert_allclose(tray.com, mesh.center_mass, atol=1e-12)
    np.testing.assert_allclose(
        tray.inertia / tray.mass, mesh.moment_inertia / mesh.mass, atol=1e-12
    )
    np.testing.assert_allclose(mesh.bounds, [[-0.2, -0.15, 0.0], [0.2, 0.15, 0.12]], atol=1e-12)


def test_a_tray_with_no_room_inside_is_one_located_error(tmp_path: Path) -> None:
    path = tray_grammar(tmp_path, TRAY.replace("wall: 0.01", "wall: 0.2"))
    result = run("validate", path)
    assert result.exit_code == 1
    assert f"{path}:7:" in result.output and "leaves no room inside" in result.output
    assert "Traceback" not in result.output


def test_a_mug_rests_in_a_tray_in_every_simulator(tmp_path: Path) -> None:
    """MuJoCo and Drake collide a tray as its five boxes, USD has five collider Cubes, glTF
    draws it: the mug standing on its floor touches nothing but the floor and stays."""
    import mujoco
    from pxr import Usd, UsdGeom, UsdPhysics
    from pydrake.geometry import Box
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    grammar = tray_grammar(tmp_path)
    formats = [a for f in ("mjcf", "sdf", "usd", "glb") for a in ("--export", f)]
    result = run("sample", grammar, "-n", 1, "-o", tmp_path / "s", "-q", *formats)
    assert result.exit_code == 0, result.output
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "s" / "mjcf" / "bin_000000.xml"))
    bin_geoms = (model.geom_bodyid == model.body("Bin_0").id) & (model.geom_group == 3)
    assert (model.geom_type[bin_geoms] == mujoco.mjtGeom.mjGEOM_BOX).sum() == 5
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert data.ncon == 0 or -data.contact.dist[: data.ncon].min() < 1e-6
    plant, scene_graph = AddMultibodyPlantSceneGraph(DiagramBuilder(), 0.0)
    Parser(plant).AddModels(str(tmp_path / "s" / "sdf" / "bin_000000.sdf"))
    plant.Finalize()
    body = plant.GetBodyByName("body", plant.GetModelInstanceByName("Bin_0"))
    ids = plant.GetCollisionGeometriesForBody(body)
    inspector = scene_graph.model_inspector()
    assert len(ids) == 5 and all(isinstance(inspector.GetShape(i), Box) for i in ids)
    floor = min(ids, key=lambda i: inspector.GetPoseInFrame(i).translation()[2])
    np.testing.assert_allclose(inspector.GetPoseInFrame(floor).translation(), [0, 0, 0.005])
    stage = Usd.Stage.Open(str(tmp_path / "s" / "usd" / "bin_000000.usda"))
    cubes = stage.GetPrimAtPath("/World/Bin_0/collision").GetChildren()
    assert len(cubes) == 5 and all(c.IsA(UsdGeom.Cube) for c in cubes)
    assert all(c.HasAPI(UsdPhysics.CollisionAPI) for c in cubes)
    assert not stage.GetPrimAtPath("/World/Bin_0/geometry").HasAPI(UsdPhysics.CollisionAPI)
    glb = trimesh.load(tmp_path / "s" / "glb" / "bin_000000.glb")
    assert len(glb.geometry["Bin"].faces) == 28
    settled = tmp_path / "settled"
    assert run("settle", tmp_path / "s", "-g", grammar, "-o", settled, "-q").exit_code == 0
    g = load_grammar(grammar)
    before = read_scene_file(tmp_path / "s" / "bin_000000.json", g)
    after = read_scene_file(settled / "bin_000000.json", g)
    assert np.linalg.norm(after.xyz - before.xyz, axis=1).max() < 1e-3


def test_non_penetration_sees_what_rests_in_a_tray_apart_and_what_goes_through_it(tmp_path):
    """FCL collides with the tray's closed surface: the mug on its floor is clear of it (by
    less than a millimetre), a mug sunk 3 cm through the floor is not."""
    import dataclasses

    from ssgc.sample.forward import sample_trees

    text = TRAY + "constraints:\n  apart: {non_penetration: {types: [Bin, Mug]}}\n"
    g = load_grammar(tray_grammar(tmp_path, text))
    (check,) = g.constraints
    trees, _ = sample_trees(g, 1, 0)
    mug = int(np.flatnonzero(trees.type == g.type_ids["Mug"])[0])
    assert 0 <= check.margin(trees)[0] < 1e-3
    sunk = trees.xyz.copy()
    sunk[mug, 2] -= 0.03
    assert check.margin(dataclasses.replace(trees, xyz=sunk))[0] < 0


def test_a_tray_is_drawn_by_render() -> None:
    from ssgc.dsl import TrayG, TrayGeometry
    from ssgc.render.scene import primitive_mesh

    g = TrayG(tray=TrayGeometry(size=[0.4, 0.3, 0.12], wall=0.01))
    vertices, faces = primitive_mesh(g)
    assert vertices.shape == (16, 3) and len(faces) == 28


@pytest.mark.parametrize("name", ["env_1632269755585", "env_1632269874884"])
def test_a_real_sink_scene_settles_with_its_dishes_in_the_bin(name: str) -> None:
    """The bin was a free solid box centred on its frame (z = 0), its dishes resting inside
    it at z = 0.015: settling lifted the bin 15 cm and threw the dishes onto its lid or off.
    It is now a static tray whose floor's top is at z = 0.015: the bin stays, every dish moves
    less than 5 cm (1.3 and 1.4 cm here)."""
    from conftest import GRAMMARS, SINK_DATA

    from ssgc.export import scene_bodies
    from ssgc.io.scene import load_scenes
    from ssgc.simulate.settle import settle_scene

    g = load_grammar(GRAMMARS / "sink.yaml")
    (scene,) = [s for s in load_scenes(SINK_DATA, g) if s.name == name]
    result = settle_scene(scene_bodies(g, scene, load_shapes(g)))
    moved = np.linalg.norm(result.xyz - scene.xyz, axis=1)
    is_bin = scene.types == g.type_ids["DishBin"]
    assert result.settled
    assert moved[is_bin].max() == 0.0
    assert moved[~is_bin].max() < 0.05, moved


# --------------------------------------------------------------------------- glTF axes ---


def _gltf_world_poses(path: Path) -> dict[str, np.ndarray]:
    """Each named node's world matrix, read from the glb's own JSON (glTF 2.0: +Y up)."""
    import struct

    data = path.read_bytes()
    (length,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20 : 20 + length])
    nodes = doc["nodes"]
    out: dict[str, np.ndarray] = {}

    def walk(i: int, parent: np.ndarray) -> None:
        node = nodes[i]
        local = np.eye(4)
        if "matrix" in node:
            local = np.array(node["matrix"]).reshape(4, 4).T
        else:
            local[:3, :3] = trimesh.transformations.quaternion_matrix(
                np.roll(node.get("rotation", [0, 0, 0, 1]), 1)
            )[:3, :3]
            local[:3, 3] = node.get("translation", [0, 0, 0])
        world = parent @ local
        out[node.get("name", str(i))] = world
        for child in node.get("children", []):
            walk(child, world)

    for root in doc["scenes"][doc.get("scene", 0)]["nodes"]:
        walk(root, np.eye(4))
    return out


@pytest.mark.parametrize("geometry", [True, False])
def test_glb_is_y_up_with_object_poses_under_its_root(tmp_path: Path, geometry: bool) -> None:
    """glTF is +Y up; the glb was written Z-up, so viewers showed the table on its side.  A
    root node `Z_UP` now turns it -90 degrees about x: each object's world pose in the file is
    that rotation times its scene pose, its node keeps its name (with and without meshes)."""
    from ssgc.export.glb import ROOT_NAME, Z_UP_TO_Y_UP
    from ssgc.geometry import quat_to_matrix

    shape = "geometry: {box: {size: [0.2, 0.2, 0.1]}}" if geometry else ""
    grammar = tmp_path / "g.yaml"
    grammar.write_text(
        "grammar: up\nroot: {type: Base, pose: {xyz: [0.1, 0.2, 0.3]}}\ntypes:\n"
        f"  Base:\n    observed: true\n    {shape}\n    and:\n"
        "      - {child: Top, translation: {offset: [0, 0.5, 1.0]}, "
        "rotation: {offset: {rpy_deg: [10, 20, 30]}}}\n"
        f"  Top: {{observed: true, {shape}}}\n"
    )
    result = run("sample", grammar, "-n", 1, "-o", tmp_path / "s", "-q", "--export", "glb")
    assert result.exit_code == 0, result.output
    doc = json.loads((tmp_path / "s" / "up_000000.json").read_text())
    poses = _gltf_world_poses(tmp_path / "s" / "glb" / "up_000000.glb")
    np.testing.assert_allclose(poses[ROOT_NAME], Z_UP_TO_Y_UP, atol=1e-12)
    for i, o in enumerate(doc["objects"]):
        want = np.eye(4)
        want[:3, :3] = quat_to_matrix(o["pose"]["quat_wxyz"])
        want[:3, 3] = o["pose"]["xyz"]
        np.testing.assert_allclose(poses[f"{o['type']}_{i}"], Z_UP_TO_Y_UP @ want, atol=1e-6)
    top = poses["Top_1"][:3, 3]
    assert top[1] == pytest.approx(1.3)  # 1.3 m up: glTF's y
    if geometry:  # trimesh reads the same poses through the root
        scene = trimesh.load(tmp_path / "s" / "glb" / "up_000000.glb")
        matrix, _ = scene.graph.get("Top_1")
        np.testing.assert_allclose(matrix, poses["Top_1"], atol=1e-6)
