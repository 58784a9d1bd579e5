"""`ssg export` and `ssg settle` on the mistakes and extremes a hunt found: outputs that are
inputs or another export's files, numbers simulators refuse, meshes too small, poses out of
range, and grammars with several types whose masses no file holds."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from ssgc.assets import load_shapes
from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.dsl import MAX_COORDINATE
from ssgc.errors import SsgError
from ssgc.export.bodies import obj_text
from ssgc.export.write import write_files

runner = CliRunner()
BOX = (
    "grammar: g\nroot: Box\ntypes:\n"
    "  Box: {observed: true, geometry: {box: {size: [0.1, 0.1, 0.1]}}}\n"
)


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


def scene_file(path: Path, name: str, objects: list[tuple[str, list, list]]) -> Path:
    doc = {
        "format": "ssgc.scene/1",
        "name": name,
        "grammar": "g",
        "objects": [{"type": t, "pose": {"xyz": x, "quat_wxyz": q}} for t, x, q in objects],
    }
    path.write_text(json.dumps(doc))
    return path


def box_scene(path: Path, name: str, xyz: list | None = None, quat: list | None = None) -> Path:
    return scene_file(path, name, [("Box", xyz or [0, 0, 0.05], quat or [1, 0, 0, 0])])


def mesh_grammar(folder: Path, file: str = "meshes/Cup.obj", scale: float = 1.0) -> Path:
    """A grammar of one mesh type `Cup`, an icosphere of radius 5 cm (coordinates that no
    fixed number of decimals writes exactly)."""
    (folder / file).parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=2, radius=0.05).export(folder / file)
    grammar = folder / "g.yaml"
    grammar.write_text(
        "grammar: g\nroot: Cup\ntypes:\n"
        f"  Cup: {{observed: true, geometry: {{mesh: {{file: {file}, scale: {scale!r}}}}}}}\n"
    )
    return grammar


# ------------------------------------------------------------ 1. inputs are never outputs ---


def test_a_grammar_named_like_a_scenes_main_file_is_not_overwritten(tmp_path: Path) -> None:
    grammar = tmp_path / "g.dmd.yaml"
    grammar.write_text(BOX)
    scene = box_scene(tmp_path / "g_scene.json", "g")
    result = run("export", scene, "-g", grammar, "-f", "dmd", "-o", tmp_path)
    assert result.exit_code == 1, result.output
    assert "is the input file" in result.output and "would destroy the input" in result.output
    assert grammar.read_text() == BOX
    assert not (tmp_path / "package.xml").exists()  # refused before anything is written


def test_a_mesh_of_the_grammar_inside_the_output_is_not_overwritten(tmp_path: Path) -> None:
    grammar = mesh_grammar(tmp_path)
    mesh = tmp_path / "meshes" / "Cup.obj"
    before = mesh.read_bytes()
    scene = scene_file(tmp_path / "s.json", "s", [("Cup", [0, 0, 0.05], [1, 0, 0, 0])])
    result = run("export", scene, "-g", grammar, "-f", "sdf", "-o", tmp_path)
    assert result.exit_code == 1, result.output
    assert "is the input file" in result.output and "remove it first" not in result.output
    assert mesh.read_bytes() == before and not (tmp_path / "s.sdf").exists()


# ------------------------------------------------- 2. a main file over another's file ---


def test_a_main_file_never_replaces_another_exports_shared_file(tmp_path: Path) -> None:
    (tmp_path / "g.yaml").write_text(BOX)
    out = tmp_path / "mix"
    first = run("export", box_scene(tmp_path / "a.json", "a"), "-g", tmp_path / "g.yaml",
                "-f", "dmd", "-o", out)  # fmt: skip
    assert first.exit_code == 0, first.output
    package = (out / "package.xml").read_bytes()
    scene = box_scene(tmp_path / "p.json", "package")
    result = run("export", scene, "-g", tmp_path / "g.yaml", "-f", "mjcf", "-o", out)
    assert result.exit_code == 1, result.output
    assert "package.xml" in result.output and "not a mjcf scene" in result.output
    assert (out / "package.xml").read_bytes() == package
    again = run("export", box_scene(tmp_path / "a.json", "a"), "-g", tmp_path / "g.yaml",
                "-f", "mjcf", "-o", out)  # fmt: skip
    twice = run("export", tmp_path / "a.json", "-g", tmp_path / "g.yaml", "-f", "mjcf", "-o", out)
    assert again.exit_code == 0 and twice.exit_code == 0, twice.output  # its own main file


# -------------------------------------------------------------- 3. subnormal numbers ---


def test_subnormal_numbers_are_written_as_zero_and_drake_loads_the_world(tmp_path: Path) -> None:
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    (tmp_path / "g.yaml").write_text(BOX)
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    box_scene(scenes / "d.json", "d", quat=[1.0, 1e-310, 0, 0])
    box_scene(scenes / "f.json", "f", xyz=[5e-324, 0.1, 0.2])
    out = tmp_path / "out"
    result = run("export", scenes, "-g", tmp_path / "g.yaml", "-f", "sdf", "-o", out)
    assert result.exit_code == 0, result.output
    for name in ("d", "f"):
        plant, _ = AddMultibodyPlantSceneGraph(DiagramBuilder(), 0.0)
        Parser(plant).AddModels(str(out / f"{name}.sdf"))  # "Out of range" before
        plant.Finalize()
    assert "e-310" not in (out / "d.sdf").read_text()


# ----------------------------------------------------------------------- 4. tiny meshes ---


def test_obj_files_keep_a_tiny_meshs_shape(tmp_path: Path) -> None:
    shape = load_shapes(load_grammar(mesh_grammar(tmp_path, scale=1e-6)))[0]
    text = obj_text(shape.mesh)
    lines = [ln.split() for ln in text.splitlines()]
    written = np.array([list(map(float, w[1:])) for w in lines if w and w[0] == "v"])
    np.testing.assert_allclose(written, shape.mesh.vertices, rtol=1e-12, atol=0)


def test_a_tiny_meshs_hull_has_triangles_and_mujoco_loads_it(tmp_path: Path) -> None:
    grammar = mesh_grammar(tmp_path, scale=1e-5)
    hull = load_shapes(load_grammar(grammar))[0].collision[0]
    assert len(hull.faces) > 0  # trimesh merged its points: no triangle
    scene = scene_file(tmp_path / "s.json", "s", [("Cup", [0, 0, 0.05], [1, 0, 0, 0])])
    result = run("export", scene, "-g", grammar, "-f", "mjcf", "-o", tmp_path / "out")
    assert result.exit_code == 0, result.output
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "out" / "s.xml"))
    assert model.nmesh == 2


def test_a_mesh_too_small_for_mujoco_is_refused_naming_its_type(tmp_path: Path) -> None:
    grammar = mesh_grammar(tmp_path, scale=1e-6)  # edges of about 1.5e-8 m
    scene = scene_file(tmp_path / "s.json", "s", [("Cup", [0, 0, 0.05], [1, 0, 0, 0])])
    out = tmp_path / "out"
    result = run("export", scene, "-g", grammar, "-f", "mjcf", "-o", out)
    assert result.exit_code == 1 and "'Cup'" in result.output, result.output
    assert "too small for MuJoCo" in result.output and "Traceback" not in result.output
    assert not out.exists() or not any(out.rglob("*.*"))


# ------------------------------------------------------- 5. settled poses out of range ---


def test_a_settled_scene_beyond_the_readers_range_keeps_its_poses(tmp_path: Path) -> None:
    grammar = tmp_path / "g.yaml"
    grammar.write_text(BOX.replace("[0.1, 0.1, 0.1]", "[1.0e5, 1.0e5, 1.0e5]"))
    scene = box_scene(tmp_path / "s.json", "s", xyz=[0, 0, 0])
    out = tmp_path / "settled"
    result = run("settle", scene, "-g", grammar, "-o", out)
    assert result.exit_code == 2, result.output
    doc = json.loads((out / "s.json").read_text())
    assert np.all(np.abs(doc["objects"][0]["pose"]["xyz"]) <= MAX_COORDINATE)
    assert doc["metadata"]["settle"]["unstable"] is True
    again = run("export", out / "s.json", "-g", grammar, "-f", "mjcf", "-o", tmp_path / "e")
    assert again.exit_code == 0, again.output  # an ssg command reads it back


# ---------------------------------------------------- 7. every output checked first ---


def test_a_file_where_a_folder_goes_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    (tmp_path / "g.yaml").write_text(BOX)
    out = tmp_path / "out"
    out.mkdir()
    (out / "models").write_text("mine")
    result = run("export", box_scene(tmp_path / "s.json", "s"), "-g", tmp_path / "g.yaml",
                 "-f", "dmd", "-o", out)  # fmt: skip
    assert result.exit_code == 1 and "models" in result.output, result.output
    assert sorted(p.name for p in out.iterdir()) == ["models"]  # no package.xml


def test_a_folder_where_a_file_goes_is_named_not_a_temporary_file(tmp_path: Path) -> None:
    grammar = mesh_grammar(tmp_path / "in")
    out = tmp_path / "out"
    (out / "meshes" / "Cup.obj").mkdir(parents=True)
    scene = scene_file(tmp_path / "s.json", "s", [("Cup", [0, 0, 0.05], [1, 0, 0, 0])])
    result = run("export", scene, "-g", grammar, "-f", "sdf", "-o", out)
    assert result.exit_code == 1, result.output
    assert "Cup.obj:" in result.output and ".tmp" not in result.output
    with pytest.raises(SsgError) as caught:  # and the writer itself, should it get there
        write_files(out, {"meshes/Cup.obj": "v 0 0 0\n", "s.sdf": "<sdf/>"}, "s.sdf")
    assert ".tmp" not in str(caught.value) and "Cup.obj" in str(caught.value)
    assert not (out / "s.sdf").exists()


# ------------------------------------------------------ 8. masses no file holds ---


def test_every_type_with_an_unstorable_mass_is_named_at_its_line(tmp_path: Path) -> None:
    grammar = tmp_path / "g.yaml"
    grammar.write_text(
        "grammar: g\nroot: T\ntypes:\n"
        "  T:\n    observed: true\n    geometry: {box: {size: [1.0e-13, 1.0e-13, 1.0e-13]}}\n"
        "    and:\n      - {child: B, translation: {offset: [0, 0, 0.4]}}\n"
        "  B: {observed: true, geometry: {sphere: {radius: 1.0e-20}}}\n"
    )
    objects = [("T", [0, 0, 0], [1, 0, 0, 0]), ("B", [0, 0, 0.4], [1, 0, 0, 0])]
    scene = scene_file(tmp_path / "s.json", "s", objects)
    result = run("export", scene, "-g", grammar, "-f", "sdf", "-o", tmp_path / "sdf")
    assert result.exit_code == 1, result.output
    assert "g.yaml:6:" in result.output and "g.yaml:9:" in result.output, result.output
    assert "type 'T'" in result.output and "type 'B'" in result.output
    glb = run("export", scene, "-g", grammar, "-f", "glb", "-o", tmp_path / "glb")
    assert glb.exit_code == 0, glb.output  # glTF holds no masses
