"""`ssg settle`: scenes simulated in MuJoCo to rest, written back as scenes with provenance."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.errors import SsgError
from ssgc.io.resume import MANIFEST
from ssgc.io.scene import read_scene_file
from ssgc.simulate.settle import SettleOptions

runner = CliRunner()

# A fixed tray (top at z = 0.01), a box 1 cm above it, a ball 2 cm into it.
GRAMMAR = """
grammar: drop
root: Tray
types:
  Tray:
    observed: true
    geometry: {box: {size: [1.0, 1.0, 0.02]}}
    body: {static: true}
    and:
      - {child: Block, translation: {offset: [0.2, 0, 0.06]}}
      - {child: Ball, translation: {offset: [-0.2, 0, 0.02]}}
  Block: {observed: true, geometry: {box: {size: [0.1, 0.1, 0.08]}}, body: {mass: 0.5}}
  Ball: {observed: true, geometry: {sphere: {radius: 0.03}}, body: {density: 800}}
"""


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def dropped(tmp_path: Path) -> tuple[Path, Path]:
    grammar = tmp_path / "drop.yaml"
    grammar.write_text(GRAMMAR)
    result = run("sample", grammar, "-n", 1, "-o", tmp_path / "scenes", "-q")
    assert result.exit_code == 0, result.output
    return grammar, tmp_path / "scenes"


def test_settling_drops_the_block_and_lifts_the_ball(dropped, tmp_path: Path) -> None:
    grammar, scenes = dropped
    out, report = tmp_path / "settled", tmp_path / "report.json"
    result = run("settle", scenes, "-g", grammar, "-o", out, "--report", report)
    assert result.exit_code == 0, result.output
    assert "settled 1 of 1 scene(s)" in result.output
    (r,) = json.loads(report.read_text())["scenes"]
    assert r["settled"]
    assert r["penetration_before"] == pytest.approx(0.02, abs=1e-3)  # the ball, into the tray
    assert r["penetration_after"] <= 1e-3
    g = load_grammar(grammar)
    scene = read_scene_file(out / "drop_000000.json", g)
    before = read_scene_file(scenes / "drop_000000.json", g)
    np.testing.assert_array_equal(scene.xyz[0], before.xyz[0])  # the fixed tray stays
    # Resting on the tray's top (z = 0.01): the block's centre at 0.05, the ball's at 0.04.
    np.testing.assert_allclose(scene.xyz[1], [0.2, 0.0, 0.05], atol=1.5e-3)
    np.testing.assert_allclose(scene.xyz[2], [-0.2, 0.0, 0.04], atol=1.5e-3)
    assert r["max_displacement"] == pytest.approx(0.02, abs=2e-3)
    doc = json.loads((out / "drop_000000.json").read_text())
    assert "tree" not in doc and "log_prob" not in doc  # they describe the unsettled poses
    settle = doc["metadata"]["settle"]
    assert settle["engine"] == "mujoco" and settle["source_scene"] == "drop_000000"
    assert settle["settled"] is True


def test_too_short_a_simulation_is_reported_not_settled(dropped, tmp_path: Path) -> None:
    grammar, scenes = dropped
    result = run("settle", scenes, "-g", grammar, "-o", tmp_path / "o", "--max-time", 0.21)
    assert result.exit_code == 2, result.output
    assert "drop_000000: not settled: did not come to rest" in result.stderr
    doc = json.loads((tmp_path / "o" / "drop_000000.json").read_text())
    assert doc["metadata"]["settle"]["settled"] is False
    # --max-time is at most: 0.21 s simulated 0.25 s, five 50 ms chunks of steps
    assert doc["metadata"]["settle"]["sim_time"] == pytest.approx(0.21)


def test_sample_settle_writes_settled_scenes(tmp_path: Path) -> None:
    grammar = tmp_path / "drop.yaml"
    grammar.write_text(GRAMMAR)
    result = run("sample", grammar, "-n", 2, "-o", tmp_path / "s", "-q", "--settle")
    assert result.exit_code == 0, result.output
    for path in sorted((tmp_path / "s").glob("*.json")):
        doc = json.loads(path.read_text())
        assert doc["metadata"]["settle"]["settled"] is True
        assert doc["metadata"]["settle"]["index"] == int(path.stem[-1])
        assert doc["objects"][1]["pose"]["xyz"][2] == pytest.approx(0.05, abs=1.5e-3)


def test_unknown_engine_is_a_message(dropped, tmp_path: Path) -> None:
    grammar, scenes = dropped
    result = run("settle", scenes, "-g", grammar, "--engine", "bullet", "-o", tmp_path / "o")
    assert result.exit_code == 1
    assert "unknown engine 'bullet'" in result.output


def test_dimsum_scene_settles(tmp_path: Path) -> None:
    """A sampled dimsum table with meshes and a convex decomposition settles in MuJoCo."""
    scenes = tmp_path / "s"
    assert run("sample", GRAMMARS / "dimsum_table.yaml", "-n", 1, "-o", scenes, "-q").exit_code == 0
    report = tmp_path / "r.json"
    result = run(
        "settle",
        scenes,
        "-g",
        GRAMMARS / "dimsum_table.yaml",
        "-o",
        tmp_path / "o",
        "--report",
        report,
    )
    assert result.exit_code == 0, result.output
    (r,) = json.loads(report.read_text())["scenes"]
    assert r["settled"] and r["penetration_after"] <= 1e-3
    assert r["max_displacement"] < 0.05


UNSTABLE = """grammar: unstable
root: Tray
types:
  Tray:
    observed: true
    geometry: {box: {size: [1.0, 1.0, 0.02]}}
    body: {static: true}
    and:
      - child: Hair
        translation: {world_box_offset: {min: [-0.1, -0.1, 0.0], max: [0.1, 0.1, 0.02]}}
        rotation: uniform
      - child: Hair
        translation: {world_box_offset: {min: [-0.1, -0.1, 0.0], max: [0.1, 0.1, 0.02]}}
        rotation: uniform
      - child: Slab
        translation: {world_box_offset: {min: [-0.05, -0.05, 0.02], max: [0.05, 0.05, 0.03]}}
  Hair:
    observed: true
    geometry: {cylinder: {radius: 0.00003, length: 0.5}}
    body: {density: 1.0e5}
  Slab: {observed: true, geometry: {box: {size: [0.4, 0.4, 0.02]}}, body: {density: 20000}}
