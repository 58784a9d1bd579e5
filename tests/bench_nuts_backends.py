"""Measure NUTS backends on one fixed-structure target (not a test; run by hand).

    python tests/bench_nuts_backends.py [N_DISCS] [CHAINS]

The target is the bin example's poses for a fixed number of discs, with the thesis's penalty
(ε = 1e-3) on `in_bin` and `no_overlap`: ssgc's numpy NUTS (`ssgc.sample.nuts`, all chains in
lockstep over the grammar's own constraint code) against BlackJAX's NUTS with window
adaptation, vmapped over chains, on the same log-density written in jax.numpy.  Prints
compile time (JAX), wall-clock time, and effective samples per second of the first disc's x.
Needs `pip install jax jaxlib blackjax` (not a dependency of ssgc; docs/dependencies.md).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ssgc.compile import load_grammar
from ssgc.sample.forward import sample_chunk
from ssgc.sample.hmc import FixedTrees
from ssgc.sample.nuts import DualAveraging, Nuts

EPS, WARMUP, DRAWS = 1e-3, 200, 200
R, HALF, LO, HI = 0.05, 0.15, -0.1, 0.1


def ess(x: np.ndarray) -> float:
    """Effective sample size of one chain (Geyer's initial positive sequence)."""
    x = x - x.mean()
    n = len(x)
    if not np.any(x):
        return 0.0
    acf = np.correlate(x, x, "full")[n - 1 :] / (np.arange(n, 0, -1) * x.var())
    s = 0.0
    for k in range(1, n - 1, 2):
        pair = acf[k] + acf[k + 1]
        if pair < 0:
            break
        s += pair
    return n / (1 + 2 * s) if 1 + 2 * s > 0 else float(n)


def trees_with(n_discs: int, chains: int):  # type: ignore[no-untyped-def]
    g = load_grammar(Path(__file__).resolve().parents[1] / "grammars" / "bin_packing.yaml")
    t, _ = sample_chunk(g, np.random.default_rng(0), 4096)
    counts = np.bincount(t.scene, minlength=t.n_scenes) - 1
    keep = counts == n_discs
    keep &= np.cumsum(keep) <= chains
    return g, t.select(keep)


def numpy_nuts(n_discs: int, chains: int) -> None:
    g, trees = trees_with(n_discs, chains)
    target = FixedTrees(g, trees, list(g.constraints), EPS, rotations=False)
    nuts = Nuts(target, trees.scene, target.coords.free, chains, np.random.default_rng(1))
    z = target.z0
    lp, grad = target(z)
    adapt = DualAveraging(np.full(chains, 0.1))
    t0 = time.perf_counter()
    for _ in range(WARMUP):
        z, lp, grad, st = nuts.step(z, lp, grad, adapt.step)
        adapt.update(st["accept"])
    t1 = time.perf_counter()
    first = np.flatnonzero(trees.parent >= 0)[
        np.r_[True, np.diff(trees.scene[trees.parent >= 0]) > 0]
    ]
    xs = []
    for _ in range(DRAWS):
        z, lp, grad, st = nuts.step(z, lp, grad, adapt.final())
        xs.append(target.at(z).xyz[first, 0])
    t2 = time.perf_counter()
    e = sum(ess(c) for c in np.array(xs).T)
    print(
        f"numpy NUTS: {chains} chains, {n_discs} discs: warmup {t1 - t0:.1f} s, "
        f"draws {t2 - t1:.1f} s, ESS {e:.0f}, {e / (t2 - t0):.1f} effective samples/s (all in)"
    )


def jax_nuts(n_discs: int, chains: int) -> None:
    import blackjax
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    pairs = np.array([(i, j) for i in range(n_discs) for j in range(i + 1, n_discs)]).T

    def logdensity(z: jnp.ndarray) -> jnp.ndarray:
        s = jax.nn.sigmoid(z)
        xy = (LO + (HI - LO) * s).reshape(n_discs, 2)
        prior = jnp.sum(jax.nn.log_sigmoid(z) + jax.nn.log_sigmoid(-z))
        inside = jnp.min(jnp.minimum(xy + HALF - R, HALF - R - xy))
        d = xy[pairs[0]] - xy[pairs[1]]
        gap = jnp.min(jnp.sqrt(jnp.sum(d**2, axis=1) + 1e-300) - 2 * R)
        pen = jnp.minimum(inside, 0.0) ** 2 + jnp.minimum(gap, 0.0) ** 2
        return prior - pen / (2 * EPS**2)

    def one_chain(key, z0):  # type: ignore[no-untyped-def]
        k1, k2 = jax.random.split(key)
        warm = blackjax.window_adaptation(blackjax.nuts, logdensity)
        (state, params), _ = warm.run(k1, z0, num_steps=WARMUP)
        kernel = blackjax.nuts(logdensity, **params).step

        def body(s, k):  # type: ignore[no-untyped-def]
            s, _ = kernel(k, s)
            return s, s.position[0]

        _, xs = jax.lax.scan(body, state, jax.random.split(k2, DRAWS))
        return xs

    run = jax.jit(jax.vmap(one_chain))
    keys = jax.random.split(jax.random.PRNGKey(1), chains)
    z0 = jnp.asarray(np.random.default_rng(2).standard_normal((chains, 2 * n_discs)))
    t0 = time.perf_counter()
    compiled = run.lower(keys, z0).compile()
    t1 = time.perf_counter()
    xs = np.asarray(compiled(keys, z0))
    t2 = time.perf_counter()
    x = LO + (HI - LO) / (1 + np.exp(-xs))
    e = sum(ess(c) for c in x)
    print(
        f"BlackJAX NUTS: {chains} chains, {n_discs} discs: compile {t1 - t0:.1f} s, "
        f"run {t2 - t1:.1f} s, ESS {e:.0f}, {e / (t2 - t1):.1f} effective samples/s "
        f"(without compile), {e / (t2 - t0):.1f} with"
    )


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    c = int(sys.argv[2]) if len(sys.argv) > 2 else 32
    numpy_nuts(n, c)
    jax_nuts(n, c)
