"""`ssg fit`: approximate EM against exact EM, parameter recovery, the M-step's pieces, the CLI."""

from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest
from conftest import GRAMMARS
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import optimize
from scipy.special import logsumexp
from typer.testing import CliRunner

import ssgc
from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.distributions.bingham import Bingham
from ssgc.distributions.discrete import CountLaw, fit_geometric_p
from ssgc.errors import SsgError
from ssgc.fit.em import FitJournal, FitOptions, GrammarSource, fit_grammar, fit_header
from ssgc.fit.mstep import FitSettings, _or_probs, m_step
from ssgc.geometry import rpy_to_quat
from ssgc.io.scene import dumps_scene, scene_from_tree
from ssgc.sample.forward import sample_trees

GMM = (GRAMMARS / "gmm.yaml").read_text()
# A poor start: equal weights, one mode misplaced and wide.
GMM_START = (
    GMM.replace("p: 0.2", "p: 0.34")
    .replace("p: 0.4", "p: 0.33")
    .replace(
        "mean: [-1.0, 0.0, 0.0], variance: [0.04, 0.09, 0.04]",
        "mean: [-0.5, 0.3, 0.0], variance: [0.3, 0.3, 0.3]",
    )
)


def scenes_of(grammar_text, n, seed):
    g = compile_text(grammar_text)
    trees, logp = sample_trees(g, n, seed)
    return g, [scene_from_tree(g, trees.tree(i), f"s{i}", float(logp[i])) for i in range(n)]


def run_fit(tmp_path, text, scenes, **options):
    opts = FitOptions(**options)
    header = fit_header(text, tmp_path, scenes, opts)
    with FitJournal(tmp_path / "fit.partial.jsonl", header, resume=False) as journal:
        return fit_grammar(text, GrammarSource("<start>"), scenes, opts, journal)


def exact_gmm_em(x, weights, means, variances, isotropic, iterations):
    """Textbook EM for a 3-D Gaussian mixture with per-component diagonal or isotropic
    variances: the loop ssg fit must reproduce when its top-N parses are all the trees."""
    pi, mu, var = np.array(weights), np.array(means), np.array(variances)
    loglik = []
    for _ in range(iterations):
        logn = -0.5 * np.sum((x[:, None, :] - mu) ** 2 / var + np.log(2 * np.pi * var), axis=2)
        joint = np.log(pi) + logn
        total = logsumexp(joint, axis=1)
        loglik.append(float(total.sum()))
        r = np.exp(joint - total[:, None])
        nk = r.sum(axis=0)
        pi = nk / nk.sum()
        mu = (r.T @ x) / nk[:, None]
        var = np.einsum("nk,nkd->kd", r, (x[:, None, :] - mu) ** 2) / nk[:, None]
        var[isotropic] = var[isotropic].mean(axis=1, keepdims=True)
    return loglik, pi, mu, var


def gmm_parameters(text):
    g = compile_text(text)
    root = g.types[g.root]
    means = np.array([g.rules[r].translation.offset for r in root.rules])
    variances = np.array([np.diag(g.rules[r].translation.normal.cov) for r in root.rules])
    return root.probs, means, variances


