"""Speed measurements behind `ssg bench`: numbers a user can compare across machines."""

from __future__ import annotations

import os
import platform
import resource
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


def bench_parse(
    grammar: Grammar,
    n: int,
    seed: int,
    top: int = 1,
    time_limit: float | None = None,
    method: str = "auto",
) -> dict[str, Any]:
    """Sample n scenes, parse each, and compare the best parse with the sampled tree."""
    from ssgc.io.scene import scene_from_tree
    from ssgc.parse.parser import Parser

    parser = Parser(grammar, method=method)
    trees, logp = sample_trees(grammar, n, seed)
    rows = []
    for i in range(n):
        scene = scene_from_tree(grammar, trees.tree(i), f"{grammar.name}_{i:06d}", float(logp[i]))
        result = parser.parse(scene, top=top, time_limit=time_limit)
        best = result.parses[0].score if result.parses else float("-inf")
        raw = float(result.extra.get("raw_score", best))
        rows.append(
            {
                "scene": scene.name,
                "objects": len(scene),
                "status": result.status,
                "phase": result.phase or None,
                "timed_out_in": result.timed_out_in or None,
                "certified": result.status == "optimal",
                **result.model,
                **{k: round(v, 6) for k, v in result.timing.items()},
                "parses": len(result.parses),
                "ground_truth_score": float(logp[i]),
                "parse_score": best,
                "match_or_beat": bool(best >= logp[i] - 1e-6),
                "raw_parse_score": raw,
                "raw_match_or_beat": bool(raw >= logp[i] - 1e-6),
                "gap": _finite_or_none(result.parses[0].gap if result.parses else None),
                "bound": _finite_or_none(result.extra.get("bound")),
            }
        )
    total = np.array([r["total_s"] for r in rows])
    build = np.array([r["build_s"] for r in rows])
    size = np.array([r["nonzeros"] for r in rows], float)
    return {
        "grammar": grammar.name,
        "scenes": n,
        "seed": seed,
        "top": top,
        "method": method,
        "rows": rows,
        "summary": {
            "match_or_beat_rate": float(np.mean([r["match_or_beat"] for r in rows])),
            # statuses (docs/parsing.md): certified = optimal, the others have no proof
            "certified_rate": _rate(rows, "optimal"),
            "feasible_rate": _rate(rows, "feasible"),
            "no_parse_rate": _rate(rows, "no_parse"),
            "infeasible_rate": _rate(rows, "infeasible"),
            "error_rate": _rate(rows, "error"),
            # a certificate below the sampled tree's score would be a false proof: must be 0
            "false_certificates": sum(r["certified"] and not r["match_or_beat"] for r in rows),
            "raw_match_or_beat_rate": float(np.mean([r["raw_match_or_beat"] for r in rows])),
            "max_gap": max((r["gap"] for r in rows if r["gap"] is not None), default=None),
            "gap_known_rate": float(np.mean([r["gap"] is not None for r in rows])),
            "median_total_s": float(np.median(total)),
            "max_total_s": float(np.max(total)),
            "build_linearity": _linearity(size, build),
        },
    }


def _rate(rows: list[dict[str, Any]], status: str) -> float:
    return float(np.mean([r["status"] == status for r in rows]))


def _finite_or_none(x: float | None) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def _linearity(size: np.ndarray, seconds: np.ndarray) -> dict[str, float]:
    """Build time against model size: seconds per 1k nonzeros, and how well a line fits."""
    if len(size) < 3 or np.ptp(size) == 0:
        return {}
    slope, intercept = np.polyfit(size, seconds, 1)
    r = float(np.corrcoef(size, seconds)[0, 1])
    return {
        "seconds_per_1k_nonzeros": float(slope * 1e3),
        "intercept_s": float(intercept),
        "pearson_r": r,
        "smallest_nonzeros": float(size.min()),
        "largest_nonzeros": float(size.max()),
    }


DEFAULT_CAP = {"rjmcmc": 256, "hmc": 32, "project": 32}  # scenes, when no method is named


