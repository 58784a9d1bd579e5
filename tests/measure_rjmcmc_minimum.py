"""Residual burn-in bias of RJMCMC against the minimum number of sweeps (docs/constraints.md,
"Why at least 100 sweeps").

python tests/measure_rjmcmc_minimum.py MIN [MIN ...]: on bin_packing.yaml, for seeds 2, 3, 4
and each MIN, 4,096 chains from P(T) under the burn-in rule with `min_sweeps=MIN`; prints the
sweeps made, the mean number of discs and its distance from the exact mean (16,384 staged
rejection scenes) in standard errors, and the χ² p of the histogram.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import test_rjmcmc_kernel as T

from ssgc.sample.rjmcmc import RjSettings, rjmcmc_batch


def main(minimums: list[int]) -> None:
    g = T._bundled("bin_packing.yaml")
    disc = g.type_id("Disc")
    exact = T._counts(T._exact(g, 16384, 1), [disc])
    print(f"exact mean {exact.mean():.3f}, sd {exact.std():.3f}")
    for seed in (2, 3, 4):
        for least in minimums:
            settings = RjSettings(start_candidates=0, min_sweeps=least)
            rng = np.random.default_rng(seed)
            out = rjmcmc_batch(g, list(g.constraints), 4096, rng, settings=settings)
            c = T._counts(out.trees, [disc])
            z = (c.mean() - exact.mean()) / (exact.std() / np.sqrt(len(c)))
            print(
                f"seed {seed} min {least}: {out.chain['sweeps'][0]:.0f} sweeps, {len(c)} "
                f"scenes, mean {c.mean():.3f}, z {z:+.1f}, χ² p {T._chi2(exact, c):.3g}"
            )


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]])
