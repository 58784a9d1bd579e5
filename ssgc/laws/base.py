"""What every placement law is, the frames it can be written in, and the registry of laws.

A rule places its child in two parts, a translation and a rotation, and each part is one *law*
(a Normal, a box, a Bingham, ...) written in one *frame*: over the child's own pose (`WORLD`),
over its offset from the parent along world axes (`WORLD_OFFSET`), or in the parent's frame
(`PARENT`).  The frame is the same arithmetic for every law, so it lives here and in
`ssgc.rules`; everything a law knows lives in its own class, in one file of this package:

- its parameters, with their domains, checked and lowered from the document (`lower`);
- drawing local values and their log-density (`sample`), for the sampler;
- its parameters stacked per rule (`columns`, `row`) and a log-density over many edges of
  many rules at once (`density`), for the scorer and the parser;
- its mode and the supremum of its log-density, for pose proposals and the parser's bound;
- its weighted maximum-likelihood fit and the YAML values that write it back (`fit`).

Adding a law is one file: a subclass of `TranslationLaw` or `RotationLaw` decorated with
`register`, which also adds its document shape to the grammar language (`ssgc.dsl`).

Measures (docs/conventions.md): translations are densities w.r.t. Lebesgue measure on the free
axes (a pinned axis or a fixed offset is a point mass, contributing 0 to the log); rotations
are densities w.r.t. the volume measure on SO(3) of total volume π².
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar, Protocol, dataclass_transform

import numpy as np
from numpy.typing import NDArray

from ssgc import dsl

FloatArray = NDArray[np.float64]
Loc = tuple[str | int, ...]
Columns = Mapping[str, NDArray[Any]]

POS_TOL = 1e-6  # meters: how far a pinned coordinate may be from its value
ROT_TOL = 1e-6  # radians: same for fixed rotations and revolute axes
# m, rad: the narrowest free box axis or revolute range.  Their densities count points within
# POS_TOL / ROT_TOL outside as inside (frame arithmetic and rounded data put objects on a face
# with round-off), so a range w wide carries mass (w + 2 tol) / w: at most 1.02 from here up.
MIN_WIDTH = 100 * POS_TOL
LOG_2 = float(np.log(2.0))


class Frame(IntEnum):
    """The coordinates a law is written in (thesis Table 2.1)."""

    WORLD = 0  # the child's own position / rotation
    WORLD_OFFSET = 1  # the child's position minus the parent's, along world axes
    PARENT = 2  # the child's pose in the parent's frame


class Lowering(Protocol):
    """What a law's `lower` may ask of the compiler: report a located error or warning, read
    a rotation."""

    def error(self, loc: Loc, message: str) -> None: ...

    def warn(self, loc: Loc, message: str) -> None: ...

    def orientation(self, o: dsl.Orientation, loc: Loc) -> FloatArray: ...


class FitSettings(Protocol):
    """The M-step's regularisation (`ssgc.fit.mstep.FitSettings`)."""

    min_variance: float
    max_concentration: float


@dataclass(frozen=True)
class Deviation:
    """How far a value is from what its law expects, in words (`ssg explain`)."""

    text: str  # a phrase: "position 0.31 m from where Plate #1 places it (4.2σ, ...)"
    sigma: float | None = None  # a Mahalanobis distance, where the law has one
    percentile: float | None = None  # P(a draw of the law is no more likely)


@dataclass(frozen=True)
class Context:
    """What a law needs beside the value to put its deviation in words: who placed the node,
    and the share of the law's own draws no more likely than a log-density (Monte Carlo,
    `ssgc.explain`)."""

    parent: str
    percentile: Callable[[float], float]


@dataclass(frozen=True)
class Orientation:
    """A fitted rotation (unit quaternion, wxyz), written back in the form the user used."""

    quat_wxyz: tuple[float, float, float, float]


