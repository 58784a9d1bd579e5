"""Pictures of scenes, sampled trees and parse results (`ssg render`, docs/render.md).

Everything is read from the input file alone: a scene's objects, a sampled scene's tree, or the
best parse of each scene of an `ssg parse` result.  A grammar, when given, only adds each type's
geometry (its box, cylinder, sphere, revolve or tray); without one, or for a mesh type, an
object is a marker.  Each scene is drawn twice, in 3-D and from above, coloured by type, with
the tree's edges between node poses; a parse's edges are coloured by the log-probability of the
rule that produced the child, so the part of the scene the grammar finds unusual stands out
(thesis Fig. 4-8).
"""

from __future__ import annotations

import colorsys
import io
import json
import math
import os
import re
import sys
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import SceneError, SsgError, SsgWarning, one_line
from ssgc.geometry import quat_to_matrix
from ssgc.io.outputs import STDOUT_NAMES, Output, write_output_bytes
from ssgc.io.outputs import check_output as check_output_path
from ssgc.io.parsed import ParseDoc, best_tree, read_parse_doc
from ssgc.io.scene import (
    Locator,
    NodeTable,
    SceneDoc,
    SceneRead,
    is_parse_result,
    json_files,
    lazy_source,
    load_scenes,
    loads_json,
    read_scene_doc,
    read_scene_text,
    shown,
    validated,
)
from ssgc.ir import Grammar, HoldsGrammar, as_ir

FloatArray = NDArray[np.float64]
MAX_GRID = 64  # scenes in one picture; more would be unreadable
FORMATS = (".png", ".svg")
MIN_ASPECT = 0.35  # in 3-D, no axis is drawn shorter than this share of the longest
LEGEND_CHARS = 40  # a type's name in the legend is cut to this many characters (the bundled
# grammars' longest, PlateRoomEssentialsSaladTurquoise, is 33)
LEGEND_ENTRY_PT = 10.5  # the height of a legend entry at font size 7 (points)
HELD_TOL = 0.002  # m: an object resting on its container's floor may reach this far below it
SMALLER = 0.9  # what a container holds covers less than this share of its area from above
PANEL_PT = 200.0  # the longer side of a panel's drawing area, at most about this (points)
MIN_SHAPE_PT = 4.0  # a shape drawn smaller than this (points) also gets a dot, to be seen
OFFSET_SHARE = 1000  # a panel counts from a round number near a scene this far off (in sizes)
DOT_AREA = 30  # the dot of an object without a shape, or with one too small (points²)
TITLE_PT = 230.0  # a panel's title is at most about this wide (points): it is centred over the
# 3-D panel, whose centre is at least 1.6 inches (115 points) from the edge of its cell
MIN_TITLE_CHARS = 12  # a name is never cut shorter than this in a title
SPREAD = 1e-9  # rule log-probabilities closer than this are one value (no colour scale)
# The colours of the observed types, `ssg render`'s and `ssg view`'s: matplotlib's "tab20",
# its ten dark colours first (tab10's, in its order), then the ten light ones, so that up to
# ten types get ten strong colours and two neighbours in their order never share a hue.
PALETTE = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
    "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf",
    "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5",
    "#c49c94", "#f7b6d2", "#c7c7c7", "#dbdb8d", "#9edae5",
)  # fmt: skip


@dataclass(frozen=True)
class View:
    """One scene to draw: its nodes (objects, and latent nodes when a tree is known)."""

    name: str
    title: str
    types: tuple[str, ...]
    xyz: FloatArray  # (n, 3)
    quat: FloatArray  # (n, 4) wxyz
    observed: NDArray[np.bool_]
    parent: NDArray[np.int64]  # -1: a root, or no tree known
    score: FloatArray | None = None  # a parse's per-node rule log-probability
    rules: tuple[str | None, ...] | None = None  # per node, the rule that made it (`ssg view`)


def require_matplotlib() -> Any:
    """matplotlib is an optional extra; without it the user gets one clear message."""
    try:
        import matplotlib
        import mpl_toolkits.mplot3d  # noqa: F401  (registers the 3-D projection)
    except ImportError:
        raise SsgError.single(
            "drawing needs matplotlib, which is not installed: pip install 'ssgc[viz]'"
        ) from None
    return matplotlib


def check_output(
    path: Path, inputs: tuple[str | Path, ...] = (), example: str = "scene.png"
) -> tuple[Output, str]:
    """The picture's output (checked before any work, as every output: docs/robustness.md) and
    its format from the file name; a device or standard output without a suffix gets PNG.
    A directory (`-o .`) is refused with a file name the user can type (`example` in it), as
    the general check's `NAME` is not one."""
    if str(path) not in STDOUT_NAMES and os.path.isdir(path):
        raise SsgError.single(
            f"the picture is a directory; give a file name (such as {Path(path) / example})",
            str(path),
        )
    out = check_output_path(path, "picture", inputs=inputs)
    suffix = Path(path).suffix.lower()
    if out.stream and suffix not in FORMATS:
        return out, "png"
    if suffix not in FORMATS:
        raise SsgError.single(
            f"the output must end in .png or .svg, got '{Path(path).name}'", str(path)
        )
    return out, suffix[1:]


