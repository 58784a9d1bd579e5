"""`ssg view`: the page it writes, opened in a real headless Chromium (driven by playwright).

In the browser: the page loads without a script error, the canvas is not blank, the object
count it shows is the scene's, a click on an object lists that object's path from the root of
its tree with its rules' log-probabilities (as the parse result gives them), and the "next"
button steps to the next scene.  Without playwright or a Chromium, those tests skip and say
which is missing; the page's data and the command's mistakes are tested without a browser.
"""

from __future__ import annotations

import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAMMARS
from hypothesis import given
from hypothesis import strategies as st
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.view.page import _score_colours, view_page

runner = CliRunner()
SINK = GRAMMARS / "sink.yaml"


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes")
    assert run("sample", SINK, "-n", 3, "--seed", 5, "-o", out, "-q").exit_code == 0
    return out


@pytest.fixture(scope="module")
def parse_result(scenes, tmp_path_factory):
    out = tmp_path_factory.mktemp("parse") / "parse.json"
    result = run("parse", scenes, "-g", SINK, "-o", out, "-q")
    assert result.exit_code == 0, result.output
    return out


def expected_objects(parse_doc: dict, grammar) -> list[list[dict]]:
    """Per scene, per object (observed node, in node order): its path from the root, each step
    with its type, rule and log-probability, read from the parse result itself."""
    scenes = []
    for s in parse_doc["scenes"]:
        best = s["parses"][0]
        nodes, rules = best["tree"]["nodes"], {r["node"]: r for r in best["rules"]}
        paths = []
        for i, n in enumerate(nodes):
            if not grammar.types[grammar.type_ids[n["type"]]].observed:
                continue
            chain = [i]
            while nodes[chain[0]]["parent"] is not None:
                chain.insert(0, nodes[chain[0]]["parent"])
            paths.append([{"node": j, "type": nodes[j]["type"], **rules[j]} for j in chain])
        scenes.append(paths)
    return scenes


# ------------------------------------------------------------------ without a browser ---


def page_data(html: str) -> dict:
    start = html.index("id='ssg-data'>") + len("id='ssg-data'>")
    return json.loads(html[start : html.index("</script>", start)])


def test_page_holds_every_object_with_its_path_scores(parse_result, sink):
    html, count = view_page(parse_result, sink)
    data = page_data(html)
    want = expected_objects(json.loads(parse_result.read_text()), sink)
    assert count == len(want) == len(data["scenes"])
    for scene, paths in zip(data["scenes"], want, strict=True):
        assert len(scene["objects"]) == len(paths)
        for node, path in zip(scene["objects"], paths, strict=True):
            assert node == path[-1]["node"]
            for step in path:
                got = scene["nodes"][step["node"]]
                assert data["types"][got["type"]]["name"] == step["type"]
                assert got["rule"] == step["rule"]
                assert got["log_prob"] == pytest.approx(step["log_prob"])
    assert "http" not in html.replace("http://www.w3.org", "")  # nothing fetched


@given(
    st.lists(
        st.one_of(st.floats(-1e6, 1e6), st.just(-np.inf), st.just(np.nan)), min_size=1, max_size=30
    )
)
def test_edge_colours_follow_the_scores(scores):
    """Red at the page's lowest score (and −∞), green at its highest, none where no score."""
    score = np.array(scores)
    finite = score[np.isfinite(score)]
    bounds = (float(finite.min()), float(finite.max())) if finite.size else None
    colours = _score_colours(score, bounds)
    assert len(colours) == len(score)
    for s, c in zip(score, colours, strict=True):
        if bounds is None or np.isnan(s):
            assert c is None
            continue
        assert re.fullmatch(r"#[0-9a-f]{6}", c)
        spread = bounds[1] - bounds[0] > 1e-9  # a narrower range is drawn as one score
        if s == -np.inf or (s == bounds[0] and spread):
            assert c == "#d73027"
        elif s == bounds[1] and spread:
            assert c == "#1a9850"


