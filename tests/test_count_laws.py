"""Discrete node kinds (`repeat`, `or`, `independent`, recursion bounds) follow their laws.

Each law is checked by a chi-square test of 20k sampled trees against the law computed here
from the grammar's *stated* numbers (never from ssgc's own tables), and each tree's score must
equal the sampler's log-probability.  Fixed seeds, acceptance at p > 1e-3; each test also checks
that a slightly wrong law (untruncated geometric, unnormalised weights, a bound one level
deeper, ...) is rejected by the same statistic, so the tests have power.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from ssgc.compile import compile_text
from ssgc.geometry import quat_rotate
from ssgc.ir import Grammar
from ssgc.sample.forward import CHUNK, sample_trees
from ssgc.score import explain, node_terms, score_trees
from ssgc.tree import Trees

N = 20_000
P_MIN = 1e-3
LOGP_ATOL = 1e-9


# ------------------------------------------------------------------------------ helpers ---


def _compile(types: str, root: str = "R") -> Grammar:
    text = (
        "grammar: count_laws\n"
        f"root: {{type: {root}, pose: {{xyz: [0.5, -1.0, 2.0], rpy: [0.2, 0.4, -1.0]}}}}\n"
        "types:\n" + types
    )
    return compile_text(text)


def _repeat_grammar(count: str) -> Grammar:
    return _compile(
        "  R:\n"
        "    repeat:\n"
        f"      count: {count}\n"
        "      rule:\n"
        "        child: C\n"
        "        translation: {world_normal_offset: {mean: [0, 0, 0.1], variance: 0.01}}\n"
        "        rotation: {parent_bingham: {concentration: 4.0}}\n"
        "  C: {observed: true}\n"
    )


def _sample(g: Grammar, seed: int, n: int = N) -> tuple[Trees, np.ndarray]:
    trees, logp = sample_trees(g, n, seed)
    assert trees.n_scenes == n and logp.shape == (n,)
    assert np.all(np.isfinite(logp))
    np.testing.assert_allclose(score_trees(g, trees), logp, rtol=0, atol=LOGP_ATOL)
    return trees, logp


def _per_scene(trees: Trees, mask: np.ndarray) -> np.ndarray:
    """How many nodes of each scene satisfy `mask`."""
    return np.bincount(trees.scene[mask], minlength=trees.n_scenes)


def _chisquare_p(observed: np.ndarray, probs: np.ndarray) -> float:
    """Goodness of fit of category counts to `probs`; impossible categories must be empty."""
    observed = np.asarray(observed, float)
    probs = np.asarray(probs, float)
    if len(observed) > len(probs):  # outcomes beyond the law's support
        assert observed[len(probs) :].sum() == 0
        observed = observed[: len(probs)]
    possible = probs > 0
    assert observed[~possible].sum() == 0, "an impossible outcome was sampled"
    if possible.sum() == 1:
        return 1.0
    expected = probs[possible] / probs[possible].sum() * observed.sum()
    return float(stats.chisquare(observed[possible], expected).pvalue)


def _rejects(observed: np.ndarray, probs: np.ndarray) -> bool:
    """Power check: True if the chi-square test rejects the (wrong) law `probs`."""
    try:
        return _chisquare_p(observed, probs) < P_MIN
    except AssertionError:
        return True


def _dup_last(t: Trees, parent: int | None = None) -> Trees:
    """One tree with a copy of its last node appended (as a child of `parent`, by default
    the same parent as the copied node)."""
    p = t.parent[-1] if parent is None else parent
    return Trees(
        np.zeros(len(t) + 1, np.int64),
        np.r_[t.type, t.type[-1]],
        np.r_[t.parent, p],
        np.r_[t.rule, t.rule[-1]],
        np.vstack([t.xyz, t.xyz[-1]]),
        np.vstack([t.quat, t.quat[-1]]),
        1,
    )


def _drop(t: Trees, node: int) -> Trees:
    """One tree without leaf `node` (parent indices renumbered)."""
    keep = np.arange(len(t)) != node
    assert not np.any(t.parent == node), "only leaves can be dropped"
    parent = np.where(t.parent > node, t.parent - 1, t.parent)[keep]
    return Trees(
        np.zeros(keep.sum(), np.int64),
        t.type[keep],
        parent,
        t.rule[keep],
        t.xyz[keep],
        t.quat[keep],
        1,
    )


def _geometric(p: float, top: int, start: int) -> np.ndarray:
    """P(n) ∝ p (1-p)^(n-start) on start..top, renormalised; zero below start."""
    probs = np.zeros(top + 1)
    n = np.arange(start, top + 1)
    probs[start:] = p * (1.0 - p) ** (n - start)
    return probs / probs.sum()


# -------------------------------------------------------------------------------- repeat ---


@pytest.mark.parametrize(
    ("count", "law", "wrong"),
    [
        (
            "{probs: [0.1, 0.3, 0.0, 0.4, 0.2]}",
            np.array([0.1, 0.3, 0.0, 0.4, 0.2]),
            np.array([0.11, 0.3, 0.0, 0.39, 0.2]),
        ),
        # Unnormalised weights are normalised.
        (
            "{probs: [2, 6, 0, 8, 4]}",
            np.array([0.1, 0.3, 0.0, 0.4, 0.2]),
            np.array([0.1, 0.32, 0.0, 0.38, 0.2]),
        ),
        (
            "{geometric: {p: 0.3, max: 8, start: 0}}",
            _geometric(0.3, 8, 0),
            # the untruncated geometric: tail mass missing from the other counts
            np.r_[0.3 * 0.7 ** np.arange(8), 0.7**8],
        ),
        (
            "{geometric: {p: 0.45, max: 5, start: 1}}",
            _geometric(0.45, 5, 1),
            _geometric(0.45, 5, 0),
        ),
        ("{geometric: {p: 0.2, max: 4, start: 1}}", _geometric(0.2, 4, 1), _geometric(0.25, 4, 1)),
        (
            "{geometric: {p: 1.0, max: 3, start: 2}}",
            np.array([0, 0, 1.0, 0]),
            np.array([0, 0, 0.9, 0.1]),
        ),
    ],
    ids=[
        "probs",
        "probs-unnormalised",
        "geometric-start0",
        "geometric-start1",
        "geometric-flat",
        "geometric-point",
    ],
)
def test_repeat_counts_follow_the_law(count: str, law: np.ndarray, wrong: np.ndarray) -> None:
    g = _repeat_grammar(count)
    trees, logp = _sample(g, 1001)
    counts = _per_scene(trees, trees.parent >= 0)
    observed = np.bincount(counts, minlength=len(law))
    assert _chisquare_p(observed, law) > P_MIN
    assert _rejects(observed, wrong)
    # The root's discrete term is log P(count) under the stated law.
    choice = node_terms(g, trees).choice[trees.parent < 0]
    with np.errstate(divide="ignore"):
        np.testing.assert_allclose(choice, np.log(law)[counts], rtol=0, atol=LOGP_ATOL)
    assert np.all(np.isfinite(logp))
    # Hand-edited counts: one child more or fewer scores log P(count ± 1), -inf if impossible.
    with np.errstate(divide="ignore"):
        log_law = np.log(np.r_[law, 0.0])
    for i in np.flatnonzero(counts >= 1)[:20]:
        t, c = trees.tree(int(i)), int(counts[i])
        edited = {c + 1: _dup_last(t), c - 1: _drop(t, len(t) - 1)}
        for k, tree in edited.items():
            delta = score_trees(g, tree)[0] - score_trees(g, t)[0]
            if log_law[k] == -np.inf:
                assert score_trees(g, tree)[0] == -np.inf, (c, k)
            else:  # the dropped / copied child's own edge density changes the score too
                edge = node_terms(g, tree).edge.sum() - node_terms(g, t).edge.sum()
                np.testing.assert_allclose(delta - edge, log_law[k] - log_law[c], atol=1e-9)


# ------------------------------------------------------------------------------------ or ---


OR_TYPES = (
    "  R:\n"
    "    or:\n"
    "      - {{child: A{pa}}}\n"
    "      - {{child: B{pb}, translation: {{offset: [0, 0, 1]}}}}\n"
    "      - {{child: D{pd}, rotation: uniform}}\n"
    "  A: {{observed: true}}\n"
    "  B: {{observed: true}}\n"
    "  D: {{observed: true}}\n"
)


@pytest.mark.parametrize(
    ("weights", "law", "wrong"),
    [
        ((0.4, 0.2, 0.2), np.array([0.5, 0.25, 0.25]), np.array([0.48, 0.26, 0.26])),
        ((0.2, 0.0, 0.6), np.array([0.25, 0.0, 0.75]), np.array([0.2, 0.0, 0.6 + 0.2])),
        (None, np.full(3, 1 / 3), np.array([0.35, 0.325, 0.325])),
    ],
    ids=["weights", "zero-weight", "equal"],
)
def test_or_picks_one_rule_by_normalised_weight(weights, law, wrong) -> None:  # type: ignore[no-untyped-def]
    if weights is None:
        pa = pb = pd = ""
    else:
        pa, pb, pd = (f", p: {w}" for w in weights)
    g = _compile(OR_TYPES.format(pa=pa, pb=pb, pd=pd))
    trees, logp = _sample(g, 2002)
    kids = trees.parent >= 0
    assert np.array_equal(_per_scene(trees, kids), np.ones(N, int))  # exactly one child
    which = np.select([trees.type[kids] == g.type_id(t) for t in "ABD"], [0, 1, 2])
    observed = np.bincount(which, minlength=3)
    assert _chisquare_p(observed, law) > P_MIN
    assert _rejects(observed, wrong)
    # The tree's log-probability: log of the chosen rule's normalised weight (+ the edge,
    # which is 0 for the fixed rules and -log π² for the uniform rotation).
    edge = np.where(which == 2, -np.log(np.pi**2), 0.0)
    np.testing.assert_allclose(logp, np.log(law[which]) + edge, rtol=0, atol=LOGP_ATOL)
    # Hand edits: two children, no child, or a child of a zero-weight rule are impossible.
    t = trees.tree(0)
    assert score_trees(g, _dup_last(t))[0] == -np.inf
    assert score_trees(g, _drop(t, 1))[0] == -np.inf
    b_rule = next(r.id for r in g.rules if r.child == g.type_id("B"))
    as_b = dataclasses.replace(
        t,
        type=np.array([t.type[0], g.type_id("B")]),
        rule=np.array([-1, b_rule]),
        xyz=np.vstack([t.xyz[0], t.xyz[0] + quat_rotate(t.quat[0], [0.0, 0.0, 1.0])]),
        quat=np.vstack([t.quat[0], t.quat[0]]),
    )
    assert (score_trees(g, as_b)[0] == -np.inf) == (law[1] == 0)
    if law[1] > 0:
        np.testing.assert_allclose(score_trees(g, as_b), np.log(law[1]), atol=LOGP_ATOL)


# --------------------------------------------------------------------------- independent ---


def test_independent_rules_fire_independently() -> None:
    g = _compile(
        "  R:\n"
        "    independent:\n"
        "      - {child: A, p: 0.3}\n"
        "      - {child: B, p: 0.8, translation: {world_box_offset: {min: [0, 0, 0], "
        "max: [1, 1, 0]}}}\n"
        "      - {child: D, p: 1.0}\n"
        "      - {child: E, p: 0.0}\n"
        "  A: {observed: true}\n"
        "  B: {observed: true}\n"
        "  D: {observed: true}\n"
        "  E: {observed: true}\n"
    )
    trees, logp = _sample(g, 3003)
    fired = {t: _per_scene(trees, trees.type == g.type_id(t)) for t in "ABDE"}
    assert all(f.max() <= 1 for f in fired.values())
    assert np.all(fired["D"] == 1) and np.all(fired["E"] == 0)
    a, b = fired["A"], fired["B"]
    for f, p in ((a, 0.3), (b, 0.8)):
        assert stats.binomtest(int(f.sum()), N, p).pvalue > P_MIN
        assert stats.binomtest(int(f.sum()), N, p + 0.015).pvalue < P_MIN  # power
    # Joint 2x2 table against the product law (marginals and independence at once).
    table = np.bincount(2 * a + b, minlength=4)
    product = np.outer([0.7, 0.3], [0.2, 0.8]).ravel()
    assert _chisquare_p(table, product) > P_MIN
    assert stats.chi2_contingency(table.reshape(2, 2)).pvalue > P_MIN
    # Power: a positively correlated law with the same marginals is rejected.
    correlated = product + np.array([0.01, -0.01, -0.01, 0.01])
    assert _rejects(table, correlated)
    # log P = Σ log p (fired) + log (1 - p) (not fired), plus the box edge -log 1 = 0.
    expected = np.where(a, np.log(0.3), np.log(0.7)) + np.where(b, np.log(0.8), np.log(0.2))
    np.testing.assert_allclose(logp, expected, rtol=0, atol=LOGP_ATOL)
    # Hand edits: dropping the p = 1 child, adding the p = 0 child, or firing a rule twice is
    # impossible; dropping the A child changes the score by log(0.7 / 0.3).
    t = trees.tree(int(np.flatnonzero((a == 1) & (b == 1))[0]))
    kinds = list(t.type)
    node_d = kinds.index(g.type_id("D"))
    node_a = kinds.index(g.type_id("A"))
    assert score_trees(g, _drop(t, node_d))[0] == -np.inf
    e_rule = next(r.id for r in g.rules if r.child == g.type_id("E"))
    with_e = Trees(
        np.zeros(len(t) + 1, np.int64),
        np.r_[t.type, g.type_id("E")],
        np.r_[t.parent, 0],
        np.r_[t.rule, e_rule],
        np.vstack([t.xyz, t.xyz[0]]),
        np.vstack([t.quat, t.quat[0]]),
        1,
    )
    assert score_trees(g, with_e)[0] == -np.inf
    twice = Trees(
        np.zeros(len(t) + 1, np.int64),
        np.r_[t.type, t.type[node_a]],
        np.r_[t.parent, 0],
        np.r_[t.rule, t.rule[node_a]],
        np.vstack([t.xyz, t.xyz[node_a]]),
        np.vstack([t.quat, t.quat[node_a]]),
        1,
    )
    assert score_trees(g, twice)[0] == -np.inf
    np.testing.assert_allclose(
        score_trees(g, _drop(t, node_a))[0] - score_trees(g, t)[0],
        np.log(0.7 / 0.3),
        rtol=0,
        atol=LOGP_ATOL,
    )


# --------------------------------------------------------------------------- recursion ---


STACK_2 = (
    "  Base:\n"
    "    and:\n"
    "      - {child: Stack}\n"
    "  Stack:\n"
    "    max_nesting: 3\n"
    "    or:\n"
    "      - {child: Stop, p: 0.3}\n"
    "      - {child: Stack, p: 0.7, translation: {offset: [0, 0, 0.1]}}\n"
    "  Stop: {observed: true}\n"
)
STACK_3 = (
    "  Base:\n"
    "    and:\n"
    "      - {child: Stack}\n"
    "  Stack:\n"
    "    max_nesting: 3\n"
    "    or:\n"
    "      - {child: Stop, p: 0.3}\n"
    "      - {child: Stack, p: 0.5, rotation: {revolute: {axis: [0, 0, 1]}}}\n"
    "      - {child: Leaf, p: 0.2}\n"
    "  Stop: {observed: true}\n"
    "  Leaf: {observed: true}\n"
)


def _chain_law(weights: dict[str, float], bound: int) -> dict[tuple[int, str], float]:
    """Law of (number of Stack nodes, terminal type) for `Stack: or [...]` with max_nesting.

    Below the bound every rule is available; at the bound the recursive rule is blocked and
    the `or` renormalises over the other rules.
    """
    total = sum(weights.values())
    stop = {k: w for k, w in weights.items() if k != "Stack"}
    out: dict[tuple[int, str], float] = {}
    reach = 1.0  # P(the chain has at least `level` Stack nodes)
    for level in range(1, bound + 1):
        if level < bound:
            for k, w in stop.items():
                out[(level, k)] = reach * w / total
            reach *= weights["Stack"] / total
        else:
            for k, w in stop.items():
                out[(level, k)] = reach * w / sum(stop.values())
    return out


@pytest.mark.parametrize(
    ("types", "weights", "recursive_edge"),
    [
        (STACK_2, {"Stop": 0.3, "Stack": 0.7}, 0.0),  # fixed offset: a point mass
        # full-circle revolute: density 1/(2π) per recursive edge
        (STACK_3, {"Stop": 0.3, "Stack": 0.5, "Leaf": 0.2}, -np.log(2 * np.pi)),
    ],
    ids=["or-2", "or-3"],
)
def test_recursion_bound_renormalises_the_or(
    types: str, weights: dict[str, float], recursive_edge: float
) -> None:
    g = _compile(types, root="Base")
    trees, logp = _sample(g, 4004)
    length = _per_scene(trees, trees.type == g.type_id("Stack"))
    terminals = [k for k in weights if k != "Stack"]
    end = np.full(N, -1)
    for i, k in enumerate(terminals):
        end[_per_scene(trees, trees.type == g.type_id(k)) == 1] = i
    assert np.all(end >= 0) and np.all((length >= 1) & (length <= 3))
    law = _chain_law(weights, 3)
    cells = [(lv, k) for lv in (1, 2, 3) for k in terminals]
    probs = np.array([law[c] for c in cells])
    np.testing.assert_allclose(probs.sum(), 1.0)
    observed = np.bincount((length - 1) * len(terminals) + end, minlength=len(cells))
    assert _chisquare_p(observed, probs) > P_MIN
    # Power: the law with the bound one level deeper is rejected, and so is the law that
    # never renormalises at the bound (the untruncated chain conditioned on length <= 3).
    deeper = _chain_law(weights, 4)
    assert _rejects(observed, np.array([deeper.get(c, 0.0) for c in cells]))
    untruncated = np.array(
        [
            (weights["Stack"] / sum(weights.values())) ** (lv - 1)
            * weights[k]
            / sum(weights.values())
            for lv, k in cells
        ]
    )
    assert _rejects(observed, untruncated / untruncated.sum())
    # The sampler's log-probability is the product of the chosen weights along the chain.
    choice = np.log([law[(lv, terminals[e])] for lv, e in zip(length, end, strict=True)])
    expected = choice + (length - 1) * recursive_edge
    np.testing.assert_allclose(logp, expected, rtol=0, atol=LOGP_ATOL)


def _chain_tree(g: Grammar, n_stack: int, end: str = "Stop") -> Trees:
    """Base -> Stack -> ... -> Stack (n_stack of them) -> end, built by hand."""
    rule_of = {(g.rules[r].parent, g.rules[r].child): r for r in range(len(g.rules))}
    base, stack, last = g.type_id("Base"), g.type_id("Stack"), g.type_id(end)
    types = [base] + [stack] * n_stack + [last]
    n = len(types)
    parent = np.arange(-1, n - 1)
    rules = [-1] + [rule_of[(types[i - 1], types[i])] for i in range(1, n)]
    xyz = np.tile(g.root_xyz, (n, 1))
    quat = np.tile(g.root_quat, (n, 1))
    for i in range(1, n):  # the recursive rule offsets by 0.1 along the parent's z
        recursive = types[i] == stack and types[i - 1] == stack
        step = quat_rotate(quat[i - 1], [0.0, 0.0, 0.1]) if recursive else 0.0
        xyz[i] = xyz[i - 1] + step
    return Trees(
        np.zeros(n, np.int64),
        np.array(types, np.int64),
        parent.astype(np.int64),
        np.array(rules, np.int64),
        xyz,
        quat,
        1,
    )


def test_recursion_bound_in_the_scorer() -> None:
    g = _compile(STACK_2, root="Base")
    for depth, expected in ((1, 0.3), (2, 0.7 * 0.3), (3, 0.7 * 0.7 * 1.0)):
        score = score_trees(g, _chain_tree(g, depth))
        np.testing.assert_allclose(score, [np.log(expected)], rtol=0, atol=LOGP_ATOL)
    # One Stack more than max_nesting allows: impossible.
    assert score_trees(g, _chain_tree(g, 4))[0] == -np.inf
    assert score_trees(g, _chain_tree(g, 6))[0] == -np.inf
    # A tree sampled at the bound scores the same in a batch with an over-deep tree.
    both = Trees.concatenate([_chain_tree(g, 3), _chain_tree(g, 4)])
    score = score_trees(g, both)
    assert explain(g, _chain_tree(g, 3)) == []
    assert explain(g, _chain_tree(g, 4)) != []
    np.testing.assert_allclose(score[0], np.log(0.49), rtol=0, atol=LOGP_ATOL)
    assert score[1] == -np.inf


def test_or_with_every_rule_blocked_produces_nothing() -> None:
    g = _compile(
        "  Base:\n"
        "    and:\n"
        "      - {child: Loop}\n"
        "  Loop:\n"
        "    max_nesting: 2\n"
        "    or:\n"
        "      - {child: Loop, p: 0.5, rotation: uniform}\n",
        root="Base",
    )
    trees, logp = _sample(g, 4040, 500)
    # Loop -> Loop with probability 1 (the only rule), then the bound blocks it: nothing.
    assert np.array_equal(_per_scene(trees, trees.type == g.type_id("Loop")), np.full(500, 2))
    # nothing observed: the one rotation's density is integrated out of the score, and
    # Eq. 2.1 as written counts it (docs/conventions.md, "Unseen nodes")
    np.testing.assert_allclose(logp, 0.0, rtol=0, atol=LOGP_ATOL)
    joint = score_trees(g, trees, marginal=False)
    np.testing.assert_allclose(joint, -np.log(np.pi**2), rtol=0, atol=LOGP_ATOL)
    # A third Loop is impossible.
    t = trees.tree(0)
    assert score_trees(g, _dup_last(t, parent=2))[0] == -np.inf


def test_blocked_repeat_produces_nothing() -> None:
    g = _compile(
        "  Base:\n"
        "    and:\n"
        "      - {child: Branch}\n"
        "  Branch:\n"
        "    max_nesting: 2\n"
        "    repeat:\n"
        "      count: {probs: [0.5, 0.25, 0.25]}\n"
        "      rule: {child: Branch, translation: {world_normal_offset: {variance: 1.0}}}\n",
        root="Base",
    )
    trees, _ = _sample(g, 5005)
    depth = trees.depth()
    assert depth.max() <= 2  # Base (0) -> Branch (1) -> Branch (2), nothing below
    counts = _per_scene(trees, depth == 2)
    observed = np.bincount(counts, minlength=3)
    assert _chisquare_p(observed, np.array([0.5, 0.25, 0.25])) > P_MIN
    assert _rejects(observed, np.array([0.45, 0.3, 0.25]))
    # Hand-made: a third level of Branch is impossible.
    t = trees.tree(int(np.flatnonzero(counts == 1)[0]))
    assert np.isfinite(score_trees(g, t)[0])
    assert score_trees(g, _dup_last(t, parent=len(t) - 1))[0] == -np.inf


# ------------------------------------------------------------ reproducibility and chunks ---


SINK_LIKE = (
    "  R:\n"
    "    repeat:\n"
    "      count: {geometric: {p: 0.3, max: 6, start: 1}}\n"
    "      rule:\n"
    "        child: Obj\n"
    "        translation: {world_normal_offset: {mean: [0, 0, 0.1], "
    "variance: [0.01, 0.02, 0.005]}}\n"
    "        rotation: {world_bingham: {concentration: 1.0}}\n"
    "  Obj:\n"
    "    or:\n"
    "      - {child: Plate, p: 0.6}\n"
    "      - {child: Cup, p: 1}\n"
    "  Plate:\n"
    "    independent:\n"
    "      - {child: Cup, p: 0.4, translation: {parent_normal_offset: {mean: [0, 0, 0.02], "
    "variance: 0.001}}, rotation: {revolute: {axis: [0, 0, 1]}}}\n"
    "      - {child: Cup, p: 0.6, rotation: uniform}\n"
    "  Cup: {observed: true}\n"
)


def _assert_same_trees(a: Trees, b: Trees) -> None:
    assert a.n_scenes == b.n_scenes
    for f in dataclasses.fields(Trees):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert np.array_equal(x, y), f.name
        else:
            assert x == y, f.name


def test_same_seed_same_trees_and_scores_match() -> None:
    g = _compile(SINK_LIKE)
    t1, lp1 = _sample(g, 6006, 1000)
    t2, lp2 = sample_trees(g, 1000, 6006)
    _assert_same_trees(t1, t2)
    assert np.array_equal(lp1, lp2)
    t3, _ = sample_trees(g, 1000, 6007)
    assert len(t3) != len(t1) or not np.array_equal(t3.xyz, t1.xyz)


@pytest.mark.parametrize("n", [0, 1, 10, CHUNK - 1, CHUNK, CHUNK + 1, 600])
def test_fewer_scenes_are_a_prefix(n: int) -> None:
    g = _compile(SINK_LIKE)
    full, lp_full = sample_trees(g, 600, 77)
    part, lp_part = sample_trees(g, n, 77)
    assert part.n_scenes == n and lp_part.shape == (n,)
    end = int(full.offsets[n])
    prefix = Trees(
        full.scene[:end],
        full.type[:end],
        full.parent[:end],
        full.rule[:end],
        full.xyz[:end],
        full.quat[:end],
        n,
    )
    _assert_same_trees(part, prefix)
    assert np.array_equal(lp_part, lp_full[:n])
    if n:
        np.testing.assert_allclose(score_trees(g, part), lp_part, rtol=0, atol=LOGP_ATOL)


def test_tree_invariants() -> None:
    g = _compile(SINK_LIKE)
    trees, _ = _sample(g, 8008, 2000)
    assert np.all(np.diff(trees.scene) >= 0)
    child = trees.parent >= 0
    assert np.all(trees.parent[child] < np.flatnonzero(child))
    assert np.all(trees.scene[trees.parent[child]] == trees.scene[child])
    assert np.all((trees.parent < 0) == (trees.rule < 0))


# ------------------------------------------------------------------- property: any law ---


@st.composite
def count_laws(draw: st.DrawFn) -> str:
    if draw(st.booleans()):
        probs = draw(
            st.lists(st.sampled_from([0.0, 0.05, 0.5, 1.0, 3.0]), min_size=1, max_size=6).filter(
                lambda ps: sum(ps) > 0
            )
        )
        return f"{{probs: {probs}}}"
    top = draw(st.integers(0, 6))
    start = draw(st.integers(0, top))
    p = draw(st.sampled_from([0.05, 0.3, 0.5, 0.99, 1.0]))
    return f"{{geometric: {{p: {p}, max: {top}, start: {start}}}}}"


@settings(max_examples=40, deadline=None)
@given(count=count_laws(), seed=st.integers(0, 2**32 - 1))
def test_any_count_law_scores_its_sampler_logp(count: str, seed: int) -> None:
    g = _repeat_grammar(count)
    trees, logp = sample_trees(g, 300, seed)
    assert np.all(np.isfinite(logp))
    np.testing.assert_allclose(score_trees(g, trees), logp, rtol=0, atol=LOGP_ATOL)


TRAILING = """grammar: trailing
root: R
types:
  R:
    and: [{child: P}, {child: Q}]
  P:
    repeat:
      count: COUNT
      rule: {child: A}
  Q:
    repeat:
      count: {geometric: {p: 1.0, max: 4}}
      rule: {child: A}
  A: {observed: true}
"""


@pytest.mark.parametrize(
    ("count", "copies"), [("{probs: [0.5, 0.5, 0, 0]}", 1), ("{probs: [0, 0, 1, 0, 0]}", 2)]
)
def test_the_supertree_holds_no_copies_a_count_law_cannot_make(count: str, copies: int) -> None:
    """A count of probability 0 at the end of a law (written, or geometric with p = 1) is never
    made: the supertree held 3 copies for `probs: [0.5, 0.5, 0, 0]` and 4 for the geometric one
    of p = 1 that always makes none, which only enlarged the parser's model."""
    from ssgc.io.scene import Scene
    from ssgc.parse.parser import Parser
    from ssgc.parse.supertree import build_supertree
    from ssgc.supertree_size import supertree_size

    g = compile_text(TRAILING.replace("COUNT", count))
    st = build_supertree(g)
    a = g.type_ids["A"]
    assert int(np.sum(st.type == a)) == copies
    assert supertree_size(g) == len(st.type) == 3 + copies  # R, P, Q and the copies
    for n, status in ((copies, "optimal"), (copies + 1, "infeasible")):
        scene = Scene("s", np.full(n, a), np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)))
        assert Parser(g).parse(scene).status == status
