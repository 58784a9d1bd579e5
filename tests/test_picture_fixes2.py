"""Picture defects of `ssg render`, `ssg inspect --diagram` and `ssg view` found by the second
bug hunt, each checked on what the user gets (the figure's artists, the page's data, the page in
Chromium, the terminal): a type's colour that depended on the other types drawn, rules of one
log-probability drawn and marked as the most unusual, matplotlib's raw glyph warnings from
`--diagram`, outputs written by two runs at once, a rule name that could not have made its
node, titles running off the figure, and three cosmetic slips (a repeat's mean as `1.9e+02`,
a grid of `200000 m`, `such as NAME`)."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.ir import as_ir

pytest.importorskip("matplotlib")
runner = CliRunner()
GREEN, RED = "#1a9850", "#d73027"  # the page's top and lowest edge colours
UNDER = """grammar: under
root: _root
types:
  _root:
    and:
      - child: _cup
        translation: {offset: [0.1, 0, 0]}
      - child: plate
        translation: {offset: [-0.1, 0, 0]}
  _cup:
    observed: true
    geometry: {box: {size: [0.05, 0.05, 0.1]}}
  plate:
    observed: true
    geometry: {cylinder: {radius: 0.1, length: 0.02}}
"""
SWAPPED = UNDER.replace(
    """      - child: _cup
        translation: {offset: [0.1, 0, 0]}
      - child: plate
        translation: {offset: [-0.1, 0, 0]}""",
    """      - child: plate
        translation: {offset: [-0.1, 0, 0]}
      - child: _cup
        translation: {offset: [0.1, 0, 0]}""",
)


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


def ssg(*args: object) -> subprocess.CompletedProcess[str]:
    """`ssg ARGS` as a real process, so that Python's own warnings reach its stderr."""
    return subprocess.run(
        [sys.executable, "-m", "ssgc.cli.app", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,  # a guard against a hang, not a measurement
    )


def drawn_figure(monkeypatch, source: Path, grammar: Any, n: int = 1) -> Any:
    """The figure `render_file` saves, laid out as when it is saved."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from ssgc.render import scene

    figures: list[Any] = []
    monkeypatch.setattr(scene, "save_figure", lambda fig, *args, **kw: figures.append(fig))
    scene.render_file(source, source.with_suffix(".png"), n=n, grammar=grammar)
    FigureCanvasAgg(figures[0]).draw()
    return figures[0]


def legend_colours(fig: Any) -> dict[str, str]:
    from matplotlib.colors import to_hex
    from matplotlib.patches import Patch

    return {
        h.get_label(): to_hex(h.get_facecolor())
        for h in fig.legends[0].legend_handles
        if isinstance(h, Patch)
    }


def page_colours(source: Path, grammar: Any) -> dict[str, str]:
    """Each observed type's colour on `ssg view`'s page of `source`."""
    from ssgc.render.scene import load_views
    from ssgc.view.page import page_data

    data = page_data(load_views(source, 100, grammar), grammar, "page")
    return {t["name"]: t["colour"] for t in data["types"] if t["observed"]}


# ------------------------------------------------- 1: one colour per type ---


@pytest.fixture(scope="module")
def sink_scenes(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sink")
    result = run("sample", GRAMMARS / "sink.yaml", "-n", 4, "--seed", 3, "-o", out, "-q")
    assert result.exit_code == 0, result.output
    return out


def test_a_type_has_one_colour_in_every_picture_and_page_of_its_grammar(monkeypatch, sink_scenes):
    """Scene 0 holds DishBin and a plate, scene 1 DishBin and bowls: DishBin was blue in one
    picture and green in the other, as the colours went to the types present, sorted."""
    grammar = as_ir(load_grammar(GRAMMARS / "sink.yaml"))
    pictures = []
    for path in sorted(sink_scenes.glob("*.json")):
        legend = legend_colours(drawn_figure(monkeypatch, path, grammar))
        types = {o["type"] for o in json.loads(path.read_text())["objects"]}
        assert set(legend) == types  # the legend lists the picture's types only
        pictures += [legend, page_colours(path, grammar)]
    pictures.append(page_colours(sink_scenes, grammar))  # a page of all four
    colour: dict[str, str] = {}
    for picture in pictures:
        for name, c in picture.items():
            assert colour.setdefault(name, c) == c, name
    assert len(colour) >= 4
    assert len(set(colour.values())) == len(colour)  # still one colour per type


# ------------------------------------------- 2: rules of one log-probability ---


def under_parse(tmp_path: Path, cup_log_prob: float) -> Path:
    """A parse result of the `under` grammar's one scene: every rule scores 0 (fixed
    offsets), but the cup's rule scores `cup_log_prob`."""
    (tmp_path / "under.yaml").write_text(UNDER)
    nodes = [
        ("_root", None, None, [0.0, 0, 0]),
        ("_cup", 0, 0, [0.1, 0, 0]),
        ("plate", 0, 1, [-0.1, 0, 0]),
    ]
    tree = {
        "nodes": [
            {
                "id": i,
                "type": t,
                "parent": p,
                "rule": r,
                "observed": t != "_root",
                "pose": {"xyz": xyz, "quat_wxyz": [1.0, 0, 0, 0]},
            }
            for i, (t, p, r, xyz) in enumerate(nodes)
        ]
    }
    rules = [
        {"node": 0, "rule": None, "log_prob": 0.0},
        {"node": 1, "rule": "_root[0]->_cup", "log_prob": cup_log_prob},
        {"node": 2, "rule": "_root[1]->plate", "log_prob": 0.0},
    ]
    parse = {"score": 0.0, "status": "optimal", "tree": tree, "rules": rules}
    doc = {"grammar": "under", "scenes": [{"name": "u", "status": "optimal", "parses": [parse]}]}
    path = tmp_path / f"under_{cup_log_prob}.json"
    path.write_text(json.dumps(doc).replace("-Infinity", "-1e999"))
    return path


