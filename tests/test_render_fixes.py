"""Defects of `ssg render` and `ssg view` found by a bug hunt, each checked on what the user gets:
the terminal's warnings, the picture's pixels, the page in Chromium, the messages.

Raw matplotlib warnings for names the font lacks, shapes too small to see in a scene a
kilometre wide, a collapsed view from above, scenes far from the origin, one palette for both,
the view's axis marker, `--open` without a browser, a narrow window, a grammar's path passed
to the Python API, +∞ log-probabilities in a parse result, and what a directory listing
holds."""

from __future__ import annotations

import io
import itertools
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.errors import SsgWarning
from ssgc.ir import as_ir

pytest.importorskip("matplotlib")
runner = CliRunner()
ROOT = Path(__file__).parent.parent
SHAPES = """grammar: shapes
root: Root
types:
  Root:
    and: [{child: Box}, {child: Ball}, {child: Can}]
  Box: {observed: true, geometry: {box: {size: [0.4, 0.1, 0.05]}}}
  Ball: {observed: true, geometry: {sphere: {radius: 0.05}}}
  Can: {observed: true, geometry: {cylinder: {radius: 0.03, length: 0.3}}}
"""


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


def ssg(*args: object, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """`ssg ARGS` as a real process, so that Python's own warnings reach its stderr."""
    return subprocess.run(
        [sys.executable, "-m", "ssgc.cli.app", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,  # a guard against a hang, not a measurement
    )


def scene(name: str, *objects: tuple[str, list[float]]) -> dict:
    return {"name": name, "objects": [{"type": t, "pose": {"xyz": xyz}} for t, xyz in objects]}


def write(path: Path, doc: dict) -> Path:
    path.write_text(json.dumps(doc), encoding="utf-8")
    return path


@pytest.fixture
def shapes(tmp_path):
    file = tmp_path / "shapes.yaml"
    file.write_text(SHAPES)
    return load_grammar(file)


def rgb(colour: str) -> np.ndarray:
    return np.array([int(colour[i : i + 2], 16) for i in (1, 3, 5)])


def figure_of(doc: dict, grammar):
    """`ssg render`'s figure of a scene, drawn by Agg as the PNG is."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from ssgc.render.scene import document_views, draw_views, geometry_of

    ir = None if grammar is None else as_ir(grammar)
    fig = draw_views(document_views(doc, ir, Path("s.json")), geometry_of(ir))
    FigureCanvasAgg(fig).draw()
    return fig


def panel_pixels(fig, k: int) -> np.ndarray:
    """The RGB pixels of the figure's panel `k` (1: the view from above)."""
    image = np.asarray(fig.canvas.buffer_rgba())[:, :, :3].astype(int)
    box, height = fig.axes[k].get_window_extent(), image.shape[0]
    return image[int(height - box.y1) : int(height - box.y0), int(box.x0) : int(box.x1)]


def pixels_of(pixels: np.ndarray, colour: str, tol: int = 3) -> int:
    return int(np.all(np.abs(pixels - rgb(colour)) <= tol, axis=-1).sum())


def legend_colours(fig) -> dict[str, str]:
    from matplotlib.colors import to_hex

    legend = fig.legends[0]
    return {
        t.get_text(): to_hex(h.get_facecolor()[:3])
        for t, h in zip(legend.get_texts(), legend.legend_handles, strict=True)
    }


# ------------------------------------------------------- 1: matplotlib's words ---


@pytest.mark.parametrize(
    ("name", "suffix", "codes"),
    [
        ("茶碗", ".png", "U+8336, U+7897"),
        ("茶碗", ".svg", "U+8336, U+7897"),
        ("tab\there", ".png", "U+0009"),
    ],
)
def test_a_character_the_font_lacks_is_one_ssg_warning_on_the_terminal(
    tmp_path, name, suffix, codes
):
    src = write(tmp_path / "jp.json", scene("jp", (name, [0, 0, 0])))
    proc = ssg("render", src, "-o", tmp_path / f"jp{suffix}", "-q")
    assert proc.returncode == 0, proc.stderr
    assert "UserWarning" not in proc.stderr and "scene.py" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{src}: warning: "), proc.stderr
    assert lines[0].endswith(f"drawn as boxes: {codes}")


def test_render_file_gives_one_ssg_warning_for_missing_characters(tmp_path):
    from ssgc.render.scene import render_file

    src = write(tmp_path / "jp.json", scene("jp", ("茶碗", [0, 0, 0])))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        render_file(src, tmp_path / "jp.png")
    assert [w.category for w in caught] == [SsgWarning]
    assert "U+8336, U+7897" in str(caught[0].message)


# -------------------------------------------------- 2: a kilometre-wide scene ---

DIAG = scene("diag", ("Box", [-500, -500, 0]), ("Ball", [500, 500, 0]), ("Can", [0, 0, 0]))


def test_shapes_too_small_for_the_panel_are_still_seen_from_above(shapes):
    with warnings.catch_warnings(record=True) as caught:  # none, from the cylinder's faces
        warnings.simplefilter("always")
        fig = figure_of(DIAG, shapes)
    assert [str(w.message) for w in caught] == []
    colours = legend_colours(fig)
    for k in (0, 1):  # in 3-D and from above
        pixels = panel_pixels(fig, k)
        for name in ("Box", "Ball", "Can"):
            assert pixels_of(pixels, colours[name]) >= 10, (k, name)


def test_a_normal_scene_gets_no_dots_over_its_shapes(shapes):
    """The dots are only for shapes too small to see: a 40 cm box in a 1 m scene has none."""
    fig = figure_of(scene("near", ("Box", [0, 0, 0]), ("Ball", [0.5, 0.3, 0])), shapes)
    assert not any(len(c.get_offsets()) for c in fig.axes[1].collections)


def test_objects_in_a_line_a_kilometre_long_keep_a_panel_with_readable_ticks(shapes):
    fig = figure_of(scene("far", ("Box", [-500, 0, 0]), ("Ball", [500, 0, 0])), shapes)
    ax = fig.axes[1]
    box = ax.get_window_extent()
    assert box.height >= 0.3 * box.width
    y0, y1 = ax.get_ylim()
    labels = [
        t.get_window_extent()
        for t, v in zip(ax.get_yticklabels(), ax.get_yticks(), strict=True)
        if y0 <= v <= y1 and t.get_text()
    ]
    assert len(labels) >= 2
    ordered = sorted(labels, key=lambda b: b.y0)
    assert all(a.y1 <= b.y0 for a, b in itertools.pairwise(ordered))
    colours = legend_colours(fig)
    assert all(pixels_of(panel_pixels(fig, 1), colours[n]) >= 10 for n in ("Box", "Ball"))


# ---------------------------------------------------- 3: far from the origin ---


@pytest.mark.parametrize("x", [1500.0, 1_000_000.0])
def test_a_scene_far_from_the_origin_is_drawn(tmp_path, shapes, x):
    doc = scene("offset", ("Box", [x, 0, 0]), ("Ball", [x - 0.5, 0, 0]))
    src = write(tmp_path / "offset.json", doc)
    grammar_file = tmp_path / "shapes.yaml"
    for command in ("render", "view"):
        out = tmp_path / ("o.png" if command == "render" else "o.html")
        result = run(command, src, "-g", grammar_file, "-o", out, "-q")
        assert result.exit_code == 0, result.output
        assert out.stat().st_size > 0
    fig = figure_of(doc, shapes)
    assert fig.axes[1].get_xlabel() == f"x − {x:,.0f} (m)"
    colours, pixels = legend_colours(fig), panel_pixels(fig, 1)
    for name in ("Box", "Ball"):  # shapes of their size (alpha 0.45 over white), not dots
        faded = np.rint(0.45 * rgb(colours[name]) + 0.55 * 255)
        assert np.all(np.abs(pixels - faded) <= 3, axis=-1).sum() > 100, name


# ---------------------------------------------------------- 4: one palette ---


def test_render_and_view_colour_twelve_types_alike_dark_ones_first():
    from matplotlib.colors import to_hex

    from ssgc.render.scene import PALETTE, document_views
    from ssgc.view.page import page_data

    doc = scene("twelve", *((f"T{i:02d}", [0.1 * i, 0, 0]) for i in range(12)))
    drawn = legend_colours(figure_of(doc, None))
    page = page_data(document_views(doc, None, Path("s.json")), None, "twelve")
    shown = {t["name"]: to_hex(t["colour"]) for t in page["types"]}
    assert drawn == shown
    assert [drawn[f"T{i:02d}"] for i in range(12)] == list(PALETTE[:12])
    assert drawn["T00"] == "#1f77b4" and drawn["T01"] == "#ff7f0e" and drawn["T10"] == "#aec7e8"


# ------------------------------------------------------- 6: --open, no browser ---


def test_open_without_a_browser_says_where_the_page_was_written(tmp_path, monkeypatch):
    import webbrowser

    monkeypatch.setattr(webbrowser, "open", lambda *a, **k: False)
    src = write(tmp_path / "one.json", scene("one", ("Box", [0.3, 0.2, 0.1])))
    page = tmp_path / "opened.html"
    result = run("view", src, "--open", "-o", page, "-q")
    assert result.exit_code == 0, result.output
    assert page.stat().st_size > 0
    assert f"{page}: warning: no browser found to open the page; it is written there" in (
        " ".join(result.output.split())
    )
    result = run("view", src, "--open", "-q")  # nothing written: an error
    assert result.exit_code == 1
    assert "no browser found to open the page: write it with -o PAGE.html" in result.output


# ------------------------------------------------------------- 8: the API ---


def test_a_grammar_s_path_is_the_type_error_ssgc_parse_gives(tmp_path):
    from ssgc.render.scene import render_file
    from ssgc.view.page import view_page, write_view

    src = write(tmp_path / "one.json", scene("one", ("Box", [0.3, 0.2, 0.1])))
    said = r"expected a Grammar \(ssgc.load_grammar\) as grammar, got str"
    path = str(GRAMMARS / "sink.yaml")
    with pytest.raises(TypeError, match=said):
        write_view(src, tmp_path / "v.html", path)
    with pytest.raises(TypeError, match=said):
        view_page(src, path)
    with pytest.raises(TypeError, match=said):
        render_file(src, tmp_path / "rf.png", grammar=path)
    with pytest.raises(TypeError, match="n must be a whole number from 1 to 64, got '3'"):
        render_file(src, tmp_path / "rf.png", n="3")
    assert not (tmp_path / "rf.png").exists() and not (tmp_path / "v.html").exists()


# ------------------------------------------------- 9: infinite log-probabilities ---

TWO = """grammar: two
root: A
types:
  A: {observed: true, and: [{child: B}]}
  B: {observed: true, geometry: {box: {size: [0.1, 0.1, 0.1]}}}
"""


def parse_result(log_prob: str, score: str = "-1.0") -> str:
    """A parse result of one scene, A holding B, as `ssg parse` writes one (numbers as text,
    so that `1e999` and `NaN` reach the reader as they would from a file)."""
    node = (
        '{{"id": {i}, "type": "{t}", "parent": {p}, "rule": {r}, "observed": true, '
        '"pose": {{"xyz": [{x}, 0, 0], "quat_wxyz": [1, 0, 0, 0]}}}}'
    )
    nodes = [
        node.format(i=0, t="A", p="null", r="null", x=0),
        node.format(i=1, t="B", p=0, r=0, x=0.2),
    ]
    rules = (
        '[{"node": 0, "rule": null, "log_prob": 0.0}, '
        f'{{"node": 1, "rule": "A[0]->B", "log_prob": {log_prob}}}]'
    )
    return (
        '{"grammar": "two", "scenes": [{"name": "s", "status": "optimal", "parses": '
        f'[{{"score": {score}, "tree": {{"nodes": [{", ".join(nodes)}]}}, "rules": {rules}}}]}}]}}'
    )


@pytest.mark.parametrize(
    ("log_prob", "score", "said"),
    [("1e999", "-1.0", "Infinity"), ("NaN", "-1.0", "NaN"), ("-1.0", "Infinity", "Infinity")],
)
def test_a_parse_result_with_an_infinite_log_probability_is_refused(
    tmp_path, log_prob, score, said
):
    grammar = tmp_path / "two.yaml"
    grammar.write_text(TWO)
    src = tmp_path / "parse.json"
    src.write_text(parse_result(log_prob, score))
    for args in (
        ("render", src, "-o", tmp_path / "p.png"),
        ("view", src, "-o", tmp_path / "p.html"),
        ("export", src, "-g", grammar, "-f", "sdf", "-o", tmp_path / "export"),
    ):
        result = run(*args)
        assert result.exit_code == 1, (args, result.output)
        text = " ".join(result.output.split())
        assert text.startswith(f"{src}:1:"), text
        said_in_full = (
            "a log-probability must be a finite number or -Infinity (a rule that could not "
            f"have made the child), got {said}"
        )
        assert said_in_full in text
    assert not (tmp_path / "p.png").exists() and not (tmp_path / "p.html").exists()


def test_a_minus_infinite_log_probability_is_still_drawn(tmp_path):
    src = tmp_path / "parse.json"
    src.write_text(parse_result("-1e999"))
    assert run("render", src, "-o", tmp_path / "p.png", "-q").exit_code == 0
    assert run("view", src, "-o", tmp_path / "p.html", "-q").exit_code == 0


# -------------------------------------------------------- 10: directories ---


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_directory_lists_only_its_regular_json_files(tmp_path):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    write(scenes / "a.json", scene("a", ("Box", [0, 0, 0])))
    (scenes / "x.json").mkdir()
    os.mkfifo(scenes / "0f.json")
    proc = ssg("render", scenes, "-o", tmp_path / "d.png", "-n", 4, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "drew 1 scene(s)" in proc.stdout
    proc = ssg("view", scenes, "-o", tmp_path / "d.html", timeout=60)
    assert proc.returncode == 0 and "1 scene(s)" in proc.stderr, proc.stderr
    proc = ssg("parse", scenes, "-g", GRAMMARS / "gmm.yaml", "-o", tmp_path / "p.json", timeout=60)
    assert "expected a" not in proc.stderr and "0f.json" not in proc.stderr, proc.stderr


def test_the_docs_list_the_tray_and_the_page_s_measured_size(monkeypatch):
    """The page's title holds the input's path as given: measured with the docs' own command,
    from the repository, so that the size does not depend on where the clone is."""
    from ssgc.view.page import view_page

    render = " ".join((ROOT / "docs" / "render.md").read_text().split())
    assert "`revolve` (its surface, 20 facets around) or `tray`" in render
    view = " ".join((ROOT / "docs" / "view.md").read_text().split())
    monkeypatch.chdir(ROOT)
    html, count = view_page(
        Path("ssgc/data/sink/saved_scenes.yaml"), load_grammar("grammars/sink.yaml")
    )
    assert count == 80
    size = len(html.encode("utf-8"))
    assert f"{round(size / 1000)} kB page ({size:,} bytes)" in view
    script = (ROOT / "ssgc" / "view" / "viewer.js").stat().st_size
    assert f"a canvas painter, {script / 1000:.1f} kB" in view


# ------------------------------------------------------------- in Chromium ---


def click_each(page, box, names: str) -> None:
    """Click object k of the page's scene for each name, and check that it is selected."""
    for k, name in enumerate(names):
        point = page.evaluate(f"ssgView.screenPoint({k})")
        assert point is not None, name
        page.mouse.click(box["x"] + point[0], box["y"] + point[1])
        assert page.locator("#path li").last.get_attribute("data-type") == name


def open_view(chromium, source: Path, page_file: Path, width: int = 1100, height: int = 650):
    result = run("view", source, "-o", page_file, "-q")
    assert result.exit_code == 0, result.output
    page = chromium.new_page(viewport={"width": width, "height": height})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(page_file.resolve().as_uri())
    page.wait_for_function("window.ssgView && window.ssgView.ready", timeout=10_000)
    return page, errors


def canvas_pixels(page) -> np.ndarray:
    from PIL import Image

    png = page.locator("#canvas").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int64)


def test_the_axis_marker_is_on_screen_in_the_default_view(chromium, tmp_path):
    src = write(tmp_path / "one.json", scene("one", ("Box", [0.3, 0.2, 0.1])))
    page, errors = open_view(chromium, src, tmp_path / "one.html")
    pixels = canvas_pixels(page)
    for colour in ("#c0392b", "#27ae60", "#2e5fb3"):  # x, y, z (viewer.js drawFloor)
        assert pixels_of(pixels, colour, 4) >= 10, colour
    page.close()
    assert errors == []


def test_a_narrow_window_still_draws_the_scene_and_answers_clicks(chromium, tmp_path):
    src = write(tmp_path / "two.json", scene("two", ("A", [0, 0, 0]), ("B", [0.3, 0.2, 0])))
    page, errors = open_view(chromium, src, tmp_path / "two.html", 300, 300)
    box = page.locator("#canvas").bounding_box()
    assert box["width"] >= 200 and box["height"] >= 100
    pixels = canvas_pixels(page)
    assert np.any(pixels != pixels[0, 0], axis=-1).mean() > 0.01
    click_each(page, box, "AB")
    page.close()
    assert errors == []


@pytest.mark.parametrize("x", [1500.0, 1_000_000.0])
def test_a_scene_far_from_the_origin_is_seen_and_clicked_in_the_viewer(chromium, tmp_path, x):
    src = write(tmp_path / "o.json", scene("o", ("A", [x, 0, 0]), ("B", [x - 0.5, 0, 0])))
    page, errors = open_view(chromium, src, tmp_path / "o.html")
    box = page.locator("#canvas").bounding_box()
    click_each(page, box, "AB")
    page.close()
    assert errors == []
