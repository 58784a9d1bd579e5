"""`ssg inspect --diagram` and the inspect table, checked on what they hold (the figure's
artists, the summary's fields): no arrow runs through a box, labels do not overlap each other
or boxes, a probability strictly between 0 and 1 never prints as "1" or "0", a `repeat`'s
range is its counts of positive probability, and the types an `observation` section adds are
marked (docs/render.md, docs/grammar.md 9)."""

from __future__ import annotations

import itertools
import json

import grammar_gen
import numpy as np
import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import compile_text, load_grammar
from ssgc.inspect import grammar_summary
from ssgc.ir import Grammar, as_ir

pytest.importorskip("matplotlib")

MISC = """
grammar: misc
root: R
types:
  R:
    and: [{child: O}, {child: I}, {child: P}, {child: Q}]
  O:
    or: [{child: A, p: 3}, {child: B, p: 1}, {child: A, p: 0}]
  I:
    independent: [{child: A, p: 0.999}, {child: B, p: 0}, {child: A, p: 0.0004}]
  P:
    repeat: {count: {probs: [0.5, 0.5, 0, 0]}, rule: {child: A}}
  Q:
    repeat: {count: {probs: [0, 0, 1]}, rule: {child: B}}
  A: {observed: true}
  B: {observed: true}
"""

REC = """
grammar: rec
root: Start
types:
  Start: {and: [{child: Top}]}
  Top:
    max_nesting: 2
    or: [{child: Mid, p: 0.5}, {child: Leaf, p: 0.5}]
  Mid:
    max_nesting: 3
    independent: [{child: Top, p: 0.3}, {child: Mid, p: 0.25}, {child: Deep, p: 0.5}]
  Deep: {and: [{child: Mid}, {child: Leaf}]}
  Leaf: {observed: true}
"""

OBSERVED_ROOT = """
grammar: seen
root: L0
types:
  A: {observed: true}
  L0:
    observed: true
    independent: [{child: A, p: 0.3}]
observation:
  noise: {default: {position: 0.01, rotation_deg: 2}}
  clutter:
    region: {min: [-1, -1, 0], max: [1, 1, 1]}
    rates: {A: 0.1}
"""