def percent(p: float) -> str:
    """A probability as a user reads it: 0.0068 -> "0.68%", 1.0 -> "100%" (two significant
    digits below 10%, whole percents above: `.2g` alone would print 1e+02%)."""
    v = 100 * p
    return f"{v:.0f}%" if v >= 10 else f"{v:.2g}%"


def frozen(a: object, dtype: Any = None) -> NDArray[Any]:
    """A read-only copy: booleans stay boolean (axis masks), the rest becomes float."""
    arr = np.asarray(a)
    out = np.array(arr, dtype=dtype or (bool if arr.dtype == bool else float))
    out.flags.writeable = False
    return out


@dataclass_transform(frozen_default=True, kw_only_default=True, eq_default=False)
@dataclass(frozen=True, eq=False, kw_only=True)
class PoseLaw:
    """One part of a rule: a law, the frame it is written in, and where it was written.

    `key` is the document word it was written with (`world_normal`, `same`, ...), `path` the
    document path of its parameter block, and `fixed` keeps it as written when fitting.  Every
    subclass is a frozen, keyword-only dataclass of its parameters (no decorator needed).
    """

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        dataclass(frozen=True, eq=False, kw_only=True)(cls)

    part: ClassVar[str]  # "translation" or "rotation"
    keys: ClassVar[dict[str, Frame]]  # document word -> frame
    columns: ClassVar[dict[str, tuple[int, ...]]] = {}  # stacked parameters: name -> shape

    key: str
    frame: Frame
    path: Loc
    fixed: bool = False

    @classmethod
    def lower(cls, params: Any, key: str, loc: Loc, ctx: Lowering) -> PoseLaw | None:
        """The law written as `params` under `key` at `loc`; None after reporting errors."""
        raise NotImplementedError

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        """`n` draws in the law's coordinates, and the log-density of each, computed from
        the draw itself (not by `density`: the tests compare the two)."""
        raise NotImplementedError

    def row(self) -> dict[str, Any]:
        """This law's values of its class's `columns`."""
        return {}

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        """Log-density of values `u` (one per edge) under each edge's law of this class;
        `cols` are this class's columns, one row per edge."""
        raise NotImplementedError

    def mode(self) -> FloatArray | None:
        """The most likely value in the law's coordinates (None: every value is)."""
        return None

    def supremum(self) -> float:
        """The largest value of the log-density."""
        raise NotImplementedError

    def concave_form(self) -> tuple[FloatArray, ...] | None:
        """The log-density as a quadratic form, for the parser's convex relaxation
        (`ssgc.parse.bound`), or None if it is not one (the bound then uses `supremum`).

        Translations: (mean, P, c) with log p(u) = -½ (u - mean)ᵀ P (u - mean) + c (P ⪰ 0).
        Rotations: (A, c) with log p(q) = qᵀ A q + c on unit quaternions, A symmetric.
        """
        return None

    @property
    def point(self) -> FloatArray | None:
        """The value of a point mass (a fixed offset), else None."""
        return None

    @property
    def fits(self) -> bool:
        """Whether `ssg fit` changes this law (it has an M-step and is not `fixed`)."""
        return type(self).fit is not PoseLaw.fit and not self.fixed

    def fit(self, u: FloatArray, w: FloatArray, settings: FitSettings) -> dict[str, object] | None:
        """Weighted maximum-likelihood parameters in the form written, as the values to
        write at `path` (see `ssgc.fit.writeback`); None to keep the law as written."""
        return None

    def describe(self) -> str:
        """One line for `ssg inspect`."""
        return self.key

    def describe_deviation(self, u: FloatArray, log_prob: float, ctx: Context) -> Deviation:
        """`u` (this law's coordinates of one value, of log-density `log_prob`) in words: how
        far from what the law expects, and how rare.  Each law says it its own way."""
        return Deviation(f"{self.part} placed by {ctx.parent} ({self.key}), log p {log_prob:.3g}")

    def describe_violation(self, u: FloatArray) -> str:
        """Why `u` has no density under this law (a pinned axis off by 1 cm, ...)."""
        return f"its {self.part} has no density under {self.key}"


