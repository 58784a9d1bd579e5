"""Pictures of a fit (`ssg fit --plot DIR`, docs/fitting.md): does the fitted grammar make
scenes like the data?

Three PNG files, as the thesis shows a fit (Fig. 4-4):

- `log_evidence.png`: the log-evidence (and the mean best-tree score) per EM iteration, from the
  fit's own per-iteration reports;
- `counts.png`: per observed type, how many objects of it a scene holds: the data's histogram
  against that of scenes sampled from the fitted grammar (and from the grammar before the fit);
- `positions.png`: per observed type, the objects' positions seen from above (x, y): the data
  against the samples.

Only what the fit already computed is read (its reports, the dataset, the grammars); the
samples are drawn here with the fit's seed, so the pictures are reproducible.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.io.outputs import Output, check_output
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.render.scene import plain, require_matplotlib, save_figure
from ssgc.sample.forward import sample_trees

FILES = ("log_evidence.png", "counts.png", "positions.png")
MIN_SAMPLES = 200  # scenes sampled from each grammar (at least as many as the data has)
MIN_WIDTH = 6.4  # inches: room for the titles and the legend above a single panel
DATA_COLOUR, FITTED_COLOUR, INITIAL_COLOUR = "0.15", "tab:orange", "tab:blue"


@dataclass(frozen=True)
class Population:
    """Objects of many scenes at once: each object's scene, type id and position."""

    label: str
    n_scenes: int
    scene: NDArray[np.int64]
    type: NDArray[np.int64]
    xyz: NDArray[np.float64]


def check_plot_outputs(
    directory: str | Path, inputs: Sequence[str | Path], others: Sequence[Output | None] = ()
) -> list[Output]:
    """The three pictures' outputs, checked before the fit starts (the directory must exist,
    as for every output file)."""
    checked: list[Output] = [o for o in others if o is not None]
    outs = []
    for name in FILES:
        out = check_output(Path(directory) / name, "plot", inputs=inputs, others=checked)
        checked.append(out)
        outs.append(out)
    return outs


def plot_fit(
    outputs: Sequence[Output],
    iterations: list[dict[str, Any]],
    data: list[Scene],
    fitted: Grammar,
    initial: Grammar | None = None,
    seed: int = 0,
) -> None:
    """Draw the three pictures of a fit into `outputs` (from `check_plot_outputs`)."""
    require_matplotlib()
    n = max(MIN_SAMPLES, len(data))
    pops = [data_population(data)]
    if initial is not None:
        pops.append(sample_population(initial, n, seed, "samples, before the fit"))
    pops.append(sample_population(fitted, n, seed, "samples, fitted grammar"))
    # The root is left out, as by --mmd: its pose is the same in every scene.
    observed = [t.id for t in fitted.types if t.observed and t.id != fitted.root]
    types = [t for t in observed if any(np.any(p.type == t) for p in pops)]
    names = [fitted.types[t].name for t in types]
    save_figure(evidence_figure(iterations), outputs[0], "png")
    save_figure(counts_figure(pops, types, names), outputs[1], "png")
    save_figure(positions_figure(pops, types, names), outputs[2], "png")


def data_population(scenes: list[Scene]) -> Population:
    sizes = [len(s.types) for s in scenes]
    return Population(
        "data",
        len(scenes),
        np.repeat(np.arange(len(scenes)), sizes),
        np.concatenate([s.types for s in scenes] + [np.zeros(0, np.int64)]).astype(np.int64),
        np.concatenate([s.xyz for s in scenes] + [np.zeros((0, 3))]),
    )


def sample_population(grammar: Grammar, n: int, seed: int, label: str) -> Population:
    trees, _ = sample_trees(grammar, n, seed)
    observed = np.array([t.observed for t in grammar.types], bool)[trees.type]
    return Population(label, n, trees.scene[observed], trees.type[observed], trees.xyz[observed])


def _colour(p: Population) -> str:
    if p.label == "data":
        return DATA_COLOUR
    return INITIAL_COLOUR if "before" in p.label else FITTED_COLOUR