def bench_constrained(
    grammar: Grammar, names: str, n: int, seed: int, methods: list[str] | None = None, jobs: int = 1
) -> dict[str, Any]:
    """Valid scenes per second under constraints, and where the candidates were rejected.

    `n` valid scenes are drawn (after a warm-up of one small run) by `jobs` processes; the
    acceptance rate of a constraint is the share of the candidates it judged that it let
    through.  Wall-clock rates depend on what else the machine runs: the CPU time of this
    process and its workers, and the load average, are reported next to them.
    """
    from ssgc.sample.constrained import EXACT, METHODS, Tally, choose_method, sample_blocks, select

    chosen = select(grammar, names)
    list(sample_blocks(grammar, chosen, 8, seed + 1))  # warm caches
    rows = {}
    for method in methods or list(METHODS):
        method = choose_method(method, chosen)  # an unknown name is a message
        # without --method every method runs: the slow ones on fewer scenes
        m = n if methods else min(n, DEFAULT_CAP.get(method, n))
        tally = Tally()
        cpu0 = _cpu_seconds()
        t0 = time.perf_counter()
        chain: dict[str, list[float]] = {}
        for block in sample_blocks(grammar, chosen, m, seed, method, tally=tally, jobs=jobs):
            for k, v in block.chain.items():  # MCMC: per-scene chain statistics
                chain.setdefault(k, []).extend(v.tolist())
        seconds = time.perf_counter() - t0
        cpu = _cpu_seconds() - cpu0
        rows[method] = {
            "scenes": m,
            "valid_scenes_per_second": round(m / seconds, 1),
            "valid_scenes_per_cpu_second": round(m / cpu, 1) if cpu > 0 else None,
            "seconds": round(seconds, 3),
            "cpu_seconds": round(cpu, 3),
            # CPU seconds per wall-clock second: near `jobs` when every worker had a core
            "cores_busy": round(cpu / seconds, 2) if seconds > 0 else None,
            "candidates": tally.drawn,
            "candidates_per_second": round(tally.drawn / seconds, 1),
            "acceptance_rate": tally.passed / tally.drawn if tally.drawn else None,
            "exact": EXACT[method],
            "chain_means": {k: float(np.mean(v)) for k, v in chain.items()},
            "constraints": {
                k: {
                    "judged": tally.evaluated[k],
                    "rejected": tally.rejected[k],
                    "acceptance_rate": (
                        1 - tally.rejected[k] / tally.evaluated[k] if tally.evaluated[k] else None
                    ),
                }
                for k in tally.evaluated
            },
        }
    return {
        "grammar": grammar.name,
        "constraints": [c.name for c in chosen],
        "scenes": n,
        "seed": seed,
        "jobs": jobs,
        "methods": rows,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "machine": platform.machine(),
    }


def bench_fit(
    grammar_path: str,
    dataset: str,
    iterations: int = 2,
    top: int = 1,
    jobs: int = 1,
    max_concentration: float = 1e4,
    allow_outside: bool = False,
) -> dict[str, Any]:
    """Seconds per EM iteration of `ssgc.fit` on a dataset, split into the E-step (parsing
    every scene) and the M-step (every law's maximum-likelihood update, the write-back and
    the recompile), with the fit's CPU time and the machine's load next to them."""
    from ssgc.api import fit, load_grammar

    grammar = load_grammar(grammar_path, allow_outside)
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    result = fit(
        grammar,
        dataset,
        iterations=iterations,
        top=top,
        jobs=jobs,
        tol=0.0,
        max_concentration=max_concentration,
    )
    seconds = time.perf_counter() - t0
    rows = [
        {
            "iteration": r["iteration"],
            "log_evidence": r["log_evidence"],
            "seconds": round(r["seconds"], 3),
            "estep_seconds": round(r["seconds"] - r["mstep_seconds"], 3),
            "mstep_seconds": round(r["mstep_seconds"], 3),
        }
        for r in result.iterations
    ]
    return {
        "grammar": grammar.ir.name,
        "dataset": dataset,
        "scenes": result.iterations[0]["scenes"] if result.iterations else 0,
        "top": top,
        "jobs": jobs,
        "iterations": rows,
        "summary": {
            "seconds": round(seconds, 3),
            "cpu_seconds": round(_cpu_seconds() - cpu0, 3),
            "mean_estep_seconds": round(float(np.mean([r["estep_seconds"] for r in rows])), 3),
            "mean_mstep_seconds": round(float(np.mean([r["mstep_seconds"] for r in rows])), 3),
        },
        "load_average_1min": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "machine": platform.machine(),
    }


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished (waited-for) worker processes."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime
