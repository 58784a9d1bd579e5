"""Pictures of scenes, sampled trees and parse results (`ssg render`, docs/render.md).

Everything is read from the input file alone: a scene's objects, a sampled scene's tree, or the
best parse of each scene of an `ssg parse` result.  A grammar, when given, only adds each type's
geometry (its box, cylinder, sphere or revolve); without one, or for a mesh type, an
object is a marker.  Each scene is drawn twice, in 3-D and from above, coloured by type, with
the tree's edges between node poses; a parse's edges are coloured by the log-probability of the
rule that produced the child, so the part of the scene the grammar finds unusual stands out
(thesis Fig. 4-8).
"""

from __future__ import annotations

import io
import json
import math
import re
import sys
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import SceneError, SsgError, SsgWarning, one_line
from ssgc.geometry import quat_to_matrix
from ssgc.io.outputs import Output, write_output_bytes
from ssgc.io.outputs import check_output as check_output_path
from ssgc.io.parsed import ParseDoc, best_tree, read_parse_doc
from ssgc.io.scene import (
    Locator,
    NodeTable,
    SceneDoc,
    SceneRead,
    is_parse_result,
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
MAX_COORD = 1000.0  # meters
MAX_GRID = 64  # scenes in one picture; more would be unreadable
FORMATS = (".png", ".svg")


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
    rules: tuple[str | None, ...] | None = None  # a parse's per-node rule name (`ssg view`)


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


def check_output(path: Path, inputs: tuple[str | Path, ...] = ()) -> tuple[Output, str]:
    """The picture's output (checked before any work, as every output: docs/robustness.md) and
    its format from the file name; a device or standard output without a suffix gets PNG."""
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
    output, grammar = Path(output), None if grammar is None else as_ir(grammar)
    out, fmt = check_output(output, inputs=(source,))
    require_matplotlib()
    if not 1 <= n <= MAX_GRID:
        raise SsgError.single(f"-n must be between 1 and {MAX_GRID}, got {n}")
    if scene is None:
        views = load_views(Path(source), n, grammar)
    else:
        views = [v for v in load_views(Path(source), sys.maxsize, grammar) if v.name == scene]
        if not views:
            raise SsgError.single(f"no scene named '{scene}' in it", str(source))
        views = views[:n]
    fig = draw_views(views, geometry_of(grammar))
    save_figure(fig, out, fmt)
    return len(views)


def render_document(data: Any, output: str | Path, grammar: Grammar | None = None) -> int:
    """Draw a scene or parse-result document held in memory (the Python API's `.render`, whose
    `.to_json()` is the document `ssg render` would read from a file); returns how many scenes
    were drawn."""
    out, fmt = check_output(Path(output))
    require_matplotlib()
    views = document_views(data, grammar, Path("<memory>"))[:MAX_GRID]
    save_figure(draw_views(views, geometry_of(grammar)), out, fmt)
    return len(views)


# ------------------------------------------------------------------ reading ---


def load_views(path: Path, n: int, grammar: Grammar | None) -> list[View]:
    """A scene or parse-result JSON file, a directory of them, or (with a grammar) a sink
    dataset; the first `n` scenes."""
    if path.is_dir():
        files = sorted(path.glob("*.json"))
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
            _drawable(_scene_view(s.name, grammar, s.types, s.xyz, s.quat), path)
            for s in load_scenes(path, grammar)[:n]
        ]
    return _file_views(path, grammar)[:n]


def _file_views(path: Path, grammar: Grammar | None) -> list[View]:
    """A file read as `ssg parse` reads a scene: strict JSON, every mistake located."""
    text = read_scene_text(path, "input file")
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
        views = _parse_views(read_parse_doc(data, text, file), grammar, source, file)
        return [_drawable(v, path) for v in views]
    if isinstance(data, dict) and "objects" in data:
        doc = validated(SceneDoc, data, text, file)
        view = _doc_view(doc, read_scene_doc(doc, grammar, source), grammar, one_line(path.stem))
        return [_drawable(view, path)]
    raise SceneError.single(
        "not a scene (a JSON object with `objects`) or an `ssg parse` result (with `scenes`)",
        file,
    )


