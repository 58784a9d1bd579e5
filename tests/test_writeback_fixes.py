"""Write-back fixes found by a fit hunt (ssgc.fit.writeback, docs/fitting.md section 5.1).

A JSON grammar must come back as JSON also where the fit adds a whole mapping (a `mode`, a
`tail`): its keys have no neighbours to copy the quoting from.  A number the fit leaves at its
value must keep its text (`0` is not rewritten `0.0`), and an end-of-line comment keeps its
column where the new text leaves room, so a diff of a fitted grammar shows only new numbers.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from ruamel.yaml import YAML
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.fit.writeback import Orientation, Update, apply_updates, format_number
from ssgc.geometry import quat_canonical, rpy_to_quat
from ssgc.io.scene import dumps_scene, scene_from_tree
from ssgc.sample.forward import sample_trees

JSON_GRAMMAR = """\
{"grammar":"j","root":"Root","types":{"Root":{"observed":true,"and":[
 {"child":"P","translation":{"world_normal":{"mean":[0,0,0],"variance":0.1}},\
"rotation":{"world_bingham":{"concentration":1}}},
 {"child":"P","translation":{"world_normal":{"mean":[1,0,0],"variance":0.1}},\
"rotation":{"world_bingham":{"mode":{"quat_wxyz":[1,0,0,0]},"concentration":1}}}]},
 "P":{"observed":true,"geometry":{"sphere":{"radius":0.05}}}},
 "constraints":{"apart":{"non_penetration":{"types":["P"]}}}}
"""
BINGHAM = ("types", "Root", "and", 0, "rotation", "world_bingham")
APART = ("constraints", "apart", "non_penetration")


def yaml_reading(text: str) -> Any:
    """The text as a YAML reader (and so the grammar loader) sees it."""
    return YAML(typ="safe", pure=True).load(text)


def column(text: str, comment: str) -> int:
    """Column of `comment` on its line."""
    line = next(line for line in text.splitlines() if comment in line)
    return line.index(comment)


def test_a_new_mode_and_tail_in_a_json_grammar_have_quoted_keys() -> None:
    """The new `mode` and `tail` mappings were written `{rpy_deg: [...]}` and `{rate: ...,
    mean: ...}`: `_insert` quoted a key only like the existing keys of its mapping, and a new
    mapping has none, so the file was no longer JSON."""
    q = rpy_to_quat([0.4, -0.3, 2.0])
    updates = [
        Update(BINGHAM, {"mode": Orientation(tuple(q)), "concentration": 3.25}),
        Update(APART, {"tail": {"rate": 0.025, "mean": 0.0123456789}}),
    ]
    out = apply_updates(JSON_GRAMMAR, updates, "g.json")
    data = json.loads(out)
    assert data == yaml_reading(out)
    bingham = data["types"]["Root"]["and"][0]["rotation"]["world_bingham"]
    assert list(bingham) == ["mode", "concentration"] and list(bingham["mode"]) == ["rpy_deg"]
    back = rpy_to_quat(np.radians(bingham["mode"]["rpy_deg"]))
    np.testing.assert_allclose(quat_canonical(back), quat_canonical(q), atol=1e-7)
    assert bingham["concentration"] == 3.25
    tail = data["constraints"]["apart"]["non_penetration"]["tail"]
    assert tail == {"rate": 0.025, "mean": float(format_number(0.0123456789))}


def test_a_key_added_to_an_empty_mapping_is_quoted_in_json() -> None:
    """`"mode": {}` written by the user has no keys to copy: the document's quoting decides."""
    text = JSON_GRAMMAR.replace('{"concentration":1}', '{"mode":{},"concentration":1}', 1)
    q = rpy_to_quat([0.0, 0.0, 0.5])
    out = apply_updates(text, [Update(BINGHAM, {"mode": Orientation(tuple(q))})])
    assert '"mode": {"rpy_deg": [' in out
    assert json.loads(out) == yaml_reading(out)


def test_yaml_keys_stay_plain() -> None:
    """Only a document that quotes its keys gets quoted new keys."""
    text = "law: {concentration: 1}\ncon: {types: [P]}\n"
    q = rpy_to_quat([0.0, 0.0, 0.5])
    updates = [
        Update(("law",), {"mode": Orientation(tuple(q))}),
        Update(("con",), {"tail": {"rate": 0.5, "mean": 0.25}}),
    ]
    out = apply_updates(text, updates)
    assert out.startswith("law: {mode: {rpy_deg: [")
    assert out.endswith("con: {types: [P], tail: {rate: 0.5, mean: 0.25}}\n")


