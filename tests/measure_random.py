"""Measure parses over random small grammars (tests/latent_grammars.py).

python tests/measure_random.py FIRST LAST SCENES [METHOD]: grammars FIRST..LAST-1, SCENES sampled
scenes each (seeded by the grammar's number), each parsed under a 20 s limit; prints the counts
of statuses, certified, match-or-beat, gap known, bounds below a sampled tree (VIOLATION lines),
grammars whose every scene matched or beat its tree, and the parse time distribution.
"""

from __future__ import annotations

import collections
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from latent_grammars import random_grammar
from measure_latent import outcome

from ssgc.compile import compile_text
from ssgc.io.scene import scene_from_tree
from ssgc.parse.parser import Parser
from ssgc.sample.forward import sample_trees


def main(first: int, last: int, per: int, method: str = "auto") -> None:
    warnings.simplefilter("ignore")
    counts: collections.Counter[str] = collections.Counter()
    times, whole = [], 0
    for seed in range(first, last):
        grammar = compile_text(random_grammar(seed), f"random_{seed}.yaml")
        parser = Parser(grammar, method=method)
        trees, logp = sample_trees(grammar, per, seed)
        all_ok = True
        for i in range(per):
            scene = scene_from_tree(grammar, trees.tree(i), f"s{i}", float(logp[i]))
            if not len(scene):
                continue
            t0 = time.perf_counter()
            result = parser.parse(scene, time_limit=20)
            times.append(time.perf_counter() - t0)
            counts["scenes"] += 1
            counts["status " + result.status] += 1
            got = outcome(result, float(logp[i]))
            counts.update(k for k, v in got.items() if v)
            all_ok &= got["match_or_beat"]
            if got["bound_below_truth"] or (got["certified"] and not got["match_or_beat"]):
                print("VIOLATION", seed, i, result.extra.get("bound"), float(logp[i]))
        whole += all_ok
    q = np.percentile(times, [50, 90, 99])
    print(
        f"{last - first} grammars, {dict(counts)}, every scene matched in {whole}; "
        f"parse time median {q[0]:.3f} s, p90 {q[1]:.3f} s, p99 {q[2]:.3f} s, "
        f"max {np.max(times):.2f} s"
    )


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), *sys.argv[4:5])
