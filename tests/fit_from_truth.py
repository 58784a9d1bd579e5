"""Fit a grammar to scenes sampled from itself, starting at the truth (docs/fitting.md 1.1).

    python tests/fit_from_truth.py GRAMMAR N SEED ITERATIONS ESTEP [ESTEP ...]

Prints the true-tree maximum-likelihood `p` of every count law and `or` rule (the M-step on
the sampled trees themselves), then, per E-step, the fitted values and the wall time.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from ruamel.yaml import YAML

from ssgc.compile import compile_text
from ssgc.fit.em import FitJournal, FitOptions, GrammarSource, fit_grammar, fit_header
from ssgc.fit.mstep import FitSettings, m_step
from ssgc.io.scene import scene_from_tree
from ssgc.sample.forward import sample_trees


def main(grammar: str, n: int, seed: int, iterations: int, esteps: list[str]) -> None:
    text = Path(grammar).read_text()
    g = compile_text(text)
    trees, logp = sample_trees(g, n, seed)
    scenes = [scene_from_tree(g, trees.tree(i), f"s{i}", float(logp[i])) for i in range(n)]
    print("true-tree MLE:")
    for u in m_step(g, trees, np.ones(n), FitSettings()):
        if "p" in u.values:
            print(f"  {'.'.join(map(str, u.path))}: {u.values['p']:.3f}")
    for estep in esteps:
        t0 = time.monotonic()
        opts = FitOptions(iterations=iterations, estep=estep, tol=0)
        d = Path(tempfile.mkdtemp())
        with FitJournal(d / "j.jsonl", fit_header(text, d, scenes, opts), resume=False) as j:
            res = fit_grammar(text, GrammarSource(grammar), scenes, opts, j)
        print(f"{estep}: {time.monotonic() - t0:.1f} s")
        for name, t in YAML(typ="safe").load(res.text)["types"].items():
            if "repeat" in t:
                print(f"  {name} count: {t['repeat']['count']}")
            if "or" in t and any("p" in r for r in t["or"]):
                print(f"  {name} or: {[round(r['p'], 3) for r in t['or']]}")
        post = res.iterations[-1].get("posterior", {})
        print("  posterior:", {k: v for k, v in post.items() if k != "spread"})


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5:])
