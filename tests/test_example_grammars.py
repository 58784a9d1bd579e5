"""The example grammars in grammars/: they compile cleanly, follow the house style, and the
forward sampler and the scorer agree on every scene they produce."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest

from ssgc.compile import load_grammar
from ssgc.ir import Grammar
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees
from ssgc.tree import Trees

GRAMMARS = Path(__file__).resolve().parent.parent / "grammars"
PATHS = sorted(GRAMMARS.glob("*.yaml"))
SCHEMA_LINE = "# yaml-language-server: $schema=../schemas/grammar.schema.json"
N_SCENES = 500


@cache
def compiled(name: str) -> Grammar:
    return load_grammar(GRAMMARS / name)


@cache
def sampled(name: str) -> tuple[Trees, np.ndarray]:
    return sample_trees(compiled(name), N_SCENES, 0)


def path_counts(trees: Trees, type_id: int) -> np.ndarray:
    """For every node, how many nodes of `type_id` lie on the path from its root to it."""
    count = (trees.type == type_id).astype(np.int64)
    depth = trees.depth()
    for d in range(1, int(depth.max(initial=0)) + 1):
        at = np.flatnonzero(depth == d)
        count[at] += count[trees.parent[at]]  # parents are one level up, already final
    return count


def test_there_are_example_grammars() -> None:
    names = {p.name for p in PATHS}
    assert {"sink.yaml", "gmm.yaml", "dimsum_table.yaml"} <= names


@pytest.mark.parametrize("path", PATHS, ids=lambda p: p.stem)
def test_loads_without_warnings(path: Path) -> None:
    grammar = compiled(path.name)
    assert [str(w) for w in grammar.warnings] == []
    assert grammar.observed_types, "an example grammar should produce something observable"


@pytest.mark.parametrize("path", PATHS, ids=lambda p: p.stem)
def test_header(path: Path) -> None:
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[0] == SCHEMA_LINE
    header = []
    for line in lines[1:]:
        if not line.startswith("#"):
            break
        header.append(line.lstrip("#").strip())
    assert sum(len(text.split()) for text in header) >= 10, "say what the grammar models"


@pytest.mark.parametrize("path", PATHS, ids=lambda p: p.stem)
def test_sampler_and_scorer_agree(path: Path) -> None:
    grammar = compiled(path.name)
    trees, logp = sampled(path.name)
    assert trees.n_scenes == N_SCENES
    assert np.all(np.isfinite(logp))
    scores = score_trees(grammar, trees)
    assert np.all(np.isfinite(scores))
    np.testing.assert_allclose(scores, logp, rtol=0, atol=1e-8)


@pytest.mark.parametrize("path", PATHS, ids=lambda p: p.stem)
def test_max_nesting_respected(path: Path) -> None:
    grammar = compiled(path.name)
    trees, _ = sampled(path.name)
    for t in grammar.types:
        if t.max_nesting is not None:
            assert path_counts(trees, t.id).max() <= t.max_nesting, t.name


def test_dimsum_steamer_stacks() -> None:
    grammar = compiled("dimsum_table.yaml")
    trees, _ = sampled("dimsum_table.yaml")
    steamer = grammar.types[grammar.type_id("SteamerBottom")]
    assert steamer.max_nesting is not None
    # A SteamerBottom only comes from SharedSteamers or from another SteamerBottom, so the
    # number of them on a path is the height of that stack.
    heights = path_counts(trees, steamer.id)[trees.type == steamer.id]
    assert heights.max() >= 3
    assert heights.max() <= steamer.max_nesting
