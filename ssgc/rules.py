"""What a rule does to a child's pose: draw it, and the log-density of a given one.

The densities here (`translation_log_density`, `rotation_log_density`) are the single
definition of Table 2.1 that the scorer, and later the parser, use: they read the stacked
parameter tables of the IR and handle a mix of rules over many edges at once.  The sampler
(`sample_children`) draws through the distribution objects instead and computes its own
log-density from its draws, so tests comparing the two check two independent code paths.

Measures (docs/conventions.md): translations are densities w.r.t. Lebesgue measure on the free
axes (a pinned axis or a fixed offset is a point mass, contributing 0 to the log); rotations
are densities w.r.t. the volume measure on SO(3) of total volume π², so a uniform rotation
has log-density -log π² and a Bingham on quaternions counts twice (q and -q are one rotation);
a revolute rule has a density w.r.t. its angle (radians); fixed rotations are point masses.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ssgc.distributions.uniform import UNIFORM_SO3_LOG_DENSITY
from ssgc.geometry import (
    axis_angle_to_quat,
    quat_angle,
    quat_conjugate,
    quat_multiply,
    quat_rotate,
    random_quat,
)
from ssgc.ir import LOG_2, Grammar, RKind, RotationPart, TKind, TranslationPart

FloatArray = NDArray[np.float64]

POS_TOL = 1e-6  # meters: how far a pinned coordinate may be from its value
ROT_TOL = 1e-6  # radians: same for fixed rotations and revolute axes


def translation_log_density(
    grammar: Grammar,
    rules: NDArray[np.int64],
    parent_xyz: FloatArray,
    parent_quat: FloatArray,
    child_xyz: FloatArray,
) -> FloatArray:
    """log p(child translation | parent pose) for each edge, under each edge's rule."""
    tb = grammar.tables
    kind = tb.t_kind[rules]
    u = translation_coordinates(grammar, rules, parent_xyz, parent_quat, child_xyz)
    free = tb.t_free[rules]
    delta = u - tb.t_offset[rules]
    out = np.zeros(len(rules))
    pinned_ok = np.all(free | (np.abs(delta) <= POS_TOL), axis=1)

    normal = (
        (kind == TKind.WORLD_NORMAL)
        | (kind == TKind.WORLD_NORMAL_OFFSET)
        | (kind == TKind.PARENT_NORMAL_OFFSET)
    )
    if np.any(normal):
        r = rules[normal]
        white = np.einsum("nij,nj->ni", tb.t_whiten[r], np.where(free[normal], delta[normal], 0))
        out[normal] = -0.5 * np.sum(white**2, axis=1) - tb.t_lognorm[r]
    box = (kind == TKind.WORLD_BOX) | (kind == TKind.WORLD_BOX_OFFSET)
    if np.any(box):
        r = rules[box]
        inside = (u[box] >= tb.box_lo[r] - POS_TOL) & (u[box] <= tb.box_hi[r] + POS_TOL)
        out[box] = np.where(np.all(inside, axis=1), -tb.t_lognorm[r], -np.inf)
    return np.where(pinned_ok, out, -np.inf)


def translation_coordinates(
    grammar: Grammar,
    rules: NDArray[np.int64],
    parent_xyz: FloatArray,
    parent_quat: FloatArray,
    child_xyz: FloatArray,
) -> FloatArray:
    """The child's position in the coordinates its rule's law is written in.

    World laws see the position itself, offset laws the offset from the parent, parent-frame
    laws that offset in the parent's frame.  Scoring and fitting both read positions this way.
    """
    kind = grammar.tables.t_kind[rules]
    world = (kind == TKind.WORLD_NORMAL) | (kind == TKind.WORLD_BOX)
    parent_frame = (kind == TKind.FIXED) | (kind == TKind.PARENT_NORMAL_OFFSET)
    u = np.where(world[:, None], child_xyz, child_xyz - parent_xyz)
    if np.any(parent_frame):
        u[parent_frame] = quat_rotate(quat_conjugate(parent_quat[parent_frame]), u[parent_frame])
    return u


def rotation_coordinates(
    grammar: Grammar, rules: NDArray[np.int64], parent_quat: FloatArray, child_quat: FloatArray
) -> FloatArray:
    """The child's rotation as its rule's law sees it: absolute for world laws, else relative."""
    world = grammar.tables.r_kind[rules] == RKind.WORLD_BINGHAM
    return np.where(
        world[:, None], child_quat, quat_multiply(quat_conjugate(parent_quat), child_quat)
    )


