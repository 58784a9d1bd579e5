"""`ssg view`: one self-contained HTML page showing scenes, sampled trees and parses in 3-D.

The page is a single file with no outside requests: the scenes as JSON, and a small canvas
renderer written for this project (`viewer.js`, `viewer.css` beside this module, read from the
installed package).  Why a page of our own and not a viewer library: docs/dependencies.md.

Everything the page shows is computed here, in Python: each type's shape as triangles (from the
grammar's geometry, `ssgc.assets.load_shapes`; a small cube marks a type without one), each
node's pose, its path from the root and, for a parse, each node's rule and the log-probability
of that rule (`rules[i].log_prob`), and the colour of each tree edge.  The JavaScript only
projects, sorts and fills triangles, and answers clicks.
"""

from __future__ import annotations

import json
import math
import warnings
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ssgc.errors import SsgError, SsgWarning
from ssgc.geometry import quat_to_matrix
from ssgc.io.outputs import Output, check_output, write_output_text
from ssgc.ir import Grammar, HoldsGrammar
from ssgc.render.scene import View, grammar_colours, grammar_ir, holders, load_views, spread

MAX_SCENES = 1000  # one page; more would make a page too heavy to open
MAX_FACES = 4000  # a mesh with more triangles is shown as its convex hull
MARKER = 0.03  # m: the side of the cube marking an object without geometry
LATENT = "#555555"
# A rule's log-probability as a colour: red (low, unusual), yellow, green (high).
SCORE_STOPS = np.array([[215, 48, 39], [254, 224, 139], [26, 152, 80]], float)
LOW_SHARE = 0.25  # a rule in the lowest quarter of the page's range is marked in the panel


def view_page(source: str | Path, grammar: Grammar | HoldsGrammar | None = None) -> tuple[str, int]:
    """The viewer page of `source` (a scene, a directory of scenes, a sink dataset with its
    grammar, or an `ssg parse` result) and the number of scenes on it."""
    grammar = grammar_ir(grammar)
    views = load_views(Path(source), MAX_SCENES + 1, grammar)
    if len(views) > MAX_SCENES:  # one more was read only to know that there are more
        views = views[:MAX_SCENES]
        message = f"the page shows the first {MAX_SCENES} scenes; a page holds no more"
        warnings.warn(SsgWarning(message), stacklevel=2)
    data = page_data(views, grammar, str(source))
    return page_html(data), len(views)


def write_view(
    source: str | Path, output: str | Path, grammar: Grammar | HoldsGrammar | None = None
) -> int:
    """Write the viewer page of `source` to `output` (checked first, written atomically);
    returns the number of scenes on it."""
    grammar = grammar_ir(grammar)
    out = check_page(output, source, None if grammar is None else grammar.file)
    html, count = view_page(source, grammar)
    write_output_text(out, html)
    return count


PAGE_SUFFIXES = (".html", ".htm")


def check_page(output: str | Path, source: str | Path, grammar_file: str | Path | None) -> Output:
    """The page's output, checked before any work: never an input (the grammar either: a page
    once replaced it), and an .html file, so that a page never lands as a `.json` among
    scenes or over a YAML file."""
    inputs = (source,) if grammar_file is None else (source, grammar_file)
    dest = check_output(output, "page", inputs=inputs)
    if not dest.stream and Path(output).suffix.lower() not in PAGE_SUFFIXES:
        raise SsgError.single(
            f"the page must end in .html or .htm, got '{Path(output).name}'", str(output)
        )
    return dest


# ------------------------------------------------------------------ the data ---


