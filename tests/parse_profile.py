"""The parser on random grammars: what it says about scenes sampled from them (issue 11).

`check_scene` parses one sampled scene and lists what is false in the answer (the
properties of tests/test_parse_property.py); `run_profile` does it for many grammars and
counts statuses by law.  Run as a script for the long profile:

    python tests/parse_profile.py --grammars 1000 --scenes 10 --seed 0 [--time-limit 10]

prints one JSON object: grammars and scenes tried, false answers (must be 0), and the share
of scenes certified / feasible / no_parse / infeasible, overall and by law.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import grammar_gen as gg
from bruteforce import enumerate_parses

from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.parse.parser import Parser

SCORE_TOL = 1e-6
GAP_TOL = 1e-6
BRUTE_NODES = 12  # brute force only on trees this small


@dataclass
class Verdict:
    """What one parse of one sampled scene said, and what was false in it."""

    status: str
    certified: bool
    score: float | None
    truth: float
    false: list[str] = field(default_factory=list)
    brute: float | None = None  # the brute-force MAP score, when it could be enumerated
    result: Any = None  # the parser's answer


def certified(result: Any) -> bool:
    """A certificate: status `optimal` and a known gap within tolerance on the best parse."""
    if result.status != "optimal" or not result.parses:
        return False
    gap = result.parses[0].gap
    return bool(np.isfinite(gap) and gap <= GAP_TOL)


def check_scene(
    grammar: Grammar,
    parser: Parser,
    scene: Scene,
    time_limit: float | None = None,
    brute: float | None = None,
) -> Verdict:
    """Parse a scene sampled from `grammar` and list the false statements in the answer:
    `infeasible` (the scene has a tree: the one it was sampled from), `optimal` with a score
    below the sampled tree's, a score above the brute-force MAP, or `optimal` below it."""
    truth = float(scene.log_prob)
    result = parser.parse(scene, time_limit=time_limit)
    best = result.parses[0].score if result.parses else None
    v = Verdict(result.status, certified(result), best, truth, brute=brute, result=result)
    tol = SCORE_TOL * max(1.0, abs(truth))
    if result.status == "infeasible":
        v.false.append("infeasible")
    if result.status == "optimal" and (best is None or best < truth - tol):
        v.false.append("optimal_below_truth")
    if v.certified and best is not None and best < truth - tol:
        v.false.append("certificate_below_truth")  # a false certificate: a wrong gap
    if brute is not None and best is not None:
        if best > brute + tol:
            v.false.append("above_brute_force")
        if result.status == "optimal" and best < brute - tol:
            v.false.append("optimal_below_brute_force")
    return v


def brute_force_map(grammar: Grammar, scene: Scene) -> float | None:
    """The MAP score by enumeration, when the grammar is a dependency grammar and its trees
    for this scene are small; None otherwise."""
    try:
        parses = enumerate_parses(grammar, scene, max_nodes=BRUTE_NODES)
    except (NotImplementedError, RecursionError):
        return None
    if scene.tree is not None and len(scene.tree) > BRUTE_NODES:
        return None
    return parses[0][0] if parses else None


def micp_cause(grammar: Grammar, parser: Parser, scene: Scene, result: Any) -> str:
    """Why a scene parsed with `micp` is not certified (issue 11's breakdown): the step that
    gave up (`no_parse:PHASE`), the bound's scope (`out_of_scope`: some latent set has no
    assignments; `decoupled`: a latent set under a latent parent got its rule's supremum), or
    the size of the gap of an in-scope bound (`gap>1e-2`, ...), or `gap_unknown`."""
    from ssgc.parse.bound import certify_only, set_bounds
    from ssgc.parse.posed import candidate_poses

    if certified(result):
        return "certified"
    if result.status == "no_parse":
        return f"no_parse:{result.phase}"
    if result.status != "feasible":
        return result.status
    cand = candidate_poses(grammar, parser.supertree, scene)
    bounds = set_bounds(grammar, parser.supertree, cand)
    if bounds is None:
        return "out_of_scope"
    scope = "decoupled" if certify_only(bounds) else "coupled"
    gap = result.parses[0].gap
    if not np.isfinite(gap):
        return f"{scope}:gap_unknown"
    for edge in (1e-1, 1e-2, 1e-4):
        if gap > edge:
            return f"{scope}:gap>{edge:g}"
    return f"{scope}:gap<=1e-4"


