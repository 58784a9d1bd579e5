"""Count laws of `repeat` types: how many times the one rule fires.

Two ways to write one (`probs`, `geometric`), each lowered here and fitted in its own form:
`probs` gets its weighted count frequencies, `geometric` its maximum-likelihood `p` (the count
range is kept).  Both wrap a `ssgc.distributions.discrete.CountLaw`, which samples and scores.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ssgc import dsl
from ssgc.distributions.discrete import CountLaw, fit_geometric_p
from ssgc.laws.base import FloatArray, Loc, Lowering


@dataclass(frozen=True, eq=False, kw_only=True)
class RepeatCount:
    """A count law as written at `path` (the `count` block of a `repeat`)."""

    law: CountLaw
    path: Loc

    @staticmethod
    def lower(spec: dsl.Repeat, loc: Loc, ctx: Lowering) -> RepeatCount | None:
        count = spec.count
        cls = GeometricCount if isinstance(count, dsl.GeometricCountSpec) else ProbsCount
        try:
            return cls.lower_count(count, loc, ctx)
        except ValueError as exc:
            ctx.error(loc, str(exc))
            return None

    @property
    def probs(self) -> FloatArray:
        return self.law.probs

    @property
    def log_probs(self) -> FloatArray:
        return self.law.log_probs

    @property
    def max_count(self) -> int:
        return self.law.max_count

    @property
    def largest(self) -> int:
        return self.law.largest

    @property
    def mean(self) -> float:
        return self.law.mean

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.int64]:
        return self.law.sample(rng, n)

    def log_prob(self, counts: ArrayLike) -> FloatArray:
        return self.law.log_prob(counts)

    def fit(self, histogram: FloatArray) -> tuple[Loc, dict[str, object]] | None:
        """The values to write (and where) for weighted count frequencies `histogram`."""
        raise NotImplementedError


@dataclass(frozen=True, eq=False, kw_only=True)
class ProbsCount(RepeatCount):
    @classmethod
    def lower_count(cls, spec: dsl.ProbsCount, loc: Loc, ctx: Lowering) -> ProbsCount | None:
        if sum(spec.probs) <= 0:
            ctx.error((*loc, "probs"), "count probabilities sum to zero")
            return None
        return cls(law=CountLaw(np.asarray(spec.probs, float)), path=loc)

    def fit(self, histogram: FloatArray) -> tuple[Loc, dict[str, object]] | None:
        """Frequencies of the possible counts; None (keep as written) at a count of
        probability 0, which stays impossible: a written `0` would come back as `0.0`."""
        possible = self.probs > 0
        probs = np.where(possible, histogram, 0.0)
        freq = (probs / probs.sum()).tolist()
        return self.path, {"probs": [x if p else None for x, p in zip(freq, possible, strict=True)]}


@dataclass(frozen=True, eq=False, kw_only=True)
class GeometricCount(RepeatCount):
    start: int  # the smallest count

    @classmethod
    def lower_count(
        cls, spec: dsl.GeometricCountSpec, loc: Loc, ctx: Lowering
    ) -> GeometricCount | None:
        g = spec.geometric
        if g.start > g.max:
            ctx.error((*loc, "geometric", "start"), f"start {g.start} exceeds max {g.max}")
            return None
        return cls(law=CountLaw.geometric(g.p, g.max, g.start), path=loc, start=g.start)

    def fit(self, histogram: FloatArray) -> tuple[Loc, dict[str, object]] | None:
        p = fit_geometric_p(histogram, self.start)
        return None if p is None else ((*self.path, "geometric"), {"p": p})