"""


def test_an_unstable_simulation_is_said_in_our_words(tmp_path: Path, monkeypatch, capfd) -> None:
    """MuJoCo printed its own warning (also with -q) and left MUJOCO_LOG.TXT in the current
    directory; the scene's line said only that it did not come to rest."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "g.yaml").write_text(UNSTABLE)
    assert CliRunner().invoke(app, ["sample", "g.yaml", "-n", "3", "-o", "s", "-q"]).exit_code == 0
    capfd.readouterr()
    result = CliRunner().invoke(
        app, ["settle", "s", "-g", "g.yaml", "-o", "st", "--report", "r.json"]
    )
    assert result.exit_code == 2, result.output
    printed = capfd.readouterr()
    assert "WARNING" not in printed.err + printed.out
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    report = json.loads((tmp_path / "r.json").read_text())
    unstable = [s["name"] for s in report["scenes"] if s["unstable"]]
    assert unstable and all(
        f"{n}: not settled: the simulation went unstable" in result.output for n in unstable
    )


def test_settle_never_writes_over_its_input_scene(dropped, tmp_path: Path) -> None:
    """`ssg settle d/s.json -o d` would replace the scene it reads: refused before any work."""
    grammar, scenes = dropped
    scene = next(scenes.glob("*.json"))
    before = scene.read_bytes()
    result = run("settle", scene, "-g", grammar, "-o", scenes)
    assert result.exit_code == 1, result.output
    assert "is the input file" in result.output and "Traceback" not in result.output
    assert scene.read_bytes() == before
    assert sorted(p.name for p in scenes.iterdir()) == sorted([MANIFEST, scene.name])


