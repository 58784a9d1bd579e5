"""`ssg fit --estep mcmc`: the chain samples the exact posterior, and a fit from the truth
stays at the truth (the top-N E-step does not: it nests too many objects, issue 13)."""

from __future__ import annotations

import tempfile
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from bruteforce import enumerate_parses
from conftest import GRAMMARS
from fit_from_truth import flatten, read_values
from scipy.special import logsumexp

from ssgc.compile import compile_text
from ssgc.fit.em import (
    FitJournal,
    FitOptions,
    GrammarSource,
    _tree_json,
    _weigh,
    fit_grammar,
    fit_header,
)
from ssgc.fit.mstep import FitSettings, Ties, m_step
from ssgc.fit.posterior import McmcSettings, posterior_e_step, posterior_scores, sample_posterior
from ssgc.io.scene import scene_from_tree
from ssgc.parse.parser import tree_signature
from ssgc.sample.forward import sample_trees
from ssgc.tree import Trees

# Cups on a tray, some in boxes: a cup near a box may be in it or beside it.
NEST = """\
grammar: nest
root:
  type: Tray
  pose: {xyz: [0.0, 0.0, 0.0]}
types:
  Tray:
    observed: true
    repeat:
      count: {geometric: {p: 0.4, max: 4, start: 1}}
      rule:
        child: Thing
        translation: {world_normal_offset: {mean: [0.0, 0.0, 0.0], variance: 0.01}}
  Thing:
    or:
      - child: Box
      - child: Cup
  Box:
    and:
      - child: BoxShell
      - child: InBox
  InBox:
    repeat:
      count: {geometric: {p: 0.5, max: 2}}
      rule:
        child: Cup
        translation: {parent_normal_offset: {mean: [0.0, 0.0, 0.0], variance: 0.01}}
  BoxShell: {observed: true}
  Cup: {observed: true}
"""


def _ambiguous_scene(g):
    """A scene of NEST with at least five trees (cups in and beside boxes), all enumerated."""
    trees, _ = sample_trees(g, 50, 3)
    scene = next(
        s
        for s in (scene_from_tree(g, trees.tree(i), f"s{i}", 0.0) for i in range(50))
        if len(s) >= 5
    )
    parses = enumerate_parses(g, scene)
    assert len(parses) >= 5
    return scene, parses


@pytest.fixture(scope="module")
def ambiguous():
    """NEST, its ambiguous scene's parses, and 40 chains' visit frequencies on them."""
    g = compile_text(NEST)
    _, parses = _ambiguous_scene(g)
    return g, parses, _chain_frequencies(g, parses[0][1])


def _chain_frequencies(g, start, chains=40):
    post = sample_posterior(g, [start] * chains, McmcSettings(samples=100, burn_in=10), 0, 1)
    freq: Counter[bytes] = Counter()
    for k in range(post.trees.n_scenes):
        freq[tree_signature(g, post.trees.tree(k))] += post.weights[k] / chains
    return freq


def _tv(freq, keys, probs):
    return 0.5 * sum(abs(freq.get(k, 0.0) - p) for k, p in zip(keys, probs, strict=True))


def test_the_chain_samples_the_exact_posterior_of_an_ambiguous_scene(ambiguous):
    g, parses, freq = ambiguous
    exact_scores = posterior_scores(g, Trees.concatenate([t for _, t in parses]))
    exact = np.exp(exact_scores - exact_scores.max())
    exact /= exact.sum()
    keys = [tree_signature(g, t) for _, t in parses]
    assert set(freq) <= set(keys)
    # 4,000 correlated draws over a handful of trees: sampling noise in TV is a few 0.01;
    # the best tree alone (what top-1 would say) is ≥ 0.3 away.
    assert _tv(freq, keys, exact) < 0.06
    assert 0.5 * (1 - exact[0] + sum(exact[1:])) > 0.3


def test_top_n_weights_over_every_tree_are_the_posterior_the_chain_samples(ambiguous):
    """With N covering every tree, `--estep topn` and `--estep mcmc` estimate one posterior:
    the top-N weights (from the parse scores, as journalled) must add log c! per repeat node
    as the chain does.  Without it they are ≥ 0.1 away from the chain's frequencies here."""
    g, parses, freq = ambiguous
    records = [
        {
            "name": "s",
            "status": "optimal",
            "message": "",
            "scores": [score for score, _ in parses],
            "trees": [_tree_json(t) for _, t in parses],
        }
    ]
    _, weights, report = _weigh(g, records, 1)
    keys = [tree_signature(g, t) for _, t in parses]
    assert _tv(freq, keys, weights) < 0.06
    ordered = np.exp([score for score, _ in parses])
    assert _tv(freq, keys, ordered / ordered.sum()) > 0.1  # the check can tell them apart
    exact = posterior_scores(g, Trees.concatenate([t for _, t in parses]))
    assert report["log_evidence"] == pytest.approx(float(logsumexp(exact)), rel=1e-12)


def _p(updates, name):
    for u in updates:
        if u.path[:2] == ("types", name) and "p" in u.values:
            return u.values["p"]
    raise KeyError(name)


def _e_step_estimates(grammar_text, n, seed, samples, burn_in):
    """Geometric p's from one MCMC E-step at the true grammar, and from the true trees."""
    g = compile_text(grammar_text)
    trees, _ = sample_trees(g, n, seed)
    truth = [trees.tree(i) for i in range(n)]
    mle = m_step(g, trees, np.ones(n), FitSettings())
    post, weights, report = posterior_e_step(
        g, [[t] for t in truth], McmcSettings(samples, burn_in), FitSettings(), Ties.none(g), 0, 1
    )
    fitted = m_step(g, post, weights, FitSettings())
    return mle, fitted, report


