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
DIMSUM = GRAMMARS / "dimsum_table.yaml"


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


def named_scenes(tmp_path: Path, *names: str) -> Path:
    """A directory of one sampled dimsum table saved under each of `names`."""
    assert run("sample", DIMSUM, "-n", 1, "-o", tmp_path / "s", "-q").exit_code == 0
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
    result = run(command[0], scenes, "-g", DIMSUM, *command[1:], "-o", out)
    assert result.exit_code == 1, result.output
    message = f"{scenes}: error: scenes 'a b' and 'a/b' would both be written to {file}; rename one"
    assert message in result.output
    assert "Traceback" not in result.output
    assert not any(out.rglob("*"))  # nothing written (the directory itself is made first)


def test_two_scenes_of_one_name_are_refused(tmp_path: Path) -> None:
    scenes = named_scenes(tmp_path, "same", "same")
    result = run("export", scenes, "-g", DIMSUM, "-f", "mjcf", "-o", tmp_path / "out")
    assert result.exit_code == 1, result.output
    assert "two scenes 'same' would both be written to same.xml; rename one" in result.output


def test_names_with_distinct_file_names_all_export(tmp_path: Path) -> None:
    """Only a shared file name is refused: 'a b' and 'a_c' are two files."""
    scenes = named_scenes(tmp_path, "a b", "a_c", ".hidden")
    result = run("export", scenes, "-g", DIMSUM, "-f", "glb", "-o", tmp_path / "out", "-q")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "a_b.glb",
        "a_c.glb",
        "hidden.glb",
    ]