def test_the_report_cannot_be_a_settled_scene(dropped, tmp_path: Path) -> None:
    grammar, scenes = dropped
    out = tmp_path / "settled"
    out.mkdir()
    report = out / next(scenes.glob("*.json")).name
    result = run("settle", scenes, "-g", grammar, "-o", out, "--report", report, "-q")
    assert result.exit_code == 1, result.output
    assert "the settled scene and the report are the same file" in result.output
    assert list(out.iterdir()) == []


def test_a_settled_sample_run_resumes(tmp_path: Path) -> None:
    """Settled files keep the run's seed and index in `metadata.settle` only; `--resume` reads
    them there (it once refused every file: 'this scene file has seed null, index null')."""
    grammar = tmp_path / "drop.yaml"
    grammar.write_text(GRAMMAR)
    out = tmp_path / "s"
    args = ("sample", grammar, "-n", 3, "--seed", 1, "-o", out, "--settle")
    assert run(*args, "-q").exit_code == 0
    files = {p.name: p.read_bytes() for p in sorted(out.glob("*.json"))}
    result = run(*args, "--resume")
    assert result.exit_code == 0, result.output
    assert "wrote 0 scene(s)" in result.output and "kept 3 complete" in result.output
    assert {p.name: p.read_bytes() for p in sorted(out.glob("*.json"))} == files
    (out / "drop_000001.json").unlink()
    result = run(*args, "--resume")
    assert result.exit_code == 0, result.output
    assert "wrote 1 scene(s)" in result.output and "kept 2 complete" in result.output
    doc = json.loads((out / "drop_000001.json").read_text())
    assert doc["metadata"]["settle"]["index"] == 1


def test_a_settled_and_a_plain_run_are_two_runs(tmp_path: Path) -> None:
    """--settle is part of a run: resuming a plain run with it (or a settled one without it)
    filled the directory with a mixture of settled and unsettled scenes, exit 0."""
    grammar = tmp_path / "drop.yaml"
    grammar.write_text(GRAMMAR)
    out = tmp_path / "s"
    args = ("sample", grammar, "-n", 3, "--seed", 1, "-o", out)
    assert run(*args, "-q").exit_code == 0
    (out / "drop_000001.json").unlink()
    files = {p.name: p.read_bytes() for p in sorted(out.glob("*.json"))}
    result = run(*args, "--settle", "--resume", "-q")
    assert result.exit_code == 1
    assert "another run (settle: false, now true)" in result.output
    assert {p.name: p.read_bytes() for p in sorted(out.glob("*.json"))} == files
    result = run(*args, "--export", "sdf", "--resume", "-q")
    assert result.exit_code == 1 and '(export: [], now ["sdf"])' in result.output


def test_sample_settle_exits_2_when_a_scene_does_not_settle(tmp_path: Path, monkeypatch) -> None:
    """As `ssg settle` does; the scenes are written all the same."""
    import ssgc.simulate.settle as settle

    real = settle.settle_scene
    monkeypatch.setattr(settle, "settle_scene", lambda b, o=None: real(b, SettleOptions(0.2)))
    grammar = tmp_path / "drop.yaml"
    grammar.write_text(GRAMMAR)
    out = tmp_path / "s"
    result = run("sample", grammar, "-n", 2, "-o", out, "--settle", "-q")
    assert result.exit_code == 2, result.output
    assert "2 scene(s) did not settle" in result.output
    assert len(list(out.glob("*.json"))) == 2