def _observed(grammar: Grammar | None, name: str, given: bool | None) -> bool:
    if grammar is not None and name in grammar.type_ids:
        return grammar.types[grammar.type_ids[name]].observed
    return True if given is None else given


def _tree_view(title: str, tree: NodeTable, grammar: Grammar | None) -> View:
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
    )


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


def _drawable(view: View, path: Path) -> View:
    """Coordinates a picture can hold: finite, within a kilometre of the origin."""
    if view.xyz.size and not np.all(np.abs(view.xyz) <= MAX_COORD):
        raise SceneError.single(
            f"'{shown(view.name)}': a position is beyond {MAX_COORD:g} m, too far to draw",
            str(path),
        )
    return view


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
    """Vertices and polygon faces of a box, a cylinder (along z), a sphere or a revolve (its
    surface about z, `ssgc.constraints.revolved`); else None."""
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
    return None


def plain(text: str) -> str:
    """A user's string as matplotlib shows it literally: no mathtext, nothing unprintable."""
    return text.encode("utf-8", "replace").decode("utf-8").replace("$", r"\$")


def _colours(views: list[View]) -> dict[str, Any]:
    from matplotlib import colormaps

    names = sorted({t for v in views for t, o in zip(v.types, v.observed, strict=True) if o})
    cmap = colormaps["tab10" if len(names) <= 10 else "tab20"]
    return {name: cmap(i % cmap.N) for i, name in enumerate(names)}