def render_file(
    source: str | Path,
    output: str | Path,
    n: int = 1,
    grammar: Grammar | HoldsGrammar | None = None,
    scene: str | None = None,
) -> int:
    """Draw the first `n` scenes of `source` (or only those named `scene`) into `output`
    (.png or .svg); returns how many were drawn."""
    output, grammar = Path(output), grammar_ir(grammar)
    _check_count(n)
    out, fmt = check_output(output, inputs=(source,))
    require_matplotlib()
    if not 1 <= n <= MAX_GRID:
        raise SsgError.single(f"-n must be between 1 and {MAX_GRID}, got {n}")
    if scene is None:
        views = load_views(Path(source), n, grammar)
    else:
        views = [v for v in load_views(Path(source), sys.maxsize, grammar) if v.name == scene]
        if not views:
            raise _no_scene(Path(source), scene)
        views = views[:n]
    fig = draw_views(views, geometry_of(grammar), grammar)
    save_figure(fig, out, fmt)
    return len(views)


def grammar_ir(grammar: Any) -> Grammar | None:
    """The compiled grammar of what a Python caller passed as `grammar`: None, or either form
    `as_ir` takes (a path is its TypeError, not an AttributeError deep inside)."""
    return None if grammar is None else as_ir(grammar)


def _check_count(n: Any) -> None:
    """`n` of the Python API: a whole number (a string such as '3' raised a TypeError of
    comparison, which named no argument); its range is checked as `-n`'s."""
    if isinstance(n, bool) or not isinstance(n, int | np.integer):
        raise TypeError(f"n must be a whole number from 1 to {MAX_GRID}, got {n!r}")


def _no_scene(source: Path, scene: str) -> SsgError:
    """`--scene NAME` drew nothing: a parse result's scene of that name that has no parse
    (infeasible, timed out) is there, and the user is told so, with its status."""
    status = next(_statuses(source, scene), None)
    if status is None:
        return SsgError.single(f"no scene named '{shown(scene)}' in it", str(source))
    return SsgError.single(
        f"scene '{shown(scene)}' has no parse to draw (its status: {shown(status)})", str(source)
    )


def _statuses(source: Path, scene: str) -> Iterator[str]:
    """The status of each unparsed scene named `scene` in the parse results of `source` (a
    file, or a directory's `*.json`), which `load_views` has already read and checked."""
    for path in json_files(source) if source.is_dir() else [source]:
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if is_parse_result(data):
            for s in data["scenes"]:
                if isinstance(s, dict) and s.get("name") == scene and not s.get("parses"):
                    yield str(s.get("status") or "unknown")


def render_document(data: Any, output: str | Path, grammar: Grammar | None = None) -> int:
    """Draw a scene or parse-result document held in memory (the Python API's `.render`, whose
    `.to_json()` is the document `ssg render` would read from a file); returns how many scenes
    were drawn."""
    grammar = grammar_ir(grammar)
    out, fmt = check_output(Path(output))
    require_matplotlib()
    views = document_views(data, grammar, Path("<memory>"))[:MAX_GRID]
    save_figure(draw_views(views, geometry_of(grammar), grammar), out, fmt)
    return len(views)


# ------------------------------------------------------------------ reading ---


def load_views(path: Path, n: int, grammar: Grammar | None) -> list[View]:
    """A scene or parse-result JSON file, a directory of them, or (with a grammar) a sink
    dataset; the first `n` scenes."""
    if path.is_dir():
        files = json_files(path)
        if not files:
            raise SsgError.single("no *.json files in this directory", str(path))
        views: list[View] = []
        for f in files:
            views += _file_views(f, grammar)
            if len(views) >= n:
                break
        return views[:n]
    if path.suffix.lower() in (".yaml", ".yml"):
        if grammar is None:
            raise SsgError.single(
                "a YAML dataset names no types: give its grammar with -g", str(path)
            )
        return [
            _scene_view(s.name, grammar, s.types, s.xyz, s.quat)
            for s in load_scenes(path, grammar)[:n]
        ]
    return _file_views(path, grammar)[:n]


def _file_views(path: Path, grammar: Grammar | None) -> list[View]:
    """A file read as `ssg parse` reads a scene: strict JSON, every mistake located."""
    text = read_scene_text(path, "scene or parse result file")
    data = loads_json(text, str(path), "not JSON (expected a scene or an `ssg parse` result)")
    return document_views(data, grammar, path, text)


