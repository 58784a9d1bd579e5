"""Rotation helpers: the single place where ssgc decides how rotations are written.

Every other module goes through these functions so that one convention holds
across grammars, samplers, parsers and output files:

* quaternions are ``wxyz`` (scalar first), arrays of shape ``(..., 4)``;
* rotation matrices are ``(..., 3, 3)`` and act on column vectors ``(..., 3)``,
  so ``quat_to_matrix(q) @ v == quat_rotate(q, v)``;
* quaternion products are Hamilton products;
* roll-pitch-yaw follows Drake's ``RollPitchYaw``: fixed-axis (extrinsic) X-Y-Z,
  ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``;
* everything is float64 and broadcasts over leading batch dimensions, so a single
  ``(4,)`` quaternion combines with an ``(N, 4)`` batch without reshaping.

Unit norm is the caller's duty unless a function says it normalises; this keeps the
hot paths free of hidden renormalisation that could mask upstream bugs.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "IDENTITY_QUAT",
    "QUAT_NORM_TOL",
    "axis_angle_to_quat",
    "is_unit_quat",
    "matrix_to_quat",
    "profile_area",
    "profile_problem",
    "quat_angle",
    "quat_between",
    "quat_canonical",
    "quat_conjugate",
    "quat_multiply",
    "quat_normalize",
    "quat_relative",
    "quat_rotate",
    "quat_to_axis_angle",
    "quat_to_matrix",
    "quat_to_rpy",
    "random_quat",
    "rpy_to_matrix",
    "rpy_to_quat",
]

FloatArray = NDArray[np.float64]

IDENTITY_QUAT: FloatArray = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float64)
IDENTITY_QUAT.setflags(write=False)
# How far the norm of a quaternion a user wrote (in a grammar or a scene file) may be from 1:
# printed values keep a few digits, so "unit" means unit to about three of them.
QUAT_NORM_TOL = 1e-3


# --------------------------------------------------------------------------- input checks


def _as_last_dim(x: ArrayLike, size: int, what: str) -> FloatArray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != size:
        raise ValueError(f"{what} must have shape (..., {size}), got {arr.shape}")
    return arr


def _as_quat(q: ArrayLike) -> FloatArray:
    return _as_last_dim(q, 4, "quaternion")


def _as_vec3(v: ArrayLike, what: str = "vector") -> FloatArray:
    return _as_last_dim(v, 3, what)


def _as_mat3(m: ArrayLike) -> FloatArray:
    arr = np.asarray(m, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrix must have shape (..., 3, 3), got {arr.shape}")
    return arr


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    # Written out by component so that broadcasting follows the same rules as the
    # rest of the module (np.cross has its own axis conventions).
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


# --------------------------------------------------------------------------- algebra


def quat_multiply(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Hamilton product ``a ⊗ b``: rotating by ``b`` first, then by ``a``."""
    a = _as_quat(a)
    b = _as_quat(b)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conjugate(q: ArrayLike) -> FloatArray:
    """Conjugate; equals the inverse rotation for unit quaternions."""
    q = _as_quat(q)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: ArrayLike) -> FloatArray:
    """Project onto the unit sphere, e.g. to undo drift after many products.

    Raises ``ValueError`` on a zero quaternion, which has no rotation to recover.
    """
    q = _as_quat(q)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm == 0.0):
        raise ValueError("cannot normalise a zero quaternion")
    return q / norm


def quat_canonical(q: ArrayLike) -> FloatArray:
    """Pick the sign of ``q`` so that equal rotations get identical output.

    ``q`` and ``-q`` are the same rotation; the representative chosen has ``w > 0``,
    or, when ``w == 0`` exactly, a positive first nonzero of ``x, y, z``. Negative
    zeros are turned into ``+0.0`` so written files do not show ``-0.0``.
    """
    q = _as_quat(q)
    nonzero = q != 0.0
    first = np.argmax(nonzero, axis=-1)[..., None]  # index 0 (w) when w != 0
    lead = np.take_along_axis(q, first, axis=-1)
    sign = np.where(lead < 0.0, -1.0, 1.0)
    return q * sign + 0.0


def quat_relative(q_parent: ArrayLike, q_child: ArrayLike) -> FloatArray:
    """``conj(q_parent) ⊗ q_child``: the child's orientation in the parent's frame."""
    return quat_multiply(quat_conjugate(q_parent), q_child)


