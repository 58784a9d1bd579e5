"""`--method project`: thesis 2.4.2, the closest poses that satisfy the constraints (biased).

Each candidate that meets the structural constraints is projected: over the local
translations of its nodes (rotations held), minimise the squared distance of every node's
world position to its drawn one, subject to every pose constraint's margin ≥ 0 and to the
support of each uniform-box law, with scipy's SLSQP (one problem per tree: scipy's
optimisers take one problem at a time).  Margins and their gradients come from
`ssgc.constraints.gradients`, carried to the local coordinates by the Jacobian of the (affine)
map from local translations to positions (`ssgc.sample.poses.pullback_many`).
A projection is reported only if every constraint then holds exactly.

Biased: trees that violated a constraint are moved onto its boundary, so scenes pile up
there (thesis 2.4.2); the output says `"exact": false`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.optimize import minimize

from ssgc.constraints.base import Constraint
from ssgc.constraints.gradients import element_gradients
from ssgc.ir import Grammar
from ssgc.sample.chains import ChainOutcome, Judge
from ssgc.sample.forward import sample_chunk
from ssgc.sample.lawspace import BOX, Coords
from ssgc.sample.poses import Levels, local_poses, pullback_many
from ssgc.sample.staged import check_deadline
from ssgc.tree import Trees

MAX_ITER = 40  # SLSQP iterations; a tree needing more is dropped (overfull bins never converge)
MAX_TREES = 64
SAFETY = 1e-7  # m: aim this far inside, so that the projection satisfies them exactly
ACTIVE = 0.05  # m: terms farther than this from violation are left out of a round
ROUNDS = 3


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
        check_deadline(deadline)
    out = Trees.concatenate(projected) if projected else trees
    good = judge.judge(judge.margins(out, ("pose",)), np.ones(out.n_scenes, bool))
    stats = {"distance_moved": moved, "iterations": iters}
    return judge.outcome(grammar, out, good, size, stats)


def project_tree(
    grammar: Grammar, tree: Trees, constraints: list[Constraint]
) -> tuple[Trees, float, int]:
    """(the projected tree, how far its positions moved (m, root of the squared sum),
    SLSQP iterations).  A tree that already satisfies every constraint is its own projection.

    With rotations held, world positions are affine in the local translations: x = x0 + J δ,
    J found once (`pullback_many` of the unit vectors), so no iteration rebuilds the tree.
    Only terms within `ACTIVE` of violation are given to SLSQP (its cost grows with the
    number of inequalities); if the answer violates a term left out, the terms near that
    answer are added and the problem solved again from the start (at most `ROUNDS` times):
    a solution of the reduced problem that satisfies every term solves the full one."""
    if all(np.all(c.margin(tree) >= 0) for c in constraints):
        return tree, 0.0, 0
    levels = Levels.of(tree)
    u0, _ = local_poses(grammar, tree)
    coords = Coords.of(grammar, tree.rule)
    free = np.flatnonzero(coords.free.ravel())
    if not len(free):  # every position fixed by its rule: nothing to project (SLSQP needs one)
        return tree, 0.0, 0
    x0 = tree.xyz.copy()
    n3 = x0.size
    jac_x = pullback_many(grammar, tree, np.eye(n3).reshape(n3, -1, 3), levels)
    jac_x = jac_x.reshape(n3, n3)[:, free]  # d xyz (flat) / d u (free)
    v0 = u0.ravel()[free]

    def at(v: np.ndarray) -> Trees:
        return replace(tree, xyz=x0 + (jac_x @ (v - v0)).reshape(-1, 3))

    def objective(v: np.ndarray) -> tuple[float, np.ndarray]:
        d = jac_x @ (v - v0)
        return float(d @ d), 2.0 * (jac_x.T @ d)

    def constraint(c: Constraint, keep: np.ndarray) -> dict:  # type: ignore[type-arg]
        # every term of the margin (each pair, each box face) is its own inequality: smooth
        def fun(v: np.ndarray) -> np.ndarray:
            return element_gradients(c, at(v))[0][keep] - SAFETY

        def jac(v: np.ndarray) -> np.ndarray:
            _, g = element_gradients(c, at(v))
            return g[keep].reshape(int(keep.sum()), -1) @ jac_x

        return {"type": "ineq", "fun": fun, "jac": jac}

    r_ = np.maximum(tree.rule, 0)
    lo = np.where((coords.kind == BOX)[:, None], coords.laws.lo[r_], -np.inf).ravel()[free]
    hi = np.where((coords.kind == BOX)[:, None], coords.laws.hi[r_], np.inf).ravel()[free]
    bounds = list(zip(lo, hi, strict=True)) if np.isfinite(np.r_[lo, hi]).any() else None
    keep = [element_gradients(c, tree)[0] < ACTIVE for c in constraints]
    v, iters = v0, 0
    for _ in range(ROUNDS):
        res = minimize(
            objective,
            v0,
            jac=True,
            method="SLSQP",
            bounds=bounds,
            constraints=[
                constraint(c, k) for c, k in zip(constraints, keep, strict=True) if k.any()
            ],
            options={"maxiter": MAX_ITER},
        )
        v, iters = res.x, iters + int(res.nit)
        values = [element_gradients(c, at(v))[0] for c in constraints]
        missed = [(m < 0) & ~k for m, k in zip(values, keep, strict=True)]
        if not any(m.any() for m in missed):
            break
        keep = [k | (m < ACTIVE) for k, m in zip(keep, values, strict=True)]
    t = replace(at(v), rule=tree.rule)
    return t, float(np.sqrt(np.sum((t.xyz - x0) ** 2))), iters
