"""Bingham rotations (`world_bingham`, `parent_bingham`): the density exp(qᵀ M diag(Z) Mᵀ q)
on unit quaternions (`ssgc.distributions.bingham`), counted twice on SO(3) since q and -q are
one rotation.

It is written one of three ways, and the fit keeps the way it was written: a mode with one
concentration (isotropic), a mode with three (one per axis), or the raw `M` and `Z`.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import Enum
from typing import Any, ClassVar

import numpy as np

from ssgc import dsl
from ssgc.distributions.bingham import ORTHOGONALITY_TOL, Bingham
from ssgc.geometry import IDENTITY_QUAT, quat_angle, quat_to_matrix
from ssgc.laws.base import (
    LOG_2,
    Columns,
    Context,
    Deviation,
    FitSettings,
    FloatArray,
    Frame,
    Loc,
    Lowering,
    Orientation,
    RotationLaw,
    percent,
    register,
)

MAX_CONCENTRATION = 1e4


class Form(Enum):
    """Mode and concentrations, or the raw matrices: the fit keeps the one written."""

    ISOTROPIC = "mode, concentration: number"
    AXES = "mode, concentration: [x, y, z]"
    RAW = "M, Z"


@register
class BinghamRotation(RotationLaw):
    keys: ClassVar[dict[str, Frame]] = {
        "world_bingham": Frame.WORLD,
        "parent_bingham": Frame.PARENT,
    }
    columns: ClassVar[dict[str, tuple[int, ...]]] = {"quadratic": (4, 4), "lognorm": ()}

    bingham: Bingham
    form: Form

    @classmethod
    def lower(
        cls, p: dsl.BinghamParams, key: str, loc: Loc, ctx: Lowering
    ) -> BinghamRotation | None:
        bingham = _raw(p, loc, ctx) if p.M is not None and p.Z is not None else _moded(p, loc, ctx)
        if bingham is None:
            return None
        if p.M is not None:
            form = Form.RAW
        else:
            form = Form.AXES if isinstance(p.concentration, list) else Form.ISOTROPIC
        return cls(
            key=key, frame=cls.keys[key], path=loc, fixed=p.fixed, bingham=bingham, form=form
        )

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        q = self.bingham.sample(rng, n)
        return q, self.bingham.log_prob(q) + LOG_2

    def quadratic(self) -> FloatArray:
        """A = M diag(Z) Mᵀ: the log-density is qᵀ A q - lognorm."""
        m, z = self.bingham.M, self.bingham.Z
        return m @ np.diag(z) @ m.T

    @property
    def lognorm(self) -> float:
        """Minus the log-density's constant term on SO(3): the unit quaternions with q ~ -q,
        where the density is twice the one on S³."""
        return self.bingham.log_normalizer - LOG_2

    def concave_form(self) -> tuple[FloatArray, float]:
        return self.quadratic(), -self.lognorm

    def row(self) -> dict[str, Any]:
        return {"quadratic": self.quadratic(), "lognorm": self.lognorm}

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        return np.einsum("ni,nij,nj->n", u, cols["quadratic"], u) - cols["lognorm"]

    def mode(self) -> FloatArray:
        w, v = np.linalg.eigh(self.quadratic())
        return v[:, int(np.argmax(w))]

    def supremum(self) -> float:
        return float(np.linalg.eigvalsh(self.quadratic()).max() - self.lognorm)

    def fit(self, u: FloatArray, w: FloatArray, settings: FitSettings) -> dict[str, object] | None:
        cap = settings.max_concentration
        if self.form == Form.RAW:
            fit = Bingham.fit(u, w, max_concentration=cap)
            return {
                "M": [[float(x) for x in row] for row in fit.M],
                "Z": [float(z) for z in fit.Z],
            }
        isotropic = self.form == Form.ISOTROPIC
        mode, conc = Bingham.fit_about_mode(u, w, self.bingham.mode, isotropic, cap)
        value: float | list[float] = float(conc[0]) if isotropic else [float(c) for c in conc]
        return {"mode": Orientation(tuple(float(x) for x in mode)), "concentration": value}

    def nearest_mode(self, u: FloatArray) -> FloatArray:
        """The most likely rotation closest to `u`: its projection on the top eigenspace of
        the quadratic form (the mode itself, or the circle of modes of a free turn)."""
        w, v = np.linalg.eigh(self.quadratic())
        top = v[:, w >= w.max() - 1e-9 * max(1.0, abs(w).max())]
        q = top @ (top.T @ u)
        n = float(np.linalg.norm(q))
        return self.mode() if n < 1e-9 else q / n

    def describe_deviation(self, u: FloatArray, log_prob: float, ctx: Context) -> Deviation:
        """The angle to the nearest most likely rotation; "upside down" when the body z axis
        points away from that rotation's; the share of draws no more likely."""
        near = self.nearest_mode(u)
        angle = float(np.degrees(quat_angle(u, near)))
        flipped = float(np.dot(quat_to_matrix(u)[:, 2], quat_to_matrix(near)[:, 2])) < 0
        likely = ctx.percentile(log_prob)
        how = "upside down, " if flipped else ""
        return Deviation(
            f"rotation: {how}{angle:.0f}° from the most likely, {percent(likely)} likely",
            None,
            likely,
        )

    def describe(self) -> str:
        conc = np.round(self.bingham.concentration, 3).tolist()
        return f"{self.key} mode {np.round(self.bingham.mode, 3).tolist()} conc {conc}"


