"""The Laplace correction for latent positions (`ssgc.fit.laplace`, docs/fitting.md 4.5)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal
from test_fit import run_fit, scenes_of

from ssgc.compile import compile_text
from ssgc.fit.laplace import latent_spread
from ssgc.fit.mstep import FitSettings, _with_spread, m_step
from ssgc.rules import translation_coordinates
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees

# A constituency grammar: latent cluster centres, each with two observed points about it.
CLUSTERS = """\
grammar: c1
root: {type: Root}
types:
  Root:
    observed: true
    repeat:
      count: {probs: [0, 0.5, 0.5]}
      rule:
        child: Cluster
        translation: {world_normal: {mean: [0.0, 0.0, 0.0], variance: 1.0}}
  Cluster:
    and:
      - child: Point
        translation: {world_normal_offset: {mean: [0.2, 0.0, 0.0], variance: 0.01}}
      - child: Point
        translation: {world_normal_offset: {mean: [-0.2, 0.0, 0.0], variance: 0.01}}
  Point: {observed: true}
"""

# Two latent levels, parent-frame laws about a rotated latent node, a full covariance.
CHAIN = """\
grammar: chain
root: {type: Root}
types:
  Root:
    observed: true
    and:
      - child: A
        translation: {world_normal_offset: {mean: [0.5, 0.0, 0.0], variance: 0.5}}
        rotation: uniform
  A:
    and:
      - child: B
        translation:
          parent_normal_offset:
            mean: [0.0, 0.3, 0.0]
            covariance: [[0.04, 0.01, 0.0], [0.01, 0.02, 0.0], [0.0, 0.0, 0.03]]
        rotation: uniform
      - child: P
        translation: {parent_normal_offset: {mean: [0.1, 0.0, 0.0], variance: [0.01, 0.02, 0.03]}}
  B:
    and:
      - child: P
        translation: {parent_normal_offset: {mean: [0.0, 0.0, 0.1], variance: 0.01}}
      - child: P
        translation: {world_normal: {mean: [1.0, 0.0, 0.0], variance: 0.05}}
  P: {observed: true}
