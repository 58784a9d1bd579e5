"""Measure certified parses of one grammar: python tests/measure_latent.py GRAMMAR N [METHOD].

Samples N scenes (seed 0), parses each, and prints the statuses, how many are certified (gap at
most 1e-6), match or beat the sampled tree, and whether any bound lies below a sampled tree.
"""

from __future__ import annotations

import collections
import sys
import time
import warnings

import numpy as np

from ssgc.compile import load_grammar
from ssgc.io.scene import scene_from_tree
from ssgc.parse.parser import Parser
from ssgc.sample.forward import sample_trees

TOL = 1e-6


def outcome(result, truth: float) -> dict[str, bool]:  # type: ignore[no-untyped-def]
    """One parse against its sampled tree: certified, match-or-beat, bound below the tree."""
    best = result.parses[0] if result.parses else None
    bound = result.extra.get("bound", np.nan)
    slack = TOL * max(1.0, abs(truth))
    return {
        "certified": best is not None and bool(np.isfinite(best.gap) and best.gap <= TOL),
        "gap_known": best is not None and bool(np.isfinite(best.gap)),
        "match_or_beat": best is not None and best.score >= truth - slack,
        "bound_below_truth": bool(np.isfinite(bound) and bound < truth - slack),
    }


def main(path: str, n: int, method: str = "auto") -> None:
    warnings.simplefilter("ignore")
    grammar = load_grammar(path)
    parser = Parser(grammar, method=method)
    trees, logp = sample_trees(grammar, n, 0)
    counts: collections.Counter[str] = collections.Counter()
    times = []
    for i in range(n):
        scene = scene_from_tree(grammar, trees.tree(i), f"s{i}", float(logp[i]))
        t0 = time.perf_counter()
        result = parser.parse(scene)
        times.append(time.perf_counter() - t0)
        counts["status " + result.status] += 1
        counts.update(k for k, v in outcome(result, float(logp[i])).items() if v)
    print(
        f"{path}: {n} scenes, {dict(counts)}, "
        f"median {np.median(times):.4f} s, max {np.max(times):.3f} s"
    )


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), *sys.argv[3:4])
