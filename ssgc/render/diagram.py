"""A grammar as a picture (`ssg inspect GRAMMAR --diagram OUT`, docs/render.md; thesis Figs.
2-3, 2-6): node types as boxes with their kind, rules as arrows labelled with their
probabilities, laid out in layers by the longest path from the root.

The layout is computed here (no graphviz): recursive rules are found by a depth-first search
and drawn as curved arrows back up; the rest is a DAG whose longest-path layering puts every
type below all of its parents.  Within a layer, types are ordered by the mean position of their
parents (two barycentre sweeps); an arrow that skips layers passes each layer between through
a slot of its own (a waypoint), straight down, and runs slanted only in the gaps between
layers, where there are no boxes: so it never runs through a box.  Labels go at the first of
several places along their arrow that is clear of boxes, of other labels and, if it can be, of
other arrows.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ssgc.inspect import format_prob
from ssgc.ir import Grammar, HoldsGrammar, Kind, NodeType, Rule, as_ir
from ssgc.render.scene import check_output, plain, require_matplotlib, save_figure

LAYER_GAP = 1.3  # inches between layer centres
BOX_GAP = 0.35  # inches between boxes of a layer
BOX_HEIGHT = 0.5
CHAR = 0.062  # inches per character at the name's font size
LABEL_PAD = 0.03  # inches kept free round a label
FORWARD_AT = 0.7  # a label's favourite place: this far along its arrow
BACK_COLOUR = "#a0522d"
DIAGRAM_EXAMPLE = "diagram.svg"  # the file name a refused directory's message suggests


@dataclass(frozen=True)
class Layout:
    layer: dict[int, int]  # type or waypoint id -> layer (0: the root)
    x: dict[int, float]  # type or waypoint id -> box centre (inches)
    width: dict[int, float]
    back: frozenset[int]  # rule ids that point back up (recursion)
    route: dict[int, list[int]]  # rule id -> the waypoints of an arrow that skips layers
    n_types: int  # ids below this are types, the rest waypoints

    def y(self, t: int) -> float:
        return -self.layer[t] * LAYER_GAP

    def boxes(self) -> np.ndarray:
        """Every type's box as a row (left, bottom, right, top), in type id order."""
        return np.array([_box(self, t) for t in range(self.n_types)]).reshape(-1, 4)


def render_diagram(grammar: Grammar | HoldsGrammar, output: str | Path) -> None:
    """Draw `grammar` to `output` (.svg or .png).  Drawing measures the labels' text, when
    matplotlib warns of a character its font lacks (in the grammar's name): those warnings
    are caught and said with the saving's, once, in ssgc's words (`save_figure`)."""
    grammar = as_ir(grammar)
    inputs = (grammar.file,) if grammar.file else ()
    out, fmt = check_output(Path(output), inputs=inputs, example=DIAGRAM_EXAMPLE)
    require_matplotlib()
    with warnings.catch_warnings(record=True) as drawn:
        warnings.simplefilter("always")
        fig = draw_diagram(grammar, layout(grammar))
    save_figure(fig, out, fmt, drawn)


def layout(grammar: Grammar) -> Layout:
    children: dict[int, list[Rule]] = {t.id: [] for t in grammar.types}
    for r in grammar.rules:
        children[r.parent].append(r)
    order, back = _dfs(grammar, children)
    layer = {t: 0 for t in order}
    for t in order:  # `order` is topological for the forward edges
        for r in children[t]:
            if r.id not in back:
                layer[r.child] = max(layer[r.child], layer[t] + 1)
    rows: list[list[int]] = [[] for _ in range(max(layer.values()) + 1)]
    for t in order:
        rows[layer[t]].append(t)
    width = {
        t.id: max(len(t.name), len(_kind_line(grammar, t))) * CHAR + 0.3 for t in grammar.types
    }
    parents: dict[int, list[int]] = {t.id: [] for t in grammar.types}
    route: dict[int, list[int]] = {}
    first: dict[tuple[int, int], int] = {}  # rules between the same two types share one arrow
    for r in grammar.rules:  # an arrow that skips layers gets a waypoint in each layer between
        if r.id in back:
            continue
        if (r.parent, r.child) in first:
            route[r.id] = route[first[r.parent, r.child]]
            continue
        first[r.parent, r.child] = r.id
        above, route[r.id] = r.parent, []
        for k in range(layer[r.parent] + 1, layer[r.child]):
            way = len(width)
            layer[way], width[way], parents[way] = k, 0.2, [above]
            rows[k].append(way)
            route[r.id].append(way)
            above = way
        parents[r.child].append(above)
    x = _place(rows, width)
    for _ in range(2):  # barycentre sweeps, top to bottom
        for row in rows[1:]:
            row.sort(key=lambda t: _mean([x[p] for p in parents[t]], x[t]))
        x = _place(rows, width)
    return Layout(layer, x, width, frozenset(back), route, len(grammar.types))