def test_fit_on_a_gmm_is_exact_em(tmp_path):
    """Thesis 4.4.1: with every tree in the top N, approximate EM is EM."""
    _, scenes = scenes_of(GMM, 80, seed=3)
    x = np.array([s.xyz[1] for s in scenes])
    result = run_fit(
        tmp_path,
        GMM_START,
        scenes,
        iterations=4,
        top=3,
        tol=0.0,
        settings=FitSettings(pseudocount=0.0),
    )
    assert result.status == "iterations"
    pi0, mu0, var0 = gmm_parameters(GMM_START)
    isotropic = np.array([False, False, True])
    loglik, pi, mu, var = exact_gmm_em(x, pi0, mu0, var0, isotropic, 4)
    evidence = [r["log_evidence"] for r in result.iterations]
    np.testing.assert_allclose(evidence, loglik, rtol=1e-6)
    fitted = gmm_parameters(result.text)
    np.testing.assert_allclose(fitted[0], pi, rtol=1e-5)
    np.testing.assert_allclose(fitted[1], mu, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(fitted[2], var, rtol=1e-5)


@settings(
    max_examples=5, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(seed=st.integers(0, 10_000), shift=st.floats(-0.8, 0.8))
def test_gmm_log_evidence_never_decreases(tmp_path_factory, seed, shift):
    """EM's monotonicity, for any data and start (top-3 parses enumerate every tree)."""
    start = GMM_START.replace("mean: [-0.5, 0.3, 0.0]", f"mean: [{shift:.6f}, 0.3, 0.0]")
    _, scenes = scenes_of(GMM, 25, seed)
    result = run_fit(tmp_path_factory.mktemp("f"), start, scenes, iterations=4, top=3, tol=0.0)
    evidence = np.array([r["log_evidence"] for r in result.iterations])
    assert np.all(np.diff(evidence) >= -1e-6 * np.abs(evidence[1:]))


SP_START = (
    (GRAMMARS / "singles_pairs_dependency.yaml")
    .read_text()
    .replace(
        "p: 0.7\n      - child: Pairs\n        p: 0.7",
        "p: 0.5\n      - child: Pairs\n        p: 0.5",
    )
    .replace("mean: [-0.3, -0.5, 0.0], variance: 0.01", "mean: [-0.1, -0.2, 0.0], variance: 0.04")
    .replace("concentration: 50.0", "concentration: 10.0")
)


@pytest.mark.slow
def test_fit_recovers_known_parameters_of_a_structured_grammar(tmp_path):
    """Sampled singles/pairs scenes: EM from a wrong start finds the generating values.
    (Under `slow`: 720 parses; `test_fit_from_a_wrong_start_moves_to_the_true_tree_mle` is
    the default run's version.)"""
    truth, scenes = scenes_of((GRAMMARS / "singles_pairs_dependency.yaml").read_text(), 120, 5)
    assert "p: 0.5\n      - child: Pairs" in SP_START  # the start really differs
    result = run_fit(tmp_path, SP_START, scenes, iterations=6, top=4)
    fitted = compile_text(result.text)
    root = fitted.types[fitted.root]
    np.testing.assert_allclose(root.probs, truth.types[truth.root].probs, atol=0.12)
    wing = next(r for r in fitted.rules if fitted.rule_name(r.id) == "Pair[1]->Object")
    np.testing.assert_allclose(wing.translation.offset, [-0.3, -0.5, 0.0], atol=0.03)
    assert np.diag(wing.translation.normal.cov).mean() == pytest.approx(0.01, rel=0.35)
    assert wing.rotation.bingham.concentration[0] == pytest.approx(50.0, rel=0.35)
    evidence = [r["log_evidence"] for r in result.iterations]
    assert evidence[-1] > evidence[0]


def test_fit_from_a_wrong_start_moves_to_the_true_tree_mle(tmp_path):
    """The cheap version of the test above: 40 scenes, 3 iterations, top 2.  With so few
    scenes the data's own noise is large, so the fit is compared with the maximum-likelihood
    values of the sampled trees themselves, with the same tolerances."""
    text = (GRAMMARS / "singles_pairs_dependency.yaml").read_text()
    truth, scenes = scenes_of(text, 40, 5)
    trees, _ = sample_trees(truth, 40, 5)
    mle = {
        ".".join(map(str, u.path)): u.values
        for u in m_step(truth, trees, np.ones(40), FitSettings())
    }
    result = run_fit(tmp_path, SP_START, scenes, iterations=3, top=2)
    fitted = compile_text(result.text)
    root = fitted.types[fitted.root]
    mle_probs = [mle[f"types.{truth.types[truth.root].name}.independent.{k}"]["p"] for k in (0, 1)]
    np.testing.assert_allclose(root.probs, mle_probs, atol=0.12)
    wing = next(r for r in fitted.rules if fitted.rule_name(r.id) == "Pair[1]->Object")
    path = ".".join(map(str, wing.translation.path))
    np.testing.assert_allclose(wing.translation.offset, mle[path]["mean"], atol=0.03)
    assert np.diag(wing.translation.normal.cov).mean() == pytest.approx(
        mle[path]["variance"], rel=0.35
    )
    evidence = [r["log_evidence"] for r in result.iterations]
    assert evidence[-1] > evidence[0]


# ------------------------------------------------------------------ M-step pieces ---


def test_or_frequencies_with_blocked_rules_are_the_mle():
    """Where max_nesting blocks rules, P(k) is renormalised over the others; the MM update
    must reach the maximum of that likelihood (checked against a generic optimiser)."""
    rng = np.random.default_rng(0)
    n, k = 300, 3
    allowed = np.ones((n, k), bool)
    allowed[:120, 2] = False
    allowed[200:230, 0] = False
    true = np.array([0.5, 0.2, 0.3])
    chosen = np.array([rng.choice(np.flatnonzero(a), p=true[a] / true[a].sum()) for a in allowed])
    counts = np.zeros((n, k), np.int64)
    counts[np.arange(n), chosen] = 1
    w = rng.uniform(0.2, 1.0, n)
    p = _or_probs(counts, allowed, w, np.full(k, 1 / 3), alpha=0.0)

    def nll(z):
        q = np.exp(z - logsumexp(z))
        return -np.sum(w * (np.log(q[chosen]) - np.log(allowed @ q)))

    best = optimize.minimize(nll, np.zeros(k), method="BFGS", options={"gtol": 1e-10}).x
    np.testing.assert_allclose(p, np.exp(best - logsumexp(best)), atol=1e-6)
    assert nll(np.log(p)) <= nll(best) + 1e-9


def test_geometric_p_is_the_truncated_mle():
    law = CountLaw.geometric(0.35, 6, start=1)
    hist = np.bincount(law.sample(np.random.default_rng(2), 5000), minlength=7).astype(float)
    p = fit_geometric_p(hist, start=1)

    def nll(q):
        return -hist @ np.where(hist > 0, CountLaw.geometric(q, 6, 1).log_probs, 0.0)

    grid = optimize.minimize_scalar(nll, bounds=(1e-6, 1 - 1e-9), method="bounded").x
    assert p == pytest.approx(grid, abs=1e-5)
    assert nll(p) <= nll(grid) + 1e-9
    assert fit_geometric_p([0, 4, 0, 0], start=1) == 1.0  # every count at start: a point mass
    assert fit_geometric_p([0, 4], start=1) is None  # one possible count says nothing


@pytest.mark.parametrize("isotropic", [True, False])
def test_bingham_about_a_mode_improves_on_its_start(isotropic):
    mode = rpy_to_quat(np.array([0.4, -0.3, 1.2]))
    conc = 30.0 if isotropic else [60.0, 8.0, 200.0]
    q = Bingham.from_mode(mode, conc).sample(np.random.default_rng(4), 4000)
    w = np.random.default_rng(5).uniform(0.5, 1.0, len(q))
    start_mode, start_conc = np.array([1.0, 0, 0, 0]), 1.0
    fit_mode, fit_conc = Bingham.fit_about_mode(q, w, start_mode, isotropic)

    def loglik(m, c):
        return float(w @ Bingham.from_mode(m, c).log_prob(q))

    assert loglik(fit_mode, fit_conc) >= loglik(start_mode, start_conc)
    assert loglik(fit_mode, fit_conc) >= loglik(mode, conc) - 1e-6 * abs(loglik(mode, conc))
    assert abs(fit_mode @ mode) == pytest.approx(1.0, abs=1e-3)
    np.testing.assert_allclose(fit_conc, np.broadcast_to(conc, (3,)), rtol=0.1)


# ------------------------------------------------------------------------------ CLI ---


def write_dataset(directory, grammar_text, n, seed):
    g, scenes = scenes_of(grammar_text, n, seed)
    directory.mkdir()
    for s in scenes:
        (directory / f"{s.name}.json").write_text(dumps_scene(g, s))
    return directory


def numbers_removed(line):
    return re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "#", line)


def test_cli_fit_writes_the_grammar_back_with_its_comments(tmp_path):
    data = write_dataset(tmp_path / "data", GMM, 60, 7)
    start = tmp_path / "start.yaml"
    start.write_text(GMM_START)
    out, report = tmp_path / "fitted.yaml", tmp_path / "report.json"
    result = CliRunner().invoke(
        app,
        [
            "fit",
            str(data),
            "-g",
            str(start),
            "-o",
            str(out),
            "--top",
            "3",
            "--iterations",
            "2",
            "--report",
            str(report),
        ],
    )
    assert result.exit_code == 0, result.output
    before, after = GMM_START.splitlines(), out.read_text().splitlines()
    assert len(before) == len(after)
    for a, b in zip(before, after, strict=True):
        assert numbers_removed(a) == numbers_removed(b)
    assert after != before
    doc = json.loads(report.read_text())
    assert doc["status"] in ("converged", "iterations")
    assert [r["iteration"] for r in doc["iterations"]] == list(range(1, len(doc["iterations"]) + 1))
    assert not (tmp_path / "fitted.yaml.partial.jsonl").exists()
    validate = CliRunner().invoke(app, ["validate", str(out)])
    assert validate.exit_code == 0, validate.output


@pytest.mark.parametrize("bad", ["s0", "s4"])
def test_cli_fit_refuses_a_scene_the_grammar_cannot_produce(tmp_path, bad):
    """Whether the scene comes first or after others were journalled, nothing is left: a
    resumed run would stop at the same scene."""
    data = write_dataset(tmp_path / "data", GMM, 5, 1)
    scene = json.loads((data / f"{bad}.json").read_text())
    scene["objects"].append(dict(scene["objects"][1]))  # two points: the GMM makes one
    scene.pop("tree", None)
    (data / f"{bad}.json").write_text(json.dumps(scene))
    out = tmp_path / "fitted.yaml"
    result = CliRunner().invoke(
        app, ["fit", str(data), "-g", str(GRAMMARS / "gmm.yaml"), "-o", str(out)]
    )
    assert result.exit_code == 2
    assert result.output.startswith(f"{data}: error: scene '{bad}' cannot be explained")
    assert "Traceback" not in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


ALIASED = """
grammar: tied
root: Root
types:
  Root:
    observed: true
    and:
      - child: A
        translation: {world_normal: &law {mean: [0.0, 0.0, 0.0], variance: 1.0}}
      - child: B
        translation: {world_normal: *law}
  A: {observed: true}
  B: {observed: true}
"""


def test_a_pose_law_shared_through_an_alias_is_fitted_once_on_all_its_edges(tmp_path):
    truth = ALIASED.replace(
        "mean: [0.0, 0.0, 0.0], variance: 1.0", "mean: [1.0, 2.0, 3.0], variance: 0.04"
    )
    _, scenes = scenes_of(truth, 200, 2)
    result = run_fit(tmp_path, ALIASED, scenes, iterations=1, top=1)
    assert "&law" in result.text and "*law" in result.text
    fitted = compile_text(result.text)
    a, b = (fitted.rules[i].translation for i in (0, 1))
    np.testing.assert_array_equal(a.offset, b.offset)
    pooled = np.concatenate([[s.xyz[1] for s in scenes], [s.xyz[2] for s in scenes]])
    np.testing.assert_allclose(a.offset, pooled.mean(axis=0), rtol=1e-7)
    assert np.diag(a.normal.cov)[0] == pytest.approx(pooled.var(axis=0).mean(), rel=1e-7)


TIED_COUNTS = """
grammar: tied_counts
root: Root
types:
  Root:
    observed: true
    and: [{child: A}, {child: B}]
  A:
    repeat: {count: &c {geometric: {p: 0.5, max: 3}}, rule: {child: X}}
  B:
    repeat: {count: *c, rule: {child: X}}
  X: {observed: true}
"""


def test_a_discrete_law_shared_through_an_alias_is_refused(tmp_path):
    _, scenes = scenes_of(TIED_COUNTS, 5, 0)
    with pytest.raises(SsgError, match="one YAML node"):
        run_fit(tmp_path, TIED_COUNTS, scenes, iterations=1, top=1)


@pytest.mark.timing
@pytest.mark.parametrize("limit", [2.0, 5.0])
def test_fit_time_limit_is_honoured_within_ten_percent(tmp_path, limit):
    """A constituency grammar (latent Pair poses): the limit lands inside some scene's parse."""
    text = (GRAMMARS / "singles_pairs_constituency.yaml").read_text()
    _, scenes = scenes_of(text, 200, 11)
    opts = FitOptions(iterations=50, top=3, tol=0.0)
    header = fit_header(text, tmp_path, scenes, opts)
    with FitJournal(tmp_path / "fit.partial.jsonl", header, resume=False) as journal:
        started = time.perf_counter()
        result = fit_grammar(text, GrammarSource("<c>"), scenes, opts, journal, time_limit=limit)
        elapsed = time.perf_counter() - started
    assert result.status == "time_limit"
    assert elapsed <= 1.1 * limit, elapsed


def test_a_merged_anchor_that_would_get_two_values_is_a_user_error(tmp_path):
    """`<<: *law` copies the anchored numbers into a rule that is fitted on its own: the anchor
    cannot hold both fits, so the fit stops with a message (it used to be exit 70)."""
    text = ALIASED.replace(
        "translation: {world_normal: *law}",
        "translation: {world_normal: {<<: *law, variance: 2.0}}",
    )
    _, scenes = scenes_of(text, 20, 2)
    with pytest.raises(SsgError, match="cannot give one YAML node two values"):
        run_fit(tmp_path, text, scenes, iterations=1, top=1)


def test_cli_fit_of_a_merged_anchor_names_the_file_once_and_leaves_nothing(tmp_path):
    text = ALIASED.replace(
        "translation: {world_normal: *law}",
        "translation: {world_normal: {<<: *law, variance: 2.0}}",
    )
    data = write_dataset(tmp_path / "data", text, 20, 2)
    grammar = tmp_path / "merged.yaml"
    grammar.write_text(text)
    out = tmp_path / "fitted.yaml"
    result = CliRunner().invoke(app, ["fit", str(data), "-g", str(grammar), "-o", str(out), "-q"])
    assert result.exit_code == 1, result.output
    assert result.output.startswith(f"{grammar}: error: types.Root.and[1].translation")
    assert result.output.count(str(grammar)) == 1
    assert "`<<` merge" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "merged.yaml"]


