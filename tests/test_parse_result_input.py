"""The commands that read scenes and `ssg parse` outputs (`render`, `view`, `export`,
`settle`) read them through one checked reader: a malformed input is one located message and
exit 1, as `ssg parse` gives for a scene, never a traceback (exit 70), a silently dropped
object or a picture of something that is not a scene."""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path
from typing import Any

import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar

runner = CliRunner()
SINK = GRAMMARS / "sink.yaml"
LOCATED = re.compile(r"^(?P<file>.+?):(?P<line>\d+):(?P<col>\d+): error: ")


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def parsed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A real `ssg parse` output of a sampled sink scene (its tree has latent nodes)."""
    work = tmp_path_factory.mktemp("parsed")
    assert run("sample", SINK, "-n", 3, "--seed", 0, "-o", work / "s", "-q").exit_code == 0
    result = run("parse", work / "s" / "sink_000002.json", "-g", SINK, "-q")
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    nodes = doc["scenes"][0]["parses"][0]["tree"]["nodes"]
    assert len(nodes) >= 4 and not all(n["observed"] for n in nodes)
    return doc


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A sampled sink scene with its tree (objects are its observed nodes)."""
    work = tmp_path_factory.mktemp("scene")
    assert run("sample", SINK, "-n", 3, "--seed", 0, "-o", work, "-q").exit_code == 0
    return json.loads((work / "sink_000002.json").read_text())


def write(path: Path, doc: Any) -> Path:
    path.write_text(json.dumps(doc, indent=1))
    return path


def node_line(text: str, k: int, key: str) -> int:
    """The line of the `k`-th `"key":` in `text` (1-based), to check where an error points."""
    lines = [i + 1 for i, line in enumerate(text.splitlines()) if f'"{key}":' in line]
    return lines[k]


def one_located_error(result: Any, path: Path) -> re.Match[str]:
    """Exit 1 and exactly one `FILE:LINE:COL: error:` line about `path`."""
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    found = LOCATED.match(lines[0])
    assert found and found["file"] == str(path), result.stderr
    return found


def export(path: Path, out: Path, grammar: Path = SINK) -> Any:
    return run("export", path, "-g", grammar, "-f", "dmd", "-o", out, "-q")


def _set(doc: dict[str, Any], path: tuple[Any, ...], value: Any) -> dict[str, Any]:
    doc = copy.deepcopy(doc)
    place = doc
    for key in path[:-1]:
        place = place[key]
    if value is _DELETE:
        del place[path[-1]]
    else:
        place[path[-1]] = value
    return doc