def page_data(views: list[View], grammar: Grammar | None, title: str) -> dict[str, Any]:
    """What the page draws, as plain JSON: types (colour, shape), scenes (nodes, objects).
    Colours are `ssg render`'s (`grammar_colours`): with the grammar, one per type whatever
    the page holds."""
    names = sorted({t for v in views for t in v.types})
    seen = {t for v in views for t, o in zip(v.types, v.observed, strict=True) if o}
    colour = grammar_colours(sorted(seen), grammar)
    shapes = _shapes(grammar, sorted(seen))
    scores = [v.score[np.isfinite(v.score)] for v in views if v.score is not None]
    finite = np.concatenate(scores) if scores else np.zeros(0)
    bounds = (float(finite.min()), float(finite.max())) if finite.size else None
    types = [
        {
            "name": name,
            "observed": name in seen,  # an object somewhere on the page: in the legend
            "colour": colour.get(name, LATENT),
            "shape": shapes.get(name) or _marker(),
            "geometry": name in shapes,
        }
        for name in names
    ]
    index = {name: i for i, name in enumerate(names)}
    return {
        "title": title,
        "types": types,
        "scores": None if bounds is None else _score_scale(*bounds),
        "scenes": [_scene(v, index, shapes, bounds) for v in views],
    }


def _scene(
    view: View, index: dict[str, int], shapes: dict[str, Any], bounds: tuple[float, float] | None
) -> dict[str, Any]:
    """One scene: its nodes (pose, parent, path, rule and score) and which of them are objects."""
    n = len(view.types)
    rot = quat_to_matrix(view.quat) if n else np.zeros((0, 3, 3))
    objects = np.flatnonzero(view.observed)
    local = {
        int(i): np.array(shapes[view.types[i]]["vertices"])
        for i in objects
        if view.types[i] in shapes
    }
    faint = [bool(f) for f in holders(view, local)[objects]]
    score = view.score if view.score is not None else np.full(n, np.nan)
    edge = _score_colours(score, bounds)
    return {
        "name": view.name,
        "title": view.title,
        "grid": grid(_radius(view, rot, local)),
        "tree": bool(np.any(view.parent >= 0)),
        "nodes": [
            {
                "type": index[view.types[i]],
                "xyz": [round(float(x), 6) for x in view.xyz[i]],
                "rot": [round(float(x), 6) for x in rot[i].ravel()],
                "observed": bool(view.observed[i]),
                "parent": int(view.parent[i]),
                "rule": None if view.rules is None else view.rules[i],
                "log_prob": _number(score[i]),
                "edge": edge[i],
            }
            for i in range(n)
        ],
        "objects": [int(i) for i in objects],
        "faint": faint,
    }


def _radius(view: View, rot: np.ndarray, local: dict[int, np.ndarray]) -> float:
    """Half the diagonal of the box holding the scene's nodes and shapes (at least 5 cm), as
    the page computes it to frame the scene; a shapeless object is the page's marker cube."""
    marker = np.array(_marker()["vertices"])
    points = [view.xyz] + [
        local.get(int(i), marker) @ rot[i].T + view.xyz[i] for i in np.flatnonzero(view.observed)
    ]
    cloud = np.vstack(points) if len(view.types) else np.zeros((1, 3))
    return max(0.5 * float(np.linalg.norm(np.ptp(cloud, axis=0))), 0.05)


def grid(radius: float) -> dict[str, Any]:
    """The floor grid's step for a scene of this radius: the largest 1, 2 or 5 times a power
    of ten that puts at least 10 lines across the grid (which spans 1.3 radii each side), so
    10 cm for a scene of a metre, 100 m for one of a kilometre: never a solid grey plane."""
    raw = 2.6 * radius / 10
    power = 10.0 ** math.floor(math.log10(raw))
    step = power * max(m for m in (1, 2, 5) if m * power <= raw * (1 + 1e-9))
    step = float(f"{step:.3g}")
    return {"step": step, "label": _length(step)}


def _length(metres: float) -> str:
    """A grid step as the page's hint shows it: `10 cm`, `100 m`, `5 mm`, `200 km` (not
    `200000 m`, whose zeros the reader has to count)."""
    if metres >= 1000:
        return f"{metres / 1000:g} km"
    if metres >= 1:
        return f"{metres:g} m"
    return f"{metres * 100:g} cm" if metres >= 0.01 else f"{metres * 1000:g} mm"