@pytest.mark.parametrize("cup", [0.0, -np.inf])
def test_rules_of_one_log_probability_are_drawn_in_the_top_colour(monkeypatch, tmp_path, cup):
    """All rules 0: every edge was the darkest red, and the colour bar ran 0..1.  With the
    cup's rule at −∞, that edge alone is red (it could not have made the cup)."""
    from matplotlib import colormaps
    from matplotlib.collections import LineCollection
    from matplotlib.colors import to_hex

    source = under_parse(tmp_path, cup)
    grammar = as_ir(load_grammar(tmp_path / "under.yaml"))
    fig = drawn_figure(monkeypatch, source, grammar)
    edges = next(c for c in fig.axes[1].collections if isinstance(c, LineCollection))
    got = [to_hex(c) for c in edges.get_colors()]  # the cup's edge, the plate's
    cmap = colormaps["RdYlGn"]
    top, lowest = to_hex(cmap(1.0)), to_hex(cmap(0.0))
    assert got == [top if cup == 0 else lowest, top]
    bar = fig.axes[-1]
    assert list(bar.get_yticks()) == [0.0]  # the one value, not a scale 0..1

    from ssgc.render.scene import load_views
    from ssgc.view.page import page_data

    data = page_data(load_views(source, 1, grammar), grammar, "page")
    edges = [n["edge"] for n in data["scenes"][0]["nodes"][1:]]  # the root has none
    assert edges == [GREEN if cup == 0 else RED, GREEN]
    assert data["scores"]["mark"] is None  # no rule is marked low but a −∞ one


