"""The compiled grammar: an immutable intermediate representation.

`ssgc.compile` produces a `Grammar` from a validated document; samplers, the scorer, and later
the parser and the fitter only ever read this.  Types and rules have integer ids; every rule's
parameters exist twice, as distribution objects (for sampling and fitting) and stacked into the
numpy `Tables` (for vectorised scoring over many edges at once).  Both are derived from the same
numbers at compile time, and every parameter keeps the document path it came from so that
fitted values can be written back into the user's YAML.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.distributions.bingham import Bingham
from ssgc.distributions.discrete import CountLaw
from ssgc.distributions.normal import Normal
from ssgc.distributions.uniform import UNIFORM_SO3_LOG_DENSITY, UniformBox, UniformRevolute
from ssgc.errors import Diagnostic

Loc = tuple[str | int, ...]
LOG_2 = float(np.log(2.0))


class Kind(IntEnum):
    """How a node type chooses which of its rules fire (thesis 2.3.1)."""

    TERMINAL = 0
    AND = 1
    OR = 2
    INDEPENDENT = 3
    REPEAT = 4


class TKind(IntEnum):
    """Translation part of a rule (thesis Table 2.1)."""

    FIXED = 0  # `same` (zero offset) or a fixed offset in the parent frame
    WORLD_NORMAL = 1
    WORLD_NORMAL_OFFSET = 2
    PARENT_NORMAL_OFFSET = 3
    WORLD_BOX = 4
    WORLD_BOX_OFFSET = 5


class RKind(IntEnum):
    """Rotation part of a rule (thesis Table 2.1)."""

    FIXED = 0  # `same` or a fixed rotation offset in the parent frame
    UNIFORM = 1
    WORLD_BINGHAM = 2
    PARENT_BINGHAM = 3
    REVOLUTE = 4


NORMAL_KINDS = (TKind.WORLD_NORMAL, TKind.WORLD_NORMAL_OFFSET, TKind.PARENT_NORMAL_OFFSET)
BOX_KINDS = (TKind.WORLD_BOX, TKind.WORLD_BOX_OFFSET)
BINGHAM_KINDS = (RKind.WORLD_BINGHAM, RKind.PARENT_BINGHAM)


@dataclass(frozen=True)
class TranslationPart:
    kind: TKind
    offset: NDArray[np.float64]  # FIXED: the offset; Normal kinds: the full 3-D mean
    free: NDArray[np.bool_]  # axes with a density; the others are pinned at `offset`
    normal: Normal | None = None  # over the free axes only
    box: UniformBox | None = None
    fixed: bool = False
    path: Loc = ()
    family: str = ""  # Normal kinds: "isotropic", "diagonal" or "full", as written (for fitting)


@dataclass(frozen=True)
class RotationPart:
    kind: RKind
    offset: NDArray[np.float64]  # FIXED: the offset quaternion (wxyz)
    bingham: Bingham | None = None
    axis: NDArray[np.float64] | None = None  # REVOLUTE, unit
    revolute: UniformRevolute | None = None
    fixed: bool = False
    path: Loc = ()
    family: str = ""  # Bingham kinds: "isotropic", "axes" (mode + 3 concentrations) or "raw"


@dataclass(frozen=True)
class Rule:
    id: int
    parent: int
    index: int  # position in the parent's rule list
    child: int
    translation: TranslationPart
    rotation: RotationPart
    path: Loc = ()


@dataclass(frozen=True)
class NodeType:
    id: int
    name: str
    kind: Kind
    observed: bool
    rules: tuple[int, ...]
    probs: NDArray[np.float64]  # OR: normalised weights; INDEPENDENT: firing probabilities
    count: CountLaw | None = None  # REPEAT only
    max_nesting: int | None = None
    geometry: Any = None  # the validated dsl geometry (primitive or mesh), for export
    model: str | None = None
    body: Any = None  # the validated dsl body (static, mass or density, collision), for export
    labels: tuple[str, ...] = ()
    fixed: bool = False
    path: Loc = ()
    count_family: str = ""  # REPEAT: "geometric" or "probs", as written (for fitting)
    count_start: int = 0  # REPEAT, geometric: the smallest count


@dataclass(frozen=True)
class Tables:
    """Rule and type parameters stacked into arrays, indexed by rule id / type id."""

    rule_parent: NDArray[np.int64]
    rule_child: NDArray[np.int64]
    rule_index: NDArray[np.int64]
    t_kind: NDArray[np.int64]
    t_offset: NDArray[np.float64]  # (R, 3)
    t_free: NDArray[np.bool_]  # (R, 3)
    t_chol: NDArray[np.float64]  # (R, 3, 3) Cholesky factor embedded at the free axes
    t_whiten: NDArray[np.float64]  # (R, 3, 3) its inverse, embedded the same way
    t_lognorm: NDArray[np.float64]  # (R,) Normal: log normaliser; box: log volume of free axes
    box_lo: NDArray[np.float64]
    box_hi: NDArray[np.float64]
    r_kind: NDArray[np.int64]
    r_offset: NDArray[np.float64]  # (R, 4)
    r_quadratic: NDArray[np.float64]  # (R, 4, 4) Bingham M diag(Z) M^T
    r_lognorm: NDArray[np.float64]  # (R,) minus the log density's constant term on SO(3)
    r_axis: NDArray[np.float64]  # (R, 3)
    r_lo: NDArray[np.float64]
    r_hi: NDArray[np.float64]
    type_kind: NDArray[np.int64]
    type_observed: NDArray[np.bool_]
    type_rules: NDArray[np.int64]  # (T, K) rule ids, -1 padded
    type_logp: NDArray[np.float64]  # (T, K) OR: log weight; INDEPENDENT: log p
    type_log1mp: NDArray[np.float64]  # (T, K) INDEPENDENT: log(1 - p)
    count_logp: NDArray[np.float64]  # (T, C) REPEAT: log P(count = n), -inf padded
    count_max: NDArray[np.int64]  # (T,)
    nesting_slot: NDArray[np.int64]  # (T,) slot of a bounded type, -1 for unbounded types
    nesting_max: NDArray[np.int64]  # (B,)


@dataclass(frozen=True)
class Grammar:
    name: str
    file: str
    types: tuple[NodeType, ...]
    rules: tuple[Rule, ...]
    root: int
    root_xyz: NDArray[np.float64]
    root_quat: NDArray[np.float64]
    tables: Tables
    warnings: tuple[Diagnostic, ...] = ()
    type_ids: dict[str, int] = field(default_factory=dict)

    def type_id(self, name: str) -> int:
        return self.type_ids[name]

    def rule_name(self, rule_id: int) -> str:
        rule = self.rules[rule_id]
        return f"{self.types[rule.parent].name}[{rule.index}]->{self.types[rule.child].name}"

    @property
    def observed_types(self) -> list[NodeType]:
        return [t for t in self.types if t.observed]


def _frozen(a: Any, dtype: Any = np.float64) -> NDArray[Any]:
    out = np.array(a, dtype=dtype)
    out.flags.writeable = False
    return out


def build_tables(types: tuple[NodeType, ...], rules: tuple[Rule, ...]) -> Tables:
    """Stack per-rule and per-type parameters so the scorer can work on all edges at once."""
    n_rules, n_types = len(rules), len(types)
    t_kind = np.zeros(n_rules, np.int64)
    t_offset = np.zeros((n_rules, 3))
    t_free = np.zeros((n_rules, 3), bool)
    t_chol = np.zeros((n_rules, 3, 3))
    t_whiten = np.zeros((n_rules, 3, 3))
    t_lognorm = np.zeros(n_rules)
    box_lo = np.zeros((n_rules, 3))
    box_hi = np.zeros((n_rules, 3))
    r_kind = np.zeros(n_rules, np.int64)
    r_offset = np.tile([1.0, 0, 0, 0], (n_rules, 1))
    r_quadratic = np.zeros((n_rules, 4, 4))
    r_lognorm = np.zeros(n_rules)
    r_axis = np.tile([0.0, 0, 1], (n_rules, 1))
    r_lo = np.zeros(n_rules)
    r_hi = np.zeros(n_rules)
    for r in rules:
        t, rot = r.translation, r.rotation
        t_kind[r.id], t_offset[r.id], t_free[r.id] = t.kind, t.offset, t.free
        if t.normal is not None:
            free = np.flatnonzero(t.free)
            t_chol[r.id][np.ix_(free, free)] = t.normal.chol
            t_whiten[r.id][np.ix_(free, free)] = np.linalg.inv(t.normal.chol)
            t_lognorm[r.id] = -t.normal.log_normalizer  # Normal stores the log density at its mean
        if t.box is not None:
            box_lo[r.id], box_hi[r.id] = t.box.lo, t.box.hi
            free = t.box.free_axes
            t_lognorm[r.id] = float(np.sum(np.log(t.box.hi[free] - t.box.lo[free])))
        r_kind[r.id], r_offset[r.id] = rot.kind, rot.offset
        if rot.bingham is not None:
            m, z = rot.bingham.M, rot.bingham.Z
            r_quadratic[r.id] = m @ np.diag(z) @ m.T
            # SO(3) is the unit quaternions with q ~ -q: its density is twice the S^3 one.
            r_lognorm[r.id] = rot.bingham.log_normalizer - LOG_2
        elif rot.kind == RKind.UNIFORM:
            r_lognorm[r.id] = -UNIFORM_SO3_LOG_DENSITY
        elif rot.revolute is not None:
            r_axis[r.id] = rot.axis
            r_lo[r.id], r_hi[r.id] = rot.revolute.lo, rot.revolute.hi
            r_lognorm[r.id] = float(np.log(rot.revolute.hi - rot.revolute.lo))

    width = max([len(t.rules) for t in types] + [1])
    count_width = max([t.count.max_count + 1 for t in types if t.count is not None] + [1])
    type_rules = np.full((n_types, width), -1, np.int64)
    type_logp = np.full((n_types, width), -np.inf)
    type_log1mp = np.full((n_types, width), -np.inf)
    count_logp = np.full((n_types, count_width), -np.inf)
    count_max = np.full(n_types, -1, np.int64)
    bounded = [t.id for t in types if t.max_nesting is not None]
    nesting_slot = np.full(n_types, -1, np.int64)
    nesting_slot[bounded] = np.arange(len(bounded))
    with np.errstate(divide="ignore"):
        for t in types:
            k = len(t.rules)
            type_rules[t.id, :k] = t.rules
            if t.kind in (Kind.OR, Kind.INDEPENDENT):
                type_logp[t.id, :k] = np.log(t.probs)
                type_log1mp[t.id, :k] = np.log1p(-t.probs)
            if t.count is not None:
                count_logp[t.id, : t.count.max_count + 1] = t.count.log_probs
                count_max[t.id] = t.count.max_count
    arrays = dict(
        rule_parent=np.array([r.parent for r in rules], np.int64).reshape(n_rules),
        rule_child=np.array([r.child for r in rules], np.int64).reshape(n_rules),
        rule_index=np.array([r.index for r in rules], np.int64).reshape(n_rules),
        t_kind=t_kind,
        t_offset=t_offset,
        t_free=t_free,
        t_chol=t_chol,
        t_whiten=t_whiten,
        t_lognorm=t_lognorm,
        box_lo=box_lo,
        box_hi=box_hi,
        r_kind=r_kind,
        r_offset=r_offset,
        r_quadratic=r_quadratic,
        r_lognorm=r_lognorm,
        r_axis=r_axis,
        r_lo=r_lo,
        r_hi=r_hi,
        type_kind=np.array([t.kind for t in types], np.int64),
        type_observed=np.array([t.observed for t in types], bool),
        type_rules=type_rules,
        type_logp=type_logp,
        type_log1mp=type_log1mp,
        count_logp=count_logp,
        count_max=count_max,
        nesting_slot=nesting_slot,
        nesting_max=np.array([types[i].max_nesting for i in bounded], np.int64).reshape(-1),
    )
    return Tables(**{k: _frozen(v, v.dtype) for k, v in arrays.items()})
