"""How much constrained sampling draws at once: candidates per attempt and pairs per chunk.

A batch of candidates lives in one node store of at most `MAX_CHUNK_NODES` nodes, so an
attempt holds as many candidates as fit it (`largest_batch`), an attempt that overflows it
anyway is drawn again with fewer, and only a single scene too large for it is an error, one
that says so.  `clearance` forms its pairs in chunks of about `MAX_PAIRS`: a batch of 1,024
trees of 700 objects has 250 million of them.  The tests shrink both limits (monkeypatch) and
count what is drawn or paired at once, then check that the scenes and margins are those of
the same runs with the real limits.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from conftest import GRAMMARS

from ssgc.compile import compile_text, load_grammar
from ssgc.constraints import base, pose
from ssgc.constraints.base import lineal
from ssgc.errors import SsgError
from ssgc.ir import Grammar
from ssgc.sample import constrained, forward, rjmcmc, staged
from ssgc.sample.constrained import sample_blocks, select
from ssgc.sample.forward import sample_trees
from ssgc.sample.rjmcmc import SETTINGS as RJ_SETTINGS
from ssgc.sample.staged import View, rejection_batch
from ssgc.tree import Trees

OBJECTS = 50  # per scene: a scene has OBJECTS + 1 nodes
STORE = 20_000  # the node store of these tests: 392 such scenes, not the 1,024 of an attempt


def objects_grammar(objects: int = OBJECTS, constraint: str = "") -> Grammar:
    """`Root` with exactly `objects` `Obj` on [-10, 10]², and a constraint on them."""
    constraint = (
        constraint or "inside_box: {types: [Obj], min: [-9.9, -9.9, -1], max: [9.9, 9.9, 1]}"
    )
    return compile_text(
        f"""
grammar: objects{objects}
root: {{type: Root, pose: {{xyz: [0, 0, 0]}}}}
types:
  Root:
    observed: true
    repeat:
      count: {{geometric: {{p: 0.001, start: {objects}, max: {objects}}}}}
      rule:
        child: Obj
        translation: {{world_box: {{min: [-10, -10, 0], max: [10, 10, 0]}}}}
  Obj: {{observed: true}}
constraints:
  c: {{{constraint}}}