def document_views(
    data: Any, grammar: Grammar | None, path: Path, text: str | None = None
) -> list[View]:
    """The views of one JSON document: a scene (with its tree, when it has one) or an
    `ssg parse` result (the best parse of each scene), checked as `ssg parse` and
    `ssg export` check them (`ssgc.io.scene.read_scene_doc`, `ssgc.io.parsed`); a grammar
    adds the checks that need one (types, rules).  `text` locates mistakes in a file."""
    text = json.dumps(data) if text is None else text
    file, source = str(path), lazy_source(text, str(path))
    if is_parse_result(data):
        return _parse_views(read_parse_doc(data, text, file), grammar, source, file)
    if isinstance(data, dict) and "objects" in data:
        doc = validated(SceneDoc, data, text, file)
        view = _doc_view(doc, read_scene_doc(doc, grammar, source), grammar, one_line(path.stem))
        return [view]
    raise SceneError.single(
        "not a scene (a JSON object with `objects`) or an `ssg parse` result (with `scenes`)",
        file,
    )


def _observed(grammar: Grammar | None, name: str, given: bool | None) -> bool:
    if grammar is not None and name in grammar.type_ids:
        return grammar.types[grammar.type_ids[name]].observed
    return True if given is None else given


def _tree_view(title: str, tree: NodeTable, grammar: Grammar | None) -> View:
    """A tree's nodes, each with the rule that made it, so that the viewer can say it for a
    sampled scene as for a parse (a parse result's own rule names replace these)."""
    return View(
        name=title,
        title=title,
        types=tree.types,
        xyz=tree.xyz,
        quat=tree.quat,
        observed=np.array(
            [_observed(grammar, t, o) for t, o in zip(tree.types, tree.observed, strict=True)],
            bool,
        ).reshape(-1),
        parent=tree.parent,
        rules=tuple(_rule_name(tree, i, grammar) for i in range(len(tree.types))),
    )


def _rule_name(tree: NodeTable, i: int, grammar: Grammar | None) -> str | None:
    """Node i's rule named as a parse names it (`Parent[index]->Child`, `Grammar.rule_name`):
    the tree records only its index in the parent type's rule list.  A grammar other than
    the scene's (its rules reordered) may hold there a rule that makes another type, or none:
    the name then says so, rather than name a rule that could not have made this node."""
    parent, index = int(tree.parent[i]), int(tree.rule[i])
    if parent < 0 or index < 0:
        return None
    parent_name, child_name = tree.types[parent], tree.types[i]
    if grammar is None or parent_name not in grammar.type_ids:
        return f"{parent_name}[{index}]->{child_name}"
    rules = grammar.types[grammar.type_ids[parent_name]].rules
    if index >= len(rules):
        return f"{parent_name}[{index}] (no such rule in the grammar)"
    made = grammar.types[grammar.rules[rules[index]].child].name
    if made != child_name:
        return f"{parent_name}[{index}] (makes {made}, not {child_name})"
    return grammar.rule_name(int(rules[index]))


def _doc_view(doc: SceneDoc, read: SceneRead, grammar: Grammar | None, stem: str) -> View:
    """A scene's tree (its latent nodes too) when it has a non-empty one, else its objects."""
    name = doc.name or stem
    if read.tree is not None and len(read.tree.types):
        return _tree_view(name, read.tree, grammar)
    n = len(read.types)
    return View(name, name, read.types, read.xyz, read.quat, np.ones(n, bool), np.full(n, -1))


def _scene_view(name: str, grammar: Grammar, types: Any, xyz: Any, quat: Any) -> View:
    return View(
        name=name,
        title=name,
        types=tuple(grammar.types[int(t)].name for t in types),
        xyz=np.asarray(xyz, float),
        quat=np.asarray(quat, float),
        observed=np.ones(len(types), bool),
        parent=np.full(len(types), -1, np.int64),
    )


def _parse_views(doc: ParseDoc, grammar: Grammar | None, source: Locator, file: str) -> list[View]:
    """The best parse of each scene that has one; its rule scores colour the edges."""
    views = []
    for k, s in enumerate(doc.scenes):
        tree = best_tree(doc, k, grammar, source)
        if tree is None:
            continue
        name, best = s.name or "scene", s.parses[0]
        score = np.full(len(tree.types), np.nan)
        rules: list[str | None] = [None] * len(score)
        for r in best.rules:
            if 0 <= r.node < len(score):
                rules[r.node] = r.rule
                if r.log_prob is not None:
                    score[r.node] = r.log_prob
        title = name if best.score is None else f"{name}  (log p = {best.score:.2f})"
        view = _tree_view(name, tree, grammar)
        views.append(replace(view, title=title, score=score, rules=tuple(rules)))
    if not views:
        statuses = ", ".join(sorted({s.status or "?" for s in doc.scenes})) or "no scenes"
        raise SceneError.single(f"no scene of this parse result has a parse ({statuses})", file)
    return views


# ------------------------------------------------------------------ drawing ---


def geometry_of(grammar: Grammar | None) -> dict[str, tuple[FloatArray, list[list[int]]]]:
    """Each type's primitive as a small polygon mesh in its own frame (meshes: none)."""
    if grammar is None:
        return {}
    out = {}
    for t in grammar.types:
        mesh = primitive_mesh(t.geometry)
        if mesh is not None:  # centred on the geometry's origin in the type's frame
            out[t.name] = (mesh[0] + np.asarray(t.geometry.origin, float), mesh[1])
    return out


