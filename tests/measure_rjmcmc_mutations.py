"""Mutation check of tests/test_rjmcmc_kernel.py: does the per-move invariance test see a
move whose acceptance ratio is wrong?

python tests/measure_rjmcmc_mutations.py SWEEPS: for the subtree, structure and walk moves,
the move with its log acceptance ratio replaced by 0 (accepted whenever the constraints
hold) runs SWEEPS sweeps alone from 4,096 exact draws of the tiny grammar; prints the χ² p of
the disc counts and the KS p of each scene's mean disc distance from the axis against 8,192
other exact draws.
"""

import sys
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).parent))
import test_rjmcmc_kernel as T

from ssgc.sample.rjmcmc import Chains, RjSettings

RIGHT = Chains._accept


def without_ratio(name: str):  # type: ignore[no-untyped-def]
    def accept(self, move, new, log_ratio, rng):  # type: ignore[no-untyped-def]
        if move == name:
            log_ratio = np.where(np.isfinite(log_ratio), 0.0, -np.inf)
        return RIGHT(self, move, new, log_ratio, rng)

    return accept


def main(sweeps: int) -> None:
    g = T._tiny()
    disc = g.type_id("Disc")
    start, ref = T._exact(g, 4096, 1), T._exact(g, 8192, 2)
    for move in ("subtree", "structure", "walk"):
        Chains._accept = without_ratio(move)  # type: ignore[method-assign]
        try:
            chains = Chains(g, list(g.constraints), start, RjSettings(moves=(move,)))
            rng = np.random.default_rng(3)
            for _ in range(sweeps):
                chains.sweep(rng)
        finally:
            Chains._accept = RIGHT  # type: ignore[method-assign]
        end = chains.trees
        p_count = T._chi2(T._counts(ref, [disc]), T._counts(end, [disc]))
        p_pose = stats.ks_2samp(T._per_scene_axis(ref, [disc]), T._per_scene_axis(end, [disc]))
        print(f"{move} without its ratio: count χ² p {p_count:.3g}, KS p {p_pose.pvalue:.3g}")


if __name__ == "__main__":
    main(int(sys.argv[1]))
