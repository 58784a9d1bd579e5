"""`--method project`: thesis 2.4.2, the closest poses that satisfy the constraints (biased).

Each candidate that meets the structural constraints is projected: over the local
translations of its nodes (rotations held), minimise the squared distance of every node's
world position to its drawn one, subject to every pose constraint's margin ≥ 0 and to the
support of each uniform-box law, with scipy's SLSQP (one problem per tree: scipy's
optimisers take one problem at a time).  Margins and their gradients come from
`ssgc.constraints.gradients`, pulled back to the local coordinates (`ssgc.sample.poses`).
A projection is reported only if every constraint then holds exactly.

Biased: trees that violated a constraint are moved onto its boundary, so scenes pile up
there (thesis 2.4.2); the output says `"exact": false`.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from ssgc.constraints.base import Constraint
from ssgc.constraints.gradients import element_gradients
from ssgc.ir import Grammar
from ssgc.sample.chains import ChainOutcome, Judge
from ssgc.sample.forward import sample_chunk
from ssgc.sample.lawspace import BOX, Coords
from ssgc.sample.poses import Levels, local_poses, pullback, world_poses
from ssgc.sample.staged import _check
from ssgc.tree import Trees

MAX_ITER = 100
MAX_TREES = 64
SAFETY = 1e-7  # m: aim this far inside, so that the projection satisfies them exactly


def project_batch(
    grammar: Grammar,
    constraints: list[Constraint],
    size: int,
    rng: np.random.Generator,
    deadline: float | None = None,
) -> ChainOutcome:
    """Draw `size` candidates; project those meeting the structural constraints."""
    judge = Judge(constraints)
    trees, _ = sample_chunk(grammar, rng, size)
    ok = judge.judge(judge.margins(trees, ("structure",)), np.ones(size, bool))
    ok &= np.cumsum(ok) <= MAX_TREES
    trees = trees.select(ok)
    pose = [c for c in constraints if c.kind != "structure"]
    projected, moved, iters = [], np.zeros(trees.n_scenes), np.zeros(trees.n_scenes)
    for i in range(trees.n_scenes):
        t, moved[i], iters[i] = project_tree(grammar, trees.tree(i), pose)
        projected.append(t)
        _check(deadline)
    out = Trees.concatenate(projected) if projected else trees
    good = judge.judge(judge.margins(out, ("pose",)), np.ones(out.n_scenes, bool))
    stats = {"distance_moved": moved, "iterations": iters}
    return judge.outcome(grammar, out, good, size, stats)


def project_tree(
    grammar: Grammar, tree: Trees, constraints: list[Constraint]
) -> tuple[Trees, float, int]:
    """(the projected tree, how far its positions moved (m, root of the squared sum),
    SLSQP iterations).  A tree that already satisfies every constraint is its own projection."""
    if all(np.all(c.margin(tree) >= 0) for c in constraints):
        return tree, 0.0, 0
    levels = Levels.of(tree)
    u0, r = local_poses(grammar, tree)
    coords = Coords.of(grammar, tree.rule)
    free = np.flatnonzero(coords.free.ravel())
    x0 = tree.xyz.copy()

    def at(v: np.ndarray) -> Trees:
        u = u0.copy().ravel()
        u[free] = v
        return world_poses(grammar, tree, u.reshape(-1, 3), r, levels)

    def objective(v: np.ndarray) -> tuple[float, np.ndarray]:
        t = at(v)
        d = t.xyz - x0
        g = pullback(grammar, t, 2 * d, levels).ravel()[free]
        return float(np.sum(d**2)), g

    def constraint(c: Constraint) -> dict:  # type: ignore[type-arg]
        # every term of the margin (each pair, each box face) is its own inequality: smooth
        def fun(v: np.ndarray) -> np.ndarray:
            return element_gradients(c, at(v))[0] - SAFETY

        def jac(v: np.ndarray) -> np.ndarray:
            t = at(v)
            _, g = element_gradients(c, t)
            rows = [pullback(grammar, t, gk, levels).ravel()[free] for gk in g]
            return np.array(rows).reshape(len(g), len(free))

        return {"type": "ineq", "fun": fun, "jac": jac}

    r_ = np.maximum(tree.rule, 0)
    lo = np.where((coords.kind == BOX)[:, None], coords.laws.lo[r_], -np.inf).ravel()[free]
    hi = np.where((coords.kind == BOX)[:, None], coords.laws.hi[r_], np.inf).ravel()[free]
    res = minimize(
        objective,
        u0.ravel()[free],
        jac=True,
        method="SLSQP",
        bounds=list(zip(lo, hi, strict=True)),
        constraints=[constraint(c) for c in constraints],
        options={"maxiter": MAX_ITER},
    )
    t = at(res.x)
    return t, float(np.sqrt(np.sum((t.xyz - x0) ** 2))), int(res.nit)