def test_a_discrete_law_shared_with_a_fixed_type_is_refused(tmp_path):
    """Fitting B's count through the alias would rewrite A's, which `fixed: true` keeps."""
    text = TIED_COUNTS.replace("  A:\n", "  A:\n    fixed: true\n")
    _, scenes = scenes_of(text, 5, 0)
    with pytest.raises(SsgError, match="a type marked `fixed: true` uses it"):
        run_fit(tmp_path, text, scenes, iterations=1, top=1)
    both_fixed = text.replace("  B:\n", "  B:\n    fixed: true\n")
    fitted = run_fit(tmp_path, both_fixed, scenes, iterations=1, top=1).text
    assert "count: &c {geometric: {p: 0.5, max: 3}}" in fitted


def test_max_concentration_caps_every_fitted_bingham(tmp_path):
    """`--max-concentration` is the ceiling of the fitted rotation laws: scenes drawn with a
    concentration of 50 fit near 50 without it and at exactly the ceiling of 20 with it (the
    data say tighter), through the CLI and `ssgc.fit` alike."""
    data = write_dataset(
        tmp_path / "data", (GRAMMARS / "singles_pairs_dependency.yaml").read_text(), 30, 2
    )
    start = tmp_path / "start.yaml"
    start.write_text(SP_START)

    def fitted_concentrations(*flags):
        out = tmp_path / f"fitted{len(flags)}.yaml"
        args = ["fit", str(data), "-g", str(start), "-o", str(out), "--top", "2"]
        result = CliRunner().invoke(app, [*args, "--iterations", "2", "-q", *flags])
        assert result.exit_code == 0, result.output
        g = compile_text(out.read_text())
        return np.concatenate(
            [r.rotation.bingham.concentration for r in g.rules if hasattr(r.rotation, "bingham")]
        )

    free = fitted_concentrations()
    assert free.max() > 30.0
    capped = fitted_concentrations("--max-concentration", "20")
    assert capped.max() == pytest.approx(20.0)
    api = ssgc.fit(ssgc.load_grammar(start), data, iterations=2, top=2, max_concentration=20.0)
    np.testing.assert_allclose(
        np.concatenate(
            [
                r.rotation.bingham.concentration
                for r in api.grammar.ir.rules
                if hasattr(r.rotation, "bingham")
            ]
        ),
        capped,
    )