class TranslationLaw(PoseLaw):
    part = "translation"


class RotationLaw(PoseLaw):
    part = "rotation"


# ------------------------------------------------------------------------ registry ---

_LAWS: dict[str, list[type[PoseLaw]]] = {"translation": [], "rotation": []}
_BY_KEY: dict[tuple[str, str], type[PoseLaw]] = {}
_ADDED: dict[type[PoseLaw], list[str]] = {}


def register(cls: type[PoseLaw] | None = None, *, shapes: tuple[tuple[Any, str], ...] = ()) -> Any:
    """Class decorator: make a law known to the compiler, scorer and fitter.

    `shapes` are (pydantic model, word) pairs that the grammar language does not have yet: they
    are added to the rule's translation or rotation union (`ssgc.dsl.add_choice`).
    """

    def add(law: type[PoseLaw]) -> type[PoseLaw]:
        for word in law.keys:
            if (law.part, word) in _BY_KEY:
                raise ValueError(f"the {law.part} word '{word}' already names a law")
        for model, word in shapes:
            dsl.add_choice(law.part, model, word)
        _LAWS[law.part].append(law)
        _BY_KEY.update({(law.part, word): law for word in law.keys})
        _ADDED[law] = [word for _, word in shapes]
        return law

    return add if cls is None else add(cls)


def unregister(law: type[PoseLaw]) -> None:
    """Forget a registered law and the document shapes it added (for tests)."""
    _LAWS[law.part].remove(law)
    for word in law.keys:
        _BY_KEY.pop((law.part, word), None)
    for word in _ADDED.pop(law, []):
        dsl.remove_choice(law.part, word)


def law_for(part: str, word: str) -> type[PoseLaw]:
    return _BY_KEY[(part, word)]


def registered(part: str) -> tuple[type[PoseLaw], ...]:
    return tuple(_LAWS[part])


# -------------------------------------------------------------- stacked parameters ---


@dataclass(frozen=True)
class PartTable:
    """One part (translation or rotation) of every rule, stacked for vectorised scoring.

    `law[r]` indexes `laws`, `frame[r]` is rule r's `Frame`, and `columns[name][r]` holds
    rule r's value of a column its law declares (zeros for rules of other laws).
    """

    laws: tuple[type[PoseLaw], ...]
    law: NDArray[np.int64]
    frame: NDArray[np.int64]
    columns: dict[str, NDArray[Any]]

    @classmethod
    def build(cls, parts: list[PoseLaw]) -> PartTable:
        laws = tuple(dict.fromkeys(type(p) for p in parts))
        n = len(parts)
        shapes: dict[str, tuple[int, ...]] = {}
        for law in laws:
            for name, shape in law.columns.items():
                if shapes.setdefault(name, shape) != shape:
                    raise ValueError(f"column '{name}' has two shapes: {shape}, {shapes[name]}")
        columns: dict[str, NDArray[Any]] = {}
        for p_id, p in enumerate(parts):
            for name, value in p.row().items():
                if name not in columns:
                    value = np.asarray(value)
                    columns[name] = np.zeros((n, *shapes[name]), value.dtype)
                columns[name][p_id] = value
        return cls(
            laws,
            frozen(np.array([laws.index(type(p)) for p in parts], np.int64).reshape(n), np.int64),
            frozen(np.array([p.frame for p in parts], np.int64).reshape(n), np.int64),
            {k: frozen(v, v.dtype) for k, v in columns.items()},
        )

    def log_density(self, rules: NDArray[np.int64], u: FloatArray) -> FloatArray:
        """Each edge's log-density under its rule's law, one law class at a time."""
        out = np.zeros(len(rules))
        law = self.law[rules]
        for i, cls in enumerate(self.laws):
            take = law == i
            if np.any(take):
                r = rules[take]
                cols = {name: self.columns[name][r] for name in cls.columns}
                out[take] = cls.density(cols, u[take])
        return out
