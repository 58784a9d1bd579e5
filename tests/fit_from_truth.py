"""Fit a grammar to scenes sampled from itself, from the truth or a perturbed start
(docs/fitting.md 1.1: the table of what each E-step estimates).

    python tests/fit_from_truth.py GRAMMAR N SEED ITERATIONS [--perturb] [--json OUT]
        [--samples S] ESTEP [ESTEP ...]

Prints one row per fitted number (every count law's and `or` rule's `p`, every Normal mean
and variance component, every Bingham concentration): the truth, the true-tree
maximum-likelihood value (the M-step on the sampled trees themselves), the start, and the
value each E-step's fit ends at, then each fit's wall time and posterior report.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from ruamel.yaml import YAML

from ssgc.compile import compile_text
from ssgc.fit.em import FitJournal, FitOptions, GrammarSource, fit_grammar, fit_header
from ssgc.fit.mstep import FitSettings, m_step
from ssgc.fit.writeback import Update, apply_updates
from ssgc.io.scene import scene_from_tree
from ssgc.sample.forward import sample_trees

KEYS = ("p", "mean", "variance", "concentration")


def flatten(updates: list[Update]) -> dict[str, float]:
    """Every scalar of a list of updates, named by its document path."""
    out: dict[str, float] = {}
    for u in updates:
        where = ".".join(map(str, u.path))
        for key in KEYS:
            v = u.values.get(key)
            if isinstance(v, (int, float)):
                out[f"{where}.{key}"] = float(v)
            elif isinstance(v, list):
                out.update(
                    {f"{where}.{key}[{j}]": float(x) for j, x in enumerate(v) if x is not None}
                )  # None: a pinned axis, not fitted
    return out


def read_values(text: str, names: list[str]) -> dict[str, float]:
    """The values at `names` in a grammar's YAML (an `or` rule without `p`: its compiled
    weight; an isotropic variance read for every component)."""
    doc = YAML(typ="safe").load(text)
    g = compile_text(text)
    out: dict[str, float] = {}
    for name in names:
        path, _, key = name.rpartition(".")
        index = None
        if key.endswith("]"):
            key, index = key[:-1].split("[")
        node: Any = doc
        for part in path.split("."):
            node = node[int(part)] if isinstance(node, list) else node[part]
        v = node.get(key)
        if v is None and key == "p" and ".or." in name:
            t = g.types[g.type_id(path.split(".")[1])]
            v = float(t.probs[int(path.split(".")[-1])])
        if isinstance(v, list):
            v = v[int(index)]
        if v is not None:
            out[name] = float(v)
    return out


def perturbed(text: str, names: list[str]) -> str:
    """The truth moved: count p + 0.2 (at most 0.9), the first `or` weight doubled (then
    renormalised), means + 0.02, variances doubled."""
    truth = read_values(text, names)
    by_path: dict[tuple, dict[str, Any]] = {}
    for name, v in truth.items():
        path, _, key = name.rpartition(".")
        parts = tuple(int(p) if p.isdigit() else p for p in path.split("."))
        if key.startswith("mean"):
            by_path.setdefault(parts, {}).setdefault("mean", []).append(v + 0.02)
        elif key == "variance":  # isotropic
            by_path.setdefault(parts, {})["variance"] = 2 * v
        elif key.startswith("variance"):
            by_path.setdefault(parts, {}).setdefault("variance", []).append(2 * v)
        elif key == "p" and "count" in parts:
            by_path.setdefault(parts, {})["p"] = min(0.9, v + 0.2)
        elif key == "p":
            by_path.setdefault(parts, {})["p"] = v
    for parts in by_path:  # or weights: the first doubled, then renormalised
        if parts[-2] == "or" and parts[-1] == 0:
            sib = [
                by_path[(*parts[:-1], j)]
                for j in range(len(by_path))
                if (*parts[:-1], j) in by_path
            ]
            sib[0]["p"] *= 2
            total = sum(s["p"] for s in sib)
            for s in sib:
                s["p"] /= total
    updates = [Update(path, vals) for path, vals in by_path.items()]
    return apply_updates(text, updates, "<perturbed>")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("grammar")
    ap.add_argument("n", type=int)
    ap.add_argument("seed", type=int)
    ap.add_argument("iterations", type=int)
    ap.add_argument("esteps", nargs="+")
    ap.add_argument("--perturb", action="store_true")
    ap.add_argument("--samples", type=int, default=100)
    ap.add_argument("--top", type=int, default=10)
    ap.add_argument("--json")
    a = ap.parse_args()
    text = Path(a.grammar).read_text()
    g = compile_text(text)
    trees, logp = sample_trees(g, a.n, a.seed)
    scenes = [scene_from_tree(g, trees.tree(i), f"s{i}", float(logp[i])) for i in range(a.n)]
    mle = flatten(m_step(g, trees, np.ones(a.n), FitSettings()))
    names = list(mle)
    truth = read_values(text, names)
    start = perturbed(text, names) if a.perturb else text
    table: dict[str, dict[str, float]] = {
        "truth": truth,
        "mle": mle,
        "start": read_values(start, names),
    }
    info: dict[str, Any] = {}
    for estep in a.esteps:
        t0 = time.monotonic()
        opts = FitOptions(iterations=a.iterations, estep=estep, tol=0, samples=a.samples, top=a.top)
        d = Path(tempfile.mkdtemp())
        with FitJournal(d / "j.jsonl", fit_header(start, d, scenes, opts), resume=False) as j:
            res = fit_grammar(start, GrammarSource(a.grammar), scenes, opts, j)
        table[estep] = read_values(res.text, names)
        info[estep] = {
            "seconds": round(time.monotonic() - t0, 1),
            "log_evidence": [r["log_evidence"] for r in res.iterations],
            "posterior": res.iterations[-1].get("posterior"),
        }
        if a.json:  # after every fit: a long run's finished columns are kept
            Path(a.json).write_text(json.dumps({"table": table, "info": info}, indent=1))
    cols = list(table)
    print("| parameter | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for name in names:
        cells = [f"{table[c][name]:.4g}" if name in table[c] else "—" for c in cols]
        print(f"| `{name.removeprefix('types.')}` | " + " | ".join(cells) + " |")
    for estep, i in info.items():
        print(estep, {k: v for k, v in i.items() if k != "posterior"})
        if i["posterior"]:
            print("  posterior:", {k: v for k, v in i["posterior"].items() if k != "spread"})


if __name__ == "__main__":
    main()
