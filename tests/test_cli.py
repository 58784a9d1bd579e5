"""The `ssg` command line as a user runs it: exit codes, messages, files."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
from conftest import GRAMMARS, ROOT
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.schemas import SCHEMA_FILES, schema_text

runner = CliRunner()


def run(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def test_validate_every_example_grammar():
    files = sorted(GRAMMARS.glob("*.yaml"))
    assert len(files) >= 7
    result = run("validate", *files)
    assert result.exit_code == 0, result.output
    assert result.output.count(": ok (") == len(files)


def test_validate_reports_located_errors_and_fails(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("grammar: g\nroot: A\ntypes:\n  A:\n    or:\n      - child: Bee\n  B: {}\n")
    result = run("validate", bad, GRAMMARS / "gmm.yaml")
    assert result.exit_code == 1
    assert f"{bad}:6:16: error: child type 'Bee' is not a type of this grammar" in result.output
    assert "gmm.yaml: ok" in result.output


def test_validate_missing_file_is_a_message_not_a_traceback(tmp_path):
    result = run("validate", tmp_path / "nope.yaml")
    assert result.exit_code == 1
    assert "grammar file not found" in result.output
    assert "Traceback" not in result.output


def test_sample_writes_scene_files_and_is_reproducible(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert run("sample", GRAMMARS / "sink.yaml", "-n", 7, "--seed", 11, "-o", a).exit_code == 0
    assert (
        run("sample", GRAMMARS / "sink.yaml", "-n", 300, "--seed", 11, "-o", b, "-q").exit_code == 0
    )
    files = sorted(a.glob("*.json"))
    assert [f.name for f in files] == [f"sink_{i:06d}.json" for i in range(7)]
    for f in files:  # same seed → identical files, and -n 300 extends -n 7
        assert f.read_bytes() == (b / f.name).read_bytes()
    doc = json.loads(files[0].read_text())
    assert {"objects", "tree", "log_prob", "seed", "grammar"} <= set(doc)
    assert doc["objects"][0]["type"] == "DishBin"
    assert len(list(b.glob("*.json"))) == 300
    c = tmp_path / "c"
    run("sample", GRAMMARS / "sink.yaml", "-n", 7, "--seed", 12, "-o", c, "-q")
    assert (c / files[0].name).read_bytes() != files[0].read_bytes()


def test_sample_into_a_file_path_fails_cleanly(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    result = run("sample", GRAMMARS / "gmm.yaml", "-o", blocker / "sub")
    assert result.exit_code == 1
    assert "cannot create the output directory" in result.output


def test_sample_file_names_cannot_escape_the_output_directory(tmp_path):
    text = (GRAMMARS / "gmm.yaml").read_text()
    grammar = tmp_path / "g.yaml"
    grammar.write_text(text.replace("grammar: gmm", 'grammar: "../../evil"'))
    out = tmp_path / "o" / "sub"
    assert run("sample", grammar, "-n", 2, "-o", out, "-q").exit_code == 0
    names = sorted(p.name for p in out.iterdir() if p.name != "ssg-sample.manifest")
    assert names == ["_.._evil_000000.json", "_.._evil_000001.json"]
    assert [p.parent for p in tmp_path.rglob("*evil*")] == [out, out]
    assert (out / names[0]).stat().st_mode & 0o044  # readable by others, not 0600


def test_inspect_tables_and_json():
    result = run("inspect", GRAMMARS / "sink.yaml")
    assert result.exit_code == 0
    assert "supertree: 951 nodes" in result.output
    data = json.loads(run("inspect", GRAMMARS / "sink.yaml", "--json").output)
    assert data["root"] == "DishBin" and data["supertree_nodes"] == 951
    assert len(data["types"]) == 19


def test_bench_sample_json():
    result = run("bench", "sample", GRAMMARS / "sink.yaml", "-n", 512, "--json")
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert data["scenes_per_second"] > 0 and data["score_seconds_per_tree"] > 0
    assert data["max_abs_score_minus_sample_logp"] < 1e-9


def test_bench_fit_json(tmp_path):
    data = tmp_path / "scenes"
    assert (
        run("sample", GRAMMARS / "sink.yaml", "-n", 6, "--seed", 1, "-o", data, "-q").exit_code == 0
    )
    result = run("bench", "fit", GRAMMARS / "sink.yaml", data, "--iterations", 2, "--json")
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["scenes"] == 6 and [r["iteration"] for r in report["iterations"]] == [1, 2]
    for r in report["iterations"]:
        assert r["mstep_seconds"] > 0 and r["estep_seconds"] > 0
        assert abs(r["estep_seconds"] + r["mstep_seconds"] - r["seconds"]) < 0.01
        assert math.isfinite(r["log_evidence"])
    assert report["summary"]["seconds"] >= sum(r["seconds"] for r in report["iterations"]) - 0.01
    bad = run("bench", "fit", GRAMMARS / "sink.yaml", data, "--max-concentration", 0)
    assert bad.exit_code == 2 and "--max-concentration" in bad.output


def test_console_script_exit_codes(tmp_path):
    """The installed `ssg` entry point itself (not the in-process runner)."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("grammar: [unclosed\n")
    proc = subprocess.run(
        [sys.executable, "-m", "ssgc.cli.app", "validate", str(bad)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert proc.returncode == 1
    assert proc.stderr.startswith(f"{bad}:") and "invalid YAML" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("name", sorted(SCHEMA_FILES))
def test_committed_schemas_are_current(name):
    committed = (ROOT / "schemas" / name).read_text()
    assert committed == schema_text(SCHEMA_FILES[name]), (
        f"schemas/{name} is stale: run `ssg schema schemas`"
    )


def test_starting_ssg_does_not_import_scipy_stats() -> None:
    """scipy.stats takes 0.4-0.9 s to import, which every `ssg` command paid before it did
    anything; the code that needs it imports it where it runs."""
    code = "import sys, ssgc.cli.app; print('scipy.stats' in sys.modules)"
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.strip() == "False"