def primitive_mesh(geometry: Any) -> tuple[FloatArray, list[list[int]]] | None:
    """Vertices and polygon faces of a box, a cylinder (along z), a sphere, a revolve (its
    surface about z, `ssgc.constraints.revolved`) or a tray; else None."""
    if hasattr(geometry, "box"):
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        faces = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]
        return signs * np.asarray(geometry.box.size) / 2, faces
    if hasattr(geometry, "cylinder"):
        k, r, h = 20, geometry.cylinder.radius, geometry.cylinder.length
        a = np.linspace(0, 2 * np.pi, k, endpoint=False)
        ring = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
        verts = np.vstack([np.c_[ring, np.full(k, -h / 2)], np.c_[ring, np.full(k, h / 2)]])
        sides = [[i, (i + 1) % k, k + (i + 1) % k, k + i] for i in range(k)]
        return verts, [*sides, list(range(k)), list(range(k, 2 * k))]
    if hasattr(geometry, "sphere"):
        m, k, r = 7, 14, geometry.sphere.radius
        th, ph = np.meshgrid(np.linspace(0, np.pi, m), np.linspace(0, 2 * np.pi, k, endpoint=False))
        th, ph = th.T.ravel(), ph.T.ravel()
        verts = r * np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
        faces = [
            [i * k + j, i * k + (j + 1) % k, (i + 1) * k + (j + 1) % k, (i + 1) * k + j]
            for i in range(m - 1)
            for j in range(k)
        ]
        return verts, faces
    if hasattr(geometry, "revolve"):
        from ssgc.constraints.revolved import Revolved

        verts, tri = Revolved(geometry.revolve.profile).mesh(sections=20)
        return verts, tri.tolist()
    if hasattr(geometry, "tray"):  # its open box: floor and walls, outside and inside
        verts, tri = geometry.tray.mesh()
        return verts, tri.tolist()
    return None


def plain(text: str) -> str:
    """A user's string as matplotlib shows it literally: no mathtext, nothing unprintable."""
    return text.encode("utf-8", "replace").decode("utf-8").replace("$", r"\$")


def _colours(views: list[View], grammar: Grammar | None) -> dict[str, Any]:
    """A colour per observed type in the picture, by name, in the legend's (alphabetical)
    order: `grammar_colours`."""
    names = sorted({t for v in views for t, o in zip(v.types, v.observed, strict=True) if o})
    colours = grammar_colours(names, grammar)
    return {name: colours[name] for name in names}


def grammar_colours(names: list[str], grammar: Grammar | None) -> dict[str, str]:
    """A colour per type of `names` (the observed types drawn) and, with a grammar, per
    observed type of the grammar.  With a grammar the colours go to its observed types in its
    own order, whatever is drawn: a type then has one colour in every picture and page of that
    grammar (`ssg render`'s and `ssg view`'s), not one that depends on which other types a
    scene happens to hold.  Without one, `names` take them in alphabetical order."""
    order = [] if grammar is None else [t.name for t in grammar.types if t.observed]
    known = set(order)
    return type_colours(order + sorted(n for n in set(names) if n not in known))


def type_colours(names: list[str]) -> dict[str, str]:
    """A colour ("#rrggbb") per type of `names`, in their order: the PALETTE while it
    suffices, else as many distinct colours as types (`many_colours`), never one colour for
    two.  `ssg view` takes its colours from here too, so a type looks the same in both."""
    if len(names) <= len(PALETTE):
        return dict(zip(names, PALETTE, strict=False))
    rgb = np.rint(np.array(many_colours(len(names))) * 255).astype(int)
    return {n: "#{:02x}{:02x}{:02x}".format(*c) for n, c in zip(names, rgb, strict=True)}