def evidence_figure(iterations: list[dict[str, Any]]) -> Any:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.0, 3.6), layout="constrained")
    ax = fig.add_subplot()
    k = [r["iteration"] for r in iterations]
    # The report's log-evidence is a sum over the scenes; per scene it compares with --tol
    # and with the best tree's mean score.
    per_scene = [r["log_evidence"] / max(r.get("scenes", 1), 1) for r in iterations]
    ax.plot(k, per_scene, "o-", label="log-evidence per scene (top trees)")
    if all("mean_best_score" in r for r in iterations):
        best = [r["mean_best_score"] for r in iterations]
        ax.plot(k, best, "s--", ms=4, label="mean score of the best tree (with its Σ log c!)")
    ax.set_xlabel("EM iteration")
    ax.set_ylabel("nats per scene")
    ax.set_xticks(k if len(k) <= 20 else k[:: math.ceil(len(k) / 20)])
    ax.set_title("Fit progress", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return fig


def _grid(n: int, width: float, height: float) -> tuple[Any, list[Any]]:
    from matplotlib.figure import Figure

    cols = min(4, max(n, 1))
    rows = math.ceil(max(n, 1) / cols)
    # One panel (gmm's single type) was 3.2 in wide: the title and the legend were cut off.
    fig = Figure(figsize=(max(width * cols, MIN_WIDTH), height * rows + 0.6), layout="constrained")
    axes = [fig.add_subplot(rows, cols, i + 1) for i in range(n)]
    return fig, axes


def counts_figure(pops: list[Population], types: list[int], names: list[str]) -> Any:
    """Per type (and all types together): the fraction of scenes holding k of its objects."""
    fig, axes = _grid(len(types) + 1, 3.2, 2.4)
    width = 0.8 / len(pops)
    for ax, t, name in zip(axes, [None, *types], ["all objects", *names], strict=True):
        counts = [
            np.bincount(
                p.scene[np.isin(p.type, types) if t is None else p.type == t], minlength=p.n_scenes
            )
            for p in pops
        ]
        top = max(int(c.max(initial=0)) for c in counts)
        for j, (p, c) in enumerate(zip(pops, counts, strict=True)):
            share = np.bincount(c, minlength=top + 1) / max(p.n_scenes, 1)
            x = np.arange(top + 1) + (j - (len(pops) - 1) / 2) * width
            ax.bar(x, share, width, color=_colour(p), label=p.label)
        ax.set_title(plain(name), fontsize=8)
        ax.set_xlabel("objects in a scene", fontsize=7)
        ax.set_ylabel("share of scenes", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.xaxis.get_major_locator().set_params(integer=True)
        if top == 0:  # no object of it in any scene: one bar at 0, not ticks at -0.4 .. 0.4
            ax.set_xticks([0])
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside upper center", ncols=3, fontsize=8)
    return fig


def positions_figure(pops: list[Population], types: list[int], names: list[str]) -> Any:
    """Per type: its objects' positions from above, the data over the samples."""
    fig, axes = _grid(max(len(types), 1), 3.2, 3.0)
    order = [p for p in pops if p.label != "data"] + [p for p in pops if p.label == "data"]
    for ax, t, name in zip(axes, types, names, strict=False):
        for p in order:
            xy = p.xyz[p.type == t, :2]
            data = p.label == "data"
            ax.scatter(
                xy[:, 0],
                xy[:, 1],
                s=9 if data else 5,
                color=_colour(p),
                alpha=0.9 if data else 0.35,
                marker="x" if data else "o",
                linewidths=0.8 if data else 0,
                label=f"{p.label} ({len(xy)})",
            )
        ax.set_title(plain(name), fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=6)
        ax.set_xlabel("x (m)", fontsize=7)
        ax.set_ylabel("y (m)", fontsize=7)
        ax.legend(fontsize=5, loc="best", markerscale=1.5)
    if not types:  # only the root is observed, and its pose is the same in every scene
        axes[0].text(0.5, 0.5, "no observed type besides the root", ha="center", fontsize=8)
        axes[0].set_axis_off()
    fig.suptitle("Object positions seen from above: data (×) and sampled scenes", fontsize=9)
    return fig
