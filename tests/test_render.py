"""`ssg render` and `ssg inspect --diagram`: every kind of input draws a picture that is not
blank, user mistakes are one clear message, and no output file is left behind by a failure."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from conftest import GRAMMARS, SINK_DATA
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar

pytest.importorskip("matplotlib")
runner = CliRunner()
SINK = GRAMMARS / "sink.yaml"


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes")
    assert run("sample", SINK, "-n", 3, "--seed", 2, "-o", out, "-q").exit_code == 0
    return out


@pytest.fixture(scope="module")
def parse_result(scenes, tmp_path_factory):
    out = tmp_path_factory.mktemp("parse") / "parse.json"
    result = run("parse", scenes / "sink_000000.json", "-g", SINK, "-o", out, "-q")
    assert result.exit_code == 0, result.output
    return out


def assert_not_blank_png(path):
    from matplotlib.image import imread

    pixels = imread(path)[..., :3]
    coloured = np.any(np.abs(pixels - 1.0) > 0.05, axis=-1)  # not white
    assert coloured.mean() > 0.02
    assert np.ptp(pixels) > 0.5


def test_scene_without_tree_draws_markers_without_a_grammar(scenes, tmp_path):
    doc = json.loads((scenes / "sink_000001.json").read_text())
    del doc["tree"]
    scene = tmp_path / "plain.json"
    scene.write_text(json.dumps(doc))
    result = run("render", scene, "-o", tmp_path / "plain.png")
    assert result.exit_code == 0, result.output
    assert_not_blank_png(tmp_path / "plain.png")


def test_sampled_scene_with_geometry_svg_names_its_types(scenes, tmp_path):
    out = tmp_path / "s.svg"
    assert run("render", scenes / "sink_000002.json", "-g", SINK, "-o", out).exit_code == 0
    svg = out.read_text()
    doc = json.loads((scenes / "sink_000002.json").read_text())
    assert svg.startswith("<?xml") and "<path" in svg
    for obj in doc["objects"]:
        assert obj["type"] in svg  # the legend
    assert "latent node" in svg  # the tree's latent nodes


def test_directory_grid_and_png(scenes, tmp_path):
    out = tmp_path / "grid.png"
    result = run("render", scenes, "-n", 3, "-g", SINK, "-o", out)
    assert result.exit_code == 0, result.output
    assert "drew 3 scene(s)" in result.output
    assert_not_blank_png(out)


def test_parse_result_has_a_rule_score_colour_bar(parse_result, tmp_path):
    png, svg = tmp_path / "p.png", tmp_path / "p.svg"
    assert run("render", parse_result, "-g", SINK, "-o", png).exit_code == 0
    assert_not_blank_png(png)
    assert run("render", parse_result, "-o", svg, "--scene", "sink_000000").exit_code == 0
    assert "log-probability of the rule" in svg.read_text()


def test_sink_dataset_needs_its_grammar(tmp_path):
    out = tmp_path / "d.png"
    result = run("render", SINK_DATA, "-o", out)
    assert result.exit_code == 1 and "give its grammar with -g" in result.output
    assert run("render", SINK_DATA, "-g", SINK, "-n", 2, "-o", out).exit_code == 0
    assert_not_blank_png(out)


@pytest.mark.parametrize("grammar", sorted(GRAMMARS.glob("*.yaml")), ids=lambda p: p.stem)
def test_diagram_svg_names_every_type(grammar, tmp_path):
    out = tmp_path / "g.svg"
    result = run("inspect", grammar, "--diagram", out)
    assert result.exit_code == 0, result.output
    svg = out.read_text()
    for t in load_grammar(grammar).types:
        assert f">{t.name}<" in svg


def test_diagram_png(tmp_path):
    out = tmp_path / "g.png"
    assert run("inspect", SINK, "--diagram", out).exit_code == 0
    assert_not_blank_png(out)


def test_missing_matplotlib_is_a_clear_message_and_no_file(scenes, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` now fails
    out = tmp_path / "x.png"
    for args in (
        ("render", scenes / "sink_000000.json", "-o", out),
        ("inspect", SINK, "--diagram", out),
    ):
        result = run(*args)
        assert result.exit_code == 1
        assert "needs matplotlib" in result.output and "pip install 'ssgc[viz]'" in result.output
        assert result.output.startswith("ssg: error: ")  # about no input file
        assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # no temporary file either


def _write(path, text):
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"name": "x"}', "not a scene (a JSON object with `objects`)"),
        ("[1, 2]", "not a scene"),
        ("{oops", "not JSON"),
        ('{"objects": [{"type": "A"}]}', "pose"),
        ('{"scenes": [{"name": "a", "status": "infeasible", "parses": []}]}', "has a parse"),
        ('{"scenes": [{"parses": [{"tree": 3}]}]}', "tree"),
    ],
)
def test_bad_inputs_are_clear_messages(tmp_path, content, message):
    source = _write(tmp_path / "in.json", content)
    out = tmp_path / "out.png"
    result = run("render", source, "-o", out)
    assert result.exit_code == 1, result.output
    assert message in result.output and "internal error" not in result.output
    assert not out.exists()


def test_bad_options_are_clear_messages(scenes, tmp_path):
    scene = scenes / "sink_000000.json"
    cases = [
        (("-o", tmp_path / "out.jpg"), f"{tmp_path / 'out.jpg'}: error: the output must end in"),
        (("-o", tmp_path / "no" / "out.png"), "does not exist"),
        (("-o", tmp_path / "out.png", "-n", 0), "-n must be between"),
        (("-o", tmp_path / "out.png", "--scene", "nope"), f"{scene}: error: no scene named 'nope'"),
    ]
    for args, message in cases:
        result = run("render", scene, *args)
        assert result.exit_code == 1 and message in result.output, result.output
    missing = run("render", tmp_path / "missing.json", "-o", tmp_path / "out.png")
    assert missing.exit_code == 1 and "internal error" not in missing.output
    assert list(tmp_path.iterdir()) == []


@pytest.mark.filterwarnings("error:Glyph")  # matplotlib's own warning must not escape
def test_characters_the_font_lacks_are_one_warning_in_ssg_words(scenes, tmp_path):
    """A scene named in Japanese printed matplotlib's warning text three times, each with
    our source path and line of code; now one line names the characters drawn as boxes."""
    doc = json.loads((scenes / "sink_000001.json").read_text())
    doc["name"] = "茶碗 \U0007b730"
    scene = tmp_path / "named.json"
    scene.write_text(json.dumps(doc, ensure_ascii=False), encoding="utf-8")
    result = run("render", scene, "-o", tmp_path / "named.png", "-q")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "named.png").exists()
    assert result.stderr.splitlines() == [
        f"{scene}: warning: 3 character(s) of the names are not in the font DejaVu Sans and "
        "are drawn as boxes: U+8336, U+7897, U+7B730"
    ]