def many_colours(n: int) -> list[tuple[float, float, float]]:
    """`n` distinct RGB colours for more types than a 20-colour palette holds: a third of them
    dark, a third medium, a third light, each third spread evenly round the hue circle, so
    that two types differ in hue by 360°/ceil(n/3) or in lightness (also `ssg view`'s)."""
    hues = math.ceil(n / 3)
    return [
        colorsys.hls_to_rgb((i % hues) / hues, (0.3, 0.5, 0.7)[i // hues], 0.75) for i in range(n)
    ]


def legend_label(name: str) -> str:
    """A type's name as the legend shows it: at most LEGEND_CHARS characters, a long one cut
    in the middle (the start and the end usually tell two types apart), so that the legend
    leaves the panels their room."""
    return plain(_cut(name))


def _cut(name: str, limit: int = LEGEND_CHARS) -> str:
    """`name`, at most `limit` characters: a longer one cut in the middle."""
    if len(name) <= limit:
        return name
    tail = limit // 3
    return name[: limit - tail - 1] + "…" + name[-tail:]


def panel_title(view: View) -> str:
    """A scene's title over its 3-D panel: its name cut as a legend entry is (`_cut`), and
    shorter while the title is wider than TITLE_PT, then what the title adds to the name (a
    parse's `(log p = ...)`), whole.  The title is centred over the panel: an uncut long name
    ran off the figure's edge (or over the panels beside it), the score at its end unseen."""
    name, rest = view.name, view.title[len(view.name) :]
    if not view.title.startswith(view.name):
        name, rest = view.title, ""
    keep = LEGEND_CHARS
    while keep > MIN_TITLE_CHARS and _text_width(_cut(name, keep) + rest, 8) > TITLE_PT:
        keep -= 1
    return plain(_cut(name, keep) + rest)


def _text_width(text: str, size: float) -> float:
    """The width (points) of `text` drawn plain (no mathtext) at font size `size`."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import TextToPath

    with warnings.catch_warnings():
        # A character the font lacks: matplotlib warns here, in its words and with our source
        # line.  The same text is drawn when the figure is saved, where `save_figure` says
        # it once, in ssgc's words (docs/render.md).
        warnings.simplefilter("ignore")
        width = TextToPath().get_text_width_height_descent(text, FontProperties(size=size), False)
    return float(width[0])


def _legend(fig: Any, handles: list[Any]) -> None:
    """The legend beside the panels, in as many columns as its entries need to fit the
    figure's height: every type is listed."""
    per_column = _legend_rows(fig.get_figheight())
    fig.legend(
        handles=handles,
        loc="outside right upper",
        fontsize=7,
        frameon=False,
        ncols=math.ceil(len(handles) / per_column),
    )


def _legend_rows(height: float) -> int:
    """Legend entries one column holds in a figure `height` inches tall."""
    return max(1, int((height * 72 - 20) / LEGEND_ENTRY_PT))


def _legend_width(labels: list[str], height: float) -> float:
    """Inches the legend takes beside the panels: its columns, each as wide as its longest
    label at font size 7 (measured) plus the colour patch and the gaps."""
    columns = math.ceil(len(labels) / _legend_rows(height))
    widths = [_text_width(label, 7) for label in labels]
    return (columns * (34 + max(widths, default=0)) + 10) / 72


def draw_views(
    views: list[View],
    geoms: dict[str, tuple[FloatArray, list[list[int]]]],
    grammar: Grammar | None = None,
) -> Any:
    """One figure: a (3-D, top-down) pair of panels per scene, a legend, and for parses a
    colour bar of rule log-probabilities.  The figure is widened by what the legend needs, so
    that many types or long names never squeeze the panels.  The grammar, when known, fixes
    each type's colour (`grammar_colours`)."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure

    cols = math.ceil(math.sqrt(len(views)))
    rows = math.ceil(len(views) / cols)
    scores = score_range(views)
    norm = None if scores is None else _score_norm(*scores)
    colours, cmap = _colours(views, grammar), colormaps["RdYlGn"]
    handles = _handles(views, colours, norm)
    legend = _legend_width([h.get_label() for h in handles], 3.6 * rows)
    bar = 0.0 if norm is None else 0.9
    fig = Figure(figsize=(8.0 * cols + max(1.6, legend + bar + 0.2), 3.6 * rows))
    fig.set_layout_engine("constrained", wspace=0.1)  # room for the 3-D panel's z label
    axes = []
    for i, view in enumerate(views):
        ax3 = fig.add_subplot(rows, 2 * cols, 2 * i + 1, projection="3d")
        ax2 = fig.add_subplot(rows, 2 * cols, 2 * i + 2)
        _draw_view(ax3, ax2, view, geoms, colours, norm, cmap)
        axes += [ax3, ax2]
    _legend(fig, handles)
    if scores is not None:
        _colour_bar(fig, axes, scores, ScalarMappable(norm, cmap))
    return fig


def _colour_bar(fig: Any, axes: list[Any], scores: tuple[float, float], mappable: Any) -> None:
    """The scale of the edges' colours; for one value, only its tick, not a scale of values
    no rule has."""
    colour_bar = fig.colorbar(mappable, ax=axes, shrink=0.8, pad=0.02)
    colour_bar.set_label("log-probability of the rule making the child (low = unusual)", fontsize=7)
    colour_bar.ax.tick_params(labelsize=7)
    if not spread(*scores):
        colour_bar.set_ticks([scores[1]])


def score_range(views: list[View]) -> tuple[float, float] | None:
    """The lowest and highest of all drawn parses' finite rule log-probabilities (None when no
    view is a parse; (-1, 0) when every rule is −∞)."""
    scores = [v.score[np.isfinite(v.score)] for v in views if v.score is not None]
    if not scores:
        return None
    finite = np.concatenate(scores)
    return (float(finite.min()), float(finite.max())) if finite.size else (-1.0, 0.0)


def spread(lo: float, hi: float) -> bool:
    """Whether the rule log-probabilities differ (beyond SPREAD, float noise).  When they do
    not (a grammar of fixed offsets scores every rule 0), no rule is more unusual than another:
    `ssg render` and `ssg view` then draw every finite one in the top colour, not the lowest,
    and the viewer marks none of them low."""
    return hi - lo > SPREAD


def _score_norm(lo: float, hi: float) -> Any:
    """The colour scale of a parse's edges, from `score_range`; for one value, a scale that
    ends at it, so it takes the top colour (−∞ keeps the lowest: `_draw_marks`)."""
    from matplotlib.colors import Normalize

    return Normalize(lo, hi) if spread(lo, hi) else Normalize(hi - 1.0, hi)


def _handles(views: list[View], colours: dict[str, Any], norm: Any) -> list[Any]:
    """The legend's entries: every observed type, then the marks the panels use."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles: list[Any] = [
        Patch(facecolor=c, alpha=0.6, label=legend_label(t)) for t, c in colours.items()
    ]
    if any(not np.all(v.observed) for v in views):
        handles.append(Line2D([], [], ls="", marker="s", ms=4, color="0.35", label="latent node"))
    if any(np.any(unexplained(v)) for v in views):
        handles.append(
            Line2D(
                [], [], ls="", marker="x", ms=7, mew=2, color="red", label="unexplained (clutter)"
            )
        )
    if norm is None and any(np.any(v.parent >= 0) for v in views):
        handles.append(Line2D([], [], color="0.2", label="tree edge"))
    return handles


