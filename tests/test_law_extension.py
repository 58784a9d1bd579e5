"""A law added from outside the library: one class, registered here, and nothing else touched.

`ParentLaplaceOffset` is a translation law ssgc does not have: the child sits at a Laplace
offset in the parent's frame (independent axes, density Π exp(-|u - mean| / b) / 2b).  It is
written in this file only, as a law module would be; the tests check that the whole pipeline
takes it: the grammar language accepts it (and reports its mistakes where they are), the
sampler's log-density equals the scorer's, `ssg inspect` describes it, the parser recovers a
sampled tree, the M-step fits it and writes the fit back into the YAML, and `ssg explain`
words its deviations the law's own way.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, ClassVar

import numpy as np
import pytest
from pydantic import Field

from ssgc import dsl
from ssgc.compile import compile_text
from ssgc.errors import GrammarError
from ssgc.explain import explain
from ssgc.fit.mstep import FitSettings, m_step
from ssgc.fit.writeback import apply_updates
from ssgc.inspect import grammar_summary
from ssgc.io.scene import scene_from_tree
from ssgc.laws.base import (
    Columns,
    Context,
    Deviation,
    FloatArray,
    Frame,
    Loc,
    Lowering,
    TranslationLaw,
    frozen,
    register,
    unregister,
)
from ssgc.laws.base import FitSettings as Settings
from ssgc.parse.parser import Parser
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees


class LaplaceParams(dsl.Strict):
    mean: dsl.Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    scale: dsl.Positive


class ParentLaplaceOffsetT(dsl.Strict):
    parent_laplace_offset: LaplaceParams


class ParentLaplaceOffset(TranslationLaw):
    keys: ClassVar[dict[str, Frame]] = {"parent_laplace_offset": Frame.PARENT}
    columns: ClassVar[dict[str, tuple[int, ...]]] = {"mean": (3,), "scale": ()}

    mean: FloatArray
    scale: float

    @classmethod
    def lower(cls, p: LaplaceParams, key: str, loc: Loc, ctx: Lowering) -> ParentLaplaceOffset:
        if p.scale > 10:
            ctx.error((*loc, "scale"), "a Laplace scale over 10 m is surely a typo")
        return cls(key=key, frame=Frame.PARENT, path=loc, mean=frozen(p.mean), scale=p.scale)

    def sample(self, rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        e = rng.laplace(0.0, 1.0, (n, 3))
        return self.mean + self.scale * e, -np.abs(e).sum(axis=1) - 3 * np.log(2 * self.scale)

    def row(self) -> dict[str, Any]:
        return {"mean": self.mean, "scale": self.scale}

    @classmethod
    def density(cls, cols: Columns, u: FloatArray) -> FloatArray:
        b = cols["scale"]
        return -np.abs(u - cols["mean"]).sum(axis=1) / b - 3 * np.log(2 * b)

    def mode(self) -> FloatArray:
        return self.mean

    def supremum(self) -> float:
        return float(-3 * np.log(2 * self.scale))

    def fit(self, u: FloatArray, w: FloatArray, settings: Settings) -> dict[str, object]:
        """Weighted median per axis, then the weighted mean absolute deviation from it."""
        order = np.argsort(u, axis=0)
        cum = np.cumsum(w[order], axis=0)
        pick = np.argmax(cum >= 0.5 * w.sum(), axis=0)
        median = u[order[pick, range(3)], range(3)]
        scale = float(w @ np.abs(u - median).mean(axis=1) / w.sum())
        return {"mean": [float(x) for x in median], "scale": max(scale, 1e-6)}

    def describe(self) -> str:
        return f"{self.key} mean {self.mean.tolist()} scale {self.scale:g}"

    def describe_deviation(self, u: FloatArray, log_prob: float, ctx: Context) -> Deviation:
        scales = float(np.abs(u - self.mean).sum() / self.scale)
        return Deviation(f"position {scales:.1f} Laplace scales from where {ctx.parent} puts it")


@pytest.fixture(autouse=True)
def laplace_law() -> Iterator[None]:
    register(ParentLaplaceOffset, shapes=((ParentLaplaceOffsetT, "parent_laplace_offset"),))
    yield
    unregister(ParentLaplaceOffset)


GRAMMAR = """\
grammar: laplace
root: {type: Table, pose: {xyz: [1, 2, 0], rpy: [0, 0, 0.7]}}
types:
  Table:
    observed: true
    and:
      - child: Cup
        translation:
          parent_laplace_offset: {mean: [0.3, -0.1, 0.75], scale: 0.05}  # the new law
        rotation: same
  Cup: {observed: true}