"""


def _variances(text):
    g = compile_text(text)
    return [
        float(np.diag(r.translation.normal.cov).mean())
        for r in g.rules
        if g.types[r.child].name == "Point"
    ]


def test_offsets_about_free_latent_centres_are_not_fitted_too_tight(tmp_path):
    """The MAP centre of two points takes half their spread; the Laplace covariance gives it
    back.  (Without it one iteration fits about 0.005 to data from 0.01.)"""
    truth, scenes = scenes_of(CLUSTERS, 100, 2)
    trees, _ = sample_trees(truth, 100, 2)
    mle = m_step(truth, trees, np.ones(100), FitSettings(), map_latents=False)
    true_tree = [u.values["variance"] for u in mle if u.path[1] == "Cluster"]
    result = run_fit(tmp_path, CLUSTERS, scenes, iterations=1, top=3, tol=0.0)
    fitted = _variances(result.text)
    np.testing.assert_allclose(fitted, 0.01, rtol=0.25)
    np.testing.assert_allclose(fitted, true_tree, rtol=0.25)


def test_a_single_cluster_scene_gets_its_exact_evidence():
    """All laws Normal: score at the MAP centre + ½ log det(2πΣ) is the exact marginal."""
    g = compile_text(CLUSTERS)
    trees, _ = sample_trees(g, 40, 7)
    tree = next(trees.tree(i) for i in range(40) if len(trees.tree(i)) == 4)
    cluster = int(np.flatnonzero([g.types[t].name == "Cluster" for t in tree.type])[0])
    points = np.flatnonzero(tree.parent == cluster)
    offsets = np.array([g.rules[r].translation.offset for r in tree.rule[points]])
    y = tree.xyz[points] - offsets  # each y_i = centre + noise
    tree.xyz[cluster] = (y.sum(axis=0) / 0.01) / (1.0 + 2 / 0.01)  # the MAP centre
    spread = latent_spread(g, tree)
    laplace = score_trees(g, tree)[0] + spread.log_volume[0]
    cov = np.array([[1.01, 1.0], [1.0, 1.01]])
    exact = np.log(0.5) + sum(multivariate_normal([0, 0], cov).logpdf(y[:, a]) for a in range(3))
    assert laplace == pytest.approx(exact, abs=1e-9)
    var = 1.0 / (1.0 + 2 / 0.01)
    for p in points:
        np.testing.assert_allclose(spread.edge_cov[p], var * np.eye(3), atol=1e-12)
    np.testing.assert_allclose(spread.edge_cov[cluster], var * np.eye(3), atol=1e-12)


def test_the_covariances_are_the_inverse_hessian_of_the_tree_score():
    """Chained latent nodes, parent-frame laws about rotated parents, a world law below a
    latent node: the Gaussian and every edge's residual covariance against finite differences
    of the tree's score (exactly quadratic in the latent positions)."""
    g = compile_text(CHAIN)
    trees, _ = sample_trees(g, 1, 3)
    tree = trees.tree(0)
    latent = np.flatnonzero([not g.types[t].observed for t in tree.type])
    assert len(latent) == 2
    spread = latent_spread(g, tree)
    assert spread.free[latent].all() and spread.free.sum() == 2

    def score(x):
        moved = tree.tree(0)
        moved.xyz[latent] = x.reshape(-1, 3)
        return score_trees(g, moved)[0]

    x0, h, d = tree.xyz[latent].ravel(), 1e-3, 6
    hess = np.zeros((d, d))
    for i in range(d):
        for j in range(d):
            e_i, e_j = np.eye(d)[i] * h, np.eye(d)[j] * h
            hess[i, j] = (
                score(x0 + e_i + e_j) - score(x0 + e_i - e_j) - score(x0 - e_i + e_j)
            ) + score(x0 - e_i - e_j)
    sigma = np.linalg.inv(-hess / (4 * h * h))
    assert spread.log_volume[0] == pytest.approx(
        0.5 * np.linalg.slogdet(2 * np.pi * sigma)[1], abs=1e-5
    )
    for c in np.flatnonzero(tree.rule >= 0):
        p = tree.parent[c]

        def u(x, c=c, p=p):
            xyz = tree.xyz.copy()
            xyz[latent] = x.reshape(-1, 3)
            return translation_coordinates(g, tree.rule[[c]], xyz[[p]], tree.quat[[p]], xyz[[c]])[0]

        jac = np.stack([(u(x0 + np.eye(d)[k]) - u(x0)) for k in range(d)], axis=1)
        np.testing.assert_allclose(spread.edge_cov[c], jac @ sigma @ jac.T, atol=1e-7)


def test_latent_nodes_held_by_a_same_rule_or_a_pin_are_not_integrated():
    """A latent node tied to an observed one by `same`, or placed by a pinned Normal, stays a
    point: nothing changes for such grammars (the sink grammars)."""
    same = CLUSTERS.replace(
        "      - child: Point\n        translation: {world_normal_offset: {mean: [0.2, 0.0, 0.0], "
        "variance: 0.01}}",
        "      - child: Point",
    )
    pinned = CLUSTERS.replace("variance: 1.0}", "variance: 1.0, pin: [z]}")
    for text in (same, pinned):
        g = compile_text(text)
        trees, _ = sample_trees(g, 10, 1)
        spread = latent_spread(g, trees)
        assert not spread.any
        assert not spread.edge_cov.any() and not spread.log_volume.any()


def test_the_spread_points_carry_the_mean_and_the_added_second_moment():
    rng = np.random.default_rng(0)
    u, w = rng.normal(size=(5, 3)), rng.uniform(0.1, 1.0, 5)
    a = rng.normal(size=(5, 3, 3))
    cov = a @ np.transpose(a, (0, 2, 1))
    cov[2] = 0.0  # an edge with no covariance stays one point
    x, v = _with_spread(u, w, cov)
    assert len(x) == 4 * 6 + 1
    assert v.sum() == pytest.approx(w.sum())
    np.testing.assert_allclose(v @ x, w @ u)
    second = np.einsum("n,ni,nj->ij", v, x, x)
    want = np.einsum("n,ni,nj->ij", w, u, u) + np.einsum("n,nij->ij", w, cov)
    np.testing.assert_allclose(second, want, atol=1e-12)
