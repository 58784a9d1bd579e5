"""Unconstrained coordinates w for the local rotations of fixed trees, with the log-density of
the rotations given the structure and its gradient (HMC over rotations, `ssgc.sample.hmc`).

Each node's rotation gets up to four coordinates (a row of an (N, 4) array), by its law:

- **Bingham and uniform** (`SPHERE`): w ∈ R⁴, the rotation is q = w / |w|.  The density of w
  is f(q) · exp(-(|w| - ρ)² / 2), f the law's density on unit quaternions (exp(qᵀ A q); 1 for
  the uniform law).  In polar coordinates w = r q, dw = r³ dr dq, so the marginal of q is
  f(q) · ∫ r³ exp(-(r - ρ)² / 2) dr = f(q) · const: exactly the law (q and -q, the same
  rotation, have the same density).  The radius ρ only sets the scale: a turn of q by δ moves
  w by about ρ δ, so ρ = √κ (κ the spread of A's eigenvalues, clipped to [2, 30]) makes the
  law's tightest direction about as wide as a whitened translation.
- **Revolute over the full circle** (`CIRCLE`): w ∈ R², angle lo + atan2(w₁, w₀), density
  exp(-(|w| - 3)² / 2) (dw = r dr dφ: the angle is uniform), so the circle has no seam.
- **Revolute over an arc** (`ARC`): one coordinate, angle lo + (hi - lo) σ(w₀), log-density
  log σ + log(1 - σ) (the Jacobian; the angle's own density is constant).
- Point masses and other laws are held (`HELD`).

The gradient of anything in poses reaches w through torques: `ssgc.sample.poses.pullback_poses`
gives d f / d ω for a world-frame turn of each node's rotation; a law in the parent's frame
sees that turn as ω_local = R_parentᵀ ω, and q -> exp(ω_local) ⊗ q means dq = ½ ω_local ⊗ q,
so d f / d q = 2 (0, ω_local) ⊗ q (tangent to the sphere) and d f / d w = (d f / d q) / |w|.
A revolute angle turns about its axis a: d f / d θ = a · ω_local.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import axis_angle_to_quat, quat_multiply, quat_rotate
from ssgc.ir import Grammar
from ssgc.laws.base import Frame
from ssgc.laws.rotation_bingham import BinghamRotation
from ssgc.laws.rotation_revolute import RevoluteRotation
from ssgc.laws.rotation_uniform import UniformRotation
from ssgc.sample.lawspace import per_grammar

FloatArray = NDArray[np.float64]
HELD, SPHERE, CIRCLE, ARC = 0, 1, 2, 3
WIDTH = np.array([0, 4, 2, 1])  # coordinates used per kind
CIRCLE_RADIUS = 3.0
FULL_TURN = 2 * np.pi - 1e-9


@dataclass(frozen=True)
class RuleRotations:
    """Per rule: the kind of its rotation's coordinates and the law's parameters."""

    kind: NDArray[np.int64]
    quadratic: FloatArray  # (R, 4, 4) A of exp(qᵀ A q); zero for the uniform law
    radius: FloatArray  # (R,) ρ
    axis: FloatArray  # (R, 3) revolute axis
    lo: FloatArray
    hi: FloatArray
    world: NDArray[np.bool_]  # the law is written in the world frame

    @classmethod
    def of(cls, grammar: Grammar) -> RuleRotations:
        n = len(grammar.rules)
        kind = np.zeros(n, np.int64)
        quad, radius = np.zeros((n, 4, 4)), np.full(n, CIRCLE_RADIUS)
        axis, lo, hi = np.tile([0.0, 0.0, 1.0], (n, 1)), np.zeros(n), np.ones(n)
        for r, rule in enumerate(grammar.rules):
            law = rule.rotation
            if isinstance(law, BinghamRotation | UniformRotation):
                kind[r] = SPHERE
                if isinstance(law, BinghamRotation):
                    quad[r] = law.quadratic()
                w = np.linalg.eigvalsh(quad[r])
                radius[r] = np.clip(np.sqrt(w.max() - w.min()), 2.0, 30.0)
            elif isinstance(law, RevoluteRotation):
                lo[r], hi[r], axis[r] = law.revolute.lo, law.revolute.hi, law.axis
                width = hi[r] - lo[r]
                kind[r] = CIRCLE if width >= FULL_TURN else ARC if width > 0 else HELD
        world = grammar.tables.rotation.frame == Frame.WORLD
        return cls(kind, quad, radius, axis, lo, hi, np.asarray(world, bool))


rule_rotations = per_grammar(RuleRotations.of)


@dataclass(frozen=True)
class RotCoords:
    """The rotation coordinates of a batch's nodes; `free` (N, 4) marks the used ones."""

    laws: RuleRotations
    rule: NDArray[np.int64]  # per node (clipped to 0 for roots; their kind is HELD)
    kind: NDArray[np.int64]
    free: NDArray[np.bool_]

    @classmethod
    def of(cls, grammar: Grammar, rule: NDArray[np.int64]) -> RotCoords:
        laws = rule_rotations(grammar)
        r = np.maximum(rule, 0)
        kind = np.where(rule >= 0, laws.kind[r], HELD)
        free = np.arange(4)[None, :] < WIDTH[kind][:, None]
        return cls(laws, r, kind, free)

    def _mask(self, kind: int) -> NDArray[np.bool_]:
        return self.kind == kind

    def to_w(self, rot: FloatArray) -> FloatArray:
        """Coordinates of the local rotations `rot` (N, 4) (each law's own coordinates)."""
        w = np.zeros((len(rot), 4))
        s = self._mask(SPHERE)
        w[s] = rot[s] * self.laws.radius[self.rule[s]][:, None]
        rev = self._mask(CIRCLE) | self._mask(ARC)
        r = self.rule[rev]
        along = np.sum(rot[rev, 1:] * self.laws.axis[r], axis=1)
        phi = np.mod(2.0 * np.arctan2(along, rot[rev, 0]) - self.laws.lo[r], 2 * np.pi)
        circle = self.kind[rev] == CIRCLE
        w[rev, 0] = np.where(circle, CIRCLE_RADIUS * np.cos(phi), 0.0)
        w[rev, 1] = np.where(circle, CIRCLE_RADIUS * np.sin(phi), 0.0)
        t = np.clip(phi / (self.laws.hi[r] - self.laws.lo[r]), 1e-9, 1 - 1e-9)
        w[rev, 0] = np.where(circle, w[rev, 0], np.log(t) - np.log1p(-t))
        return w

    def _angle(self, w: FloatArray) -> FloatArray:
        """Revolute angle of every node (meaningless where the kind is not revolute)."""
        lo, hi = self.laws.lo[self.rule], self.laws.hi[self.rule]
        circle = lo + np.arctan2(w[:, 1], w[:, 0])
        arc = lo + (hi - lo) * _sigmoid(w[:, 0])
        return np.where(self.kind == CIRCLE, circle, arc)

    def to_rot(self, w: FloatArray, held: FloatArray) -> FloatArray:
        """Local rotations for coordinates w; nodes without coordinates keep `held`."""
        out = held.copy()
        s = self._mask(SPHERE)
        out[s] = w[s] / np.linalg.norm(w[s], axis=1, keepdims=True)
        rev = self._mask(CIRCLE) | self._mask(ARC)
        out[rev] = axis_angle_to_quat(self.laws.axis[self.rule[rev]], self._angle(w)[rev])
        return out

    def log_density(self, w: FloatArray, scene: NDArray[np.int64], n: int) -> FloatArray:
        """Per tree: log p(local rotations) in w, without constants."""
        terms = np.zeros(len(w))
        s, c, a = self.rows
        ws = w[s]
        norm = np.linalg.norm(ws, axis=1)
        q = ws / np.maximum(norm, 1e-300)[:, None]
        quad = np.einsum("ni,nij,nj->n", q, self.laws.quadratic[self.rule[s]], q)
        terms[s] = quad - 0.5 * (norm - self.laws.radius[self.rule[s]]) ** 2
        terms[c] = -0.5 * (np.hypot(w[c, 0], w[c, 1]) - CIRCLE_RADIUS) ** 2
        terms[a] = -np.logaddexp(0.0, -w[a, 0]) - np.logaddexp(0.0, w[a, 0])
        return np.bincount(scene, terms, minlength=n)

    @property
    def rows(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """The nodes of each kind with coordinates: (sphere, circle, arc)."""
        cached = self.__dict__.get("_rows")
        if cached is None:
            cached = tuple(np.flatnonzero(self.kind == k) for k in (SPHERE, CIRCLE, ARC))
            object.__setattr__(self, "_rows", cached)
        return cached  # type: ignore[no-any-return]

    def grad_log_density(self, w: FloatArray) -> FloatArray:
        out = np.zeros_like(w)
        s, c, a = self.rows
        ws = w[s]
        norm = np.maximum(np.linalg.norm(ws, axis=1, keepdims=True), 1e-300)
        q = ws / norm
        aq = 2.0 * np.einsum("nij,nj->ni", self.laws.quadratic[self.rule[s]], q)
        tangent = (aq - np.sum(aq * q, axis=1, keepdims=True) * q) / norm
        out[s] = tangent - (norm - self.laws.radius[self.rule[s]][:, None]) * q
        wc = w[c, :2]
        nc = np.maximum(np.hypot(wc[:, 0], wc[:, 1]), 1e-300)[:, None]
        out[c, :2] = -(nc - CIRCLE_RADIUS) * wc / nc
        out[a, 0] = 1.0 - 2.0 * _sigmoid(w[a, 0])
        return out

    def pull_to_w(self, w: FloatArray, torque: FloatArray, parent_quat: FloatArray) -> FloatArray:
        """d f / d w from each node's world-frame torque d f / d ω (`pullback_poses` in
        `ssgc.sample.poses`); `parent_quat` is each node's parent's world rotation."""
        out = np.zeros_like(w)
        s, c, a = self.rows
        moved = np.concatenate([s, c, a])
        b = torque[moved]
        local = ~self.laws.world[self.rule[moved]]
        conj = parent_quat[moved[local]] * np.array([1.0, -1.0, -1.0, -1.0])
        b[local] = quat_rotate(conj, b[local])
        bs, br = b[: len(s)], b[len(s) :]
        ws = w[s]
        norm = np.maximum(np.linalg.norm(ws, axis=1, keepdims=True), 1e-300)
        pure = np.concatenate([np.zeros((len(s), 1)), bs], axis=1)
        out[s] = 2.0 * quat_multiply(pure, ws / norm) / norm
        rev = moved[len(s) :]
        d_theta = np.sum(br * self.laws.axis[self.rule[rev]], axis=1)
        dc = d_theta[: len(c)]
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            r2 = w[c, 0] ** 2 + w[c, 1] ** 2
            out[c, 0] = -w[c, 1] * dc / r2
            out[c, 1] = w[c, 0] * dc / r2
        sa = _sigmoid(w[a, 0])
        width = (self.laws.hi - self.laws.lo)[self.rule[a]]
        out[a, 0] = d_theta[len(c) :] * width * sa * (1 - sa)
        return out


def _sigmoid(x: FloatArray) -> FloatArray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))