def arrow_points(lay: Layout, r: Rule) -> np.ndarray:
    """The corners of a forward rule's arrow, top to bottom: the parent's bottom, the top and
    bottom of each waypoint's slot, the child's top.  Slanted stretches lie between two layers'
    rows, where no box is; the arrow crosses a row only straight down through its own slot."""
    h = BOX_HEIGHT / 2
    points = [(lay.x[r.parent], lay.y(r.parent) - h)]
    for w in lay.route.get(r.id, []):
        points += [(lay.x[w], lay.y(w) + h), (lay.x[w], lay.y(w) - h)]
    points.append((lay.x[r.child], lay.y(r.child) + h))
    return np.array(points)


def back_ends(lay: Layout, r: Rule) -> tuple[np.ndarray, np.ndarray, float]:
    """A recursive rule's arrow: from the parent's right side (a little above its middle) round
    to the child's (a little below), an arc of matplotlib's `arc3` with this `rad`; a small loop
    (from below the middle to above it) when the type is its own child."""
    loop = r.parent == r.child
    right_p = lay.x[r.parent] + lay.width[r.parent] / 2
    right_c = lay.x[r.child] + lay.width[r.child] / 2
    lift = 0.12 if loop else -0.06  # a loop and the arcs up that meet at one box stay apart
    start = np.array([right_p, lay.y(r.parent) - lift])
    end = np.array([right_c, lay.y(r.child) + lift])
    return start, end, 1.6 if loop else 0.5


def arc_points(start: np.ndarray, end: np.ndarray, rad: float, n: int = 41) -> np.ndarray:
    """Points of matplotlib's `arc3` curve (a quadratic Bezier): the axes are as many inches
    as the figure, so data and display coordinates differ only by a scale."""
    d = end - start
    ctrl = (start + end) / 2 + rad * np.array([d[1], -d[0]])
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) ** 2 * start + 2 * t * (1 - t) * ctrl + t**2 * end


def _box(lay: Layout, t: int) -> tuple[float, float, float, float]:
    w, h = lay.width[t] / 2, BOX_HEIGHT / 2
    return lay.x[t] - w, lay.y(t) - h, lay.x[t] + w, lay.y(t) + h


def _mean(values: list[float], default: float) -> float:
    return float(np.mean(values)) if values else default


def _dfs(grammar: Grammar, children: dict[int, list[Rule]]) -> tuple[list[int], set[int]]:
    """Reverse post-order from the root (then any unreachable type), and the back edges."""
    state = dict.fromkeys(children, 0)  # 0 new, 1 on the stack, 2 done
    post: list[int] = []
    back: set[int] = set()
    starts = [grammar.root] + [t.id for t in grammar.types if t.id != grammar.root]
    for start in starts:
        if state[start]:
            continue
        stack = [(start, iter(children[start]))]
        state[start] = 1
        while stack:
            node, it = stack[-1]
            rule = next(it, None)
            if rule is None:
                stack.pop()
                state[node] = 2
                post.append(node)
            elif state[rule.child] == 1:
                back.add(rule.id)
            elif state[rule.child] == 0:
                state[rule.child] = 1
                stack.append((rule.child, iter(children[rule.child])))
    return post[::-1], back


def _place(rows: list[list[int]], width: dict[int, float]) -> dict[int, float]:
    x = {}
    for row in rows:
        total = sum(width[t] for t in row) + BOX_GAP * (len(row) - 1)
        left = -total / 2
        for t in row:
            x[t] = left + width[t] / 2
            left += width[t] + BOX_GAP
    return x


def count_range(t: NodeType) -> tuple[int, int]:
    """The smallest and largest count of positive probability of a `repeat`: `probs: [0.5,
    0.5, 0, 0]` makes 0..1 copies, not 0..3."""
    assert t.count is not None
    positive = np.flatnonzero(np.asarray(t.count.probs) > 0)
    return int(positive[0]), int(t.count.largest)


def _kind_line(grammar: Grammar, t: NodeType) -> str:
    kind = t.kind.name.lower()
    if t.kind == Kind.REPEAT and t.count is not None:
        probs = t.count.probs
        mean = float(np.dot(np.arange(len(probs)), probs))
        low, high = count_range(t)
        kind += f" ×{low}..{high}, mean {_mean_text(mean)}"
    observed = "observed" if t.observed else "latent"
    root = ", root" if t.id == grammar.root else ""
    added = f" · added by observation ({t.synthetic})" if t.synthetic else ""
    return f"{kind} · {observed}{root}{added}"


def _mean_text(mean: float) -> str:
    """A repeat's mean count to two significant digits, in plain digits: `190`, not the
    `1.9e+02` that `:.2g` prints from 100 on."""
    text = f"{mean:.2g}"
    return f"{float(text):.0f}" if "e+" in text else text