def case(seed: int, index: int, scenes_per: int = 10) -> tuple[Grammar, list[Scene], Any]:
    """Grammar `index` of the profile run with `seed` (its compiled grammar, its sampled
    scenes and its spec), to re-run one entry of `--cases`."""
    rng = np.random.default_rng(seed)
    for _ in range(index):
        gg.random_spec(rng)
    spec = gg.random_spec(rng)
    grammar = gg.compile_spec(spec)
    return grammar, gg.sampled_scenes(grammar, scenes_per, seed + index), spec


def shape(grammar: Grammar, parser: Parser) -> str:
    """A grammar's latent shape: the depth of latent sets (a latent set under another latent
    set is depth 2) and whether such a set is placed relative to its latent parent
    (`relative`) or in the world frame."""
    from ssgc.laws.base import Frame

    st = parser.supertree
    latent = parser.latent
    depth = np.zeros(st.n_sets, np.int64)
    relative = False
    for e in np.flatnonzero(latent):  # sets are numbered parents first
        top = int(st.set_top[e])
        p_set = int(st.set_of[st.parent[top]])
        depth[e] = depth[p_set] + 1 if latent[p_set] else 1
        rule = grammar.rules[int(st.rule[top])]
        world = rule.translation.frame == Frame.WORLD and rule.rotation.frame == Frame.WORLD
        relative |= bool(latent[p_set] and not world)
    d = int(depth.max(initial=0))
    return f"depth{d}" + (":relative" if relative else "")


def category(v: Verdict) -> str:
    if v.certified:
        return "certified"
    if v.score is not None:
        return "feasible"
    return v.status


def run_profile(
    n_grammars: int,
    scenes_per: int,
    seed: int,
    methods: tuple[str, ...] = ("ip", "micp"),
    time_limit: float | None = 10.0,
    cases: list[dict[str, Any]] | None = None,
    first: int = 0,
) -> dict[str, Any]:
    """Random grammars, sampled scenes, parsed with each method: counts and false answers.
    `cases`, when given, receives one entry per uncertified parse (grammar index, scene,
    method, status, gap, and for `micp` its cause): the list to work through next.  `first`
    skips the grammars before it (the same grammars as a run from 0: two processes can share
    a profile); the CPU seconds of every parse are in `cpu_seconds_all`."""
    rng = np.random.default_rng(seed)
    counts: Counter[str] = Counter()
    by_law: dict[str, Counter[str]] = defaultdict(Counter)
    causes: Counter[str] = Counter()  # micp: why not certified (`micp_cause`)
    by_shape: dict[str, Counter[str]] = defaultdict(Counter)  # micp: by latent shape
    false: list[dict[str, Any]] = []
    times: list[float] = []
    cpu: list[float] = []  # CPU seconds per parse: wall time says little on a shared machine
    scenes_tried = 0
    grammars_all_parsed = 0
    t_start = time.perf_counter()
    for gi in range(n_grammars):
        spec = gg.random_spec(rng)
        if gi < first:
            continue
        grammar = gg.compile_spec(spec)
        scenes = gg.sampled_scenes(grammar, scenes_per, seed + gi)
        used = gg.laws(spec)
        form = shape(grammar, Parser(grammar, method="micp"))
        all_parsed = True
        for scene in scenes:
            brute = brute_force_map(grammar, scene)
            for method in methods:
                parser = Parser(grammar, method=method)
                t0, c0 = time.perf_counter(), time.process_time()
                try:
                    v = check_scene(grammar, parser, scene, time_limit, brute)
                except Exception as exc:  # a crash is a finding, not the end of the profile
                    v = Verdict("exception", False, None, float(scene.log_prob))
                    v.false.append(f"exception: {type(exc).__name__}: {exc}"[:300])
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
                scenes_tried += 1
                cat = category(v)
                counts[cat] += 1
                counts[f"{method}:{cat}"] += 1
                all_parsed &= v.score is not None
                cause = None
                if method == "micp" and v.result is not None:
                    cause = micp_cause(grammar, parser, scene, v.result)
                    causes[cause] += 1
                    by_shape[form][cause] += 1
                if cases is not None and not v.certified:
                    gap = v.result.parses[0].gap if v.result and v.result.parses else None
                    cases.append(
                        {
                            "grammar": gi,
                            "scene": scene.name,
                            "method": method,
                            "cause": cause,
                            "status": v.status,
                            "gap": gap,
                            "score": v.score,
                            "truth": v.truth,
                            "shape": form,
                        }
                    )
                for law in used:
                    by_law[law][cat] += 1
                    by_law[law]["false"] += bool(v.false)
                if v.false:
                    false.append(
                        {
                            "grammar": gi,
                            "scene": scene.name,
                            "method": method,
                            "false": v.false,
                            "status": v.status,
                            "score": v.score,
                            "truth": v.truth,
                            "brute": v.brute,
                            "yaml": gg.to_yaml(spec),
                        }
                    )
        grammars_all_parsed += all_parsed
    share = {k: v / max(scenes_tried, 1) for k, v in sorted(counts.items()) if ":" not in k}
    return {
        "grammars": n_grammars - first,
        "grammars_all_parsed": grammars_all_parsed,
        "scene_parses": scenes_tried,
        "seconds": round(time.perf_counter() - t_start, 1),
        "share": share,
        "counts": dict(sorted(counts.items())),
        "false_answers": len(false),
        "false_certificates": sum("certificate_below_truth" in f["false"] for f in false),
        "false_kinds": dict(Counter(k.split(":")[0] for f in false for k in f["false"])),
        "parse_seconds": _quantiles(times),
        "parse_cpu_seconds": _quantiles(cpu),
        "cpu_seconds_all": [round(c, 5) for c in cpu],
        "by_law": {law: _shares(c) for law, c in sorted(by_law.items())},
        "micp_causes": dict(causes.most_common()),
        "micp_by_shape": {k: dict(c.most_common()) for k, c in sorted(by_shape.items())},
        "false_examples": false[:5],
    }