@pytest.mark.parametrize(("cup", "low"), [(0.0, []), (-np.inf, ["_cup"])])
def test_the_viewer_marks_no_rule_of_one_log_probability_low(chromium, tmp_path, cup, low):
    """Every rule was `rule low` (red) in the panel when all scored 0; a −∞ rule still is."""
    source = under_parse(tmp_path, cup)
    page_file = tmp_path / "under.html"
    result = run("view", source, "-g", tmp_path / "under.yaml", "-o", page_file, "-q")
    assert result.exit_code == 0, result.output
    page = chromium.new_page(viewport={"width": 1100, "height": 650})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(page_file.resolve().as_uri())
    page.wait_for_function("window.ssgView && window.ssgView.ready", timeout=10_000)
    marked = []
    for k in range(page.evaluate("ssgView.objectCount()")):
        page.evaluate(f"ssgView.select({k})")
        here = page.locator("#path li").last
        assert here.locator(".rule").count() == 1
        if "low" in (here.locator(".rule").get_attribute("class") or ""):
            marked.append(here.get_attribute("data-type"))
    page.close()
    assert marked == low and errors == []


# ------------------------------------------ 3: --diagram's glyph warnings ---

EVIL = """grammar: "</text><script>alert(1)</script> $\\\\alpha$ 日本"
root: R
types:
  R:
    and:
      - child: A
        translation: {offset: [0.1, 0, 0]}
  A:
    observed: true
"""


def test_diagram_of_a_name_the_font_lacks_says_one_ssg_warning_not_matplotlib_s(tmp_path):
    """`draw_diagram` measures its text before `save_figure` catches matplotlib's warnings:
    `UserWarning: Glyph 26085 ... missing from font(s)` and its source line reached stderr."""
    grammar = tmp_path / "evil.yaml"
    grammar.write_text(EVIL)
    result = ssg("inspect", grammar, "--diagram", tmp_path / "evil.png")
    assert result.returncode == 0, result.stderr
    assert "UserWarning" not in result.stderr and "Glyph" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if "warning" in line]
    assert len(lines) == 1 and "U+65E5, U+672C" in lines[0], result.stderr


def test_render_diagram_gives_python_callers_one_ssg_warning(tmp_path):
    from ssgc.errors import SsgWarning
    from ssgc.render.diagram import render_diagram

    grammar = tmp_path / "evil.yaml"
    grammar.write_text(EVIL)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        render_diagram(load_grammar(grammar), tmp_path / "evil.svg")
    assert [type(w.message) for w in caught] == [SsgWarning]


# --------------------------------------------------- 4: one writer per output ---


@pytest.mark.parametrize("command", ["render", "diagram"])
def test_a_second_run_writing_the_same_picture_is_refused(tmp_path, sink_scenes, command):
    from ssgc.io.outputs import check_output, lock_outputs

    out = tmp_path / "busy.svg"
    if command == "render":
        args: tuple[object, ...] = ("render", sink_scenes / "sink_000000.json", "-o", out)
    else:
        args = ("inspect", GRAMMARS / "sink.yaml", "--diagram", out)
    with lock_outputs([check_output(out, "picture")]):  # a first run, still writing
        result = run(*args)
        assert result.exit_code == 1
        assert "another ssg run is writing this picture" in result.output
        assert not out.exists()
    assert run(*args).exit_code == 0 and out.exists()  # the lock is gone with its holder
    assert not list(tmp_path.glob(".*.lock"))


# ------------------------------------------ 5: a rule that makes another type ---


def test_a_reordered_grammar_names_no_rule_that_could_not_have_made_the_node(tmp_path):
    """The scene's tree records rule 0 for the cup; in the swapped grammar rule 0 makes the
    plate: the viewer said "made by rule `_root[0]->plate`" for the cup."""
    from ssgc.render.scene import load_views
    from ssgc.view.page import page_data

    (tmp_path / "under.yaml").write_text(UNDER)
    (tmp_path / "swapped.yaml").write_text(SWAPPED)
    result = run("sample", tmp_path / "under.yaml", "-n", 1, "--seed", 1, "-o", tmp_path / "s")
    assert result.exit_code == 0, result.output
    source = next((tmp_path / "s").glob("*.json"))
    rules = {}
    for name in ("under", "swapped"):
        grammar = as_ir(load_grammar(tmp_path / f"{name}.yaml"))
        data = page_data(load_views(source, 1, grammar), grammar, "page")
        types = [t["name"] for t in data["types"]]
        rules[name] = {types[n["type"]]: n["rule"] for n in data["scenes"][0]["nodes"]}
    assert rules["under"] == {"_root": None, "_cup": "_root[0]->_cup", "plate": "_root[1]->plate"}
    assert rules["swapped"] == {
        "_root": None,
        "_cup": "_root[0] (makes plate, not _cup)",
        "plate": "_root[1] (makes _cup, not plate)",
    }


# ---------------------------------------------------- 6: long scene names ---


def test_long_scene_names_are_cut_in_titles_and_keep_their_score(monkeypatch, tmp_path):
    """A 98-character name ran off the figure's left edge over its panel."""
    from ssgc.render.scene import LEGEND_CHARS

    long_name = "kitchen_sink_capture_session_2024_11_03_afternoon_run_" + "x" * 40 + "_END"
    docs = []
    for k, name in enumerate([long_name, "W" * 60, "c", "d"]):
        doc = json.loads(under_parse(tmp_path, -1.5 - k).read_text())
        doc["scenes"][0]["name"] = name
        docs.append(doc["scenes"][0])
    source = tmp_path / "long.json"
    source.write_text(json.dumps({"grammar": "under", "scenes": docs}))
    grammar = as_ir(load_grammar(tmp_path / "under.yaml"))
    fig = drawn_figure(monkeypatch, source, grammar, n=4)
    titles = [ax.title for ax in fig.axes if ax.get_title()]
    first = titles[0].get_text()
    assert first.endswith("(log p = 0.00)") and first.startswith("kitchen_sink")
    assert len(first) <= LEGEND_CHARS + len("  (log p = 0.00)") and "…" in first
    boxes = [t.get_window_extent() for t in titles]
    for i, a in enumerate(boxes):
        assert a.x0 >= 0 and a.x1 <= fig.bbox.x1
        for b in boxes[i + 1 :]:
            assert a.x1 <= b.x0 or b.x1 <= a.x0 or a.y1 <= b.y0 or b.y1 <= a.y0


# --------------------------------------------------------- 7: cosmetics ---


def test_a_big_repeat_s_mean_is_printed_in_plain_digits(tmp_path):
    from ssgc.render.diagram import render_diagram

    grammar = tmp_path / "bigrep.yaml"
    grammar.write_text(
        "grammar: bigrep\nroot: R\ntypes:\n  R:\n    repeat:\n"
        "      count: {geometric: {p: 0.005, max: 1000}}\n"
        "      rule:\n        child: A\n"
        "        translation: {world_normal: {mean: [0, 0, 0], variance: 1.0}}\n"
        "  A:\n    observed: true\n"
    )
    render_diagram(load_grammar(grammar), tmp_path / "bigrep.svg")
    text = (tmp_path / "bigrep.svg").read_text()
    assert "×0..1000, mean 190 ·" in text and "e+02" not in text


def test_the_grid_of_a_scene_2000_km_across_reads_in_kilometres():
    from ssgc.view.page import grid

    assert grid(1_000_000.0) == {"step": 200_000.0, "label": "200 km"}
    assert grid(5_000.0)["label"] == "1 km"
    assert grid(500.0)["label"] == "100 m"


def test_a_directory_as_the_picture_is_refused_with_a_real_file_name(sink_scenes, monkeypatch):
    monkeypatch.chdir(sink_scenes)
    result = run("render", "sink_000000.json", "-o", ".")
    assert result.exit_code == 1
    assert "give a file name (such as scene.png)" in result.output
    result = run("inspect", GRAMMARS / "sink.yaml", "--diagram", ".")
    assert result.exit_code == 1
    assert "give a file name (such as diagram.svg)" in result.output
