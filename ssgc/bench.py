"""Speed measurements behind `ssg bench`: numbers a user can compare across machines."""

from __future__ import annotations

import platform
import time
from typing import Any

import numpy as np

from ssgc.ir import Grammar
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees

SINGLE_TREE_SAMPLES = 200


def bench_sample(grammar: Grammar, n: int, seed: int, repeats: int = 3) -> dict[str, Any]:
    """Best-of-`repeats` wall time of sampling `n` scenes and of scoring them.

    Scoring is measured two ways: the whole batch at once (how `ssg` scores many trees; the
    per-tree figure is the batch time / n), and one tree per call (the latency of a single
    score, dominated by fixed per-call costs).
    """
    sample_trees(grammar, min(n, 256), seed)  # warm caches (Bingham normalisers, imports)
    sample_s = min(_timed(lambda: sample_trees(grammar, n, seed))[0] for _ in range(repeats))
    trees, logp = sample_trees(grammar, n, seed)
    score_s, scores = min(
        (_timed(lambda: score_trees(grammar, trees)) for _ in range(repeats)), key=lambda r: r[0]
    )
    k = min(SINGLE_TREE_SAMPLES, n)
    singles = [trees.tree(i) for i in range(k)]
    single_s = min(
        _timed(lambda: [score_trees(grammar, t) for t in singles])[0] for _ in range(repeats)
    )
    observed = grammar.tables.type_observed[trees.type]
    finite = np.isfinite(scores) & np.isfinite(logp)
    return {
        "grammar": grammar.name,
        "scenes": n,
        "seed": seed,
        "scenes_per_second": round(n / sample_s, 1),
        "sample_seconds": round(sample_s, 4),
        "score_seconds_per_tree": float(f"{score_s / n:.3g}"),
        "score_seconds_single_tree": float(f"{single_s / k:.3g}"),
        "nodes_per_scene": round(len(trees) / n, 2),
        "objects_per_scene": round(float(observed.sum()) / n, 2),
        "max_abs_score_minus_sample_logp": float(np.max(np.abs(scores - logp)[finite], initial=0)),
        "python": platform.python_version(),
        "machine": platform.machine(),
    }


def _timed(fn: Any) -> tuple[float, Any]:
    t0 = time.perf_counter()
    result = fn()
    return time.perf_counter() - t0, result