def _draw_view(
    ax3: Any,
    ax2: Any,
    view: View,
    geoms: dict[str, Any],
    colours: dict[str, Any],
    norm: Any,
    cmap: Any,
) -> None:
    """A scene's two panels.  The limits come first, so that a shape too small to be seen at
    the panel's scale (a 40 cm box in a scene a kilometre wide) also gets a dot."""
    shapes = _world_shapes(view, geoms)
    centre, half = _extent(np.vstack([view.xyz, *shapes.values()]))
    origin = _origin(centre, half)
    view, centre = replace(view, xyz=view.xyz - origin), centre - origin
    shapes = {i: verts - origin for i, verts in shapes.items()}
    faint = holders(view, {i: geoms[view.types[i]][0] for i in shapes})
    for i in np.flatnonzero(view.observed):
        colour, verts = colours[view.types[i]], shapes.get(int(i))
        if verts is not None:
            _draw_shape(ax3, ax2, verts, geoms[view.types[i]][1], colour, faint[i])
        if verts is None or _tiny(np.ptp(verts, axis=0), half, 3):
            ax3.scatter(*view.xyz[i], color=colour, s=DOT_AREA, depthshade=False)
        if verts is None or _tiny(np.ptp(verts[:, :2], axis=0), _top_half(half), 2):
            ax2.scatter(*view.xyz[i, :2], color=colour, s=DOT_AREA, zorder=3)
    _draw_marks(ax3, ax2, view, norm, cmap)
    _limits(ax3, ax2, centre, half, origin)
    ax3.set_title(panel_title(view), fontsize=8)
    ax2.set_title("from above (x, y)", fontsize=8)


def _world_shapes(view: View, geoms: dict[str, Any]) -> dict[int, FloatArray]:
    """Each observed object's shape (when its type has one) placed at its pose, by node."""
    rot = quat_to_matrix(view.quat) if len(view.types) else np.zeros((0, 3, 3))
    return {
        int(i): geoms[view.types[i]][0] @ rot[i].T + view.xyz[i]
        for i in np.flatnonzero(view.observed)
        if view.types[i] in geoms
    }


def _tiny(size: FloatArray, half: FloatArray, axes: int) -> bool:
    """Whether a shape of this extent (metres, per axis) is drawn smaller than MIN_SHAPE_PT
    in a panel whose longer side (PANEL_PT at most) spans the largest of the limits `half`
    on its first `axes` axes: then a dot shows it, as `ssg view` never draws an object
    smaller than 8 pixels."""
    span = 2 * float(np.max(half[:axes]))
    return float(np.max(size)) < MIN_SHAPE_PT / PANEL_PT * span


def _draw_shape(
    ax3: Any, ax2: Any, verts: FloatArray, faces: list[list[int]], colour: Any, faint: bool
) -> None:
    """A shape in 3-D (its faces) and from above (its outline's convex hull)."""
    from matplotlib.patches import Polygon
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    from scipy.spatial import ConvexHull, QhullError

    alpha = 0.15 if faint else 0.45
    ax3.add_collection3d(
        Poly3DCollection(
            _face_array(verts, faces), facecolor=colour, edgecolor=colour, alpha=alpha, lw=0.4
        ),
        autolim=False,  # limits are set once, equal on every axis (`_limits`)
    )
    try:
        hull = verts[ConvexHull(verts[:, :2]).vertices, :2]
    except QhullError:  # a shape seen exactly edge-on from above
        hull = verts[:, :2]
    ax2.add_patch(Polygon(hull, closed=True, fc=colour, ec=colour, alpha=alpha, lw=0.8))