def _number(x: float) -> float | str | None:
    """JSON has no infinities: −∞ (a rule that could not have made the child) is a string
    the page reads back with Number(); NaN (no score) is null."""
    if math.isnan(x):
        return None
    return float(x) if math.isfinite(x) else ("-Infinity" if x < 0 else "Infinity")


def _score_scale(lo: float, hi: float) -> dict[str, Any]:
    """The page's score range and the score at or below which the panel marks a rule low
    (None: only −∞, as when every finite rule has one log-probability, `spread`)."""
    mark = lo + LOW_SHARE * (hi - lo) if spread(lo, hi) else None
    return {"low": lo, "high": hi, "mark": mark}


def _score_colours(score: np.ndarray, bounds: tuple[float, float] | None) -> list[str | None]:
    """Each node's edge colour: by its rule's log-probability across the page's range (−∞ in
    the lowest colour), or None where no score is known (then the page draws a grey edge).
    A range of one value (`spread`) is drawn in the top colour: no rule is unusual."""
    if bounds is None:
        return [None] * len(score)
    lo, hi = bounds
    known = np.where(np.isfinite(score), score, lo)  # −∞ (and NaN, dropped below): lowest
    if spread(lo, hi):
        t = np.clip((known - lo) / (hi - lo), 0, 1)
    else:
        t = np.isfinite(score).astype(float)
    seg = np.minimum((t * 2).astype(int), 1)
    frac = (t * 2 - seg)[:, None]
    rgb = SCORE_STOPS[seg] * (1 - frac) + SCORE_STOPS[seg + 1] * frac
    hexes = ["#{:02x}{:02x}{:02x}".format(*c) for c in np.rint(rgb).astype(int)]
    return [None if math.isnan(s) else h for s, h in zip(score, hexes, strict=True)]


def _shapes(grammar: Grammar | None, names: list[str]) -> dict[str, dict[str, Any]]:
    """Each drawn type's geometry as triangles in its own frame (from the grammar)."""
    if grammar is None:
        return {}
    from ssgc.assets import load_shapes

    wanted = {grammar.type_ids[n] for n in names if n in grammar.type_ids}
    out = {}
    for tid, shape in load_shapes(grammar, collision=False).items():
        if tid in wanted:
            out[grammar.types[tid].name] = _triangles(shape.mesh)
    return out


def _triangles(mesh: Any) -> dict[str, Any]:
    if len(mesh.faces) > MAX_FACES:
        mesh = mesh.convex_hull
    return {
        "vertices": np.round(np.asarray(mesh.vertices, float), 5).tolist(),
        "faces": np.asarray(mesh.faces, int).tolist(),
        # A closed surface wound outwards: the page skips the triangles facing away.
        "closed": bool(mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0),
    }


def _marker() -> dict[str, Any]:
    """A small cube, so that an object without geometry is still seen and clicked."""
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    faces = [[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads]
    return {"vertices": (signs * MARKER / 2).tolist(), "faces": faces, "closed": False}


# ------------------------------------------------------------------ the page ---


def _asset(name: str) -> str:
    return resources.files("ssgc.view").joinpath(name).read_text(encoding="utf-8")


def page_html(data: dict[str, Any]) -> str:
    """The page: the data as JSON in a script block (every '<' escaped, so no name in it can
    close the block), the stylesheet and the renderer inline.  User text reaches the page only
    through `textContent`, never as HTML."""
    payload = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
    title = _escape(f"ssg view: {data['title']}")
    if len(payload) > 200_000_000:
        raise SsgError.single("too much to show on one page: give fewer scenes")
    return (
        "<!DOCTYPE html>\n<html lang='en'>\n<head>\n<meta charset='utf-8'>\n"
        f"<title>{title}</title>\n<style>\n{_asset('viewer.css')}</style>\n</head>\n"
        f"<body>\n{_asset('viewer.html')}"
        f"<script type='application/json' id='ssg-data'>{payload}</script>\n"
        f"<script>\n{_asset('viewer.js')}</script>\n</body>\n</html>\n"
    )


def _escape(text: str) -> str:
    return (
        text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace("'", "&#39;")
    )