"""
    )


def small_store(monkeypatch: pytest.MonkeyPatch, nodes: int) -> None:
    """Make the node store hold `nodes` nodes (the sampler's budget and its message)."""
    monkeypatch.setattr(forward, "MAX_CHUNK_NODES", nodes)
    monkeypatch.setattr(staged, "MAX_CHUNK_NODES", nodes)


def record_sizes(monkeypatch: pytest.MonkeyPatch, method: str) -> list[int]:
    """The candidates of every call of `method`'s batch function (the calls that overflow
    the store included)."""
    sizes: list[int] = []
    real = constrained.METHODS[method]

    def counting(grammar: Grammar, cs: list[Any], size: int, *args: Any, **kw: Any) -> Any:
        sizes.append(size)
        return real(grammar, cs, size, *args, **kw)

    monkeypatch.setitem(constrained.METHODS, method, counting)
    return sizes


def test_expected_nodes_is_the_mean_tree_size() -> None:
    """The node count behind the attempt sizes: exact for a fixed count, and the mean of
    forward samples for the recursive dimsum stacks (`max_nesting: 6`) and the sink."""
    assert staged.expected_nodes(objects_grammar(300)) == 301
    for name in ("dimsum_table", "sink"):
        g = load_grammar(GRAMMARS / f"{name}.yaml")
        trees, _ = sample_trees(g, 4000, 0)
        sizes = np.bincount(trees.scene, minlength=4000)
        mean = staged.expected_nodes(g)
        assert mean is not None
        assert abs(sizes.mean() - mean) < 5 * sizes.std() / np.sqrt(4000)


def test_rejection_attempts_fit_the_node_store(monkeypatch: pytest.MonkeyPatch) -> None:
    """Scenes of 51 nodes and a store of 20,000: attempts of at most 196 candidates (half
    the store at the mean size), never the 1,024 of the first attempt that overflowed it
    ("256 scenes (drawn together) would hold more than 20,000 nodes")."""
    g = objects_grammar()
    small_store(monkeypatch, STORE)
    sizes = record_sizes(monkeypatch, "rejection")
    blocks = list(sample_blocks(g, select(g, "c"), 300, 5))
    assert sum(b.trees.n_scenes for b in blocks) == 300
    assert sizes and max(sizes) * (OBJECTS + 1) <= STORE // 2
    for b in blocks:
        assert np.all(b.margins["c"] >= 0)


def test_an_attempt_that_overflows_is_drawn_again_smaller(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without a known mean size (`largest_batch` None), the 1,024 candidates of the first
    attempt overflow the store, and so do 512; the attempt is drawn again with 256, and the
    block's later attempts are no larger.  The scenes are the same on every run."""
    g = objects_grammar()
    small_store(monkeypatch, STORE)
    monkeypatch.setattr(constrained, "largest_batch", lambda grammar: None, raising=False)
    sizes = record_sizes(monkeypatch, "rejection")
    one = list(sample_blocks(g, select(g, "c"), 40, 5))
    assert sizes[:3] == [1024, 512, 256]
    assert max(sizes[2:]) <= 256
    assert sum(b.trees.n_scenes for b in one) == 40
    two = list(sample_blocks(g, select(g, "c"), 40, 5))
    assert [b.logp.tolist() for b in one] == [b.logp.tolist() for b in two]


@pytest.mark.parametrize("method", ["rejection", "rjmcmc", "hmc", "project"])
def test_one_scene_too_large_says_so(monkeypatch: pytest.MonkeyPatch, method: str) -> None:
    """A store smaller than one scene: every method draws a single candidate and the error
    names it ("one scene"), not the 256 scenes that forward sampling draws together."""
    g = objects_grammar()
    small_store(monkeypatch, 30)
    sizes = record_sizes(monkeypatch, method)
    with pytest.raises(SsgError) as err:
        list(sample_blocks(g, select(g, "c"), 3, 0, method=method))
    assert "one scene would hold more than 30 nodes" in str(err.value)
    assert sizes == [1]


def test_rjmcmc_starts_fit_the_node_store(monkeypatch: pytest.MonkeyPatch) -> None:
    """RJMCMC's exact starting states come from staged rejection in batches the store holds
    (before: one batch of `start_candidates` = 16,384 candidates, 835,584 nodes here), and
    its chains too."""
    g = objects_grammar()
    small_store(monkeypatch, STORE)
    starts: list[int] = []

    def counting(grammar: Grammar, cs: list[Any], size: int, *args: Any) -> Any:
        starts.append(size)
        return rejection_batch(grammar, cs, size, *args)

    monkeypatch.setattr(rjmcmc, "rejection_batch", counting)
    chains = record_sizes(monkeypatch, "rjmcmc")
    settings = replace(RJ_SETTINGS, min_sweeps=2, max_sweeps=4, check_every=2)
    blocks = list(
        sample_blocks(g, select(g, "c"), 5, 0, method="rjmcmc", options={"settings": settings})
    )
    assert sum(b.trees.n_scenes for b in blocks) == 5
    assert starts and max(starts) * (OBJECTS + 1) <= STORE // 2
    assert max(chains) * (OBJECTS + 1) <= STORE // 2


def test_inbox_300_samples() -> None:
    """The hunt's grammar, at the real store size: 300 objects that each stay 11.5 cm inside
    [-10, 10]² (0.09% of candidates) were refused from the second attempt on, of 16,384
    candidates ("256 scenes (drawn together) would hold more than 4,000,000 nodes")."""
    g = objects_grammar(
        300, "inside_box: {types: [Obj], min: [-9.885, -9.885, -1], max: [9.885, 9.885, 1]}"
    )
    blocks = list(sample_blocks(g, select(g, "c"), 5, 0))
    assert sum(b.trees.n_scenes for b in blocks) == 5


# ----------------------------------------------------------------- clearance pairs ---


def record_pairs(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The number of pair gaps reduced at once by `clearance` (its `per_scene_min` calls)."""
    seen: list[int] = []
    real = pose.per_scene_min

    def counting(scene: Any, values: Any, n_scenes: int) -> Any:
        seen.append(len(values))
        return real(scene, values, n_scenes)

    monkeypatch.setattr(pose, "per_scene_min", counting)
    return seen


def reference_margin(c: pose.Clearance, trees: Trees, fresh: Any = None) -> np.ndarray:
    """Per tree, the smallest gap over its checked pairs, one tree at a time."""
    out = np.full(trees.n_scenes, np.inf)
    for s in range(trees.n_scenes):
        nodes = np.flatnonzero((trees.scene == s) & c.types[trees.type])
        i, j = np.triu_indices(len(nodes), 1)
        i, j = nodes[i], nodes[j]
        keep = ~c.exempt[trees.type[i], trees.type[j]]
        if fresh is not None:
            keep &= fresh[i] | fresh[j]
        if c.exempt_ancestors and len(i):
            keep &= ~lineal(i, j, trees.parent)
        i, j = i[keep], j[keep]
        d = np.hypot(*(trees.xyz[i, :2] - trees.xyz[j, :2]).T)
        gap = d - c.radius[trees.type[i]] - c.radius[trees.type[j]]
        out[s] = gap.min(initial=np.inf)
    return out


@pytest.mark.parametrize("grammar", ["objects", "dimsum_table"])
def test_clearance_pairs_come_in_chunks(monkeypatch: pytest.MonkeyPatch, grammar: str) -> None:
    """64 trees of 50 objects have 78,400 pairs; with chunks of 1,000 no more than 1,000 +
    50 are measured at once (before: all of them), and the margins are those of every pair
    (dimsum: `exempt_ancestors`, trays of one stack are not a pair), for whole trees and for
    the pairs with a fresh node."""
    if grammar == "objects":
        g = objects_grammar(constraint="clearance: {types: [Obj], radius: {Obj: 0.3}}")
        c = g.constraints[0]
    else:
        g = load_grammar(GRAMMARS / "dimsum_table.yaml")
        (c,) = select(g, "items_non_penetrating")
    trees, _ = sample_trees(g, 64, 3)
    fresh = np.random.default_rng(0).random(len(trees.type)) < 0.3
    monkeypatch.setattr(base, "MAX_PAIRS", 1000, raising=False)
    seen = record_pairs(monkeypatch)
    whole = c.margin(trees)
    assert max(seen) <= 1000 + OBJECTS
    np.testing.assert_array_equal(whole, reference_margin(c, trees))
    seen.clear()
    partial = View(
        scene=trees.scene,
        type=trees.type,
        parent=trees.parent,
        xyz=trees.xyz,
        quat=trees.quat,
        n_scenes=trees.n_scenes,
        index=np.arange(len(trees.type)),
        depth=trees.depth(),
        fresh=fresh,
    )
    margins = c.margin(partial)
    assert max(seen) <= 1000 + OBJECTS
    np.testing.assert_array_equal(margins, reference_margin(c, trees, fresh))


def test_clearance_chunks_keep_the_scenes(monkeypatch: pytest.MonkeyPatch) -> None:
    """Staged rejection under `clearance` draws the same scenes, margins and tallies with
    chunks of 500 pairs as with the default chunks."""
    g = objects_grammar(40, "clearance: {types: [Obj], radius: {Obj: 0.05}}")
    cs = list(g.constraints)
    default = rejection_batch(g, cs, 256, np.random.default_rng(2))
    monkeypatch.setattr(base, "MAX_PAIRS", 500, raising=False)
    seen = record_pairs(monkeypatch)
    small = rejection_batch(g, cs, 256, np.random.default_rng(2))
    assert max(seen) <= 500 + 40
    assert default.trees.n_scenes > 0
    np.testing.assert_array_equal(default.trees.xyz, small.trees.xyz)
    np.testing.assert_array_equal(default.margins["c"], small.margins["c"])
    assert (default.rejected, default.best) == (small.rejected, small.best)