def _face_array(verts: FloatArray, faces: list[list[int]]) -> FloatArray:
    """The faces' corners as one (faces, corners, 3) array, a short face (a cylinder's side
    beside its 20-cornered caps) padded with its own last corner, which draws the same.
    Given faces of different lengths, matplotlib pads them with uninitialised memory, whose
    huge values overflow in its projection: a RuntimeWarning, said as a drawing trouble."""
    width = max(len(f) for f in faces)
    return np.stack([verts[list(f) + [f[-1]] * (width - len(f))] for f in faces])


def _draw_marks(ax3: Any, ax2: Any, view: View, norm: Any, cmap: Any) -> None:
    """What is drawn over the objects: clutter crosses, latent nodes, the tree's edges."""
    from matplotlib.collections import LineCollection
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    clutter = unexplained(view)
    if np.any(clutter):
        ax3.scatter(*view.xyz[clutter].T, color="red", marker="x", s=60, depthshade=False)
        ax2.scatter(*view.xyz[clutter, :2].T, color="red", marker="x", s=60, zorder=6)
    latent = ~view.observed
    if np.any(latent):
        ax3.scatter(*view.xyz[latent].T, color="0.35", marker="s", s=8, depthshade=False)
        ax2.scatter(*view.xyz[latent, :2].T, color="0.35", marker="s", s=8, zorder=4)
    child = np.flatnonzero(view.parent >= 0)
    if child.size:
        segs = np.stack([view.xyz[view.parent[child]], view.xyz[child]], axis=1)
        if norm is not None and view.score is not None:
            s = view.score[child]
            colour = cmap(norm(np.where(np.isfinite(s), s, norm.vmin)))
            width = 2.0
        else:
            colour, width = "0.2", 1.0
        ax3.add_collection3d(Line3DCollection(segs, colors=colour, linewidths=width), autolim=False)
        ax2.add_collection(
            LineCollection(segs[:, :, :2], colors=colour, linewidths=width, zorder=5)
        )


def unexplained(view: View) -> NDArray[np.bool_]:
    """Objects a tree leaves to clutter: their parent is the observation model's clutter node
    (`~clutter:object`, docs/grammar.md section 9)."""
    parent_type = np.array((*view.types, ""), dtype=object)[view.parent]
    return view.observed & (view.parent >= 0) & (parent_type == "~clutter:object")


def holders(view: View, local: dict[int, FloatArray]) -> NDArray[np.bool_]:
    """Which objects hold others (a bin, a table), given the objects' shapes in their own frames
    (`local`, by node): they are drawn faintly, so that what they hold shows through.  A
    container is under what it holds and bigger than it; an object inside a bin or stacked on
    another of its size (a disc, a plate, a steamer tray under its lid) hides nothing, so it is
    drawn solid whatever lies under it."""
    rot = quat_to_matrix(view.quat) if len(view.types) else np.zeros((0, 3, 3))
    objects = np.flatnonzero(view.observed)
    world = [
        local[i] @ rot[i].T + view.xyz[i] if i in local else view.xyz[i : i + 1] for i in objects
    ]
    bottom = np.array([w[:, 2].min() for w in world])
    area = np.array([np.prod(np.ptp(w[:, :2], axis=0)) for w in world])
    out = np.zeros(len(view.types), bool)
    for k, i in enumerate(objects):
        if i in local:
            held = _held(view.xyz[objects], view.xyz[i], rot[i], local[i], bottom, area, k)
            out[i] = bool(np.any(np.delete(held, k)))
    return out


def _held(
    xyz: FloatArray,
    pose: FloatArray,
    rot: FloatArray,
    local: FloatArray,
    bottom: FloatArray,
    area: FloatArray,
    k: int,
) -> NDArray[np.bool_]:
    """Which objects (centres `xyz`, lowest points `bottom`, areas from above `area`) object k
    (at `pose`, its shape `local`) holds: each one's centre inside k's footprint and above k's
    base, reaching no lower than k does, and smaller than k from above."""
    local_xy = ((xyz - pose) @ rot)[:, :2]
    inside = np.all(np.abs(local_xy) <= np.abs(local[:, :2]).max(axis=0), axis=1)
    above = (xyz[:, 2] > bottom[k]) & (bottom >= bottom[k] - HELD_TOL)
    return inside & above & (area < SMALLER * area[k])


