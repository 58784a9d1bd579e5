"""Picture defects of `ssg render`, `ssg inspect --diagram` and `ssg view`, each checked on what
the picture holds (its figure's artists, its legend, its colours, the page's data), not by eye:
reproducible SVG files, which objects are drawn faintly, rule names in the viewer, the legend's
entries and colours, the panels' scales and the viewer's grid."""

from __future__ import annotations

import io
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.ir import as_ir

pytest.importorskip("matplotlib")
runner = CliRunner()
FAINT = 0.15  # the alpha of an object drawn faintly by `ssg render` (docs/render.md)


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


def scene(name: str, *objects: tuple[str, list[float]]) -> dict:
    """A scene document of objects given as (type, xyz), upright."""
    return {"name": name, "objects": [{"type": t, "pose": {"xyz": xyz}} for t, xyz in objects]}


def views_of(doc: dict, grammar_name: str):
    from ssgc.render.scene import document_views

    grammar = as_ir(load_grammar(GRAMMARS / f"{grammar_name}.yaml"))
    return document_views(doc, grammar, Path("scene.json")), grammar


def top_view_alphas(doc: dict, grammar_name: str) -> dict[str, list[float]]:
    """Each type's shapes' alphas in the view from above of `ssg render`'s figure."""
    from ssgc.render.scene import draw_views, geometry_of

    views, grammar = views_of(doc, grammar_name)
    fig = draw_views(views, geometry_of(grammar))
    colour_of = {h.get_label(): h.get_facecolor()[:3] for h in fig.legends[0].legend_handles}
    alphas: dict[str, list[float]] = {}
    for patch in fig.axes[1].patches:
        name = next(t for t, c in colour_of.items() if c == patch.get_facecolor()[:3])
        alphas.setdefault(name, []).append(patch.get_alpha())
    return alphas


# ------------------------------------------------------------- reproducible ---


def test_svg_pictures_carry_no_date_so_two_runs_make_the_same_file(tmp_path, monkeypatch):
    """matplotlib writes the time of saving into an SVG (`<dc:date>`), unless told not to."""
    monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    src = tmp_path / "s.json"
    src.write_text(json.dumps(scene("s", ("Cup", [0, 0, 0]), ("Cup", [0.2, 0.1, 0]))))
    outputs = []
    for k in range(2):
        picture, diagram = tmp_path / f"p{k}.svg", tmp_path / f"d{k}.svg"
        assert run("render", src, "-o", picture, "-q").exit_code == 0
        result = run("inspect", GRAMMARS / "sink.yaml", "--diagram", diagram)
        assert result.exit_code == 0, result.output
        outputs.append((picture.read_text(), diagram.read_text()))
    for text in outputs[0]:
        assert "<dc:date>" not in text
    assert outputs[0] == outputs[1]


# ------------------------------------------------------------------- faint ---


def test_only_the_bin_is_faint_not_a_disc_over_its_centre():
    doc = scene(
        "one_disc",
        ("Bin", [0, 0, 0]),
        ("Disc", [0.03, 0.02, 0.025]),
        ("Disc", [-0.09, -0.09, 0.025]),
    )
    alphas = top_view_alphas(doc, "bin_packing")
    assert alphas["Bin"] == [FAINT]
    assert FAINT not in alphas["Disc"] and len(alphas["Disc"]) == 2


def test_stacked_discs_are_solid():
    doc = scene(
        "stack", ("Bin", [0, 0, 0]), ("Disc", [0.0, 0.0, 0.025]), ("Disc", [0.0, 0.0, 0.075])
    )
    alphas = top_view_alphas(doc, "bin_packing")
    assert alphas["Bin"] == [FAINT] and FAINT not in alphas["Disc"]