"""


def test_the_language_takes_the_new_law_and_locates_its_mistakes() -> None:
    grammar = compile_text(GRAMMAR)
    law = grammar.rules[0].translation
    assert isinstance(law, ParentLaplaceOffset)
    assert law.path == ("types", "Table", "and", 0, "translation", "parent_laplace_offset")
    with pytest.raises(GrammarError) as err:
        compile_text(GRAMMAR.replace("scale: 0.05", "scale: 50"))
    assert "Laplace scale" in str(err.value) and ":9:67:" in str(err.value)
    with pytest.raises(GrammarError) as err:
        compile_text(GRAMMAR.replace("scale: 0.05", "scale: -1"))
    assert "scale" in str(err.value)


def test_sampler_and_scorer_agree() -> None:
    grammar = compile_text(GRAMMAR)
    trees, logp = sample_trees(grammar, 500, seed=3)
    np.testing.assert_allclose(score_trees(grammar, trees), logp, atol=1e-9)
    cup = trees.xyz[trees.rule == 0]
    local = cup - [1, 2, 0]
    c, s = np.cos(0.7), np.sin(0.7)
    in_parent = np.stack([c * local[:, 0] + s * local[:, 1], -s * local[:, 0] + c * local[:, 1]])
    assert np.allclose(np.median(in_parent, axis=1), [0.3, -0.1], atol=0.01)


def test_inspect_describes_it() -> None:
    rows = grammar_summary(compile_text(GRAMMAR))["rules"]
    assert rows[0]["translation"].startswith("parent_laplace_offset mean [0.3, -0.1, 0.75]")


def test_parser_recovers_a_sampled_tree() -> None:
    grammar = compile_text(GRAMMAR)
    trees, logp = sample_trees(grammar, 3, seed=5)
    parser = Parser(grammar)
    for i in range(3):
        result = parser.parse(scene_from_tree(grammar, trees.tree(i), f"s{i}"))
        assert result.status == "optimal"
        assert result.parses[0].score == pytest.approx(logp[i], abs=1e-9)


def test_m_step_fits_it_and_writes_it_back() -> None:
    grammar = compile_text(GRAMMAR)
    trees, _ = sample_trees(grammar, 2000, seed=7)
    updates = m_step(grammar, trees, np.ones(2000), FitSettings())
    assert [u.path for u in updates] == [grammar.rules[0].translation.path]
    fitted = compile_text(apply_updates(GRAMMAR, updates))
    law = fitted.rules[0].translation
    assert isinstance(law, ParentLaplaceOffset)
    np.testing.assert_allclose(law.mean, [0.3, -0.1, 0.75], atol=0.01)
    assert law.scale == pytest.approx(0.05, rel=0.1)
    assert "# the new law" in apply_updates(GRAMMAR, updates)


def test_explain_uses_the_laws_own_words() -> None:
    grammar = compile_text(GRAMMAR)
    trees, _ = sample_trees(grammar, 1, seed=2)
    e = explain(grammar, scene_from_tree(grammar, trees.tree(0), "s"))
    cup = next(o for o in e.objects if o.type == "Cup")
    words = [r.text for r in cup.reasons if r.kind == "position"]
    assert len(words) == 1 and "Laplace scales from where Table #0 puts it" in words[0]