def rotation_log_density(
    grammar: Grammar,
    rules: NDArray[np.int64],
    parent_quat: FloatArray,
    child_quat: FloatArray,
) -> FloatArray:
    """log p(child rotation | parent rotation) for each edge, under each edge's rule."""
    tb = grammar.tables
    kind = tb.r_kind[rules]
    world = kind == RKind.WORLD_BINGHAM
    rel = rotation_coordinates(grammar, rules, parent_quat, child_quat)
    out = np.zeros(len(rules))

    fixed = kind == RKind.FIXED
    if np.any(fixed):
        ok = quat_angle(rel[fixed], tb.r_offset[rules[fixed]]) <= ROT_TOL
        out[fixed] = np.where(ok, 0.0, -np.inf)
    uniform = kind == RKind.UNIFORM
    out[uniform] = UNIFORM_SO3_LOG_DENSITY
    bingham = world | (kind == RKind.PARENT_BINGHAM)
    if np.any(bingham):
        r = rules[bingham]
        q = rel[bingham]
        out[bingham] = np.einsum("ni,nij,nj->n", q, tb.r_quadratic[r], q) - tb.r_lognorm[r]
    revolute = kind == RKind.REVOLUTE
    if np.any(revolute):
        r = rules[revolute]
        out[revolute] = _revolute_log_density(
            rel[revolute], tb.r_axis[r], tb.r_lo[r], tb.r_hi[r], tb.r_lognorm[r]
        )
    return out


def _revolute_log_density(
    rel: FloatArray, axis: FloatArray, lo: FloatArray, hi: FloatArray, lognorm: FloatArray
) -> FloatArray:
    """A rotation about `axis` by an angle in [lo, hi] (mod 2π) has density 1/(hi - lo)."""
    along = np.sum(rel[:, 1:] * axis, axis=1)
    off_axis = np.linalg.norm(rel[:, 1:] - along[:, None] * axis, axis=1)
    theta = 2.0 * np.arctan2(along, rel[:, 0])
    on_axis = 2.0 * np.arcsin(np.minimum(off_axis, 1.0)) <= ROT_TOL
    rel_angle = np.mod(theta - lo, 2.0 * np.pi)
    width = hi - lo
    in_range = (rel_angle <= width + ROT_TOL) | (rel_angle >= 2.0 * np.pi - ROT_TOL)
    return np.where(on_axis & in_range, -lognorm, -np.inf)


def sample_children(
    grammar: Grammar,
    rule_id: int,
    parent_xyz: FloatArray,
    parent_quat: FloatArray,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Draw one child per parent under rule `rule_id`: (xyz, quat, log-density of the draw)."""
    rule = grammar.rules[rule_id]
    xyz, lp_t = _sample_translation(rule.translation, parent_xyz, parent_quat, rng)
    quat, lp_r = _sample_rotation(rule.rotation, parent_quat, rng)
    return xyz, quat, lp_t + lp_r


def _sample_translation(
    part: TranslationPart,
    parent_xyz: FloatArray,
    parent_quat: FloatArray,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    n = parent_xyz.shape[0]
    kind = part.kind
    if kind == TKind.FIXED:
        return parent_xyz + quat_rotate(parent_quat, part.offset), np.zeros(n)
    if part.normal is not None:
        z = rng.standard_normal((n, int(part.free.sum())))
        local = np.broadcast_to(part.offset, (n, 3)).copy()
        local[:, part.free] = part.normal.mean + z @ part.normal.chol.T
        logp = part.normal.log_prob_from_standard(z)
    else:
        local = part.box.sample(rng, n)
        logp = part.box.log_prob(local)
    if kind in (TKind.WORLD_NORMAL, TKind.WORLD_BOX):
        return local, logp
    if kind == TKind.PARENT_NORMAL_OFFSET:
        return parent_xyz + quat_rotate(parent_quat, local), logp
    return parent_xyz + local, logp


def _sample_rotation(
    part: RotationPart, parent_quat: FloatArray, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    n = parent_quat.shape[0]
    kind = part.kind
    if kind == RKind.FIXED:
        return quat_multiply(parent_quat, part.offset), np.zeros(n)
    if kind == RKind.UNIFORM:
        return random_quat(rng, n), np.full(n, UNIFORM_SO3_LOG_DENSITY)
    if kind == RKind.REVOLUTE:
        theta = part.revolute.sample(rng, n)
        rel = axis_angle_to_quat(part.axis, theta)
        return quat_multiply(parent_quat, rel), part.revolute.log_prob(theta)
    rel = part.bingham.sample(rng, n)
    logp = part.bingham.log_prob(rel) + LOG_2
    if kind == RKind.WORLD_BINGHAM:
        return rel, logp
    return quat_multiply(parent_quat, rel), logp