def test_a_lone_plate_in_the_sink_bin_is_solid():
    # on the bin's floor, where the data's plates rest (the bin is an open tray since
    # session 35; the solid box it replaced held a plate at z = -0.14 too)
    doc = scene("lone", ("DishBin", [0.5, 0, 0]), ("PlateEcoformsAvocado", [0.5, 0.0, 0.015]))
    alphas = top_view_alphas(doc, "sink")
    assert alphas == {"DishBin": [FAINT], "PlateEcoformsAvocado": [pytest.approx(0.45)]}


def test_steamer_trays_and_lid_are_solid_on_a_faint_table_in_the_viewer():
    from ssgc.view.page import page_data

    doc = scene(
        "steamers",
        ("Table", [0, 0, 0.375]),
        ("SteamerBottom", [0.2, 0.3, 0.78]),
        ("SteamerBottom", [0.2, 0.3, 0.84]),
        ("SteamerLid", [0.2, 0.3, 0.89]),
    )
    views, grammar = views_of(doc, "dimsum_table")
    data = page_data(views, grammar, "steamers")
    page = data["scenes"][0]
    names = [data["types"][page["nodes"][i]["type"]]["name"] for i in page["objects"]]
    assert dict(zip(names, page["faint"], strict=True)) == {
        "Table": True,
        "SteamerBottom": False,
        "SteamerLid": False,
    }


# --------------------------------------------------------- viewer's rules ---


@pytest.fixture(scope="module")
def sampled(tmp_path_factory):
    out = tmp_path_factory.mktemp("sampled")
    result = run("sample", GRAMMARS / "sink.yaml", "-n", 1, "--seed", 1, "-o", out, "-q")
    assert result.exit_code == 0, result.output
    return next(out.glob("*.json"))


def page_rules(source: Path, grammar) -> list[str | None]:
    from ssgc.render.scene import load_views
    from ssgc.view.page import page_data

    grammar = None if grammar is None else as_ir(grammar)
    data = page_data(load_views(source, 1, grammar), grammar, "page")
    return [node["rule"] for node in data["scenes"][0]["nodes"]]


def test_a_sampled_scene_in_the_viewer_names_each_node_s_rule_as_a_parse_does(sampled):
    grammar = as_ir(load_grammar(GRAMMARS / "sink.yaml"))
    nodes = json.loads(sampled.read_text())["tree"]["nodes"]
    expected = [None]  # the root
    for node in nodes[1:]:
        parent = grammar.type_ids[nodes[node["parent"]]["type"]]
        expected.append(grammar.rule_name(int(grammar.tables.type_rules[parent, node["rule"]])))
    assert page_rules(sampled, grammar) == expected
    assert "DishBin[0]->Object" in expected


def test_without_a_grammar_the_viewer_names_the_rule_by_its_index(sampled):
    nodes = json.loads(sampled.read_text())["tree"]["nodes"]
    rules = page_rules(sampled, None)
    assert rules[0] is None
    for node, rule in zip(nodes[1:], rules[1:], strict=True):
        parent = nodes[node["parent"]]["type"]
        assert rule == f"{parent}[{node['rule']}]->{node['type']}"


# ------------------------------------------------------- --scene unparsed ---


def test_a_scene_without_a_parse_is_said_to_have_none_not_to_be_missing(tmp_path):
    node = {"id": 0, "type": "Cup", "parent": None, "rule": None, "pose": {"xyz": [0, 0, 0]}}
    parsed = {"score": -1.0, "tree": {"nodes": [node]}, "rules": [{"node": 0, "log_prob": 0.0}]}
    doc = {
        "scenes": [
            {"name": "good", "status": "optimal", "parses": [parsed]},
            {"name": "bad", "status": "infeasible", "parses": []},
        ]
    }
    src, out = tmp_path / "p.json", tmp_path / "x.png"
    src.write_text(json.dumps(doc))
    result = run("render", src, "--scene", "bad", "-o", out)
    assert result.exit_code == 1 and not out.exists()
    assert "scene 'bad' has no parse to draw (its status: infeasible)" in result.output
    assert "no scene named 'nowhere'" in run("render", src, "--scene", "nowhere", "-o", out).output