def test_user_text_cannot_end_the_data_block(scenes, tmp_path):
    doc = json.loads((scenes / "sink_000000.json").read_text())
    del doc["tree"]
    doc["name"] = "</script><script>alert(1)</script>"
    doc["objects"][0]["type"] = "<b>x</b>"
    scene = tmp_path / "odd.json"
    scene.write_text(json.dumps(doc))
    html, _ = view_page(scene)
    assert html.count("</script>") == 2  # the data block's and the renderer's
    assert page_data(html)["scenes"][0]["name"] == doc["name"]


def test_mistakes_are_one_message_and_no_page(scenes, tmp_path):
    result = run("view", scenes)
    assert result.exit_code == 1 and "-o PAGE.html" in result.output
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    page = tmp_path / "page.html"
    result = run("view", bad, "-o", page)
    assert result.exit_code == 1 and "bad.json:1:2" in result.output
    assert not page.exists()
    result = run("view", scenes, "-o", tmp_path / "missing" / "page.html")
    assert result.exit_code == 1 and "Traceback" not in result.output


def test_a_page_that_cannot_hold_every_scene_says_so(scenes, tmp_path, monkeypatch):
    """At most MAX_SCENES go on a page: the rest were dropped without a word."""
    import ssgc.view.page

    monkeypatch.setattr(ssgc.view.page, "MAX_SCENES", 2)
    result = run("view", scenes, "-o", tmp_path / "page.html")
    assert result.exit_code == 0, result.output
    assert f"{scenes}: warning: the page shows the first 2 scenes" in result.stderr
    assert len(page_data((tmp_path / "page.html").read_text())["scenes"]) == 2
    monkeypatch.setattr(ssgc.view.page, "MAX_SCENES", 3)  # all three fit: nothing to say
    result = run("view", scenes, "-o", tmp_path / "page.html", "--quiet")
    assert result.exit_code == 0 and result.stderr == "", result.output


def test_serve_gives_the_page_on_this_machine_only(scenes, tmp_path):
    """`--serve --port 0`: the page written with -o, served on 127.0.0.1 until stopped."""
    import subprocess
    import sys
    import urllib.request

    page = tmp_path / "page.html"
    cmd = [sys.executable, "-m", "ssgc.cli.app", "view", str(scenes), "-o", str(page)]
    server = subprocess.Popen([*cmd, "--serve", "--port", "0"], stderr=subprocess.PIPE, text=True)
    try:
        lines = [server.stderr.readline() for _ in range(2)]
        url = re.search(r"http://127\.0\.0\.1:\d+/", lines[1]).group(0)
        with urllib.request.urlopen(url, timeout=10) as response:
            assert response.read() == page.read_bytes()
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(url + "other", timeout=10)
    finally:
        server.terminate()
        server.wait(timeout=10)


def test_a_port_in_use_writes_no_page(scenes, tmp_path):
    """The port is taken before the page is made: a busy one was refused only after the page
    was written and its success line printed."""
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        page = tmp_path / "page.html"
        result = run("view", scenes, "-o", page, "--serve", "--port", port)
    assert result.exit_code == 1
    assert f"cannot serve on 127.0.0.1:{port}" in result.stderr
    assert "scene(s) of" not in result.stderr and not page.exists()


# ------------------------------------------------------------------ in Chromium ---


@pytest.fixture
def open_page(chromium):
    pages = []

    def opener(path: Path):
        page = chromium.new_page(viewport={"width": 1100, "height": 650})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.goto(path.resolve().as_uri())
        page.wait_for_function("window.ssgView && window.ssgView.ready", timeout=10_000)
        pages.append(page)
        return page, errors

    yield opener
    for page in pages:
        page.close()


def canvas_pixels(page) -> np.ndarray:
    from PIL import Image

    png = page.locator("#canvas").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int64)