def _shares(c: Counter[str]) -> dict[str, float]:
    """Each category's share of a law's scene parses ("false": the share with a false answer)."""
    n = sum(v for k, v in c.items() if k != "false")
    return {"n": n, **{k: round(v / max(n, 1), 3) for k, v in sorted(c.items())}}


def _quantiles(times: list[float]) -> dict[str, float]:
    if not times:
        return {}
    q = np.quantile(times, [0.5, 0.9, 0.99, 1.0])
    return {k: round(float(x), 4) for k, x in zip(("median", "p90", "p99", "max"), q, strict=True)}


def ip_breakdown(
    n_grammars: int, scenes_per: int, seed: int, time_limit: float | None = 10.0
) -> dict[str, Any]:
    """Why `ip` leaves scenes uncertified, one cause per scene (the grammars and scenes of
    `run_profile`): `no_parse:<phase>`, `infeasible`, `below_truth` (the tree scores below
    the sampled one: a structure or pose was missed), `time:<step>` (a time limit cut a step
    short), `no_bound` (no upper bound for the grammar's shape: gap null), `gap` (at or above
    the sampled tree, but below the bound).  `examples` holds a few of each."""
    rng = np.random.default_rng(seed)
    causes: Counter[str] = Counter()
    examples: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for gi in range(n_grammars):
        spec = gg.random_spec(rng)
        grammar = gg.compile_spec(spec)
        parser = Parser(grammar, method="ip")
        for scene in gg.sampled_scenes(grammar, scenes_per, seed + gi):
            result = parser.parse(scene, time_limit=time_limit)
            cause = _ip_cause(result, float(scene.log_prob))
            causes[cause] += 1
            if cause != "certified" and len(examples[cause]) < 3:
                examples[cause].append(
                    {"grammar": gi, "scene": scene.name, "message": result.message}
                )
    return {"causes": dict(causes.most_common()), "examples": dict(examples)}


def _ip_cause(result: Any, truth: float) -> str:
    if certified(result):
        return "certified"
    if not result.parses:
        return f"no_parse:{result.phase}" if result.status == "no_parse" else result.status
    if result.parses[0].score < truth - SCORE_TOL * max(1.0, abs(truth)):
        return "below_truth"
    if result.timed_out_in:
        return f"time:{result.timed_out_in}"
    if not np.isfinite(result.extra.get("bound", np.nan)):
        return "no_bound"
    return "gap"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--grammars", type=int, default=100)
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--time-limit", type=float, default=10.0)
    ap.add_argument("--methods", default="ip,micp")
    ap.add_argument("--ip-breakdown", action="store_true", help="why `ip` is uncertified")
    ap.add_argument("--cases", help="write every uncertified parse to this JSON file")
    ap.add_argument("--first", type=int, default=0, help="skip the grammars before this one")
    a = ap.parse_args()
    if a.ip_breakdown:
        causes = ip_breakdown(a.grammars, a.scenes, a.seed, a.time_limit or None)
        print(json.dumps(causes, indent=1))
        return
    cases: list[dict[str, Any]] | None = [] if a.cases else None
    out = run_profile(
        a.grammars,
        a.scenes,
        a.seed,
        tuple(a.methods.split(",")),
        a.time_limit or None,
        cases,
        a.first,
    )
    if a.cases:
        Path(a.cases).write_text(json.dumps(cases, indent=0))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
