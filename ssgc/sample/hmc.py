"""`--method hmc`: thesis 2.4.1, NUTS over the poses of fixed trees with penalty terms.

Candidate trees are drawn from P(T); those that satisfy the structural constraints each get a
chain (all chains run together, `ssgc.sample.nuts`) over the local translations and rotations
of their nodes, in the unconstrained coordinates of `ssgc.sample.lawspace` (translations) and
`ssgc.sample.rotspace` (rotations), targeting

    P(poses | structure) · Π_C N(min(C(T), 0); 0, ε)     (ε = 1e-3 m by default).

The chains start from their draws of P(T), eased into the feasible set first (`_into_feasible`:
ε shrinks from the worst shortfall to its value, a factor 2 at a time), so no chain starts
under a penalty of millions.  Then `warmup` transitions: the first half adapts each chain's
step size (dual averaging), the second runs at the adapted step without adapting, so the
adaptation's own drift has passed before anything is recorded.  Each chain then gives `draws`
scenes, one per window of `samples` transitions: the window's last state that satisfies every
constraint exactly (a window with none gives nothing).  The penalty is 1 on the feasible set,
so a feasible state of a chain at its stationary law is a draw of P(poses | structure, C).

Not exact: each chain keeps its structure.  As (nearly) every chain reaches the feasible set,
structures follow P(S | structural constraints), measured (tests/test_hmc_tails.py), not
P(S | all constraints): structures that pose constraints make rare are over-represented
(thesis 2.7.3, docs/constraints.md).  And a finite chain only approaches its stationary law.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ssgc.constraints.base import Constraint
from ssgc.constraints.gradients import penalty_gradient
from ssgc.ir import Grammar
from ssgc.sample.chains import ChainOutcome, Judge
from ssgc.sample.forward import sample_chunk
from ssgc.sample.lawspace import BOX, NORMAL, Coords
from ssgc.sample.nuts import DualAveraging, Nuts
from ssgc.sample.penalty import Penalty
from ssgc.sample.poses import Levels, PullbackPlan, WorldPlan, local_poses, pullback
from ssgc.sample.rotspace import RotCoords
from ssgc.sample.staged import check_deadline
from ssgc.tree import Trees


@dataclass(frozen=True)
class HmcSettings:
    eps: float = 1e-3  # penalty scale (m)
    warmup: int = 60
    samples: int = 10  # transitions per draw: a draw is the window's last feasible state
    draws: int = 4  # scenes reported per chain, one per window of `samples` transitions
    max_depth: int = 6
    max_chains: int = 256  # chains per attempt; candidates beyond are dropped
    first_step: float = 0.1
    rotations: bool = True  # move rotations too (False: held at their draw)
    anneal_factor: float = 2.0  # the start's penalty ε shrinks by this factor per stage
    anneal_steps: int = 3  # NUTS transitions per stage of the start
    settle: float = 0.5  # share of the warm-up run at the final step size, not adapting


SETTINGS = HmcSettings()


class FixedTrees:
    """Trees whose structure is held: z -> their poses, log-density and its gradient.

    z is (N, 7): columns 0-2 the local translation's coordinates (`ssgc.sample.lawspace`),
    3-6 the local rotation's (`ssgc.sample.rotspace`).  With `rotations=False` the rotations
    are held at their draw (z is (N, 3)), as before rotations could move."""

    def __init__(
        self,
        grammar: Grammar,
        trees: Trees,
        constraints: list[Constraint],
        eps: float,
        rotations: bool = True,
    ):
        self.grammar, self.trees, self.eps = grammar, trees, eps
        self.constraints = [c for c in constraints if c.kind != "structure"]
        self.levels = Levels.of(trees)
        self.u, self.r = local_poses(grammar, trees)
        self.coords = Coords.of(grammar, trees.rule)
        self.rot = RotCoords.of(grammar, trees.rule) if rotations else None
        self.parent = np.maximum(trees.parent, 0)
        self.penalty = Penalty(self.constraints, trees, eps)
        self.world = WorldPlan(grammar, trees, self.levels)
        c = self.coords
        self.normal = ((c.kind == NORMAL)[:, None] & c.free).astype(float)
        self.box = np.flatnonzero(c.kind == BOX)
        self.box_free = c.free[self.box].astype(float)
        self.pull = PullbackPlan(grammar, trees, self.levels)
        z0 = self.coords.to_z(self.u)
        free = self.coords.free
        if self.rot is not None:
            z0 = np.concatenate([z0, self.rot.to_w(self.r)], axis=1)
            free = np.concatenate([free, self.rot.free], axis=1)
        self.z0, self.free = z0, free
        self.temper = 1.0  # the penalty's power: (ε / ε_k)² for a wider ε_k

    def at(self, z: np.ndarray) -> Trees:
        u = self.coords.to_u(z[:, :3], self.u)
        r = self.r if self.rot is None else self.rot.to_rot(z[:, 3:], self.r)
        return self.world(self.trees, u, r)

    def __call__(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log-density per tree, its gradient in z): P(poses | structure) times the
        penalty raised to `self.temper` (1: the target; below 1: the softer penalty of a
        wider ε, `run_chains`' way into the feasible set)."""
        t = self.at(z)
        zt = z[:, :3]
        if self.rot is None:
            lp = self.coords.log_density(zt, t.scene, t.n_scenes)
            pen, g_xyz, _ = penalty_gradient(self.constraints, t, self.eps)
            g_u = pullback(self.grammar, t, g_xyz * self.temper, self.levels)
            return (
                lp + self.temper * pen,
                self.coords.pull_to_z(zt, g_u) + self.coords.grad_log_density(zt),
            )
        pen, g_xyz, g_rot = self.penalty(t)
        g_u, torque = self.pull(t, g_xyz * self.temper, g_rot * self.temper)
        w = z[:, 3:]
        lp_u, grad_u = self._translation_density(zt)
        lp = lp_u + self.rot.log_density(w, t.scene, t.n_scenes) + self.temper * pen
        grad = np.empty_like(z)
        grad[:, :3] = self.coords.pull_to_z(zt, g_u) + grad_u
        g_w = self.rot.pull_to_w(w, torque, t.quat[self.parent])
        grad[:, 3:] = g_w + self.rot.grad_log_density(w)
        return lp, grad

    def shortfall(self, z: np.ndarray) -> np.ndarray:
        """Per tree, the largest amount by which a pose constraint fails at z (0: feasible)."""
        t = self.at(z)
        worst = np.zeros(self.trees.n_scenes)
        for c in self.constraints:
            m = c.margin(t)
            worst = np.maximum(worst, np.where(np.isfinite(m) & (m < 0), -m, 0.0))
        return worst

    def _translation_density(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`Coords.log_density` and `grad_log_density` on the rows that have them."""
        terms = -0.5 * np.sum(self.normal * z**2, axis=1)
        grad = -self.normal * z
        zb = z[self.box]
        terms[self.box] -= np.sum(
            self.box_free * (np.logaddexp(0.0, -zb) + np.logaddexp(0.0, zb)), axis=1
        )
        grad[self.box] += self.box_free * (1.0 - 2.0 * (0.5 * (1.0 + np.tanh(0.5 * zb))))
        return np.bincount(self.trees.scene, terms, minlength=self.trees.n_scenes), grad


def hmc_batch(
    grammar: Grammar,
    constraints: list[Constraint],
    size: int,
    rng: np.random.Generator,
    deadline: float | None = None,
    settings: HmcSettings = SETTINGS,
) -> ChainOutcome:
    """Draw `size` candidates; run a chain on each that meets the structural constraints."""
    judge = Judge(constraints)
    trees, _ = sample_chunk(grammar, rng, size)
    ok = judge.judge(judge.margins(trees, ("structure",)), np.ones(size, bool))
    ok &= np.cumsum(ok) <= settings.max_chains
    trees = trees.select(ok)
    final, stats, exact = run_chains(grammar, trees, constraints, rng, settings, deadline)
    judge.judge(judge.margins(final, ("pose",)), np.ones(final.n_scenes, bool))
    return judge.outcome(grammar, final, exact, size, stats)


def run_chains(
    grammar: Grammar,
    trees: Trees,
    constraints: list[Constraint],
    rng: np.random.Generator,
    settings: HmcSettings,
    deadline: float | None = None,
) -> tuple[Trees, dict[str, np.ndarray], np.ndarray]:
    """(each chain's reported trees, its statistics, whether it met every constraint)."""
    n = trees.n_scenes
    target = FixedTrees(grammar, trees, constraints, settings.eps, settings.rotations)
    exact_cs = target.constraints
    free = target.free
    nuts = Nuts(
        target, trees.scene, free, n, rng, settings.max_depth, lambda: check_deadline(deadline)
    )
    z, first = _into_feasible(target, nuts, settings, deadline)
    lp, g = target(z)
    adapt = DualAveraging(first)
    settle = int(settings.warmup * settings.settle)
    for _ in range(settings.warmup - settle):
        z, lp, g, st = nuts.step(z, lp, g, adapt.step)
        adapt.update(st["accept"])
        check_deadline(deadline)
    step = np.clip(adapt.final(), 1e-6, 10.0)  # a chain with nothing to move never rejects
    for _ in range(settle):
        z, lp, g, _ = nuts.step(z, lp, g, step)
        check_deadline(deadline)
    acc, leap, div = np.zeros(n), np.zeros(n), np.zeros(n)
    draws, found = [], []
    for _ in range(settings.draws):
        best = z.copy()
        ok = np.zeros(n, bool)
        for _ in range(settings.samples):
            z, lp, g, st = nuts.step(z, lp, g, step)
            acc += st["accept"]
            leap += st["steps"]
            div += st["diverging"]
            t = target.at(z)
            good = np.ones(n, bool)
            for c in exact_cs:
                good &= c.margin(t) >= 0
            best = np.where(good[trees.scene][:, None], z, best)
            ok |= good
            check_deadline(deadline)
        draws.append(replace(target.at(best), rule=trees.rule))
        found.append(ok)
    runs = max(settings.samples * settings.draws, 1)
    per_chain = {
        "acceptance": acc / runs,
        "step_size": step,
        "leapfrog_steps": leap / runs,
        "divergences": div,
        "warmup": np.full(n, settings.warmup, float),
        "samples": np.full(n, settings.samples, float),
        "penalty_eps": np.full(n, settings.eps),
    }
    k = len(draws)
    stats = {name: np.tile(v, k) for name, v in per_chain.items()}
    stats["draw"] = np.repeat(np.arange(k, dtype=float), n)
    final = Trees.concatenate(draws) if k > 1 else draws[0]
    return final, stats, np.concatenate(found)


def _into_feasible(
    target: FixedTrees, nuts: Nuts, settings: HmcSettings, deadline: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """The chains' starting states and step sizes: their draws of P(T), carried into the
    feasible set by NUTS under a penalty whose ε shrinks from the worst shortfall to
    `settings.eps`, by `anneal_factor` per stage of `anneal_steps` transitions; one step-size
    adaptation follows the stages (a restart per stage collapsed the steps of 9% of chains).

    Why: a draw of P(T) that misses a constraint by metres sits under a penalty of
    (metres / ε)² / 2 (ε = 1 mm: millions).  Started there, NUTS either shrank its step size
    until the chain could not move (89% of the draws on docs/constraints.md's three balls
    were infeasible), or turned that energy into speed, exactly (acceptance statistic 1):
    the chain flew to x = 116 m and crawled back while its draws were written out (33.7 m,
    where the law has sd 0.36).  Each stage starts within a few of its ε of feasibility, so
    the penalty's energy stays a few units and nothing is flung."""
    z = target.z0
    adapt = DualAveraging(np.full(target.trees.n_scenes, settings.first_step))
    top = float(np.max(target.shortfall(z), initial=0.0))
    if top <= settings.eps:
        return z, adapt.step
    stages = int(np.ceil(np.log(top / settings.eps) / np.log(settings.anneal_factor)))
    for k in range(stages, 0, -1):
        target.temper = float(settings.anneal_factor ** (-2 * k))
        lp, g = target(z)
        for _ in range(settings.anneal_steps):
            z, lp, g, st = nuts.step(z, lp, g, adapt.step)
            adapt.update(st["accept"])
            check_deadline(deadline)
    target.temper = 1.0
    return z, np.clip(adapt.step, 1e-6, 10.0)
