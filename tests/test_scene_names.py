"""Commands that name output files after scenes (`ssg export`, `ssg settle`) refuse two scenes
whose names make one file name, before writing anything: the second file would silently
replace the first."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app

runner = CliRunner()
GRAMMAR = GRAMMARS / "sink.yaml"  # geometry for export and settle, and parses in milliseconds


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


def named_scenes(tmp_path: Path, *names: str) -> Path:
    """A directory of one sampled sink scene saved under each of `names`."""
    assert run("sample", GRAMMAR, "-n", 1, "-o", tmp_path / "s", "-q").exit_code == 0
    doc = json.loads(next((tmp_path / "s").glob("*.json")).read_text())
    scenes = tmp_path / "coll"
    scenes.mkdir()
    for i, name in enumerate(names):
        (scenes / f"s{i}.json").write_text(json.dumps({**doc, "name": name}))
    return scenes


COMMANDS = [
    (("export", "-f", "glb"), "a_b.glb"),
    (("export", "-f", "dmd"), "a_b.dmd.yaml"),
    (("settle",), "a_b.json"),
]


@pytest.mark.parametrize(("command", "file"), COMMANDS)
def test_two_scenes_with_one_file_name_are_refused_before_writing(
    tmp_path: Path, command: tuple[str, ...], file: str
) -> None:
    scenes = named_scenes(tmp_path, "a b", "a/b")
    out = tmp_path / "out"
    result = run(command[0], scenes, "-g", GRAMMAR, *command[1:], "-o", out)
    assert result.exit_code == 1, result.output
    message = f"{scenes}: error: scenes 'a b' and 'a/b' would both be written to {file}; rename one"
    assert message in result.output
    assert "Traceback" not in result.output
    assert not any(out.rglob("*"))  # nothing written (the directory itself is made first)


def test_two_scenes_of_one_name_are_refused(tmp_path: Path) -> None:
    scenes = named_scenes(tmp_path, "same", "same")
    result = run("export", scenes, "-g", GRAMMAR, "-f", "mjcf", "-o", tmp_path / "out")
    assert result.exit_code == 1, result.output
    assert "two scenes 'same' would both be written to same.xml; rename one" in result.output


def test_names_with_distinct_file_names_all_export(tmp_path: Path) -> None:
    """Only a shared file name is refused: 'a b' and 'a_c' are two files."""
    scenes = named_scenes(tmp_path, "a b", "a_c", ".hidden")
    result = run("export", scenes, "-g", GRAMMAR, "-f", "glb", "-o", tmp_path / "out", "-q")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "a_b.glb",
        "a_c.glb",
        "hidden.glb",
    ]


def test_names_that_reorder_or_are_not_text_are_escaped() -> None:
    """A right-to-left override showed `report\u202efdp.exe` as `reportexe.pdf`; U+FFFF is no
    character (XML and YAML files cannot hold it)."""
    from ssgc.errors import Diagnostic, one_line

    assert one_line("report\u202efdp.exe") == "report\\u202efdp.exe"
    assert one_line("n\uffff\u2066") == "n\\uffff\\u2066"
    assert one_line("café 日本 👩\u200d🔬") == "café 日本 👩\u200d🔬"  # a joiner is text
    forged = str(Diagnostic("real", "d/x\x1b[2J\nt.yaml", 1, 1))
    assert forged == "d/x\\x1b[2J\\nt.yaml:1:1: error: real"


@pytest.mark.parametrize("name", ["n\uffff", "x\u202egnp.exe"])
def test_a_scene_name_that_is_not_plain_text_is_refused(tmp_path: Path, name: str) -> None:
    scenes = named_scenes(tmp_path, name)
    result = run("render", scenes, "-o", tmp_path / "r.svg", "-g", GRAMMAR)
    assert result.exit_code == 1 and "one line of printable text" in result.output
    assert not (tmp_path / "r.svg").exists()


def test_a_scene_named_by_an_odd_file_name_gets_it_escaped(tmp_path: Path) -> None:
    """A scene without "name" is named by its file, whose name was not checked: escapes
    reached the terminal, and `ssg settle` wrote scenes its own reader refused."""
    scenes = named_scenes(tmp_path, "x")
    odd = scenes / "evil\x1b[2J\nfake: error: x.json"
    doc = json.loads((scenes / "s0.json").read_text())
    del doc["name"]
    odd.write_text(json.dumps(doc))
    (scenes / "s0.json").unlink()
    shown = "evil\\x1b[2J\\nfake: error: x"
    result = run("explain", scenes, "-g", GRAMMAR)
    assert result.exit_code == 0, result.output
    assert "\x1b" not in result.output and shown in result.output
    settled = tmp_path / "settled"
    result = run("settle", scenes, "-g", GRAMMAR, "-o", settled, "-q", "--max-time", "0.2")
    assert result.exit_code in (0, 2), result.output
    from ssgc.compile import load_grammar
    from ssgc.io.scene import load_scenes

    assert [s.name for s in load_scenes(settled, load_grammar(GRAMMAR))] == [shown]
    parsed = tmp_path / "p.json"
    assert run("parse", scenes, "-g", GRAMMAR, "-o", parsed, "-q").exit_code == 0
    assert run("export", parsed, "-g", GRAMMAR, "-f", "glb", "-o", tmp_path / "e").exit_code == 0
    result = run("render", scenes, "-o", tmp_path / "r.svg", "-g", GRAMMAR)
    assert result.exit_code == 0, result.output
    import xml.etree.ElementTree as ET

    ET.parse(tmp_path / "r.svg")


def test_a_parse_result_with_a_name_that_is_not_text_is_refused(tmp_path: Path) -> None:
    scenes = named_scenes(tmp_path, "x")
    parsed = tmp_path / "p.json"
    assert run("parse", scenes, "-g", GRAMMAR, "-o", parsed, "-q").exit_code == 0
    doc = json.loads(parsed.read_text())
    doc["scenes"][0]["name"] = "a\x1b[31mb"
    parsed.write_text(json.dumps(doc))
    result = run("render", parsed, "-o", tmp_path / "r.svg")
    assert result.exit_code == 1 and "one line of printable text" in result.output, result.output