@pytest.mark.parametrize(
    "setting",
    [
        {"min_variance": 5.99e307},  # the full-covariance fit overflowed to inf
        {"min_variance": 0.0},
        {"max_concentration": 2e4},
        {"max_concentration": float("nan")},
        {"pseudocount": -1.0},
    ],
)
def test_fit_settings_out_of_range_are_one_message(setting):
    """`ssgc.fit`'s bounds are checked as `ssg fit`'s flags are: one message naming the
    setting, before any work (a variance floor of 6e307 was an internal error at write-back)."""
    with pytest.raises(SsgError, match=next(iter(setting)) + " must be"):
        FitSettings(**setting)


FIT_OPTION_NAMES = (
    "iterations top method seed tol estep samples pseudocount min_variance max_concentration jobs"
).split()


def test_the_tails_are_announced_after_the_last_iteration(tmp_path) -> None:
    """After the last iteration's report the fit measures the physical tails for seconds; the
    progress bar showed a next iteration at 0/N that never moved.  `on_tails` says so."""
    from ssgc.api import fit_defaults, fit_options, open_fit

    g = ssgc.load_grammar(GRAMMARS / "sink.yaml")
    scenes = [s.data for s in g.sample(2, seed=0)]
    defaults = {k: v for k, v in fit_defaults().items() if k in FIT_OPTION_NAMES}
    options = fit_options(**{**defaults, "iterations": 1, "top": 1})
    calls: list[str] = []
    with open_fit(g, scenes, tmp_path / "data", options) as run:
        run.fit(
            on_iteration=lambda r: calls.append(f"iteration {r['iteration']}"),
            on_tails=lambda: calls.append("tails"),
        )
    assert calls == ["iteration 1", "tails"]


