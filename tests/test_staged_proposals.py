"""The staged sampler's shortcuts keep the law: its scenes against plain rejection from P(T).

Each shortcut of `ssgc.sample.staged` (a proposal that is not the grammar's law, an order of
draws, an early verdict) has an argument in docs/constraints.md; these tests are the check
that would catch a biased sampler: the same statistics of the kept scenes, from plain
rejection (whole trees drawn by forward sampling, kept when every constraint holds) and from
the staged sampler, compared with chi-square tests (counts) and Kolmogorov-Smirnov tests
(poses).  The bigger comparison on the thesis's four constraints is behind the slow marker.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import GRAMMARS
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from ssgc.compile import compile_text, load_grammar
from ssgc.constraints.base import depths, fresh_pairs, lineal, lineal_few, tree_pairs
from ssgc.constraints.structural import chain_runs
from ssgc.sample.constrained import sample_blocks
from ssgc.sample.forward import sample_trees
from ssgc.sample.proposals import chain_proposal, count_proposals
from ssgc.tree import Trees

HEAD = (GRAMMARS / "dimsum_table.yaml").read_text().split("\nconstraints:")[0]
TYPES = ["Plate", "Teacup", "Teapot", "ServingBowl", "SteamerBottom", "SteamerLid"]


def _grammar(constraints: str):  # type: ignore[no-untyped-def]
    return compile_text(HEAD + "\nconstraints:\n" + constraints, "case.yaml", base_dir=GRAMMARS)


def _plain(g, n: int, seed: int) -> Trees:  # type: ignore[no-untyped-def]
    trees, _ = sample_trees(g, n, seed)
    ok = np.ones(n, bool)
    for c in g.constraints:
        ok &= c.margin(trees) >= 0
    return trees.select(ok)


def _staged(g, n: int, seed: int) -> Trees:  # type: ignore[no-untyped-def]
    return Trees.concatenate([b.trees for b in sample_blocks(g, list(g.constraints), n, seed)])


def _chi2(a: np.ndarray, b: np.ndarray) -> float:
    """p-value of a chi-square test that two samples of a count share one law (cells with
    fewer than 5 expected are pooled into their neighbour)."""
    top = int(max(a.max(), b.max())) + 1
    table = np.stack([np.bincount(a, minlength=top), np.bincount(b, minlength=top)])
    table = table[:, table.sum(axis=0) > 0]
    while table.shape[1] > 1 and table.sum(axis=0).min() < 10:
        k = int(np.argmin(table.sum(axis=0)))
        j = k - 1 if k > 0 else 1
        table[:, j] += table[:, k]
        table = np.delete(table, k, axis=1)
    if table.shape[1] < 2:
        return 1.0
    return float(stats.chi2_contingency(table)[1])


def _statistics(g, trees: Trees, length: int) -> dict[str, np.ndarray]:  # type: ignore[no-untyped-def]
    """Per scene: counts of each type, of stacks, of chains at least `length` long, the
    longest chain; and pose samples (x, y of stack bottoms, of teapots, of plates)."""
    out: dict[str, np.ndarray] = {}
    n = trees.n_scenes
    for name in TYPES:
        out[name] = np.bincount(trees.scene[trees.type == g.type_id(name)], minlength=n)
    tray = g.type_id("SteamerBottom")
    run = chain_runs(trees.type, trees.parent, tray)
    out["stacks"] = np.bincount(trees.scene[run == 1], minlength=n)
    out["tall chains"] = np.bincount(trees.scene[run == length], minlength=n)
    longest = np.zeros(n, np.int64)
    np.maximum.at(longest, trees.scene, run)
    out["longest"] = longest
    bottom = run == 1
    out["bottom x"], out["bottom y"] = trees.xyz[bottom, 0], trees.xyz[bottom, 1]
    pot = trees.type == g.type_id("Teapot")
    out["teapot x"] = trees.xyz[pot, 0]
    plate = trees.type == g.type_id("Plate")
    out["plate y"] = trees.xyz[plate, 1]
    return out


def _compare(g, a: Trees, b: Trees, length: int) -> dict[str, float]:  # type: ignore[no-untyped-def]
    sa, sb = _statistics(g, a, length), _statistics(g, b, length)
    pvalues = {}
    for key in sa:
        if key.endswith((" x", " y")):
            if min(len(sa[key]), len(sb[key])) > 20:
                pvalues[key] = float(stats.ks_2samp(sa[key], sb[key]).pvalue)
        else:
            pvalues[key] = _chi2(sa[key], sb[key])
    return pvalues


def test_chain_proposal_is_used_only_where_exact() -> None:
    g = load_grammar(GRAMMARS / "dimsum_table.yaml")
    cs = list(g.constraints)
    chain = chain_proposal(g, cs, count_proposals(g, cs))
    assert chain is not None and chain.constraint == "tall_stack" and chain.length == 4
    tray = g.type_id("SteamerBottom")
    assert (g.rules[chain.self_rule].parent, g.rules[chain.self_rule].child) == (tray, tray)
    # without `many_stacks` nothing says every kept tree has its one SharedSteamers node
    alone = _grammar("  tall: {longest_chain: {type: SteamerBottom, min: 4}}\n")
    cs = list(alone.constraints)
    assert chain_proposal(alone, cs, count_proposals(alone, cs)) is None
    # a chain of one is a count, not a chain
    short = _grammar(
        "  tall: {longest_chain: {type: SteamerBottom, min: 1}}\n"
        "  many: {children: {of: SharedSteamers, min: 3}}\n"
    )
    cs = list(short.constraints)
    assert chain_proposal(short, cs, count_proposals(short, cs)) is None


@pytest.mark.parametrize(
    ("length", "clearance", "seed", "least"),
    [
        (4, "", 33, 1500),  # structure only: the size bias shows in the number of stacks
        (3, "Teapot, SteamerBottom, SteamerLid", 31, 600),  # 1/K shows in the tall chains
    ],
)
def test_chain_proposal_keeps_the_law(length: int, clearance: str, seed: int, least: int) -> None:
    """Size-biased stack count, one stack forced tall, kept with probability 1/K: the
    stacks, the tall chains among them, every type's count and the poses follow plain
    rejection's law.  Both parts matter: without the size bias the number of stacks is off
    (p < 1e-5 at this size), without the 1/K the number of tall chains (p < 1e-5)."""
    text = (
        f"  tall: {{longest_chain: {{type: SteamerBottom, min: {length}}}}}\n"
        "  many: {children: {of: SharedSteamers, min: 3}}\n"
    )
    if clearance:
        text += f"  apart: {{clearance: {{types: [{clearance}], exempt_ancestors: true}}}}\n"
    g = _grammar(text)
    cs = list(g.constraints)
    assert chain_proposal(g, cs, count_proposals(g, cs)) is not None
    plain = _plain(g, 30_000, seed)
    assert plain.n_scenes > least
    staged = _staged(g, 2 * plain.n_scenes, seed + 1)
    pvalues = _compare(g, plain, staged, length)
    assert min(pvalues.values()) > 1e-3 / len(pvalues), pvalues


@pytest.mark.slow
def test_thesis_constraints_match_plain_rejection() -> None:
    """All four constraints of the dimsum table (every shortcut at once): 3,000,000 forward
    samples give about 2,200 scenes of plain rejection (0.074% pass); the staged sampler's
    scenes match them on counts, stacks, tall chains and poses (a few minutes)."""
    g = load_grammar(GRAMMARS / "dimsum_table.yaml")
    plain = Trees.concatenate([_plain(g, 250_000, 40 + k) for k in range(12)])
    assert plain.n_scenes > 1800
    staged = _staged(g, 2 * plain.n_scenes, 41)
    pvalues = _compare(g, plain, staged, 4)
    assert min(pvalues.values()) > 1e-3 / len(pvalues), pvalues


def test_bench_constrained_with_two_jobs_reports_wall_and_cpu_rates() -> None:
    """`ssg bench sample --constraints all -j 2 --json`: the rates with both workers, per
    wall-clock and per CPU second (the workers' CPU included), and how busy the cores were."""
    import json

    from typer.testing import CliRunner

    from ssgc.cli.app import app

    args = ["bench", "sample", str(GRAMMARS / "bin_packing.yaml"), "--constraints", "all"]
    args += ["--method", "rejection", "-n", "600", "-j", "2", "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    row = data["methods"]["rejection"]
    assert data["jobs"] == 2 and row["scenes"] == 600 and row["exact"] is True
    assert row["valid_scenes_per_second"] > 0 and row["valid_scenes_per_cpu_second"] > 0
    assert 0 < row["cores_busy"] <= data["cpus"] + 0.05


@given(st.data())
@settings(max_examples=60, deadline=None)
def test_fresh_pairs_and_lineal_shortcuts_agree_with_the_plain_versions(data) -> None:  # type: ignore[no-untyped-def]
    """The pose stage's shortcuts enumerate the same pairs (those with a fresh node, once
    each) and find the same lineal pairs (walking up from the deeper node only)."""
    n = data.draw(st.integers(1, 40))
    parent = np.array(
        [-1] + [data.draw(st.integers(-1, k - 1)) for k in range(1, n)], dtype=np.int64
    )
    scene = np.array(data.draw(st.lists(st.integers(0, 4), min_size=n, max_size=n)))
    fresh = np.array(data.draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    nodes = np.flatnonzero(np.array(data.draw(st.lists(st.booleans(), min_size=n, max_size=n))))
    i, j = tree_pairs(nodes, scene)
    new = fresh[i] | fresh[j]
    want = {frozenset(p) for p in zip(i[new], j[new], strict=True)}
    a, b = fresh_pairs(nodes, scene, fresh)
    got = [frozenset(p) for p in zip(a, b, strict=True)]
    assert len(got) == len(set(got)) and set(got) == want
    x = np.array(data.draw(st.lists(st.integers(0, n - 1), max_size=30)), dtype=np.int64)
    y = np.array(data.draw(st.lists(st.integers(0, n - 1), min_size=len(x), max_size=len(x))))
    y = y.astype(np.int64)
    assert np.array_equal(lineal_few(x, y, parent, depths(parent)), lineal(x, y, parent))


def test_size_biased_restricted_counts_follow_k_times_the_law() -> None:
    """The chain proposal's count: P(k) * k restricted to [lo, hi], normalised."""
    from ssgc.sample.forward import _restricted_counts

    p = np.array([0.1, 0.3, 0.25, 0.2, 0.1, 0.05])
    counts = _restricted_counts(p, 2, 4, np.random.default_rng(3), 20_000, size_biased=True)
    assert set(np.unique(counts)) == {2, 3, 4}
    want = np.array([2 * 0.25, 3 * 0.2, 4 * 0.1])
    got = np.bincount(counts, minlength=5)[2:5]
    assert stats.chisquare(got, want / want.sum() * len(counts)).pvalue > 1e-3