def quat_rotate(q: ArrayLike, v: ArrayLike) -> FloatArray:
    """Rotate vectors ``v`` by unit quaternions ``q`` (same result as the matrix)."""
    q = _as_quat(q)
    v = _as_vec3(v)
    w = q[..., :1]
    u = q[..., 1:]
    # v' = v + w t + u x t with t = 2 u x v: cheaper than q v q* and exact for unit q.
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def quat_between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Unit quaternions of the shortest turns taking each vector ``a`` onto the direction of
    ``b`` (``(..., 3)``, broadcast; neither need be unit, a zero vector gives the identity).

    Aligned vectors give the identity; opposite ones a half turn about an axis perpendicular
    to ``a``: the direction of ``a × x̂``, or of ``a × ŷ`` where ``|a_x| >= 0.9 |a|``.
    """
    a, b = np.broadcast_arrays(_as_vec3(a), _as_vec3(b))
    a = a / _nonzero_norm(a)
    b = b / _nonzero_norm(b)
    w = 1.0 + np.sum(a * b, axis=-1, keepdims=True)
    other = np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    opposite = w < 1e-12
    q = np.where(
        opposite,
        np.concatenate([np.zeros_like(w), _cross(a, other)], axis=-1),
        np.concatenate([w, _cross(a, b)], axis=-1),
    )
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _nonzero_norm(v: FloatArray) -> FloatArray:
    """The norms of vectors ``v`` (kept dims), 1 where a vector is zero."""
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(norm > 0.0, norm, 1.0)


def quat_angle(q1: ArrayLike, q2: ArrayLike) -> FloatArray:
    """Geodesic distance in ``[0, π]`` between two rotations, ignoring quaternion sign.

    Uses ``atan2`` of the vector and scalar parts of the relative quaternion, which
    stays accurate for tiny angles where ``arccos`` of a dot product loses digits.
    """
    d = quat_relative(q1, q2)
    vec_norm = np.linalg.norm(d[..., 1:], axis=-1)
    return 2.0 * np.arctan2(vec_norm, np.abs(d[..., 0]))


def is_unit_quat(q: ArrayLike, tol: float = 1e-6) -> NDArray[np.bool_]:
    """Check the unit-norm precondition that most functions here rely on."""
    q = _as_quat(q)
    return np.abs(np.linalg.norm(q, axis=-1) - 1.0) <= tol


# --------------------------------------------------------------------------- matrices


def quat_to_matrix(q: ArrayLike) -> FloatArray:
    """Rotation matrix of a unit quaternion, acting on column vectors."""
    q = _as_quat(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        1.0 - 2.0 * (yy + zz),
        2.0 * (xy - wz),
        2.0 * (xz + wy),
        2.0 * (xy + wz),
        1.0 - 2.0 * (xx + zz),
        2.0 * (yz - wx),
        2.0 * (xz - wy),
        2.0 * (yz + wx),
        1.0 - 2.0 * (xx + yy),
    ]
    return np.stack(rows, axis=-1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(R: ArrayLike) -> FloatArray:
    """Canonical unit quaternion of a rotation matrix (Shepperd's method).

    Each of ``4w², 4x², 4y², 4z²`` can be read off the diagonal; dividing by the
    largest of them keeps the result accurate for every rotation, including those
    near 180° where the naive ``w``-based formula divides by almost zero. Slightly
    non-orthonormal input is tolerated: the result is normalised.
    """
    R = _as_mat3(R)
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]

    tw = 1.0 + r00 + r11 + r22  # 4 w²
    tx = 1.0 + r00 - r11 - r22  # 4 x²
    ty = 1.0 - r00 + r11 - r22  # 4 y²
    tz = 1.0 - r00 - r11 + r22  # 4 z²

    # Row k is the quaternion scaled by 4 * q_k; all four rows agree up to scale
    # for an exact rotation, and the row with the largest t_k is best conditioned.
    s_x = r21 - r12  # 4 w x
    s_y = r02 - r20  # 4 w y
    s_z = r10 - r01  # 4 w z
    p_xy = r01 + r10  # 4 x y
    p_xz = r02 + r20  # 4 x z
    p_yz = r12 + r21  # 4 y z
    candidates = np.stack(
        [
            np.stack([tw, s_x, s_y, s_z], axis=-1),
            np.stack([s_x, tx, p_xy, p_xz], axis=-1),
            np.stack([s_y, p_xy, ty, p_yz], axis=-1),
            np.stack([s_z, p_xz, p_yz, tz], axis=-1),
        ],
        axis=-2,
    )  # (..., 4, 4)
    best = np.argmax(np.stack([tw, tx, ty, tz], axis=-1), axis=-1)
    q = np.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return quat_canonical(q)


# --------------------------------------------------------------------------- roll-pitch-yaw


def rpy_to_matrix(rpy: ArrayLike) -> FloatArray:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (Drake's fixed-axis X-Y-Z convention)."""
    rpy = _as_vec3(rpy, "rpy")
    cr, cp, cy = np.cos(rpy[..., 0]), np.cos(rpy[..., 1]), np.cos(rpy[..., 2])
    sr, sp, sy = np.sin(rpy[..., 0]), np.sin(rpy[..., 1]), np.sin(rpy[..., 2])
    rows = [
        cy * cp,
        cy * sp * sr - sy * cr,
        cy * sp * cr + sy * sr,
        sy * cp,
        sy * sp * sr + cy * cr,
        sy * sp * cr - cy * sr,
        -sp,
        cp * sr,
        cp * cr,
    ]
    return np.stack(rows, axis=-1).reshape(*rpy.shape[:-1], 3, 3)


def rpy_to_quat(rpy: ArrayLike) -> FloatArray:
    """Quaternion ``qz(yaw) ⊗ qy(pitch) ⊗ qx(roll)`` for Drake-style roll-pitch-yaw.

    Not canonicalised, so the output varies smoothly with the angles; apply
    :func:`quat_canonical` before writing it out.
    """
    rpy = _as_vec3(rpy, "rpy")
    half = 0.5 * rpy
    cr, cp, cy = np.cos(half[..., 0]), np.cos(half[..., 1]), np.cos(half[..., 2])
    sr, sp, sy = np.sin(half[..., 0]), np.sin(half[..., 1]), np.sin(half[..., 2])
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def quat_to_rpy(q: ArrayLike) -> FloatArray:
    """Drake-style roll-pitch-yaw with roll, yaw in ``[-π, π]`` and pitch in ``[-π/2, π/2]``.

    Yaw is derived from roll and the full matrix rather than from the first column
    alone, so at gimbal lock (pitch = ±π/2), where only roll ∓ yaw is defined, the
    returned angles still reproduce the rotation exactly.
    """
    R = quat_to_matrix(q)
    r01, r02 = R[..., 0, 1], R[..., 0, 2]
    r11, r12 = R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]

    roll = np.arctan2(r21, r22)
    pitch = np.arctan2(-r20, np.hypot(r21, r22))
    # Columns of R @ Rx(roll)^T equal Rz(yaw) @ Ry(pitch); its middle column is
    # (-sin yaw, cos yaw, 0).
    cr, sr = np.cos(roll), np.sin(roll)
    yaw = np.arctan2(sr * r02 - cr * r01, cr * r11 - sr * r12)
    return np.stack([roll, pitch, yaw], axis=-1)