def test_settle_never_writes_into_a_sample_run(tmp_path: Path) -> None:
    """`ssg settle B/s.json -o A`, A a directory of `ssg sample`, replaced A's scene file
    without a word, and A's `--resume` then failed ("this scene file has seed null ...").
    Refused now, as is replacing any file but a settled scene; settling into the same
    output again still replaces its settled scenes."""
    grammar = tmp_path / "drop.yaml"
    grammar.write_text(GRAMMAR)
    a, b = tmp_path / "A", tmp_path / "B"
    assert run("sample", grammar, "-n", 2, "--seed", 1, "-o", a, "-q").exit_code == 0
    assert run("sample", grammar, "-n", 2, "--seed", 2, "-o", b, "-q").exit_code == 0
    before = {p.name: p.read_bytes() for p in a.iterdir()}
    result = run("settle", b / "drop_000000.json", "-g", grammar, "-o", a, "-q")
    assert result.exit_code == 1, result.output
    assert f"{a}: error: the output directory holds a run of `ssg sample`" in result.output
    assert {p.name: p.read_bytes() for p in a.iterdir()} == before
    assert run("sample", grammar, "-n", 2, "--seed", 1, "-o", a, "-q", "--resume").exit_code == 0
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "drop_000000.json").write_bytes((a / "drop_000001.json").read_bytes())
    result = run("settle", b / "drop_000000.json", "-g", grammar, "-o", plain, "-q")
    assert result.exit_code == 1, result.output
    assert "is not a scene `ssg settle` wrote" in result.output
    assert (plain / "drop_000000.json").read_bytes() == (a / "drop_000001.json").read_bytes()
    for _ in range(2):
        result = run("settle", b / "drop_000000.json", "-g", grammar, "-o", tmp_path / "st", "-q")
        assert result.exit_code == 0, result.output


def test_settle_takes_the_lock_of_its_output_directory(dropped, tmp_path: Path) -> None:
    """As `ssg sample` does: a second writer into the directory is refused at once."""
    from ssgc.io.outputs import directory_lock

    grammar, scenes = dropped
    out = tmp_path / "settled"
    out.mkdir()
    with directory_lock(out):
        result = run("settle", scenes, "-g", grammar, "-o", out, "-q")
    assert result.exit_code == 1, result.output
    assert "another ssg run is writing this output directory" in result.output
    assert list(out.glob("*.json")) == []


def test_a_max_time_below_the_still_time_is_refused(dropped, tmp_path: Path) -> None:
    """Below the 0.2 s every object must stay still, nothing could ever settle: not even an
    empty scene ("not settled: did not come to rest; largest displacement 0.0 mm")."""
    grammar, scenes = dropped
    result = run("settle", scenes, "-g", grammar, "-o", tmp_path / "o", "--max-time", 0.1)
    assert result.exit_code == 1, result.output
    assert "--max-time 0.1 is shorter than the 0.2 s" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "o").exists()
    with pytest.raises(SsgError, match=r"shorter than the 0\.2 s"):
        SettleOptions(max_time=0.1)


@pytest.mark.parametrize("objects", [[], [{"type": "Tray", "pose": {"xyz": [0, 0, 0.3]}}]])
def test_a_scene_without_a_free_body_is_settled_at_once(dropped, tmp_path, objects) -> None:
    """No object, or fixed ones only: nothing can move, so there is nothing to wait for."""
    grammar, _ = dropped
    scene = tmp_path / "still.json"
    scene.write_text(json.dumps({"name": "still", "objects": objects}))
    report = tmp_path / "r.json"
    args = ("-g", grammar, "-o", tmp_path / "o", "--report", report, "--max-time", 0.2)
    result = run("settle", scene, *args)
    assert result.exit_code == 0, result.output
    (r,) = json.loads(report.read_text())["scenes"]
    assert r["settled"] and r["sim_time"] == 0.0 and r["max_displacement"] == 0.0
    doc = json.loads((tmp_path / "o" / "still.json").read_text())
    assert [o["pose"]["xyz"] for o in doc["objects"]] == [o["pose"]["xyz"] for o in objects]