# ------------------------------------------------------------------ legend ---


def many_types(count: int, name=lambda i: f"T{i}") -> dict:
    return scene("many", *((name(i), [0.1 * (i % 5), 0.1 * (i // 5), 0.0]) for i in range(count)))


def drawn(doc: dict):
    """`ssg render`'s figure of a scene without a grammar, laid out as when it is saved."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from ssgc.render.scene import document_views, draw_views

    fig = draw_views(document_views(doc, None, Path("scene.json")), {})
    FigureCanvasAgg(fig).draw()
    return fig


def min_distance(colours) -> float:
    rgb = np.array([c[:3] for c in colours], float)
    gaps = np.linalg.norm(rgb[:, None] - rgb[None], axis=-1)
    return float(gaps[~np.eye(len(rgb), dtype=bool)].min())


def test_every_one_of_25_types_is_in_the_legend_inside_the_picture_in_its_own_colour():
    fig = drawn(many_types(25))
    legend = fig.legends[0]
    assert sorted(t.get_text() for t in legend.get_texts()) == sorted(f"T{i}" for i in range(25))
    box = legend.get_window_extent()
    assert box.x0 >= 0 and box.y0 >= 0 and box.x1 <= fig.bbox.x1 and box.y1 <= fig.bbox.y1
    assert min_distance([h.get_facecolor() for h in legend.legend_handles]) > 0.15


def test_the_viewer_gives_25_types_distinct_colours():
    from matplotlib.colors import to_rgb

    from ssgc.render.scene import document_views
    from ssgc.view.page import page_data

    data = page_data(document_views(many_types(25), None, Path("s.json")), None, "many")
    assert min_distance([to_rgb(t["colour"]) for t in data["types"]]) > 0.15


def test_long_type_names_are_cut_short_in_the_legend_and_leave_the_panels_their_room():
    from ssgc.render.scene import LEGEND_CHARS

    fig = drawn(many_types(2, lambda i: chr(ord("A") + i) * (80 + 20 * i)))
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert LEGEND_CHARS <= 40
    assert all(len(label) == LEGEND_CHARS and "…" in label for label in labels)
    assert labels[0].startswith("AAAA") and labels[1].startswith("BBBB")
    short = drawn(many_types(2))
    for ax, ax_short in zip(fig.axes, short.axes, strict=True):
        width = ax.get_position().width * fig.get_figwidth()
        assert width >= 0.9 * ax_short.get_position().width * short.get_figwidth()


def test_matplotlib_s_layout_warning_is_one_ssg_warning_in_our_words(tmp_path):
    """A figure too crowded to lay out: matplotlib's UserWarning (twice, with its source
    lines) becomes one `SsgWarning`."""
    from matplotlib.figure import Figure

    from ssgc.errors import SsgWarning
    from ssgc.io.outputs import check_output
    from ssgc.render.scene import save_figure

    fig = Figure(figsize=(2, 2), layout="constrained")
    fig.add_subplot().plot([0, 1], label="x" * 300)
    fig.legend(loc="outside right upper")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        save_figure(fig, check_output(tmp_path / "c.png", "picture"), "png")
    assert [w.category for w in caught] == [SsgWarning]
    assert "too crowded to lay out" in str(caught[0].message)


# ------------------------------------------------------------------ scales ---


def test_the_docs_say_what_the_3d_panel_does_to_a_long_thin_scene(tmp_path):
    """A 1 m × 10 cm × 10 cm box: from above to scale, in 3-D its short axes stretched to 35% of
    the long one, as docs/render.md says (not 'equal scales on every axis')."""
    from ssgc.render.scene import MIN_ASPECT, document_views, draw_views, geometry_of

    grammar_file = tmp_path / "stick.yaml"
    grammar_file.write_text(
        "grammar: stick\nroot: {type: Stick}\n"
        "types:\n  Stick:\n    observed: true\n    geometry: {box: {size: [1.0, 0.1, 0.1]}}\n"
    )
    grammar = as_ir(load_grammar(grammar_file))
    views = document_views(scene("stick", ("Stick", [0, 0, 0])), grammar, Path("s.json"))
    ax3, ax2 = draw_views(views, geometry_of(grammar)).axes[:2]
    aspect = np.asarray(ax3.get_box_aspect())
    assert aspect / aspect.max() == pytest.approx([1.0, MIN_ASPECT, MIN_ASPECT])
    assert ax2.get_aspect() == 1.0
    doc = " ".join((Path(__file__).parent.parent / "docs" / "render.md").read_text().split())
    assert "equal scales on every axis" not in doc
    assert f"less than {MIN_ASPECT:.0%} of the longest one's is stretched" in doc


# ------------------------------------------------------------ viewer scale ---

FAR = scene("far", ("A", [0, 0, 0]), ("B", [1000, 0, 0]), ("C", [0, 600, 0]))


def test_the_grid_step_follows_the_scene_s_extent():
    from ssgc.render.scene import document_views
    from ssgc.view.page import page_data

    def step(doc):
        return page_data(document_views(doc, None, Path("s.json")), None, "s")["scenes"][0]["grid"]

    assert step(FAR) == {"step": 100.0, "label": "100 m"}
    assert step(scene("m", ("A", [0, 0, 0]), ("B", [0.8, 0.5, 0.2]))) == {
        "step": 0.1,
        "label": "10 cm",
    }


def open_view(chromium, source: Path, page_file: Path, *options: object):
    result = run("view", source, "-o", page_file, "-q", *options)
    assert result.exit_code == 0, result.output
    page = chromium.new_page(viewport={"width": 1100, "height": 650})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(page_file.resolve().as_uri())
    page.wait_for_function("window.ssgView && window.ssgView.ready", timeout=10_000)
    return page, errors


def test_objects_a_kilometre_apart_are_seen_and_clicked_over_a_sparse_grid(chromium, tmp_path):
    from PIL import Image

    src = tmp_path / "far.json"
    src.write_text(json.dumps(FAR))
    page, errors = open_view(chromium, src, tmp_path / "far.html")
    png = page.locator("#canvas").screenshot()
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int64)
    coloured = np.ptp(pixels, axis=-1) > 40  # a type's colour, not the grey floor or grid
    box = page.locator("#canvas").bounding_box()
    for k, name in enumerate("ABC"):
        point = page.evaluate(f"ssgView.screenPoint({k})")
        assert point is not None, name
        x, y = round(point[0]), round(point[1])
        assert coloured[y - 6 : y + 7, x - 6 : x + 7].sum() >= 25, name  # a few pixels across
        page.mouse.click(box["x"] + point[0], box["y"] + point[1])
        assert page.locator("#path li").last.get_attribute("data-type") == name
    grid_grey = np.all(np.abs(pixels - [0xD5, 0xD8, 0xDD]) <= 6, axis=-1)
    assert grid_grey.mean() < 0.2  # lines, not a solid grey plane
    assert "grid: 100 m" in page.locator("#hint").inner_text()
    page.close()
    assert errors == []


def test_a_click_on_a_sampled_object_lists_its_rules(chromium, sampled, tmp_path):
    page, errors = open_view(chromium, sampled, tmp_path / "s.html", "-g", GRAMMARS / "sink.yaml")
    box = page.locator("#canvas").bounding_box()
    count = page.evaluate("ssgView.objectCount()")
    clicked = 0
    for k in range(1, count):  # object 0 is the bin, the root
        point = page.evaluate(f"ssgView.screenPoint({k})")
        if point is None:
            continue
        page.mouse.click(box["x"] + point[0], box["y"] + point[1])
        text = page.locator("#path").inner_text()
        assert "rule DishBin[0]->Object" in text
        clicked += 1
    page.close()
    assert clicked and errors == []