def draw_views(views: list[View], geoms: dict[str, tuple[FloatArray, list[list[int]]]]) -> Any:
    """One figure: a (3-D, top-down) pair of panels per scene, a legend, and for parses a
    colour bar of rule log-probabilities."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    cols = math.ceil(math.sqrt(len(views)))
    rows = math.ceil(len(views) / cols)
    fig = Figure(figsize=(8.0 * cols + 1.6, 3.6 * rows), layout="constrained")
    fig.get_layout_engine().set(wspace=0.1)  # room for the 3-D panel's z label
    colours = _colours(views)
    scores = [v.score[np.isfinite(v.score)] for v in views if v.score is not None]
    norm, cmap = None, colormaps["RdYlGn"]
    if scores:
        finite = np.concatenate(scores)
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (-1.0, 0.0)
        norm = Normalize(lo, hi if hi > lo else lo + 1.0)
    axes = []
    for i, view in enumerate(views):
        ax3 = fig.add_subplot(rows, 2 * cols, 2 * i + 1, projection="3d")
        ax2 = fig.add_subplot(rows, 2 * cols, 2 * i + 2)
        _draw_view(ax3, ax2, view, geoms, colours, norm, cmap)
        axes += [ax3, ax2]
    handles: list[Any] = [
        Patch(facecolor=c, alpha=0.6, label=plain(shown(t))) for t, c in colours.items()
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
    fig.legend(handles=handles, loc="outside right upper", fontsize=7, frameon=False)
    if norm is not None:
        bar = fig.colorbar(ScalarMappable(norm, cmap), ax=axes, shrink=0.8, pad=0.02)
        bar.set_label("log-probability of the rule making the child (low = unusual)", fontsize=7)
        bar.ax.tick_params(labelsize=7)
    return fig


def _draw_view(
    ax3: Any,
    ax2: Any,
    view: View,
    geoms: dict[str, Any],
    colours: dict[str, Any],
    norm: Any,
    cmap: Any,
) -> None:
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Polygon
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection
    from scipy.spatial import ConvexHull, QhullError

    points = [view.xyz]
    rot = quat_to_matrix(view.quat) if len(view.types) else np.zeros((0, 3, 3))
    for i in np.flatnonzero(view.observed):
        colour, mesh = colours[view.types[i]], geoms.get(view.types[i])
        if mesh is None:
            ax3.scatter(*view.xyz[i], color=colour, s=30, depthshade=False)
            ax2.scatter(*view.xyz[i, :2], color=colour, s=30, zorder=3)
            continue
        verts = mesh[0] @ rot[i].T + view.xyz[i]
        points.append(verts)
        polys = [verts[f] for f in mesh[1]]
        alpha = 0.15 if _holds_others(view, i, mesh[0], rot[i]) else 0.45
        ax3.add_collection3d(
            Poly3DCollection(polys, facecolor=colour, edgecolor=colour, alpha=alpha, linewidth=0.4),
            autolim=False,  # limits are set once, equal on every axis (`_limits`)
        )
        try:
            hull = verts[ConvexHull(verts[:, :2]).vertices, :2]
        except QhullError:  # a shape seen exactly edge-on from above
            hull = verts[:, :2]
        ax2.add_patch(Polygon(hull, closed=True, fc=colour, ec=colour, alpha=alpha, lw=0.8))
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
    _limits(ax3, ax2, np.vstack(points))
    ax3.set_title(plain(view.title), fontsize=8)
    ax2.set_title("from above (x, y)", fontsize=8)


def unexplained(view: View) -> NDArray[np.bool_]:
    """Objects a tree leaves to clutter: their parent is the observation model's clutter node
    (`~clutter:object`, docs/grammar.md section 9)."""
    parent_type = np.array((*view.types, ""), dtype=object)[view.parent]
    return view.observed & (view.parent >= 0) & (parent_type == "~clutter:object")


def _holds_others(view: View, i: int, local: FloatArray, rot: FloatArray) -> bool:
    """A container (a bin, a table) is drawn faintly so that what it holds shows through."""
    others = np.delete(view.xyz[view.observed], np.flatnonzero(view.observed) == i, axis=0)
    local_xy = ((others - view.xyz[i]) @ rot)[:, :2]  # within its footprint, at any height
    inside = np.all(np.abs(local_xy) <= np.abs(local[:, :2]).max(axis=0), axis=1)
    return bool(np.any(inside))


def _limits(ax3: Any, ax2: Any, pts: FloatArray) -> None:
    """Equal scales on every axis, so shapes and distances look as they are."""
    if len(pts) == 0:
        pts = np.zeros((1, 3))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2 * 1.1, 0.05)
    for k, setter in enumerate((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim)):
        setter(centre[k] - half[k], centre[k] + half[k])
    ax3.set_box_aspect(tuple(np.maximum(half, 0.35 * half.max())), zoom=0.9)  # never flat
    ax3.tick_params(labelsize=6)
    ax3.set_xlabel("x (m)", fontsize=7)
    ax3.set_ylabel("y (m)", fontsize=7)
    ax3.set_zlabel("z (m)", fontsize=7)
    ax2.set_xlim(centre[0] - half[0], centre[0] + half[0])
    ax2.set_ylim(centre[1] - half[1], centre[1] + half[1])
    ax2.set_aspect("equal")
    ax2.tick_params(labelsize=6)
    ax2.set_xlabel("x (m)", fontsize=7)
    ax2.set_ylabel("y (m)", fontsize=7)


def save_figure(fig: Any, output: Output, fmt: str) -> None:
    """Rendered in memory, then written atomically: never a half-written image.  SVG text
    stays text (searchable, and the tests can read the names in it)."""
    import matplotlib

    buf = io.BytesIO()
    with (
        warnings.catch_warnings(record=True) as caught,
        matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": "ssgc"}),
    ):
        warnings.simplefilter("always")
        fig.savefig(buf, format=fmt, dpi=100)
    write_output_bytes(output, buf.getvalue())
    _say_missing_glyphs(caught)


_GLYPH = re.compile(r"Glyph (\d+) .* missing from font\(s\) (.+)\.$")


def _say_missing_glyphs(caught: list[warnings.WarningMessage]) -> None:
    """matplotlib warns once per character its font lacks (a name in Japanese, an emoji), in
    its own words and with our source line; one `SsgWarning` says which characters the picture
    shows as boxes.  Other warnings pass on as they were."""
    missing: dict[int, None] = {}
    fonts: set[str] = set()
    for w in caught:
        found = _GLYPH.match(str(w.message))
        if found:
            missing[int(found.group(1))] = None
            fonts.add(found.group(2))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if missing:
        codes = ", ".join(f"U+{c:04X}" for c in missing)
        font = ", ".join(sorted(fonts))
        message = (
            f"{len(missing)} character(s) of the names are not in the font {font} and are "
            f"drawn as boxes: {codes}"
        )
        warnings.warn(SsgWarning(message), stacklevel=2)