def _rule_label(grammar: Grammar, r: Rule) -> str:
    parent = grammar.types[r.parent]
    if parent.kind in (Kind.OR, Kind.INDEPENDENT):
        return format_prob(float(parent.probs[r.index]), 2)
    if parent.kind == Kind.REPEAT:
        return "×n"
    return "1"


def _pair_label(grammar: Grammar, rules: list[Rule]) -> str:
    """Several rules between two types are one arrow with all their probabilities."""
    labels = [_rule_label(grammar, r) for r in rules]
    if len(rules) > 1 and len(set(labels)) == 1:
        return f"{labels[0]} ({len(rules)} rules)"
    return ", ".join(labels)


def draw_diagram(grammar: Grammar, lay: Layout) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    boxes = lay.boxes()
    x0, x1 = boxes[:, 0].min() - 0.6, boxes[:, 2].max() + 0.6
    n_layers = max(lay.layer.values()) + 1
    y0, y1 = -(n_layers - 1) * LAYER_GAP - 0.6, 0.9
    fig = Figure(figsize=(x1 - x0, y1 - y0))
    FigureCanvasAgg(fig)  # a renderer to measure the labels with
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_axis_off()
    title = ax.text(
        x0 + 0.2, y1 - 0.2, plain(f"grammar '{grammar.name}'"), fontsize=9, va="top", weight="bold"
    )
    for t in grammar.types:
        _draw_box(ax, grammar, lay, t)
    pairs: dict[tuple[int, int], list[Rule]] = {}
    for r in grammar.rules:  # several rules between two types: one arrow, their labels together
        pairs.setdefault((r.parent, r.child), []).append(r)
    arrows = [_draw_arrow(ax, lay, rules[0]) for rules in pairs.values()]
    kinds = [_arrow_kind(lay, rules[0]) for rules in pairs.values()]
    placer = _LabelPlacer(ax, [*boxes, _extent(ax, title)], arrows, kinds)
    for i, rules in enumerate(pairs.values()):
        back = rules[0].id in lay.back
        placer.place(i, _pair_label(grammar, rules), BACK_COLOUR if back else "black")
    return fig


def _draw_box(ax: Any, grammar: Grammar, lay: Layout, t: NodeType) -> None:
    """A type's box: filled if observed, dashed if latent, thick for the root, grey for a type
    the observation model added (its kind line says so too)."""
    from matplotlib.patches import FancyBboxPatch

    left, bottom, _, _ = _box(lay, t.id)
    ax.add_patch(
        FancyBboxPatch(
            (left, bottom),
            lay.width[t.id],
            BOX_HEIGHT,
            boxstyle="round,pad=0,rounding_size=0.08",
            fc="#cfe3f7" if t.observed else ("0.93" if t.synthetic else "white"),
            ec="0.45" if t.synthetic else "black",
            lw=1.6 if t.id == grammar.root else 0.8,
            ls="-" if t.observed else "--",
            zorder=2,
        )
    )
    y = lay.y(t.id)
    ax.text(lay.x[t.id], y + 0.08, plain(t.name), ha="center", va="center", fontsize=8, zorder=3)
    ax.text(
        lay.x[t.id],
        y - 0.12,
        _kind_line(grammar, t),
        ha="center",
        va="center",
        fontsize=6,
        color="0.3",
        zorder=3,
    )


def _arrow_kind(lay: Layout, r: Rule) -> str:
    if r.id not in lay.back:
        return "forward"
    return "loop" if r.parent == r.child else "back"


def _draw_arrow(ax: Any, lay: Layout, r: Rule) -> np.ndarray:
    """Draws one rule's arrow and returns points along it (for placing the labels)."""
    style = {"arrowstyle": "-|>", "lw": 0.7, "color": "0.25", "shrinkA": 0, "shrinkB": 0}
    if r.id in lay.back:  # recursion: from the parent's right side round to the child's
        start, end, rad = back_ends(lay, r)
        style.update(color=BACK_COLOUR, connectionstyle=f"arc3,rad={rad}")
        ax.annotate("", xy=tuple(end), xytext=tuple(start), arrowprops=style, zorder=1)
        return arc_points(start, end, rad)
    points = arrow_points(lay, r)
    if len(points) > 2:  # through its waypoints, the arrow head on the last stretch
        ax.plot(points[:-1, 0], points[:-1, 1], color="0.25", lw=0.7, zorder=1)
    ax.annotate("", xy=tuple(points[-1]), xytext=tuple(points[-2]), arrowprops=style, zorder=1)
    return points


def _extent(ax: Any, text: Any) -> np.ndarray:
    """A text's box (left, bottom, right, top) in data inches, by the renderer's measure."""
    bbox = text.get_window_extent(ax.figure.canvas.get_renderer())
    corners = ax.transData.inverted().transform([[bbox.x0, bbox.y0], [bbox.x1, bbox.y1]])
    return np.array([*corners[0], *corners[1]])