def sample_scenes(text: str, folder: Path, scenes: int = 20) -> Path:
    """A dataset of `scenes` scenes sampled from the grammar `text`."""
    grammar = compile_text(text)
    trees, logp = sample_trees(grammar, scenes, 1)
    folder.mkdir()
    for i in range(scenes):
        scene = scene_from_tree(grammar, trees.tree(i), f"s{i}", float(logp[i]))
        (folder / f"s{i}.json").write_text(dumps_scene(grammar, scene))
    return folder


def test_ssg_fit_writes_a_json_grammar_back_as_json(tmp_path: Path) -> None:
    """The hunt's reproduction: a fit that adds a `mode` and a `tail` to a JSON grammar."""
    data = sample_scenes(JSON_GRAMMAR, tmp_path / "scenes")
    grammar, out = tmp_path / "g.json", tmp_path / "fit.json"
    grammar.write_text(JSON_GRAMMAR)
    args = ["fit", str(data), "-g", str(grammar), "-o", str(out), "--iterations", "1", "-q"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    text = out.read_text()
    fitted = json.loads(text)
    assert fitted == yaml_reading(text)
    assert "mode" in fitted["types"]["Root"]["and"][0]["rotation"]["world_bingham"]
    assert set(fitted["constraints"]["apart"]["non_penetration"]["tail"]) == {"rate", "mean"}
    compile_text(text, str(out))


def test_a_number_fitted_to_its_value_keeps_its_text() -> None:
    """`probs: [0, 1]` came back `[0, 1.0]` and `mean: [0.3, 0, 0]` as `[0.3, 0.0, 0]`: every
    fitted number was rewritten, also where its value did not change."""
    text = (
        "c: {probs: [0, 1]}   # one count\n"
        "n: {mean: [0.3, 0, 0], variance: 1.0e-06, max: 3}\n"
        "q: {quat_wxyz: [1, 0, 0, 0]}\n"
    )
    updates = [
        Update(("c",), {"probs": [0.0, 1.0]}),
        Update(("n",), {"mean": [0.3, 0.0, -0.0], "variance": 1e-6, "max": 3}),
    ]
    assert apply_updates(text, updates) == text
    changed = apply_updates(text, [Update(("n",), {"mean": [0.5, 0.0, 0.25]})])
    assert "n: {mean: [0.5, 0, 0.25], variance: 1.0e-06, max: 3}\n" in changed
    identity = Orientation((1.0, 0.0, 0.0, 0.0))
    assert apply_updates(text, [Update((), {"q": identity})]) == text


def test_an_unchanged_anchored_number_stays_with_its_aliases() -> None:
    """A number written `&v 1` and fitted to 1.0 is kept, and so are its aliases."""
    text = "a: {variance: &v 1}\nb: {variance: *v}\n"
    updates = [Update(("a",), {"variance": 1.0}), Update(("b",), {"variance": 1.0})]
    assert apply_updates(text, updates) == text


def test_ssg_fit_keeps_an_unchanged_count_law(tmp_path: Path) -> None:
    """The hunt's `probs: [0, 1]`: a count law with one possible count fits to itself."""
    text = (
        "grammar: one\nroot: Root\ntypes:\n  Root:\n    observed: true\n    repeat:\n"
        "      count: {probs: [0, 1]}   # always one\n"
        "      rule:\n        child: A\n"
        "        translation: {world_normal: {mean: [0.3, 0, 0], variance: 0.01}}\n"
        "  A: {observed: true}\n"
    )
    data = sample_scenes(text, tmp_path / "scenes", scenes=10)
    grammar, out = tmp_path / "g.yaml", tmp_path / "fit.yaml"
    grammar.write_text(text)
    args = ["fit", str(data), "-g", str(grammar), "-o", str(out), "--iterations", "1", "-q"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "      count: {probs: [0, 1]}   # always one\n" in out.read_text()


def test_a_comment_keeps_its_column_where_there_is_room() -> None:
    """An end-of-line comment stays in its column when the new text is not longer than the
    room before it, and follows one space after a longer one (ruamel.yaml's emitter writes
    a comment at the column it was read at when it can; this checks that it still does)."""
    text = (
        "a:\n"
        "  p: 0.7123456789   # shorter\n"
        "  q: 0.7      # longer\n"
        "  m:\n"
        "    - 0.0   # x\n"
        "    - 0.123456   # y\n"
        "  v: [0.0512345, 0.05]   # per axis\n"
    )
    updates = [Update(("a",), {"p": 0.39, "q": 0.39879257, "m": [0.0, 0.5], "v": [0.1, 0.2]})]
    out = apply_updates(text, updates)
    for comment in ("# shorter", "# x", "# y", "# per axis"):
        assert column(out, comment) == column(text, comment), out
    assert "  q: 0.39879257 # longer\n" in out
    assert "  p: 0.39           # shorter\n" in out
