"""Constraint kinds added from outside the library: one model, one class, one registered
builder, written in this file only, as a constraint module would be.

`min_height` (pose: the origins of some types at least `z` high in the world) and `even`
(structure: an even number of nodes of a type) are kinds ssgc does not have.  The tests check
that the grammar language takes them (and locates their mistakes), that the staged sampler
honours them (a registered structural kind is judged once the structure is drawn), and that
unregistering them takes them out of the language again.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pytest

from ssgc import dsl
from ssgc.compile import compile_text
from ssgc.constraints.base import (
    Constraint,
    FloatArray,
    Loc,
    per_scene_min,
    register,
    type_mask,
    unregister,
)
from ssgc.errors import GrammarError
from ssgc.sample.constrained import sample_blocks, select


class MinHeightC(dsl.Strict):
    types: list[str]
    z: float


class MinHeightSpec(dsl.Strict):
    min_height: MinHeightC


class EvenC(dsl.Strict):
    type: str


class EvenSpec(dsl.Strict):
    even: EvenC


@dataclass(frozen=True)
class MinHeight(Constraint):
    types: Any = field(default_factory=lambda: np.zeros(0, bool))
    z: float = 0.0
    kind: ClassVar[str] = "pose"
    word: ClassVar[str] = "min_height"

    def margin(self, batch: Any) -> FloatArray:
        nodes = np.flatnonzero(self.types[batch.type])
        if getattr(batch, "fresh", None) is not None:
            nodes = nodes[batch.fresh[nodes]]
        return per_scene_min(batch.scene[nodes], batch.xyz[nodes, 2] - self.z, batch.n_scenes)


@dataclass(frozen=True)
class Even(Constraint):
    type_id: int = 0
    n_types: int = 0
    kind: ClassVar[str] = "structure"
    word: ClassVar[str] = "even"

    def reads(self, n_types: int) -> Any:
        return type_mask([self.type_id], n_types)

    def margin(self, batch: Any) -> FloatArray:
        n = np.bincount(batch.scene[batch.type == self.type_id], minlength=batch.n_scenes)
        return np.where(n % 2 == 0, 0.0, -1.0)


def build_min_height(b: Any, name: str, spec: MinHeightC, loc: Loc) -> Constraint | None:
    ids = b.type_ids(spec.types, (*loc, "types"))
    if ids is None:
        return None
    return MinHeight(name, loc, types=type_mask(ids, b.n), z=spec.z)


def build_even(b: Any, name: str, spec: EvenC, loc: Loc) -> Constraint | None:
    t = b.type_id(spec.type, (*loc, "type"))
    return None if t is None else Even(name, loc, type_id=t, n_types=b.n)


@pytest.fixture
def kinds() -> Iterator[None]:
    register("min_height", MinHeightSpec)(build_min_height)
    register("even", EvenSpec)(build_even)
    try:
        yield
    finally:
        unregister("min_height")
        unregister("even")


GRAMMAR = """\
grammar: towers
root: Ground
types:
  Ground:
    repeat:
      count: {probs: [1, 1, 1, 1, 1]}
      rule:
        child: Block
        translation: {world_box_offset: {min: [-1, -1, 0], max: [1, 1, 1]}}
  Block: {observed: true}
constraints:
  high: {min_height: {types: [Block], z: 0.3}}
  pairs: {even: {type: Block}}
"""


def test_registered_kinds_are_sampled_exactly(kinds: None) -> None:
    g = compile_text(GRAMMAR, "towers.yaml")
    assert [type(c).__name__ for c in g.constraints] == ["MinHeight", "Even"]
    (block,) = sample_blocks(g, select(g, "all"), 200, 3)
    t = block.trees
    blocks = np.bincount(t.scene[t.type == g.type_id("Block")], minlength=t.n_scenes)
    assert np.all(blocks % 2 == 0)
    assert set(blocks.tolist()) == {0, 2, 4}  # 0, 2 and 4 blocks all occur
    assert np.all(t.xyz[t.type == g.type_id("Block"), 2] >= 0.3)
    assert np.all(block.margins["high"] >= 0) and np.all(block.margins["pairs"] == 0)
    # conditioning is exact: given the count, all heights must be >= 0.3 (P = 0.7^n), so
    # P(4) / P(2) = 0.7^2 under the constraints
    ratio = np.mean(blocks == 4) / np.mean(blocks == 2)
    assert 0.49 * 0.6 < ratio < 0.49 * 1.6


def test_registered_kinds_report_their_mistakes(kinds: None) -> None:
    with pytest.raises(GrammarError) as info:
        compile_text(GRAMMAR.replace("types: [Block], z: 0.3", "types: [Brick], z: 0.3"), "t.yaml")
    (message,) = [str(d) for d in info.value.diagnostics]
    assert "Brick" in message and "t.yaml:" in message


def test_unregistered_kinds_leave_the_language() -> None:
    with pytest.raises(GrammarError) as info:
        compile_text(GRAMMAR, "towers.yaml")
    assert any("expected a constraint" in str(d) for d in info.value.diagnostics)