def test_parse_page_in_chromium(parse_result, sink, open_page, tmp_path):
    page_file = tmp_path / "parse.html"
    result = run("view", parse_result, "-g", SINK, "-o", page_file, "-q")
    assert result.exit_code == 0, result.output
    want = expected_objects(json.loads(parse_result.read_text()), sink)
    page, errors = open_page(page_file)

    pixels = canvas_pixels(page)
    background = pixels[0, 0]
    assert np.any(pixels != background, axis=-1).mean() > 0.05  # the scene covers the canvas
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 50  # shaded shapes, not one fill
    assert page.locator("#count").inner_text() == str(len(want[0]))

    box = page.locator("#canvas").bounding_box()
    clicked = []
    for k, path in enumerate(want[0]):
        point = page.evaluate(f"ssgView.screenPoint({k})")
        if point is None:  # hidden behind another object from this side
            continue
        page.mouse.click(box["x"] + point[0], box["y"] + point[1])
        steps = page.locator("#path li")
        assert steps.evaluate_all("els => els.map(e => e.dataset.type)") == [
            s["type"] for s in path
        ]
        last = steps.nth(len(path) - 1).inner_text()
        assert f"log p = {path[-1]['log_prob']:.2f}" in last
        if path[-1]["rule"]:
            assert f"rule {path[-1]['rule']}" in last
        clicked.append(len(path))
    assert max(clicked) > 1  # at least one object below the root was clicked

    page.locator("#next").click()
    assert page.locator("#count").inner_text() == str(len(want[1]))
    assert page.locator("#position").inner_text() == f"scene 2 of {len(want)}"
    page.screenshot(path=str(tmp_path / "parse.png"))
    assert errors == []


def test_scene_directory_page_in_chromium(scenes, open_page, tmp_path):
    """Sampled scenes without a grammar: every object a marker, still counted and clickable."""
    page_file = tmp_path / "scenes.html"
    assert run("view", scenes, "-o", page_file, "-q").exit_code == 0
    page, errors = open_page(page_file)
    files = sorted(scenes.glob("*.json"))
    for i, f in enumerate(files):
        n = len(json.loads(f.read_text())["objects"])
        assert page.locator("#count").inner_text() == str(n)
        assert page.evaluate("ssgView.state.scene") == i
        page.keyboard.press("ArrowRight")
    assert errors == []


def test_views_a_dataset_with_its_grammar(tmp_path):
    """The sink dataset's first scenes (YAML, which names models: -g gives the types)."""
    from conftest import SINK_DATA

    html, count = view_page(SINK_DATA, load_grammar(SINK))
    assert count == 80
    data = page_data(html)
    assert all(t["geometry"] for t in data["types"] if t["observed"])


def test_the_page_never_replaces_the_grammar(scenes, tmp_path):
    grammar = tmp_path / "g.yaml"
    shutil.copy(GRAMMARS / "sink.yaml", grammar)
    before = grammar.read_bytes()
    result = run("view", next(scenes.glob("*.json")), "-g", grammar, "-o", grammar)
    assert result.exit_code == 1, result.output
    assert "the page is the input file" in result.output
    assert grammar.read_bytes() == before


@pytest.mark.parametrize("name", ["page.json", "page.png", "page"])
def test_the_page_must_be_an_html_file(scenes, tmp_path, name):
    """An HTML page as `page.json` among scenes would be read as a broken scene."""
    result = run("view", next(scenes.glob("*.json")), "-o", tmp_path / name)
    assert result.exit_code == 1, result.output
    assert "the page must end in .html or .htm" in result.output
    assert list(tmp_path.iterdir()) == []
    assert run("view", next(scenes.glob("*.json")), "-o", tmp_path / "page.HTM").exit_code == 0


def test_the_api_page_has_the_commands_checks(scenes, tmp_path):
    """`ssgc.view.page.write_view` wrote over the grammar it was given, and as any name."""
    from ssgc.compile import load_grammar
    from ssgc.errors import SsgError
    from ssgc.view.page import write_view

    grammar = tmp_path / "g.yaml"
    shutil.copy(GRAMMARS / "sink.yaml", grammar)
    before = grammar.read_bytes()
    scene = next(scenes.glob("*.json"))
    with pytest.raises(SsgError, match="the page is the input file"):
        write_view(scene, grammar, load_grammar(grammar))
    assert grammar.read_bytes() == before
    with pytest.raises(SsgError, match=r"must end in \.html"):
        write_view(scene, tmp_path / "page.json")
    assert write_view(scene, tmp_path / "page.html", load_grammar(grammar)) == 1
