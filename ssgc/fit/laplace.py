"""The Laplace correction for latent positions (docs/fitting.md 4.5).

The parser puts every latent node at its MAP pose.  Given the tree, its rotations held at their
MAP values and the observed positions, the log-density is quadratic in the latent positions
wherever every translation law touching them is a Normal: the latent positions' posterior is
then exactly Gaussian about the MAP, with the precision assembled here from every Normal
translation edge that touches a free latent node (each edge adds its law's precision, turned
into world axes for parent-frame laws, on the difference of its end positions, or on the
child's position alone for a `world_normal`).  The M-step (`ssgc.fit.mstep`) adds the
posterior covariance of each edge's coordinate to the outer product of its MAP residual, so a
Normal's fitted spread is the mean of r rᵀ + Cov(r), not of r rᵀ alone; and the E-step adds
½ log det(2πΣ) per tree to its score (the Laplace volume of the latent positions), so trees
are weighed by their evidence with the latent positions integrated out rather than at their
best values.

A latent node is *free* (in the Gaussian) when it is not the root, is not in a subtree that
can hold nothing observed (those are left out altogether: integrating such a subtree out gives
1, section 4.1 of the docs) and every translation edge touching it (into it and out of it) is
a Normal with no pinned axis.  Any other latent node (a `same` or fixed `offset` rule, a box,
a pinned axis) is held fixed at its MAP position like an observed one: its edges' residuals get
no covariance, and a free node's edge to it counts only on the free end.  Rotations are never
integrated.  A grammar with no free latent node gets zeros everywhere, and the fit is exactly
the uncorrected one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.fit.observable import observable_rules, unobserved_nodes
from ssgc.geometry import quat_to_matrix
from ssgc.ir import Grammar
from ssgc.laws.base import Frame
from ssgc.laws.position_normal import NormalTranslation
from ssgc.score import seen_nodes
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]
LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True)
class LatentSpread:
    """`edge_cov[n]`: the posterior covariance (3, 3), in its law's coordinates, of the edge
    into node n (zero where its end positions are all held fixed); `log_volume[t]`: ½ log
    det(2πΣ) of tree t's free latent positions (0 without any)."""

    edge_cov: FloatArray
    log_volume: FloatArray
    free: NDArray[np.bool_]  # (N,) nodes whose position was integrated

    @property
    def any(self) -> bool:
        return bool(self.free.any())


def hidden_nodes(grammar: Grammar, trees: Trees) -> NDArray[np.bool_]:
    """Nodes at or below the child of a rule whose subtree can hold nothing observed."""
    return unobserved_nodes(trees, observable_rules(grammar))


def latent_spread(
    grammar: Grammar, trees: Trees, hidden: NDArray[np.bool_] | None = None
) -> LatentSpread:
    """The Gaussian posterior of every tree's free latent positions about their MAP values."""
    n = len(trees)
    if hidden is None:  # and the unseen nodes, whose positions the score integrates out
        hidden = hidden_nodes(grammar, trees) | ~seen_nodes(grammar, trees)
    edge_cov = np.zeros((n, 3, 3))
    log_volume = np.zeros(trees.n_scenes)
    if not grammar.rules:  # a grammar of one root: no edge, nothing latent to spread
        return LatentSpread(edge_cov, log_volume, np.zeros(n, bool))
    normal, precision, frame = _rule_tables(grammar)
    is_edge = (trees.rule >= 0) & ~hidden
    rule = np.maximum(trees.rule, 0)
    bad = is_edge & ~normal[rule]  # an edge the Gaussian cannot hold: its ends stay fixed
    blocked = bad.copy()
    blocked[trees.parent[bad]] = True
    observed = np.array([t.observed for t in grammar.types], bool)[trees.type]
    free = ~observed & (trees.parent >= 0) & ~hidden & ~blocked
    if not free.any():
        return LatentSpread(edge_cov, log_volume, free)

    # Each counted Normal edge touching a free node: u = J_c x_c + J_p x_p + constant.
    parent = np.maximum(trees.parent, 0)
    edges = np.flatnonzero(is_edge & normal[rule] & (free | free[parent]))
    c, p = edges, trees.parent[edges]
    f = frame[trees.rule[edges]]
    eye = np.broadcast_to(np.eye(3), (len(edges), 3, 3))
    rot_t = np.transpose(quat_to_matrix(trees.quat[p]), (0, 2, 1))  # world -> parent frame
    j_c = np.where((f == Frame.PARENT)[:, None, None], rot_t, eye)
    j_p = np.where((f == Frame.WORLD)[:, None, None], 0.0, -j_c)
    lam = precision[trees.rule[edges]]

    # Free nodes numbered within their tree; trees grouped by how many they hold.
    tree_of = trees.scene
    k_per_tree = np.bincount(tree_of[free], minlength=trees.n_scenes)
    slot = np.full(n, -1)
    free_ids = np.flatnonzero(free)
    first = np.concatenate([[0], np.cumsum(k_per_tree)])[tree_of[free_ids]]
    slot[free_ids] = np.arange(len(free_ids)) - first
    ends = ((c, j_c), (p, j_p))
    for k in np.unique(k_per_tree[k_per_tree > 0]):
        group = np.flatnonzero(k_per_tree == k)
        row = np.full(trees.n_scenes, -1)
        row[group] = np.arange(len(group))
        h = np.zeros((len(group), k, 3, k, 3))
        mine = row[tree_of[c]] >= 0
        for a, j_a in ends:
            for b, j_b in ends:
                both = mine & free[a] & free[b]
                block = np.einsum("eji,ejk,ekl->eil", j_a[both], lam[both], j_b[both])
                at = (row[tree_of[c[both]]], slot[a[both]], slice(None), slot[b[both]])
                np.add.at(h, at, block)
        h = h.reshape(len(group), 3 * k, 3 * k)
        sigma = np.linalg.inv(h).reshape(len(group), k, 3, k, 3)
        _, logdet = np.linalg.slogdet(h)
        log_volume[group] = 0.5 * (3 * k * LOG_2PI - logdet)
        # Cov(u) = Σ_ab J_a Σ_ab J_bᵀ over the free ends of each edge of these trees.
        for a, j_a in ends:
            for b, j_b in ends:
                both = mine & free[a] & free[b]
                s = sigma[row[tree_of[c[both]]], slot[a[both]], :, slot[b[both]], :]
                edge_cov[c[both]] += np.einsum("eij,ejk,elk->eil", j_a[both], s, j_b[both])
    edge_cov = 0.5 * (edge_cov + np.transpose(edge_cov, (0, 2, 1)))
    return LatentSpread(edge_cov, log_volume, free)


def _rule_tables(grammar: Grammar) -> tuple[NDArray[np.bool_], FloatArray, NDArray[np.int64]]:
    """Per rule: whether its translation law is a Normal with every axis free, its precision
    (in the law's coordinates), and its frame."""
    m = len(grammar.rules)
    normal = np.zeros(m, bool)
    precision = np.zeros((m, 3, 3))
    frame = np.zeros(m, np.int64)
    for r in grammar.rules:
        law = r.translation
        frame[r.id] = int(law.frame)
        if isinstance(law, NormalTranslation) and bool(np.all(law.free)):
            normal[r.id] = True
            precision[r.id] = law.concave_form()[1]
    return normal, precision, frame
