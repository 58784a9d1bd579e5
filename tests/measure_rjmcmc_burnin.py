"""Trace RJMCMC's burn-in from P(T) (docs/constraints.md, "Initialisation and burn-in").

python tests/measure_rjmcmc_burnin.py GRAMMAR CHAINS SWEEPS MOVES: CHAINS chains of
grammars/GRAMMAR started from P(T) make SWEEPS sweeps of MOVES (comma-separated, e.g.
subtree,structure,translation,walk,rotation); at some sweeps it prints the feasible share, the
mean number of observed objects of the feasible chains and its distance from the exact mean
(8,192 staged-rejection scenes) in standard errors, the largest split-R̂ (the three worst
counts) and the smallest bulk ESS over the last half of the sweeps so far, and the CPU time.
"""

import sys
import time

import numpy as np

from ssgc.compile import load_grammar
from ssgc.sample.constrained import sample_blocks
from ssgc.sample.diagnostics import ess_bulk, split_rhat
from ssgc.sample.forward import sample_chunk
from ssgc.sample.rjmcmc import Chains, CountWatch, RjSettings
from ssgc.tree import Trees

name = sys.argv[1]
n = int(sys.argv[2])
sweeps = int(sys.argv[3])
moves = tuple(sys.argv[4].split(","))
g = load_grammar(f"grammars/{name}")
cs = list(g.constraints)
ref = Trees.concatenate([b.trees for b in sample_blocks(g, cs, 8192, 1)])
obs = np.array([t.observed for t in g.types])
tot_ref = np.bincount(ref.scene[obs[ref.type]], minlength=ref.n_scenes)
print("exact mean objects", tot_ref.mean(), "+-", tot_ref.std() / np.sqrt(n))
rng = np.random.default_rng(5)
trees, _ = sample_chunk(g, rng, n)
ch = Chains(g, cs, trees, RjSettings(moves=moves))
w = CountWatch(g)
names = [t.name for t in g.types] + ["total"]
t0 = time.process_time()
for k in range(1, sweeps + 1):
    ch.sweep(rng)
    w.record(ch.trees)
    if k in (5, 10, 20, 40, 60, 80, 120, 160, 200, 300, 400, 600):
        h = np.stack(w.history[k // 2 :])
        f = ch.feasible
        tot = np.bincount(ch.trees.scene[obs[ch.trees.type]], minlength=n)[f]
        r = [split_rhat(h[:, f, j]) for j in range(h.shape[2])]
        worst = np.argsort(r)[::-1][:3]
        print(
            f"sweep {k:4d} feasible {f.mean():.3f} mean objects {tot.mean():.3f} "
            f"z={(tot.mean() - tot_ref.mean()) / (tot_ref.std() / np.sqrt(f.sum())):+.1f} "
            f"rhat max {max(r):.3f} ({', '.join(f'{names[j]} {r[j]:.3f}' for j in worst)}) "
            f"ess {min(ess_bulk(h[:, f, j]) for j in range(h.shape[2])):.0f} "
            f"cpu {time.process_time() - t0:.1f}"
        )