# --------------------------------------------------------------------------- axis-angle


def axis_angle_to_quat(axis: ArrayLike, angle: ArrayLike) -> FloatArray:
    """Rotation by ``angle`` radians (right-hand rule) about ``axis``.

    The axis is normalised here because grammars often write it unnormalised
    (e.g. ``[1, 1, 0]``); a zero axis raises ``ValueError``. The output is not
    canonicalised, so angles beyond π give ``w < 0``.
    """
    axis = _as_vec3(axis, "axis")
    angle = np.asarray(angle, dtype=np.float64)
    norm = np.linalg.norm(axis, axis=-1, keepdims=True)
    if np.any(norm == 0.0):
        raise ValueError("rotation axis must be nonzero")
    half = 0.5 * angle
    w = np.cos(half)
    xyz = (axis / norm) * np.sin(half)[..., None]
    w, xyz = np.broadcast_arrays(w[..., None], xyz)
    return np.concatenate([w[..., :1], xyz], axis=-1)


def quat_to_axis_angle(q: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Unit axis and angle in ``[0, π]`` (the canonical sign is taken first).

    For the identity the axis is undefined; ``+x`` is returned so the output is
    always a valid unit vector.
    """
    q = quat_canonical(q)
    vec = q[..., 1:]
    vec_norm = np.linalg.norm(vec, axis=-1)
    angle = 2.0 * np.arctan2(vec_norm, q[..., 0])
    # Scale by the largest component before normalising: for angles near 1e-160 the squares
    # in the norm underflow and the axis would come out visibly non-unit.
    peak = np.max(np.abs(vec), axis=-1)
    zero = peak == 0.0
    scaled = vec / np.where(zero, 1.0, peak)[..., None]
    axis = scaled / np.linalg.norm(scaled, axis=-1, keepdims=True).clip(min=1.0)
    axis = np.where(zero[..., None], np.array([1.0, 0.0, 0.0]), axis)
    return axis, angle


# --------------------------------------------------------------------------- sampling


def random_quat(rng: np.random.Generator, n: int) -> FloatArray:
    """``n`` Haar-uniform rotations via Shoemake's subgroup algorithm, shape ``(n, 4)``.

    Uniform over SO(3) (not merely over Euler angles), which is what an
    "uninformative" orientation prior must mean. Signs are left as drawn.
    """
    if n < 0:
        raise ValueError(f"n must be non-negative, got {n}")
    u1, u2, u3 = rng.random((3, n))
    r1 = np.sqrt(1.0 - u1)
    r2 = np.sqrt(u1)
    theta1 = 2.0 * np.pi * u2
    theta2 = 2.0 * np.pi * u3
    return np.stack(
        [r2 * np.cos(theta2), r1 * np.sin(theta1), r1 * np.cos(theta1), r2 * np.sin(theta2)],
        axis=-1,
    )


# ------------------------------------------------- profiles of solids of revolution ---
# A `revolve` geometry's (r, z) cross-section (ssgc/constraints/revolved.py); here, below the
# grammar language that validates it (ssgc/dsl.py).


def profile_problem(profile: list[list[float]]) -> str | None:
    """Why a `revolve` profile is not a solid's cross-section, or None when it is: at least
    three points, each [r, z] with r >= 0, the first and last on the axis (r = 0) and no others,
    edges that do not cross, and a non-zero area."""
    p = np.asarray(profile, float)
    with np.errstate(all="ignore"):  # huge coordinates overflow to a clear message below
        return _problem(p)


def _problem(p: FloatArray) -> str | None:
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
        return "a profile is a list of at least three [r, z] points"
    if np.any(p[:, 0] < 0):
        return "every r of a profile is >= 0 (the axis is r = 0)"
    if p[0, 0] != 0 or p[-1, 0] != 0:
        return "a profile starts and ends on the axis (r = 0), going around the material"
    if np.any(p[1:-1, 0] == 0):
        return "only a profile's first and last points lie on the axis (r = 0)"
    if not abs(profile_area(p)) >= 1e-12:  # also when it overflows to nan
        return "a profile encloses no area"
    if _crossing(p):
        return "a profile's edges cross each other"
    return None


def profile_area(p: FloatArray) -> float:
    """Signed area of a closed (r, z) polygon (positive counter-clockwise)."""
    r, z = p[:, 0], p[:, 1]
    return float(0.5 * np.sum(r * np.roll(z, -1) - np.roll(r, -1) * z))


def _crossing(p: FloatArray) -> bool:
    """Whether two non-adjacent edges of the closed polygon (the axis closes it) properly
    cross."""
    a, b = p, np.roll(p, -1, axis=0)
    n = len(p)
    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))  # the closing edge meets the first one
    i, j = i[keep], j[keep]

    def side(o: FloatArray, x: FloatArray, y: FloatArray) -> FloatArray:
        return (x[:, 0] - o[:, 0]) * (y[:, 1] - o[:, 1]) - (x[:, 1] - o[:, 1]) * (y[:, 0] - o[:, 0])

    d1, d2 = side(a[j], b[j], a[i]), side(a[j], b[j], b[i])
    d3, d4 = side(a[i], b[i], a[j]), side(a[i], b[i], b[j])
    return bool(np.any((d1 * d2 < 0) & (d3 * d4 < 0)))
