"""The compiled grammar: an immutable intermediate representation.

`ssgc.compile` produces a `Grammar` from a validated document; the sampler, the scorer, the
parser and the fitter only ever read this.  Types and rules have integer ids; a rule places its
child by two laws (`ssgc.laws`: a translation and a rotation law, each in its frame), whose
parameters are also stacked into the numpy `Tables` for vectorised scoring over many edges at
once.  Both come from the same numbers at compile time, and every law keeps the document path
it came from so that fitted values can be written back into the user's YAML.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import Diagnostic
from ssgc.laws.base import PartTable, RotationLaw, TranslationLaw, frozen
from ssgc.laws.counts import RepeatCount

Loc = tuple[str | int, ...]


class Kind(IntEnum):
    """How a node type chooses which of its rules fire (thesis 2.3.1)."""

    TERMINAL = 0
    AND = 1
    OR = 2
    INDEPENDENT = 3
    REPEAT = 4


@dataclass(frozen=True)
class Rule:
    id: int
    parent: int
    index: int  # position in the parent's rule list
    child: int
    translation: TranslationLaw  # a law, its frame, and where it was written
    rotation: RotationLaw
    path: Loc = ()


@dataclass(frozen=True)
class NodeType:
    id: int
    name: str
    kind: Kind
    observed: bool
    rules: tuple[int, ...]
    probs: NDArray[np.float64]  # OR: normalised weights; INDEPENDENT: firing probabilities
    count: RepeatCount | None = None  # REPEAT only
    max_nesting: int | None = None
    geometry: Any = None  # the validated dsl geometry (primitive or mesh), for export
    model: str | None = None
    body: Any = None  # the validated dsl body (static, mass or density, collision), for export
    labels: tuple[str, ...] = ()
    fixed: bool = False
    path: Loc = ()
    # "" for a type of the document; else what the observation model added it for
    # (`ssgc.observation`): "scene" (the new root), "node" (an observed root's own node),
    # "clutter" (the clutter set and its placement)
    synthetic: str = ""

    def never_fires(self, index: int) -> bool:
        """Whether this type's rule `index` can never fire: an `or` rule of weight 0, an
        `independent` rule of probability 0.  The supertree leaves such rules out, so an `or`
        whose every rule of positive weight is blocked makes nothing (docs/grammar.md 3.4)."""
        return self.kind in (Kind.OR, Kind.INDEPENDENT) and not self.probs[index] > 0

    def can_hold_nothing(self, kids: list[tuple[int, bool]]) -> bool:
        """Whether a node of this type can be in a tree with no observed node at or below it
        (unseen: `ssgc.score`), given (rule index, whether its child can) for each rule that
        fires here.  The one recurrence behind the parser's `supertree.hideable_nodes` (per
        supertree node) and the scorer's `score._maybe_unseen` (per type): `least_observed`
        with children that hold 0 or at least 1."""
        return self.least_observed([(i, 0 if can else 1) for i, can in kids]) == 0

    def least_observed(self, kids: list[tuple[int, int]]) -> int:
        """The fewest observed nodes a node of this type holds, itself included, given (rule
        index, the fewest its child holds) for each rule that fires here.  AND: every child's;
        OR: the least child's (0 when no rule fires); `independent`: the rules of p = 1;
        `repeat`: the least possible count times its child's; a latent terminal holds none.
        `explain` iterates it over types for the count a law demands."""
        live = [least for i, least in kids if not self.never_fires(i)]
        if self.kind == Kind.AND:
            below = sum(live)
        elif self.kind == Kind.OR:
            below = min(live, default=0)
        elif self.kind == Kind.INDEPENDENT:
            below = sum(
                least for i, least in kids if not self.never_fires(i) and self.probs[i] >= 1.0
            )
        elif self.kind == Kind.REPEAT and self.count is not None:
            below = int(np.argmax(np.asarray(self.count.probs) > 0)) * min(live, default=0)
        else:  # a terminal, or a repeat without a count law (it may make none)
            below = 0
        return int(self.observed) + below


@dataclass(frozen=True)
class Tables:
    """Rule and type parameters stacked into arrays, indexed by rule id / type id.

    A rule's translation and rotation laws are stacked in `translation` and `rotation`; their
    columns read as attributes too: `t_kind` / `r_kind` is the law (an index into the part's
    `laws`), `t_frame` / `r_frame` the frame, and `t_<c>` / `r_<c>` a column a law declares
    (`r_quadratic`, `t_lognorm`, ...).
    """

    rule_parent: NDArray[np.int64]
    rule_child: NDArray[np.int64]
    rule_index: NDArray[np.int64]
    translation: PartTable
    rotation: PartTable
    point: NDArray[np.bool_]  # (R,) both laws are point masses: the child's pose is fixed
    point_xyz: NDArray[np.float64]  # (R, 3) its offset in the parent's frame
    point_quat: NDArray[np.float64]  # (R, 4)
    type_kind: NDArray[np.int64]
    type_observed: NDArray[np.bool_]
    type_rules: NDArray[np.int64]  # (T, K) rule ids, -1 padded
    type_logp: NDArray[np.float64]  # (T, K) OR: log weight; INDEPENDENT: log p
    type_log1mp: NDArray[np.float64]  # (T, K) INDEPENDENT: log(1 - p)
    count_logp: NDArray[np.float64]  # (T, C) REPEAT: log P(count = n), -inf padded
    count_max: NDArray[np.int64]  # (T,)
    nesting_slot: NDArray[np.int64]  # (T,) slot of a bounded type, -1 for unbounded types
    nesting_max: NDArray[np.int64]  # (B,)

    def __getattr__(self, name: str) -> NDArray[Any]:
        part = {"t_": "translation", "r_": "rotation"}.get(name[:2])
        if part is None:
            raise AttributeError(name)
        table: PartTable = object.__getattribute__(self, part)
        column = name[2:]
        if column == "kind":
            return table.law
        if column == "frame":
            return table.frame
        if column in table.columns:
            return table.columns[column]
        raise AttributeError(f"no law of this grammar has a {part} column '{column}'")


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
    constraints: tuple[Any, ...] = ()  # ssgc.constraints.Constraint, in file order
    observation: Any = None  # the validated `observation` section (ssgc.observation), if any
    # the root type every scene must show (`root: {required: true}`), else None: a scene may
    # leave an observed root out (it is then implied at its pose, at no cost)
    required_root: int | None = None

    def type_id(self, name: str) -> int:
        return self.type_ids[name]

    def rule_name(self, rule_id: int) -> str:
        rule = self.rules[rule_id]
        return f"{self.types[rule.parent].name}[{rule.index}]->{self.types[rule.child].name}"

    @property
    def observed_types(self) -> list[NodeType]:
        return [t for t in self.types if t.observed]


def build_tables(types: tuple[NodeType, ...], rules: tuple[Rule, ...]) -> Tables:
    """Stack per-rule and per-type parameters so the scorer can work on all edges at once."""
    n_rules, n_types = len(rules), len(types)
    point = np.array(
        [r.translation.point is not None and r.rotation.point is not None for r in rules], bool
    ).reshape(n_rules)
    point_xyz = np.zeros((n_rules, 3))
    point_quat = np.tile([1.0, 0, 0, 0], (n_rules, 1))
    for r in rules:
        if point[r.id]:
            point_xyz[r.id], point_quat[r.id] = r.translation.point, r.rotation.point
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
        point=point,
        point_xyz=point_xyz,
        point_quat=point_quat,
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
    return Tables(
        translation=PartTable.build([r.translation for r in rules]),
        rotation=PartTable.build([r.rotation for r in rules]),
        **{k: frozen(v, v.dtype) for k, v in arrays.items()},
    )


class HoldsGrammar(Protocol):
    """What `ssgc.load_grammar` returns: the compiled grammar with its text (`ssgc.api`)."""

    @property
    def ir(self) -> Grammar: ...


def as_ir(grammar: Grammar | HoldsGrammar) -> Grammar:
    """The compiled grammar of either form a user holds, so that the library's functions that
    draw or show scenes take the `ssgc.load_grammar` result as well as its `.ir`.  Anything
    else (a path, say) is the TypeError `ssgc.parse` gives, not an AttributeError deep in."""
    if isinstance(grammar, Grammar):
        return grammar
    held = getattr(grammar, "ir", None)
    if not isinstance(held, Grammar):
        raise TypeError(
            f"expected a Grammar (ssgc.load_grammar) as grammar, got {type(grammar).__name__}"
        )
    return held
