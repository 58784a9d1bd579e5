"""A grammar as a picture (`ssg inspect GRAMMAR --diagram OUT`, docs/render.md; thesis Figs.
2-3, 2-6): node types as boxes with their kind, rules as arrows labelled with their
probabilities, laid out in layers by the longest path from the root.

The layout is computed here (no graphviz): recursive rules are found by a depth-first search
and drawn as curved arrows back up; the rest is a DAG whose longest-path layering puts every
type below all of its parents.  Within a layer, types are ordered by the mean position of their
parents (two barycentre sweeps); an arrow that skips layers passes through a waypoint in each
layer between, so it never runs through a box.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ssgc.ir import Grammar, HoldsGrammar, Kind, NodeType, Rule, as_ir
from ssgc.render.scene import check_output, plain, require_matplotlib, save_figure

LAYER_GAP = 1.3  # inches between layer centres
BOX_GAP = 0.35  # inches between boxes of a layer
BOX_HEIGHT = 0.5
CHAR = 0.062  # inches per character at the name's font size


@dataclass(frozen=True)
class Layout:
    layer: dict[int, int]  # type id -> layer (0: the root)
    x: dict[int, float]  # type id -> box centre (inches)
    width: dict[int, float]
    back: frozenset[int]  # rule ids that point back up (recursion)
    route: dict[int, list[int]]  # rule id -> the waypoints of an arrow that skips layers


def render_diagram(grammar: Grammar | HoldsGrammar, output: str | Path) -> None:
    grammar = as_ir(grammar)
    out, fmt = check_output(Path(output), inputs=(grammar.file,) if grammar.file else ())
    require_matplotlib()
    save_figure(draw_diagram(grammar, layout(grammar)), out, fmt)


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
    for r in grammar.rules:  # an arrow that skips layers gets a waypoint in each layer between
        if r.id in back:
            continue
        above = r.parent
        for k in range(layer[r.parent] + 1, layer[r.child]):
            way = len(width)
            layer[way], width[way], parents[way] = k, 0.2, [above]
            rows[k].append(way)
            route.setdefault(r.id, []).append(way)
            above = way
        parents[r.child].append(above)
    x = _place(rows, width)
    for _ in range(2):  # barycentre sweeps, top to bottom
        for row in rows[1:]:
            row.sort(key=lambda t: _mean([x[p] for p in parents[t]], x[t]))
        x = _place(rows, width)
    return Layout(layer, x, width, frozenset(back), route)


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


def _kind_line(grammar: Grammar, t: NodeType) -> str:
    kind = t.kind.name.lower()
    if t.kind == Kind.REPEAT and t.count is not None:
        probs = t.count.probs
        mean = float(np.dot(np.arange(len(probs)), probs))
        kind += f" ×{int(np.flatnonzero(probs)[0])}..{len(probs) - 1}, mean {mean:.2g}"
    observed = "observed" if t.observed else "latent"
    root = ", root" if t.id == grammar.root else ""
    return f"{kind} · {observed}{root}"


def _rule_label(grammar: Grammar, r: Rule) -> str:
    parent = grammar.types[r.parent]
    if parent.kind in (Kind.OR, Kind.INDEPENDENT):
        return f"{parent.probs[r.index]:.2g}"
    if parent.kind == Kind.REPEAT:
        return "×n"
    return "1"


def draw_diagram(grammar: Grammar, lay: Layout) -> Any:
    from matplotlib.figure import Figure
    from matplotlib.patches import FancyBboxPatch

    lefts = [lay.x[t] - lay.width[t] / 2 for t in lay.x]
    rights = [lay.x[t] + lay.width[t] / 2 for t in lay.x]
    x0, x1 = min(lefts) - 0.6, max(rights) + 0.6
    n_layers = max(lay.layer.values()) + 1
    y0, y1 = -(n_layers - 1) * LAYER_GAP - 0.6, 0.9
    fig = Figure(figsize=(x1 - x0, y1 - y0))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_axis_off()
    ax.text(
        x0 + 0.2, y1 - 0.2, plain(f"grammar '{grammar.name}'"), fontsize=9, va="top", weight="bold"
    )
    y = {t: -lay.layer[t] * LAYER_GAP for t in lay.x}
    for t in grammar.types:
        w = lay.width[t.id]
        ax.add_patch(
            FancyBboxPatch(
                (lay.x[t.id] - w / 2, y[t.id] - BOX_HEIGHT / 2),
                w,
                BOX_HEIGHT,
                boxstyle="round,pad=0,rounding_size=0.08",
                fc="#cfe3f7" if t.observed else "white",
                ec="black",
                lw=1.6 if t.id == grammar.root else 0.8,
                ls="-" if t.observed else "--",
                zorder=2,
            )
        )
        ax.text(
            lay.x[t.id],
            y[t.id] + 0.08,
            plain(t.name),
            ha="center",
            va="center",
            fontsize=8,
            zorder=3,
        )
        ax.text(
            lay.x[t.id],
            y[t.id] - 0.12,
            _kind_line(grammar, t),
            ha="center",
            va="center",
            fontsize=6,
            color="0.3",
            zorder=3,
        )
    pairs: dict[tuple[int, int], list[Rule]] = {}
    for r in grammar.rules:  # several rules between two types: one arrow, their labels together
        pairs.setdefault((r.parent, r.child), []).append(r)
    for rules in pairs.values():
        labels = [_rule_label(grammar, r) for r in rules]
        if len(rules) > 1:
            same = len(set(labels)) == 1
            labels = [f"{labels[0]} ({len(rules)} rules)"] if same else [", ".join(labels)]
        _arrow(ax, lay, rules[0], y, labels[0])
    return fig


def _arrow(ax: Any, lay: Layout, r: Rule, y: dict[int, float], label: str) -> None:
    style = {"arrowstyle": "-|>", "lw": 0.7, "color": "0.25", "shrinkA": 0, "shrinkB": 0}
    px, cx = lay.x[r.parent], lay.x[r.child]
    if r.id in lay.back:  # recursion: from the parent's right side round to the child's
        start = (px + lay.width[r.parent] / 2, y[r.parent])
        end = (cx + lay.width[r.child] / 2, y[r.child] + (0.12 if r.parent == r.child else 0))
        rad = 1.6 if r.parent == r.child else 0.5
        style.update(color="#a0522d", connectionstyle=f"arc3,rad={rad}")
        if r.parent == r.child:
            start = (start[0], start[1] - 0.12)
        ax.annotate("", xy=end, xytext=start, arrowprops=style, zorder=1)
        mid = (max(start[0], end[0]) + 0.22, (start[1] + end[1]) / 2)
        if r.parent == r.child:  # above the loop, clear of a neighbouring box
            mid = (end[0] + 0.05, end[1] + 0.25)
        ax.text(*mid, label, fontsize=6, color="#a0522d", ha="left", va="center", zorder=4)
        return
    start = np.array([px, y[r.parent] - BOX_HEIGHT / 2])
    end = np.array([cx, y[r.child] + BOX_HEIGHT / 2])
    ways = [np.array([lay.x[w], -lay.layer[w] * LAYER_GAP]) for w in lay.route.get(r.id, [])]
    if ways:  # through its waypoints, the arrow head on the last stretch
        line = np.array([start, *ways])
        ax.plot(line[:, 0], line[:, 1], color="0.25", lw=0.7, zorder=1)
        start = ways[-1]
    rad = 0.0
    ax.annotate("", xy=tuple(end), xytext=tuple(start), arrowprops=style, zorder=1)
    # the label on the arrow, 70% of the way down: a point of matplotlib's arc3 Bezier curve
    d = end - start
    ctrl = (start + end) / 2 + rad * np.array([d[1], -d[0]])
    t = 0.7
    at = (1 - t) ** 2 * start + 2 * t * (1 - t) * ctrl + t**2 * end
    ax.text(
        *at,
        label,
        fontsize=6,
        ha="center",
        va="center",
        zorder=4,
        bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.85},
    )
