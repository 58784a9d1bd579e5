"""The No-U-Turn sampler (multinomial variant, identity metric), many chains in lockstep,
with dual-averaging step-size adaptation per chain.

Why hand-written: the targets are numpy code over a whole batch of trees of different shapes
(`ssgc.sample.hmc`); one gradient evaluation serves every chain at once, with no padding and no
compilation per tree shape.  docs/dependencies.md has the measurements against BlackJAX.

Every chain's state is the rows of its tree's nodes in one (N, 3) array (`chain[n]` says which
chain node n belongs to; `free` marks the coordinates that move); dot products are sums per
chain.  A trajectory doubles in a random direction until the generalised U-turn criterion
(Betancourt 2017) holds on it or on any subtree, or the energy error diverges; the next state
is drawn from the trajectory with multinomial weights (biased progressive sampling at the top
level, as in Stan).  All chains build the same binary tree depth together; a chain that has
stopped ignores the rest, so the law of each chain is that of NUTS run alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
# z (N, 3) -> (log-density per chain (B,), its gradient (N, 3))
Target = Callable[[FloatArray], tuple[FloatArray, FloatArray]]

MAX_DEPTH = 8
DIVERGENCE = 1000.0  # an energy error beyond this ends the trajectory


@dataclass
class _Tree:
    """One (sub)trajectory per chain: its two ends, its proposal, weight and momentum sum."""

    z_minus: FloatArray
    r_minus: FloatArray
    g_minus: FloatArray
    z_plus: FloatArray
    r_plus: FloatArray
    g_plus: FloatArray
    z_prop: FloatArray
    g_prop: FloatArray
    lp_prop: FloatArray
    log_w: FloatArray
    rho: FloatArray
    turning: BoolArray
    diverging: BoolArray
    sum_accept: FloatArray
    n_steps: FloatArray


class Nuts:
    """NUTS over `n_chains` chains whose coordinates are the `free` rows of (N, 3) arrays."""

    def __init__(
        self,
        target: Target,
        chain: NDArray[np.int64],
        free: BoolArray,
        n_chains: int,
        rng: np.random.Generator,
        max_depth: int = MAX_DEPTH,
        check: Callable[[], None] | None = None,
    ) -> None:
        """`check` is called before every gradient evaluation (a trajectory of depth 8 is 256
        of them, each a pass over every constraint): it may raise to stop at a deadline."""
        self.target, self.chain, self.free, self.n = target, chain, free, n_chains
        self.rng, self.max_depth, self.check = rng, max_depth, check

    def _dot(self, a: FloatArray, b: FloatArray) -> FloatArray:
        return np.bincount(self.chain, np.sum(a * b, axis=1), minlength=self.n)

    def _per_node(self, x: FloatArray) -> FloatArray:
        return x[self.chain][:, None]

    def _uturn(self, rho: FloatArray, r_minus: FloatArray, r_plus: FloatArray) -> BoolArray:
        return (self._dot(rho, r_minus) <= 0) | (self._dot(rho, r_plus) <= 0)

    def _leaf(
        self, z: FloatArray, r: FloatArray, g: FloatArray, step: FloatArray, h0: FloatArray
    ) -> _Tree:
        if self.check is not None:
            self.check()
        s = self._per_node(step)
        r1 = r + 0.5 * s * g
        z1 = np.where(self.free, z + s * r1, z)
        lp1, g1 = self.target(z1)
        g1 = np.where(self.free, g1, 0.0)
        r1 = np.where(self.free, r1 + 0.5 * s * g1, 0.0)
        h1 = lp1 - 0.5 * self._dot(r1, r1)
        dh = np.where(np.isnan(h1), -np.inf, h1 - h0)
        no = np.zeros(self.n, bool)
        return _Tree(
            z1, r1, g1, z1, r1, g1, z1, g1, lp1, dh, r1, no, dh < -DIVERGENCE,
            np.exp(np.minimum(dh, 0.0)), np.ones(self.n),
        )  # fmt: skip

    def _build(
        self, z: FloatArray, r: FloatArray, g: FloatArray, v: FloatArray, depth: int,
        step: FloatArray, h0: FloatArray,
    ) -> _Tree:  # fmt: skip
        if depth == 0:
            return self._leaf(z, r, g, v * step, h0)
        a = self._build(z, r, g, v, depth - 1, step, h0)
        fwd = self._per_node(v) > 0
        z0 = np.where(fwd, a.z_plus, a.z_minus)
        r0 = np.where(fwd, a.r_plus, a.r_minus)
        g0 = np.where(fwd, a.g_plus, a.g_minus)
        b = self._build(z0, r0, g0, v, depth - 1, step, h0)
        return self._merge(a, b, v, fwd, uniform=True)

    def _merge(self, a: _Tree, b: _Tree, v: FloatArray, fwd: BoolArray, uniform: bool) -> _Tree:
        """`a` extended by `b` (later in direction v); chains where `a` stopped keep `a`."""
        go = ~(a.turning | a.diverging)
        log_w = np.logaddexp(a.log_w, b.log_w)
        u = np.log(self.rng.random(self.n))
        threshold = b.log_w - (log_w if uniform else a.log_w)
        valid = ~(b.turning | b.diverging)  # at the top level only a valid subtree is drawn from
        take = go & (u < threshold) & (valid | uniform)
        tk = self._per_node(take.astype(float)) > 0
        gn = self._per_node(go.astype(float)) > 0
        minus = fwd & gn | ~gn  # a's minus end stays unless going backward
        z_minus = np.where(minus, a.z_minus, b.z_minus)
        r_minus = np.where(minus, a.r_minus, b.r_minus)
        g_minus = np.where(minus, a.g_minus, b.g_minus)
        plus = ~fwd & gn | ~gn
        z_plus = np.where(plus, a.z_plus, b.z_plus)
        r_plus = np.where(plus, a.r_plus, b.r_plus)
        g_plus = np.where(plus, a.g_plus, b.g_plus)
        rho = np.where(gn, a.rho + b.rho, a.rho)
        turning = a.turning | (go & (b.turning | self._uturn(rho, r_minus, r_plus)))
        return _Tree(
            z_minus, r_minus, g_minus, z_plus, r_plus, g_plus,
            np.where(tk, b.z_prop, a.z_prop), np.where(tk, b.g_prop, a.g_prop),
            np.where(take, b.lp_prop, a.lp_prop), np.where(go, log_w, a.log_w), rho,
            turning, a.diverging | (go & b.diverging),
            a.sum_accept + np.where(go, b.sum_accept, 0.0),
            a.n_steps + np.where(go, b.n_steps, 0.0),
        )  # fmt: skip

    def step(
        self, z: FloatArray, lp: FloatArray, g: FloatArray, step: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, dict[str, FloatArray]]:
        """One NUTS transition of every chain: (z, log-density, gradient, statistics)."""
        r = np.where(self.free, self.rng.standard_normal(z.shape), 0.0)
        h0 = lp - 0.5 * self._dot(r, r)
        no = np.zeros(self.n, bool)
        t = _Tree(z, r, g, z, r, g, z, g, lp, np.zeros(self.n), r, no, no.copy(),
                  np.zeros(self.n), np.zeros(self.n))  # fmt: skip
        depth = np.zeros(self.n)
        for j in range(self.max_depth):
            live = ~(t.turning | t.diverging)
            if not live.any():
                break
            v = np.where(self.rng.random(self.n) < 0.5, -1.0, 1.0)
            fwd = self._per_node(v) > 0
            z0 = np.where(fwd, t.z_plus, t.z_minus)
            r0 = np.where(fwd, t.r_plus, t.r_minus)
            g0 = np.where(fwd, t.g_plus, t.g_minus)
            sub = self._build(z0, r0, g0, v, j, step, h0)
            t = self._merge(t, sub, v, fwd, uniform=False)
            depth += live
        stats = {
            "accept": t.sum_accept / np.maximum(t.n_steps, 1),
            "steps": t.n_steps,
            "depth": depth,
            "diverging": t.diverging.astype(float),
        }
        return t.z_prop, t.lp_prop, t.g_prop, stats


@dataclass
class DualAveraging:
    """Hoffman & Gelman (2014), Algorithm 5: per-chain step sizes aiming at `target`."""

    step: FloatArray
    target: float = 0.8
    gamma: float = 0.05
    t0: float = 10.0
    kappa: float = 0.75

    def __post_init__(self) -> None:
        self.mu = np.log(10 * self.step)
        self.h_bar = np.zeros_like(self.step)
        self.log_bar = np.zeros_like(self.step)
        self.m = 0

    def update(self, accept: FloatArray) -> FloatArray:
        self.m += 1
        w = 1.0 / (self.m + self.t0)
        self.h_bar = (1 - w) * self.h_bar + w * (self.target - accept)
        log_step = self.mu - np.sqrt(self.m) / self.gamma * self.h_bar
        eta = self.m**-self.kappa
        self.log_bar = eta * log_step + (1 - eta) * self.log_bar
        self.step = np.exp(log_step)
        return self.step

    def final(self) -> FloatArray:
        return np.exp(self.log_bar)
