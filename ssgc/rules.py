"""What a rule does to a child's pose: draw it, and the log-density of a given one.

Each part of a rule (translation, rotation) is a law written in a frame (`ssgc.laws`).  The
law knows its own density in its own coordinates; this module holds the frames: it moves a
child's pose into each edge's law coordinates (`translation_coordinates`,
`rotation_coordinates`, also used by the fitter) and a draw in law coordinates back to a pose.

The densities (`translation_log_density`, `rotation_log_density`) read the stacked tables of
the IR and handle a mix of rules over many edges at once, for the scorer and the parser.  The
sampler (`sample_children`) draws through the law objects instead and computes its own
log-density from its draws, so tests comparing the two check two independent code paths.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import quat_conjugate, quat_multiply, quat_rotate
from ssgc.ir import Grammar
from ssgc.laws.base import POS_TOL, ROT_TOL, Frame, RotationLaw, TranslationLaw

FloatArray = NDArray[np.float64]

__all__ = [
    "POS_TOL",
    "ROT_TOL",
    "rotation_coordinates",
    "rotation_log_density",
    "sample_children",
    "translation_coordinates",
    "translation_log_density",
]


def translation_log_density(
    grammar: Grammar,
    rules: NDArray[np.int64],
    parent_xyz: FloatArray,
    parent_quat: FloatArray,
    child_xyz: FloatArray,
) -> FloatArray:
    """log p(child translation | parent pose) for each edge, under each edge's rule."""
    u = translation_coordinates(grammar, rules, parent_xyz, parent_quat, child_xyz)
    return grammar.tables.translation.log_density(rules, u)


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
    frame = grammar.tables.translation.frame[rules]
    u = np.where((frame == Frame.WORLD)[:, None], child_xyz, child_xyz - parent_xyz)
    parent_frame = frame == Frame.PARENT
    if np.any(parent_frame):
        u[parent_frame] = quat_rotate(quat_conjugate(parent_quat[parent_frame]), u[parent_frame])
    return u


def rotation_coordinates(
    grammar: Grammar, rules: NDArray[np.int64], parent_quat: FloatArray, child_quat: FloatArray
) -> FloatArray:
    """The child's rotation as its rule's law sees it: absolute for world laws, else relative."""
    world = grammar.tables.rotation.frame[rules] == Frame.WORLD
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
    rel = rotation_coordinates(grammar, rules, parent_quat, child_quat)
    return grammar.tables.rotation.log_density(rules, rel)


def sample_children(
    grammar: Grammar,
    rule_id: int,
    parent_xyz: FloatArray,
    parent_quat: FloatArray,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Draw one child per parent under rule `rule_id`: (xyz, quat, log-density of the draw)."""
    rule = grammar.rules[rule_id]
    xyz, lp_t = place_translation(rule.translation, parent_xyz, parent_quat, rng)
    quat, lp_r = place_rotation(rule.rotation, parent_quat, rng)
    return xyz, quat, lp_t + lp_r


def place_translation(
    law: TranslationLaw,
    parent_xyz: FloatArray,
    parent_quat: FloatArray,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """A draw of `law` per parent, moved from the law's frame to the world (a point mass
    needs no draw: its one value broadcasts)."""
    n, point = parent_xyz.shape[0], law.point
    local, logp = (point, np.zeros(n)) if point is not None else law.sample(rng, n)
    if law.frame == Frame.WORLD:
        return np.broadcast_to(local, (n, 3)).copy(), logp
    if law.frame == Frame.PARENT:
        return parent_xyz + quat_rotate(parent_quat, local), logp
    return parent_xyz + local, logp


def place_rotation(
    law: RotationLaw, parent_quat: FloatArray, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    n, point = parent_quat.shape[0], law.point
    local, logp = (point, np.zeros(n)) if point is not None else law.sample(rng, n)
    if law.frame == Frame.WORLD:
        return np.broadcast_to(local, (n, 4)).copy(), logp
    return quat_multiply(parent_quat, local), logp