class _LabelPlacer:
    """Puts each arrow's label at the first of its candidate places that is clear of every box,
    every label placed before and every other arrow; failing that, clear of boxes and labels
    only; failing that, the favourite place.  Without this, labels 70% along arrows that meet
    at one child ran into each other ("0.2!×n")."""

    def __init__(
        self, ax: Any, obstacles: list[np.ndarray], arrows: list[np.ndarray], kinds: list[str]
    ) -> None:
        self.ax = ax
        self.kinds = kinds
        self.taken = [np.asarray(o, dtype=float) for o in obstacles]
        self.arrows = arrows
        # every arrow's straight stretches, and whose each is
        self.starts = np.vstack([a[:-1] for a in arrows])
        self.ends = np.vstack([a[1:] for a in arrows])
        self.owner = np.repeat(np.arange(len(arrows)), [len(a) - 1 for a in arrows])
        self.low = np.minimum(self.starts, self.ends)  # each stretch's bounding box
        self.high = np.maximum(self.starts, self.ends)

    def place(self, i: int, label: str, colour: str) -> None:
        text = self.ax.text(
            0.0,
            0.0,
            label,
            fontsize=6,
            color=colour,
            ha="center",
            va="center",
            zorder=4,
            gid="rule-label",
            bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.85},
        )
        size = np.ptp(_extent(self.ax, text).reshape(2, 2), axis=0) / 2 + LABEL_PAD
        centres = _candidates(self.arrows[i], size, self.kinds[i])
        boxes = np.hstack([centres - size, centres + size])
        best = self._best(i, boxes)
        text.set_position(tuple(centres[best]))
        self.taken.append(boxes[best])

    def _best(self, i: int, boxes: np.ndarray) -> int:
        taken = np.array(self.taken)
        hits = (
            (boxes[:, None, 0] < taken[None, :, 2])
            & (taken[None, :, 0] < boxes[:, None, 2])
            & (boxes[:, None, 1] < taken[None, :, 3])
            & (taken[None, :, 1] < boxes[:, None, 3])
        ).any(axis=1)
        lo, hi = boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)  # round all the places
        near = np.all((self.low < hi) & (self.high > lo), axis=1)
        others = near & (self.owner != i)
        crossed = _segments_cross(self.starts[others], self.ends[others], boxes).any(axis=1)
        for ok in (~hits & ~crossed, ~hits):
            if ok.any():
                return int(np.argmax(ok))
        return 0


def _candidates(points: np.ndarray, size: np.ndarray, kind: str) -> np.ndarray:
    """Places for a label's centre, best first.  On a forward arrow: along it, nearest to 70%
    of its length first.  On a back arc (brown, on the right): along it from its middle, then
    beside it; a loop's label beside the loop, above it or below it, then on it."""
    if kind == "forward":
        at = np.linspace(0.05, 0.95, 37)
        return _along(points, at[np.argsort(np.abs(at - FORWARD_AT), kind="stable")])
    at = np.linspace(0.1, 0.9, 33)
    on_arc = _along(points, at[np.argsort(np.abs(at - 0.5), kind="stable")])
    right = points[:, 0].max() + size[0] + 0.01
    top, bottom = points[:, 1].max(), points[:, 1].min()
    beside = np.array(
        [
            [right, (top + bottom) / 2],
            [points[-1, 0] + size[0], top + size[1] + 0.02],
            [points[0, 0] + size[0], bottom - size[1] - 0.02],
        ]
    )
    return np.vstack([beside, on_arc]) if kind == "loop" else np.vstack([on_arc, beside])


def _along(points: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The points at fractions `at` of a polyline's length."""
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    length = np.concatenate([[0.0], np.cumsum(steps)])
    s = at * length[-1]
    return np.column_stack([np.interp(s, length, points[:, 0]), np.interp(s, length, points[:, 1])])


def _segments_cross(a: np.ndarray, b: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Whether each box (rows left, bottom, right, top) meets each segment a-b: a (boxes,
    segments) array, by Liang-Barsky clipping of every segment to every box at once."""
    d = (b - a)[None]  # (1, segments, 2)
    lo, hi = boxes[:, None, :2], boxes[:, None, 2:]  # (boxes, 1, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lo, t_hi = (lo - a[None]) / d, (hi - a[None]) / d
    flat = d == 0  # a segment parallel to an axis: inside the slab or never
    inside = (lo < a[None]) & (a[None] < hi)
    t_in = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(t_lo, t_hi))
    t_out = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(t_lo, t_hi))
    return np.maximum(t_in.max(axis=2), 0.0) < np.minimum(t_out.min(axis=2), 1.0)