def test_an_e_step_at_the_truth_gives_the_true_tree_estimates():
    mle, fitted, report = _e_step_estimates(NEST, 200, 7, samples=40, burn_in=10)
    for name, tol in (("Tray", 0.04), ("InBox", 0.07)):
        assert abs(_p(fitted, name) - _p(mle, name)) < tol, name
    assert 0.0 < report["topn_mass_mean"] < 1.0  # the true trees alone: most, not all
    assert set(report["spread"]) >= {"types.InBox.repeat.count.geometric.p"}


@pytest.mark.slow
def test_an_e_step_at_the_truth_of_the_sink_gives_the_true_tree_estimates():
    text = (GRAMMARS / "sink.yaml").read_text()
    mle, fitted, _ = _e_step_estimates(text, 200, 1, samples=100, burn_in=50)
    # measured: 0.297/0.301, 0.550/0.539, 0.505/0.484 (without the c! factor: 0.346, 0.422,
    # 0.363); the spread across draws is 0.006, 0.015, 0.024
    for name, tol in (("DishBin", 0.02), ("ObjectsOnPlate", 0.05), ("ObjectsInBowl", 0.06)):
        assert abs(_p(fitted, name) - _p(mle, name)) < tol, name


def test_an_mcmc_fit_resumed_from_its_journal_is_the_same_with_any_jobs(tmp_path):
    g = compile_text(NEST)
    trees, logp = sample_trees(g, 8, 11)
    scenes = [scene_from_tree(g, trees.tree(i), f"s{i}", float(logp[i])) for i in range(8)]

    def run(path, iterations, jobs, resume):
        opts = FitOptions(iterations=iterations, estep="mcmc", samples=6, tol=0, jobs=jobs)
        with FitJournal(path, fit_header(NEST, tmp_path, scenes, opts), resume) as journal:
            return fit_grammar(NEST, GrammarSource("<nest>"), scenes, opts, journal)

    whole = run(tmp_path / "a.jsonl", 2, 1, False)
    first = run(tmp_path / "b.jsonl", 1, 2, False)
    resumed = run(tmp_path / "b.jsonl", 2, 1, True)
    assert resumed.iterations[0] == first.iterations[0]  # read back, its seconds included
    assert resumed.text == whole.text
    assert resumed.iterations[1]["posterior"] == whole.iterations[1]["posterior"]
    assert whole.text != NEST


# ----------------------------------------------- a fit from the truth stays there ---

CHECKED = ("p", "mean", "variance")  # concentrations: reported, not checked (few edges)


def _true_tree_noise(g, trees, n, boots=40, seed=0):
    """The true-tree MLE of every fitted number and its standard error (bootstrap over
    scenes): the sampling noise a fit from the truth should stay within."""
    mle = flatten(m_step(g, trees, np.ones(n), FitSettings()))
    rng = np.random.default_rng(seed)
    one = [trees.tree(i) for i in range(n)]
    values = []
    for _ in range(boots):
        pick = Trees.concatenate([one[i] for i in rng.integers(n, size=n)])
        values.append(flatten(m_step(g, pick, np.ones(n), FitSettings())))
    se = {k: float(np.std([v[k] for v in values if k in v])) for k in mle}
    return mle, se


def _off(fitted, mle, se, sigmas=3.0):
    """The checked numbers further than `sigmas` standard errors from the true-tree MLE."""
    return {
        k: (round(fitted[k], 4), round(v, 4), round(se[k], 4))
        for k, v in mle.items()
        if k.rsplit(".", 1)[-1].split("[")[0] in CHECKED
        and k in fitted
        and abs(fitted[k] - v) > sigmas * se[k] + 1e-9
    }


def _fit_from_truth(text, n, seed, iterations, estep, **options):
    g = compile_text(text)
    trees, logp = sample_trees(g, n, seed)
    scenes = [scene_from_tree(g, trees.tree(i), f"s{i}", float(logp[i])) for i in range(n)]
    mle, se = _true_tree_noise(g, trees, n)
    opts = FitOptions(iterations=iterations, estep=estep, tol=0, **options)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "j.jsonl"
        with FitJournal(path, fit_header(text, Path(d), scenes, opts), resume=False) as j:
            result = fit_grammar(text, GrammarSource("<truth>"), scenes, opts, j)
    return read_values(result.text, list(mle)), mle, se, result


def test_a_small_mcmc_fit_from_the_truth_stays_at_the_truth():
    """The cheap version of the slow test below (40 scenes, one iteration, short chains):
    every count law, `or` weight, mean and variance within 3 standard errors."""
    fitted, mle, se, result = _fit_from_truth(NEST, 40, 3, 1, "mcmc", samples=20, top=1)
    assert not _off(fitted, mle, se)
    assert (
        "types.InBox.repeat.rule.translation.parent_normal_offset.mean[0]"
        in (result.iterations[0]["posterior"]["spread"])
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    "grammar", ["sink.yaml", "dimsum_table.yaml", "nest"], ids=["sink", "dimsum", "nest"]
)
def test_an_mcmc_fit_from_the_truth_stays_at_the_truth(grammar):
    """200 scenes, 3 iterations from the true grammar: every count law, `or` weight, mean
    and variance within 3 standard errors of the true-tree MLE (top-N EM leaves the sink's
    count laws far outside, issue 13; docs/fitting.md 1.1 has the table)."""
    text = NEST if grammar == "nest" else (GRAMMARS / grammar).read_text()
    fitted, mle, se, _ = _fit_from_truth(text, 200, 1, 3, "mcmc", top=1)
    assert not _off(fitted, mle, se)