def _raw(p: dsl.BinghamParams, loc: Loc, ctx: Lowering) -> Bingham | None:
    """`M` and `Z` are checked apart, so one run reports a mistake in each."""
    m = np.asarray(p.M, float)
    with np.errstate(all="ignore"):
        err = np.abs(m.T @ m - np.eye(4)).max()
    orthogonal = bool(err <= ORTHOGONALITY_TOL)  # NaN (overflow) is not orthogonal either
    if not orthogonal:
        ctx.error((*loc, "M"), f"Bingham M must be orthogonal (max |MᵀM - I| = {err:.2g})")
    z = np.asarray(p.Z, float)
    spread = z.max() - z.min()
    if spread > MAX_CONCENTRATION:
        ctx.error(
            (*loc, "Z"), f"Bingham Z spans {spread:g}, over the supported {MAX_CONCENTRATION:g}"
        )
    if not orthogonal or spread > MAX_CONCENTRATION:
        return None
    return _checked(lambda: Bingham(m, z), (*loc, "M"), ctx)


def _moded(p: dsl.BinghamParams, loc: Loc, ctx: Lowering) -> Bingham | None:
    """The concentrations and the mode are checked apart, so one run reports both; each
    concentration over the limit is named at its own number."""
    conc = np.broadcast_to(np.asarray(p.concentration, float), (3,))
    over = np.flatnonzero(conc > MAX_CONCENTRATION)
    listed = isinstance(p.concentration, list)
    for i in over if listed else over[:1]:
        ctx.error(
            (*loc, "concentration", int(i)) if listed else (*loc, "concentration"),
            f"concentration must be at most {MAX_CONCENTRATION:g}, got {conc[i]:.10g}",
        )
    mode = ctx.orientation(p.mode, (*loc, "mode")) if p.mode else IDENTITY_QUAT
    if over.size:
        return None
    return _checked(lambda: Bingham.from_mode(mode, conc), loc, ctx)


def _checked(make: Callable[[], Bingham], loc: Loc, ctx: Lowering) -> Bingham | None:
    """`make()`, with the distribution's own checks reported as located errors."""
    try:
        return make()
    except (ValueError, np.linalg.LinAlgError) as exc:
        ctx.error(loc, f"invalid Bingham parameters: {exc}")
        return None