_DELETE = object()
NODE3 = ("scenes", 0, "parses", 0, "tree", "nodes", 3)
MALFORMED = {
    "no type": ((*NODE3, "type"), _DELETE, "type: missing required key"),
    "parse is a number": (("scenes", 0, "parses"), [1], "parses[0]: expected a mapping"),
    "parse is empty": (("scenes", 0, "parses"), [{}], "tree: missing required key"),
    "parses a mapping": (("scenes", 0, "parses"), {"a": 1}, "parses: expected a list"),
    "tree null": (("scenes", 0, "parses", 0, "tree"), None, "tree: expected a mapping"),
    "nodes null": (("scenes", 0, "parses", 0, "tree", "nodes"), None, "nodes: expected a list"),
    "node a number": (NODE3, 5, "nodes[3]: expected a mapping"),
    "type a list": ((*NODE3, "type"), ["x"], "type: expected a string"),
    "scenes a mapping": (("scenes",), {"a": 1}, "scenes: expected a list"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_export_of_a_malformed_parse_result_is_a_located_message(parsed, tmp_path, case):
    """`ssg export` indexed the raw document (`parses[0]["tree"]["nodes"]`, `n["type"]`) and
    stopped with a KeyError or TypeError (exit 70) where `ssg render` said what was wrong."""
    where, value, fragment = MALFORMED[case]
    path = write(tmp_path / "p.json", _set(parsed, where, value))
    result = export(path, tmp_path / "out")
    one_located_error(result, path)
    assert fragment in result.stderr, result.stderr
    assert not (tmp_path / "out").exists()


def test_settle_of_a_malformed_parse_result_is_a_located_message(parsed, tmp_path):
    path = write(tmp_path / "p.json", _set(parsed, (*NODE3, "type"), _DELETE))
    result = run("settle", path, "-g", SINK, "-o", tmp_path / "out", "-q")
    one_located_error(result, path)
    assert "missing required key" in result.stderr


def test_a_parse_node_of_a_type_not_in_the_grammar_is_an_error(parsed, tmp_path):
    """A node of a type the grammar lacks was dropped, and the scene exported without it
    (exit 0); latent nodes of the grammar are part of every parse and are no objects."""
    path = write(tmp_path / "p.json", _set(parsed, (*NODE3, "type"), "Spaceship"))
    found = one_located_error(export(path, tmp_path / "out"), path)
    assert int(found["line"]) == node_line(path.read_text(), 3, "type")
    assert "'Spaceship', not a type in grammar 'sink'" in found.string
    good = write(tmp_path / "good.json", parsed)
    assert export(good, tmp_path / "good").exit_code == 0
    (dmd,) = (tmp_path / "good").glob("*.dmd.yaml")
    observed = [n for n in parsed["scenes"][0]["parses"][0]["tree"]["nodes"] if n["observed"]]
    assert dmd.read_text().count("add_model") == len(observed)


def test_a_parse_of_another_grammar_is_an_error(tmp_path):
    """A parse of a dimsum_table scene exported with the sink grammar wrote `directives: []`."""
    table = GRAMMARS / "dimsum_table.yaml"
    assert run("sample", table, "-n", 1, "--seed", 0, "-o", tmp_path / "s", "-q").exit_code == 0
    (sampled,) = (tmp_path / "s").glob("*.json")
    doc = json.loads(sampled.read_text())
    parse = {"scenes": [{"name": "t", "parses": [{"tree": doc["tree"]}]}]}
    path = write(tmp_path / "p.json", parse)
    result = export(path, tmp_path / "out")
    assert result.exit_code == 1, result.output
    assert f"has unknown type '{doc['tree']['nodes'][0]['type']}'" in result.stderr
    assert "not a type in grammar 'sink'" in result.stderr
    assert not (tmp_path / "out").exists()
    assert export(path, tmp_path / "own", table).exit_code == 0


def test_a_bad_quaternion_in_a_parse_is_located_at_its_node(parsed, tmp_path):
    """It was reported at 1:1: the reader looked for it at `objects[i]`, which a parse
    output does not have."""
    path = write(tmp_path / "p.json", _set(parsed, (*NODE3, "pose", "quat_wxyz"), [2, 0, 0, 0]))
    for command in ("export", "render"):
        out = tmp_path / ("out" if command == "export" else "p.png")
        args = ("-f", "dmd", "-o", out) if command == "export" else ("-o", out)
        found = one_located_error(run(command, path, "-g", SINK, *args, "-q"), path)
        assert "unit norm, got norm 2" in found.string
        assert int(found["line"]) == node_line(path.read_text(), 3, "quat_wxyz")


def test_a_huge_parent_is_a_located_message_for_render_and_view(parsed, scene, tmp_path):
    """`parent: 10**30` overflowed numpy's int64 (OverflowError, exit 70)."""
    inputs = {
        "p.json": _set(parsed, (*NODE3, "parent"), 10**30),
        "s.json": _set(scene, ("tree", "nodes", 3, "parent"), 10**30),
    }
    for name, doc in inputs.items():
        path = write(tmp_path / name, doc)
        for command, out in (("render", "x.png"), ("view", "x.html")):
            found = one_located_error(run(command, path, "-o", tmp_path / out, "-q"), path)
            assert "a node's parent must be listed before it" in found.string
            assert int(found["line"]) == node_line(path.read_text(), 3, "parent")
            assert not (tmp_path / out).exists()


SCENE_MISTAKES = {
    "zero quaternion": (("objects", 0, "pose", "quat_wxyz"), [0, 0, 0, 0], "got norm 0"),
    "long quaternion": (("objects", 0, "pose", "quat_wxyz"), [2, 0, 0, 0], "got norm 2"),
    "bad id": (("tree", "nodes", 2, "id"), 7, "node ids must be 0..3 in order"),
    "parent after": (("tree", "nodes", 1, "parent"), 2, "parent must be listed before it"),
    "objects not the tree": (("objects", 0, "pose", "xyz", 0), 0.25, "observed nodes of `tree`"),
}


@pytest.mark.parametrize("case", sorted(SCENE_MISTAKES))
@pytest.mark.parametrize("command", ["render", "view"])
def test_render_and_view_refuse_what_parse_refuses(scene, tmp_path, case, command):
    """They drew a zero quaternion as the identity, normalised [2, 0, 0, 0] silently and drew
    malformed trees; without a grammar as with one, they check what needs no grammar."""
    where, value, fragment = SCENE_MISTAKES[case]
    path = write(tmp_path / "s.json", _set(scene, where, value))
    out = tmp_path / ("x.png" if command == "render" else "x.html")
    found = one_located_error(run(command, path, "-o", out, "-q"), path)
    assert fragment in found.string
    parse = run("parse", path, "-g", SINK, "-q")
    assert parse.exit_code == 1 and found.string in parse.stderr  # the same words and place


def test_render_checks_rules_against_a_grammar_when_given_one(scene, tmp_path):
    path = write(tmp_path / "s.json", _set(scene, ("tree", "nodes", 1, "rule"), 7))
    found = one_located_error(run("render", path, "-g", SINK, "-o", tmp_path / "x.png"), path)
    assert "rule(s), no rule 7" in found.string


def test_render_refuses_duplicate_keys(scene, tmp_path):
    """JSON's last-wins for a repeated key hid a mistake that `ssg parse` reports."""
    text = json.dumps(scene, indent=1).replace('"xyz":', '"xyz": [9, 9, 9], "xyz":', 1)
    path = tmp_path / "dup.json"
    path.write_text(text)
    found = one_located_error(run("render", path, "-o", tmp_path / "x.png", "-q"), path)
    assert "duplicate key 'xyz'" in found.string


def test_a_tree_error_in_render_names_the_file_and_place(scene, tmp_path):
    """`ssg render` said `tree_cycle: error: 'sink_000002': ...`: the stem as the file."""
    path = write(tmp_path / "tree_cycle.json", _set(scene, ("tree", "nodes", 1, "parent"), 2))
    found = one_located_error(run("render", path, "-o", tmp_path / "x.png", "-q"), path)
    assert int(found["line"]) == node_line(path.read_text(), 1, "parent")


def test_non_finite_metadata_is_refused(scene, tmp_path):
    """`json` reads NaN and Infinity, and `ssg settle` wrote them back as bare `NaN`, which is
    not JSON; the sink YAML's `.nan` too."""
    text = json.dumps({**scene, "metadata": {"a": [1, float("-inf")]}}, indent=1)
    path = tmp_path / "meta.json"
    path.write_text(text)
    line = next(i + 1 for i, s in enumerate(text.splitlines()) if "-Infinity" in s)
    for args in (("parse", path, "-g", SINK), ("settle", path, "-g", SINK, "-o", tmp_path / "o")):
        found = one_located_error(run(*args, "-q"), path)
        assert "finite numbers" in found.string and int(found["line"]) == line
    model = next(t.model for t in load_grammar(SINK).types if t.model)
    sink = tmp_path / "d.yaml"
    sink.write_text(
        f"s1:\n  objects:\n  - model_file: {model}\n    metadata: {{weight: .nan}}\n"
        "    pose: {xyz: [0, 0, 0], rpy: [0, 0, 0]}\n"
    )
    found = one_located_error(run("parse", sink, "-g", SINK, "-q"), sink)
    assert "finite numbers" in found.string and found["line"] == "4"


def test_a_long_type_name_is_shortened_in_the_message(scene, tmp_path):
    path = write(tmp_path / "long.json", _set(scene, ("objects", 0, "type"), "T" * 100_000))
    del_tree = json.loads(path.read_text())
    del del_tree["tree"]
    write(path, del_tree)
    found = one_located_error(run("parse", path, "-g", SINK, "-q"), path)
    assert len(found.string) < 300 and "T" * 60 + "…'" in found.string


@pytest.mark.parametrize("encoding", ["utf-16", "utf-16-le"])
def test_a_utf16_file_is_said_to_be_utf16(scene, tmp_path, encoding):
    path = tmp_path / "wide.json"
    path.write_bytes(json.dumps(scene).encode(encoding))
    for args in (("parse", path, "-g", SINK), ("render", path, "-o", tmp_path / "x.png")):
        result = run(*args, "-q")
        assert result.exit_code == 1, result.output
        assert f"{path}: error: " in result.stderr and "UTF-16" in result.stderr
        assert "reads UTF-8" in result.stderr and "NUL" not in result.stderr.split("(")[0]


def test_a_parse_result_given_as_a_scene_says_which_commands_read_it(parsed, tmp_path):
    """It was `unknown key 'scenes' ... (did you mean 'seed'?)`."""
    path = write(tmp_path / "p.json", parsed)
    for args in (
        ("parse", path, "-g", SINK, "-q"),
        ("explain", path, "-g", SINK),
        ("fit", path, "-g", SINK, "-o", tmp_path / "f.yaml", "-q"),
    ):
        found = one_located_error(run(*args), path)
        assert "this is an `ssg parse` output" in found.string
        assert "`ssg render`, `view`, `export` and `settle`" in found.string
        assert "did you mean" not in found.string