def _extent(pts: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The centre of the box holding `pts` and its half-sizes, 10% larger, at least 5 cm."""
    if len(pts) == 0:
        pts = np.zeros((1, 3))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return (lo + hi) / 2, np.maximum((hi - lo) / 2 * 1.1, 0.05)


def _origin(centre: FloatArray, half: FloatArray) -> FloatArray:
    """Per axis, the round number the panels count from: 0, or for a scene far from the
    origin for its size (0.5 m across at x = 1500 m) a round number near its centre, which
    the axis's label states (`x − 1,500 (m)`).  Its ticks then read 0.1, 0.2, not 1500.1,
    1500.2 crowded together, nor matplotlib's offset printed over a tick label."""
    origin = np.zeros(3)
    for k in range(3):
        if abs(centre[k]) >= OFFSET_SHARE * half[k]:
            step = 10.0 ** math.ceil(math.log10(2 * half[k]))
            origin[k] = round(centre[k] / step) * step
    return origin


def _axis_label(axis: str, origin: float) -> str:
    """An axis's label, with the number its ticks count from (`_origin`) when not 0."""
    if origin == 0:
        return f"{axis} (m)"
    number = f"{abs(origin):,.0f}" if abs(origin) >= 1 else f"{abs(origin):g}"
    return f"{axis} {'−' if origin > 0 else '+'} {number} (m)"


def _top_half(half: FloatArray) -> FloatArray:
    """The view from above's half-sizes on x and y: the shorter one padded to MIN_ASPECT of
    the longer, so that objects in a line a kilometre long do not make a panel a few points
    tall, its y tick labels printed over each other (the scale stays equal on both axes)."""
    return np.maximum(half[:2], MIN_ASPECT * half[:2].max())


def _limits(ax3: Any, ax2: Any, centre: FloatArray, half: FloatArray, origin: FloatArray) -> None:
    """Equal scales on x and y from above, so shapes and distances look as they are; in 3-D
    too, but an axis shorter than MIN_ASPECT of the longest is stretched to it, so that a flat
    scene (all on a tabletop) or a long thin one is not drawn as a sheet or a line."""
    for k, setter in enumerate((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim)):
        setter(centre[k] - half[k], centre[k] + half[k])
    ax3.set_box_aspect(tuple(np.maximum(half, MIN_ASPECT * half.max())), zoom=0.9)
    ax3.tick_params(labelsize=6)
    x, y, z = (_axis_label(a, float(o)) for a, o in zip("xyz", origin, strict=True))
    ax3.set_xlabel(x, fontsize=7)
    ax3.set_ylabel(y, fontsize=7)
    ax3.set_zlabel(z, fontsize=7)
    top = _top_half(half)
    ax2.set_xlim(centre[0] - top[0], centre[0] + top[0])
    ax2.set_ylim(centre[1] - top[1], centre[1] + top[1])
    ax2.set_aspect("equal")
    ax2.tick_params(labelsize=6)
    ax2.set_xlabel(x, fontsize=7)
    ax2.set_ylabel(y, fontsize=7)


def save_figure(
    fig: Any, output: Output, fmt: str, drawn: list[warnings.WarningMessage] | None = None
) -> None:
    """Rendered in memory, then written atomically: never a half-written image.  SVG text
    stays text (searchable, and the tests can read the names in it), and carries no date, so
    that the same input makes the same file.  `drawn`: matplotlib's warnings caught while the
    figure was drawn (`ssg inspect --diagram` measures its labels then, which is when a
    character missing from the font is warned of): said with the saving's, once."""
    import matplotlib

    buf, metadata = io.BytesIO(), {"Date": None} if fmt == "svg" else None
    with (
        warnings.catch_warnings(record=True) as caught,
        matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": "ssgc"}),
    ):
        warnings.simplefilter("always")
        fig.savefig(buf, format=fmt, dpi=100, metadata=metadata)
    write_output_bytes(output, buf.getvalue())
    _say_warnings([*(drawn or []), *caught])


_GLYPH = re.compile(r"Glyph (\d+) .* missing from font\(s\) (.+)\.$")


def _say_warnings(caught: list[warnings.WarningMessage]) -> None:
    """matplotlib warns in its own words and with its source lines: once per character its
    font lacks (a name in Japanese, an emoji), or that a crowded figure could not be laid out.
    The user gets one `SsgWarning` about the missing characters and at most one about the
    rest, never matplotlib's raw text."""
    missing: dict[int, None] = {}
    fonts: set[str] = set()
    other: list[str] = []
    for w in caught:
        found = _GLYPH.match(str(w.message))
        if found:
            missing[int(found.group(1))] = None
            fonts.add(found.group(2))
        else:
            other.append(one_line(str(w.message)))
    if missing:
        codes = ", ".join(f"U+{c:04X}" for c in missing)
        font = ", ".join(sorted(fonts))
        message = (
            f"{len(missing)} character(s) of the names are not in the font {font} and are "
            f"drawn as boxes: {codes}"
        )
        warnings.warn(SsgWarning(message), stacklevel=3)
    if other:
        warnings.warn(SsgWarning(_drawing_trouble(other)), stacklevel=3)


def _drawing_trouble(messages: list[str]) -> str:
    """matplotlib's other warnings, said once in ssgc's words."""
    if any("constrained_layout" in m for m in messages):
        return (
            "the picture is too crowded to lay out (too many scenes, types or too long names): "
            "its panels and legend may overlap"
        )
    return f"drawing the picture, matplotlib warned: {shown(messages[0], 200)}"