def generated(n: int = 30) -> list[Grammar]:
    """Grammars of tests/grammar_gen.py, with observation sections and the rare corners."""
    out = []
    for seed in range(n):
        extras, rare = bool(seed % 2), bool((seed // 2) % 2)
        spec = grammar_gen.make_spec(picker(np.random.default_rng(seed)), extras, rare)
        out.append(compile_text(grammar_gen.to_yaml(spec)))
    return out


def picker(rng: np.random.Generator):
    return lambda what, options: options[int(rng.integers(len(options)))]


def every_grammar() -> list[Grammar]:
    bundled = [as_ir(load_grammar(p)) for p in sorted(GRAMMARS.glob("*.yaml"))]
    return [*bundled, compile_text(MISC), compile_text(REC), *generated()]


def drawn(grammar: Grammar):
    """The diagram's figure, drawn (so that text extents are final), and its renderer."""
    from ssgc.render.diagram import draw_diagram, layout

    fig = draw_diagram(grammar, layout(grammar))
    if fig.canvas.__class__.__name__ != "FigureCanvasAgg":
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig, fig.canvas.get_renderer()


def boxes_of(ax) -> np.ndarray:
    """The type boxes (left, bottom, right, top) in data inches."""
    return np.array(
        [
            [p.get_x(), p.get_y(), p.get_x() + p.get_width(), p.get_y() + p.get_height()]
            for p in ax.patches
            if p.__class__.__name__ == "FancyBboxPatch"
        ]
    ).reshape(-1, 4)


def arrow_lines(ax) -> list[np.ndarray]:
    """Every arrow as the polyline the figure draws: the plotted polylines and the shafts of
    the annotations' arrows (arcs flattened by matplotlib), in data inches."""
    lines = [line.get_xydata() for line in ax.lines]
    to_data = ax.transData.inverted()
    for ann in ax.texts:
        patch = getattr(ann, "arrow_patch", None)
        if patch is None:
            continue
        path = patch.get_transform().transform_path(patch.get_path())
        shaft = path.to_polygons(closed_only=False)[0]  # then the head, at the child's edge
        lines.append(to_data.transform(shaft))
    return lines


def arrow_segments(ax) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every straight stretch of every arrow."""
    return [(a, b) for line in arrow_lines(ax) for a, b in itertools.pairwise(line)]


def crosses(a: np.ndarray, b: np.ndarray, box: np.ndarray, margin: float = 0.01) -> bool:
    """Whether segment a-b enters the box shrunk by `margin` (Liang-Barsky clipping): touching
    a box's edge, as an arrow does at its own ends, is not crossing it."""
    lo, hi = box[:2] + margin, box[2:] - margin
    d = b - a
    t0, t1 = 0.0, 1.0
    for k in range(2):
        if abs(d[k]) < 1e-12:
            if not lo[k] < a[k] < hi[k]:
                return False
            continue
        ta, tb = sorted(((lo[k] - a[k]) / d[k], (hi[k] - a[k]) / d[k]))
        t0, t1 = max(t0, ta), min(t1, tb)
    return t0 < t1


def label_texts(ax) -> list:
    """The rule labels: the texts drawn above the boxes (zorder 4)."""
    return [t for t in ax.texts if t.get_zorder() == 4 and not hasattr(t, "arrow_patch")]


def overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


@pytest.fixture(scope="module")
def figures():
    return [(g, *drawn(g)) for g in every_grammar()]


def test_no_arrow_runs_through_a_box(figures):
    """sink_detailed's CarryingPlate -> TerminalPlate ran through PlatesOnPlate, L1 -> A of a
    generated grammar with clutter through `~clutter`."""
    bad = []
    for g, fig, _ in figures:
        ax = fig.axes[0]
        boxes = boxes_of(ax)
        assert len(boxes) == len(g.types)
        for a, b in arrow_segments(ax):
            hit = [g.types[i].name for i, box in enumerate(boxes) if crosses(a, b, box)]
            if hit:
                bad.append((g.name, hit, a.round(2).tolist(), b.round(2).tolist()))
    assert not bad


def test_labels_overlap_neither_each_other_nor_boxes(figures):
    """misc's "0.25" (O -> B) sat on "×n" (P -> A), sink_detailed's labels near TerminalPlate
    ran together."""
    bad = []
    for g, fig, renderer in figures:
        ax = fig.axes[0]
        labels = label_texts(ax)
        assert len(labels) == len({(r.parent, r.child) for r in g.rules})
        extents = [t.get_window_extent(renderer) for t in labels]
        patches = [p.get_window_extent(renderer) for p in ax.patches]
        for i, a in enumerate(extents):
            bad += [(g.name, labels[i].get_text(), labels[j].get_text()) for j in range(i)
                    if overlap(a, extents[j])]  # fmt: skip
            bad += [(g.name, labels[i].get_text(), "box") for p in patches if overlap(a, p)]
    assert not bad


def test_a_loop_label_stays_off_the_other_arrows():
    """rec's Mid -> Mid label "0.25" sat on the Mid -> Top arc and the Top -> Leaf line."""
    fig, renderer = drawn(compile_text(REC))
    ax = fig.axes[0]
    (loop,) = [t for t in label_texts(ax) if t.get_text() == "0.25"]
    corners = ax.transData.inverted().transform(loop.get_window_extent(renderer).get_points())
    box = np.concatenate([corners[0] - 0.02, corners[1] + 0.02])  # 2 pixels round the text
    for line in arrow_lines(ax):
        if np.linalg.norm(line[0] - line[-1]) < 0.3:
            continue  # the loop itself
        assert not any(crosses(a, b, box, 0.0) for a, b in itertools.pairwise(line))


@pytest.mark.parametrize(
    ("p", "text"),
    [(0.999, "0.999"), (0.9996, "0.9996"), (0.0004, "0.0004"), (1e-9, "1e-09"), (0.25, "0.25")],
)
def test_a_probability_strictly_between_0_and_1_never_prints_as_either(p, text):
    from ssgc.inspect import format_prob  # one helper for the diagram and the table

    assert format_prob(p, 2) == text
    assert format_prob(p) == text
    assert format_prob(1 - 1e-12) == ">0.99999999"
    assert (format_prob(0.0), format_prob(1.0), format_prob(1 / 3, 2)) == ("0", "1", "0.33")


def test_near_certain_rules_in_the_diagram_and_the_table():
    """misc's independent rule p 0.999 was labelled "1" like an `and` rule; the table printed p
    0.9996 as "p = 1" and a count probability 0.0004 as 0."""
    fig, _ = drawn(compile_text(MISC))
    labels = {t.get_text() for t in label_texts(fig.axes[0])}
    assert "0.999, 0.0004" in labels  # I's two rules to A
    text = MISC.replace("0.999", "0.9996").replace("[0.5, 0.5, 0, 0]", "[0.0004, 0.9996]")
    rows = {t["name"]: t for t in grammar_summary(compile_text(text))["types"]}
    assert rows["I"]["choice"] == "p = 0.9996, 0, 0.0004"
    assert rows["P"]["choice"] == "count 0..1: 0.0004, 0.9996"


def test_repeat_range_is_its_counts_of_positive_probability():
    """P (probs [0.5, 0.5, 0, 0]) said ×0..3, Q (probs [0, 0, 1]) ×2..2."""
    fig, _ = drawn(compile_text(MISC))
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert "repeat ×0..1, mean 0.5 · latent" in texts
    assert "repeat ×2..2, mean 2 · latent" in texts


def test_types_added_by_observation_are_marked(tmp_path):
    """Under `observation:`, `~scene`, `~node:L0` and the clutter types were listed like the
    file's own, L0 as a terminal."""
    grammar = compile_text(OBSERVED_ROOT)
    rows = {t["name"]: t["synthetic"] for t in grammar_summary(grammar)["types"]}
    assert rows == {
        "A": None,
        "L0": None,
        "~scene": "scene",
        "~node:L0": "node",
        "~clutter": "clutter",
        "~clutter:object": "clutter",
    }
    (tmp_path / "seen.yaml").write_text(OBSERVED_ROOT)
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "seen.yaml"), "--json"])
    assert result.exit_code == 0, result.output
    types = json.loads(result.stdout)["types"]
    assert {t["name"]: t["synthetic"] for t in types} == rows
    fig, _ = drawn(grammar)
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert sum("added by observation" in t for t in texts) == 4
