"""Unconstrained coordinates z for the local translations of fixed trees, with the
log-density of the poses given the structure and its gradient.

A Normal law's free axes are whitened (u = mean + L z, L its Cholesky factor), so its
log-density is -|z|²/2; a uniform box's free axes go through a logistic map,
u = lo + (hi - lo) σ(z), whose log-Jacobian log σ(z) + log(1 - σ(z)) is the log-density of z
(the box's own density is constant).  Point masses and pinned axes have no coordinate.
Other translation laws are held where they are.  Rotations are held: HMC moves translations
only (`ssgc.sample.hmc`).  All constants are dropped.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from ssgc.ir import Grammar
from ssgc.laws.position_box import BoxTranslation
from ssgc.laws.position_normal import NormalTranslation

T = TypeVar("T")

FloatArray = NDArray[np.float64]
HELD, NORMAL, BOX = 0, 1, 2


@dataclass(frozen=True)
class RuleLaws:
    """Per rule: which kind of coordinate its translation has, and its parameters."""

    kind: NDArray[np.int64]
    free: NDArray[np.bool_]  # (R, 3)
    mean: FloatArray  # (R, 3) Normal mean (pinned axes too)
    chol: FloatArray  # (R, 3, 3) Cholesky factor, embedded in the free axes
    whiten: FloatArray  # (R, 3, 3) its inverse, embedded
    lo: FloatArray  # (R, 3)
    hi: FloatArray

    @classmethod
    def of(cls, grammar: Grammar) -> RuleLaws:
        n = len(grammar.rules)
        kind = np.zeros(n, np.int64)
        free = np.zeros((n, 3), bool)
        mean, lo, hi = np.zeros((n, 3)), np.zeros((n, 3)), np.ones((n, 3))
        chol, whiten = np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
        for r, rule in enumerate(grammar.rules):
            law = rule.translation
            if isinstance(law, NormalTranslation):
                kind[r], free[r], mean[r] = NORMAL, law.free, law.offset
                ax = np.flatnonzero(law.free)
                chol[r][np.ix_(ax, ax)] = law.normal.chol
                whiten[r][np.ix_(ax, ax)] = np.linalg.inv(law.normal.chol)
            elif isinstance(law, BoxTranslation):
                kind[r], lo[r], hi[r] = BOX, law.box.lo, law.box.hi
                free[r] = law.box.hi > law.box.lo
        return cls(kind, free, mean, chol, whiten, lo, hi)


def per_grammar(make: Callable[[Grammar], T]) -> Callable[[Grammar], T]:
    """`make(grammar)` computed once per grammar: samplers ask for a grammar's law tables at
    every step.  Keyed by id, checked by identity (an id may be reused once a grammar is gone)."""
    cache: dict[int, tuple[Grammar, T]] = {}

    def table(grammar: Grammar) -> T:
        hit = cache.get(id(grammar))
        if hit is None or hit[0] is not grammar:
            hit = cache[id(grammar)] = (grammar, make(grammar))
        return hit[1]

    return table


rule_laws = per_grammar(RuleLaws.of)


@dataclass(frozen=True)
class Coords:
    """The free coordinates of a batch's nodes: `free` (N, 3) marks them; rows of nodes
    without a coordinate are all False."""

    laws: RuleLaws
    rule: NDArray[np.int64]  # per node, -1 for roots
    kind: NDArray[np.int64]
    free: NDArray[np.bool_]

    @classmethod
    def of(cls, grammar: Grammar, rule: NDArray[np.int64]) -> Coords:
        laws = rule_laws(grammar)
        r = np.maximum(rule, 0)
        kind = np.where(rule >= 0, laws.kind[r], HELD)
        free = laws.free[r] & (kind != HELD)[:, None]
        return cls(laws, rule, kind, free)

    def to_z(self, u: FloatArray) -> FloatArray:
        r = np.maximum(self.rule, 0)
        z = np.zeros_like(u)
        nrm = self.kind == NORMAL
        z[nrm] = np.einsum("nij,nj->ni", self.laws.whiten[r[nrm]], u[nrm] - self.laws.mean[r[nrm]])
        box = self.kind == BOX
        lo, hi = self.laws.lo[r[box]], self.laws.hi[r[box]]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip((u[box] - lo) / (hi - lo), 1e-12, 1 - 1e-12)
            z[box] = np.log(t) - np.log1p(-t)
        return np.where(self.free, z, 0.0)

    def to_u(self, z: FloatArray, held: FloatArray) -> FloatArray:
        """Local translations for coordinates z; nodes and axes without one keep `held`."""
        r = np.maximum(self.rule, 0)
        u = held.copy()
        nrm = self.kind == NORMAL
        u[nrm] = self.laws.mean[r[nrm]] + np.einsum("nij,nj->ni", self.laws.chol[r[nrm]], z[nrm])
        box = self.kind == BOX
        lo, hi = self.laws.lo[r[box]], self.laws.hi[r[box]]
        u[box] = lo + (hi - lo) * _sigmoid(z[box])
        return np.where(self.free, u, held)

    def log_density(self, z: FloatArray, scene: NDArray[np.int64], n: int) -> FloatArray:
        """Per tree: log p(local translations) in z, without constants."""
        nrm = (self.kind == NORMAL)[:, None] & self.free
        box = (self.kind == BOX)[:, None] & self.free
        terms = np.where(nrm, -0.5 * z**2, 0.0)
        terms += np.where(box, -np.logaddexp(0.0, -z) - np.logaddexp(0.0, z), 0.0)
        return np.bincount(scene, terms.sum(axis=1), minlength=n)

    def grad_log_density(self, z: FloatArray) -> FloatArray:
        nrm = (self.kind == NORMAL)[:, None] & self.free
        box = (self.kind == BOX)[:, None] & self.free
        return np.where(nrm, -z, 0.0) + np.where(box, 1.0 - 2.0 * _sigmoid(z), 0.0)

    def pull_to_z(self, z: FloatArray, g_u: FloatArray) -> FloatArray:
        """d f / d z from d f / d u."""
        r = np.maximum(self.rule, 0)
        out = np.zeros_like(z)
        nrm = self.kind == NORMAL
        out[nrm] = np.einsum("nji,nj->ni", self.laws.chol[r[nrm]], g_u[nrm])
        box = self.kind == BOX
        s = _sigmoid(z[box])
        out[box] = (self.laws.hi[r[box]] - self.laws.lo[r[box]]) * s * (1 - s) * g_u[box]
        return np.where(self.free, out, 0.0)


def _sigmoid(x: FloatArray) -> FloatArray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))