IMPOSSIBLE = """\
grammar: g13
root: {type: Table, pose: {xyz: [0, 0, 0.5]}}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0.25, 0, 0.5, 0.25]}
      rule:
        child: Thing
        translation:
          parent_normal_offset: {mean: [0, 0, 0.05], variance: [0.05, 0.05, 0], pin: [z]}
        rotation: {revolute: {axis: [0, 0, 1]}}
  Thing:
    or:
      - {child: Saucer, p: 0}
      - {child: Cup, p: 1}
      - {child: Plate, p: 1}
  Saucer: {observed: true}
  Cup: {observed: true}
  Plate: {observed: true}
"""


def test_impossible_outcomes_keep_their_written_zeros(tmp_path) -> None:
    """A 0 the fit keeps (docs/fitting.md 4.2) was rewritten as 0.0."""
    _, scenes = scenes_of(IMPOSSIBLE, 20, seed=1)
    text = run_fit(tmp_path, IMPOSSIBLE, scenes, iterations=1, top=1).text
    assert re.search(r"count: \{probs: \[0\.\d+, 0, 0\.\d+, 0\.\d+\]\}", text), text
    assert "- {child: Saucer, p: 0}\n" in text
    assert "- {child: Cup, p: 1}" not in text  # fitted


def test_a_grammar_without_tails_announces_no_tail_measurement(tmp_path) -> None:
    """The progress line "measuring overlaps and support" was shown after every fit, though a
    grammar without such constraints gets no tails (docs/fitting.md 4.4)."""
    from ssgc.api import fit_defaults, fit_options, open_fit

    g = ssgc.load_grammar(GRAMMARS / "gmm.yaml")
    scenes = [s.data for s in g.sample(3, seed=0)]
    defaults = {k: v for k, v in fit_defaults().items() if k in FIT_OPTION_NAMES}
    options = fit_options(**{**defaults, "iterations": 1, "top": 1})
    calls: list[str] = []
    with open_fit(g, scenes, tmp_path / "data", options) as run:
        run.fit(
            on_iteration=lambda r: calls.append(f"iteration {r['iteration']}"),
            on_tails=lambda: calls.append("tails"),
        )
    assert calls == ["iteration 1"]
