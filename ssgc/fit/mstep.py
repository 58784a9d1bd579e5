"""The M-step of approximate EM (thesis 4.3): closed-form parameter updates from weighted trees.

Every parse tree of every scene comes with its posterior weight (the softmax of the top-N
tree scores of its scene), and each of its nodes and edges counts with that weight.  Each
parameter is then set to its weighted maximum-likelihood value *within the family the user
wrote*: an isotropic variance stays one number, a diagonal one three, a Bingham given by mode
and concentrations keeps that form, a geometric count law stays geometric.  So the fitted
grammar reads like the original with new numbers, and EM stays a (generalised) EM: every
update is the exact maximiser of its term, or, for a Bingham about a mode, a coordinate ascent
that starts from the current value and never lowers it.

Discrete laws get a small pseudocount on every outcome the user left possible, so an outcome
that the current parses happen not to use does not become impossible (the reference code let
unseen counts fall to probability 0).  Outcomes the user made impossible (a weight of 0, an
independent rule with p = 0 or 1) stay so.  Boxes and revolute ranges are supports, not
shapes: their maximum-likelihood value is the hull of the data, which would make every scene
slightly outside it impossible, so they are kept as written (docs/fitting.md).  Nodes below a
rule whose subtree can hold no observed node (`ssgc.fit.observable`) are not counted: the
parser puts them at their modes, which says nothing about the data (docs/fitting.md 4.1).
Latent poses with observed nodes below are counted at the parser's (MAP) values.  Where a
latent position's posterior is Gaussian (every translation law touching it a Normal,
`ssgc.fit.laplace`), each Normal edge also gets its residual's posterior covariance, so a
Normal's spread is fitted to E[r rᵀ] = r̂ r̂ᵀ + Cov(r) rather than to the MAP residuals alone,
which are too tight (docs/fitting.md 4.5); rotations stay at their MAP values.

The output is a list of `Update`s: document paths and the numbers to put there, which
`ssgc.fit.writeback` writes into the user's YAML.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import SsgError
from ssgc.fit.laplace import latent_spread
from ssgc.fit.observable import observable_rules, pose_observable_rules, unobserved_nodes
from ssgc.fit.writeback import Update
from ssgc.ir import Grammar, Kind, NodeType
from ssgc.laws.position_normal import NormalTranslation
from ssgc.laws.rotation_bingham import MAX_CONCENTRATION
from ssgc.rules import rotation_coordinates, translation_coordinates
from ssgc.score import fired_slots, seen_nodes
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]
MM_ROUNDS = 200  # rule-frequency iterations when max_nesting blocks rules at some nodes


# m²: the largest variance floor (a 1 km deviation).  A floor near the largest float made the
# full-covariance fit's eigenvalue products overflow to inf, which no grammar can hold.
MAX_MIN_VARIANCE = 1e6
# The largest pseudocount: a million nodes per outcome outweighs any dataset ssg fit takes, and
# one near the largest float overflowed the geometric count law's fit (an internal error).
MAX_PSEUDOCOUNT = 1e6


@dataclass(frozen=True)
class FitSettings:
    """How the M-step regularises: see `ssg fit --help` and docs/fitting.md."""

    pseudocount: float = 0.01  # added to every possible outcome of a discrete law
    min_variance: float = 1e-6  # m², the floor of every fitted variance (1 mm std)
    max_concentration: float = MAX_CONCENTRATION

    def __post_init__(self) -> None:
        """Out-of-range settings are the caller's mistake, told before any work."""
        checks = (
            (
                "pseudocount",
                self.pseudocount,
                0.0 <= self.pseudocount <= MAX_PSEUDOCOUNT,
                f"≥ 0 and at most {MAX_PSEUDOCOUNT:g}",
            ),
            (
                "min_variance",
                self.min_variance,
                0.0 < self.min_variance <= MAX_MIN_VARIANCE,
                f"above 0 and at most {MAX_MIN_VARIANCE:g} m²",
            ),
            (
                "max_concentration",
                self.max_concentration,
                0.0 < self.max_concentration <= MAX_CONCENTRATION,
                f"above 0 and at most {MAX_CONCENTRATION:g}",
            ),
        )
        refuse_out_of_range(checks)


def refuse_out_of_range(checks: Iterable[tuple[str, Any, bool, str]]) -> None:
    """(name, value, in range, what is wanted) per option: the first out of range is the
    caller's mistake, told before any work."""
    for name, value, ok, wanted in checks:
        if not ok:
            raise SsgError.single(f"{name} must be {wanted}, got {value!r}")


@dataclass(frozen=True)
class Ties:
    """Pose laws written once and used by several rules (a YAML anchor and its aliases).

    `translation[r]` is the rule whose translation law rule r shares (itself if none), and the
    same for `rotation`: one law, so one fit, to the edges of every rule that uses it.
    """

    translation: NDArray[np.int64]
    rotation: NDArray[np.int64]

    @classmethod
    def none(cls, grammar: Grammar) -> Ties:
        ids = np.arange(len(grammar.rules))
        return cls(ids, ids.copy())


@dataclass(frozen=True)
class _Edges:
    """Every edge of the weighted trees: its rule, weight and child pose in its rule's terms."""

    rule: NDArray[np.int64]
    weight: FloatArray
    u: FloatArray  # (E, 3) translation coordinates
    q: FloatArray  # (E, 4) rotation coordinates
    cov: FloatArray | None  # (E, 3, 3) posterior covariance of u (ssgc.fit.laplace), if any


def m_step(
    grammar: Grammar,
    trees: Trees,
    tree_weight: FloatArray,
    settings: FitSettings,
    ties: Ties | None = None,
    rotations: bool = True,
    map_latents: bool = True,
) -> list[Update]:
    """New values for every fittable parameter that the weighted trees say something about.

    `rotations=False` leaves the rotation laws out: their Bingham fits are most of an M-step's
    time, and the posterior E-step's per-draw spread (`ssgc.fit.posterior`) repeats the M-step
    twenty times for the discrete laws and the translations.

    `map_latents`: the trees' latent positions are the parser's MAP values, so the Normal
    edges touching free ones get their posterior covariance (`ssgc.fit.laplace`).  Pass False
    for trees whose latent positions are known (sampled trees: the maximum likelihood on the
    true trees)."""
    ties = ties or Ties.none(grammar)
    observable = observable_rules(grammar)
    hidden = unobserved_nodes(trees, observable)
    node_weight = np.where(hidden, 0.0, tree_weight[trees.scene])
    counts, exists, blocked = fired_slots(grammar, trees)
    allowed = exists & ~blocked
    updates: list[Update] = []
    weighted = np.flatnonzero(node_weight > 0)
    by_type = _groups(trees.type[weighted], len(grammar.types))
    for t in grammar.types:
        if t.fixed or t.kind in (Kind.TERMINAL, Kind.AND):
            continue
        rows = weighted[by_type[t.id]]
        c, a, w = counts[rows], allowed[rows], node_weight[rows]
        seen = observable[list(t.rules)]
        updates += _choice_updates(grammar, t, c, a, w, seen, settings.pseudocount)
    # an unseen node's pose is integrated out of the score (`ssgc.score`): where the parser
    # left it says nothing about its law
    shown = seen_nodes(grammar, trees)
    edge_weight = np.where(shown, node_weight, 0.0)
    edges = _edges(grammar, trees, edge_weight, (hidden | ~shown) if map_latents else None)
    by_translation = _groups(ties.translation[edges.rule], len(grammar.rules))
    by_rotation = _groups(ties.rotation[edges.rule], len(grammar.rules))
    # a pose that moves no observed pose says nothing about its law (`pose_observable_rules`)
    moves_position, moves_rotation = pose_observable_rules(grammar)
    for rule in grammar.rules:
        take_t = by_translation[rule.id]
        parts = [(rule.translation, take_t[moves_position[edges.rule[take_t]]], edges.u)]
        if rotations:
            take_r = by_rotation[rule.id]
            parts.append((rule.rotation, take_r[moves_rotation[edges.rule[take_r]]], edges.q))
        for law, take, local in parts:
            if law.fits and take.size:
                x, w = local[take], edges.weight[take]
                spread = local is edges.u and edges.cov is not None
                if spread and isinstance(law, NormalTranslation):
                    x, w = _with_spread(x, w, edges.cov[take])
                values = law.fit(x, w, settings)
                if values is not None:
                    updates.append(Update(law.path, values))
    return updates


def _groups(keys: NDArray[np.int64], n: int) -> list[NDArray[np.int64]]:
    """For each key 0..n-1, the positions holding it: one sort rather than a scan per key."""
    order = np.argsort(keys, kind="stable")
    return np.split(order, np.searchsorted(keys[order], np.arange(1, n)))


def _edges(
    grammar: Grammar, trees: Trees, node_weight: FloatArray, hidden: NDArray[np.bool_] | None
) -> _Edges:
    """`hidden`: the nodes `unobserved_nodes` names, to integrate the free latent positions of the
    others (`ssgc.fit.laplace`); None to take every pose as it is."""
    child = np.flatnonzero((trees.rule >= 0) & (node_weight > 0))
    rule, parent = trees.rule[child], trees.parent[child]
    u = translation_coordinates(
        grammar, rule, trees.xyz[parent], trees.quat[parent], trees.xyz[child]
    )
    q = rotation_coordinates(grammar, rule, trees.quat[parent], trees.quat[child])
    spread = None if hidden is None else latent_spread(grammar, trees, hidden)
    cov = spread.edge_cov[child] if spread is not None and spread.any else None
    return _Edges(rule, node_weight[child], u, q, cov)


def _with_spread(u: FloatArray, w: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Points and weights whose weighted mean is that of `u` and whose weighted second moment
    is that of `u` plus `cov`: each edge with a covariance C = Σ λᵢ vᵢ vᵢᵀ becomes the six
    points u ± √(3λᵢ) vᵢ, each with a sixth of its weight (the points of an unscented
    transform).  A Normal's weighted maximum-likelihood fit reads only these two moments, so
    it is then the fit to E[u uᵀ] = û ûᵀ + C.  Edges without a covariance stay one point."""
    spread = np.any(cov != 0, axis=(1, 2))
    if not spread.any():
        return u, w
    lam, vec = np.linalg.eigh(cov[spread])
    axes = vec * np.sqrt(3.0 * np.maximum(lam, 0.0))[:, None, :]  # columns √(3λᵢ) vᵢ
    steps = np.concatenate([axes, -axes], axis=2).transpose(0, 2, 1)  # (S, 6, 3)
    points = (u[spread][:, None, :] + steps).reshape(-1, 3)
    weights = np.repeat(w[spread] / 6.0, 6)
    return np.concatenate([u[~spread], points]), np.concatenate([w[~spread], weights])


# ------------------------------------------------------------------ discrete laws ---


def _choice_updates(
    grammar: Grammar,
    t: NodeType,
    counts: NDArray[np.int64],
    allowed: NDArray[np.bool_],
    w: FloatArray,
    observable: NDArray[np.bool_],
    alpha: float,
) -> list[Update]:
    """The type's discrete law.  `observable[k]`: whether rule k's subtree can hold an
    observed node; the data say nothing about whether one that cannot fired."""
    k = len(t.rules)
    counts, allowed = counts[:, :k], allowed[:, :k]
    if t.kind == Kind.OR:
        fired = counts.sum(axis=1) == 1
        probs = _or_probs(counts[fired], allowed[fired], w[fired], t.probs, alpha)
        if probs is None:
            return []
        probs = _share_unobservable(probs, t.probs, observable)
        return [
            Update(grammar.rules[r].path, {"p": float(p)})
            for r, p, old in zip(t.rules, probs, t.probs, strict=True)
            if old > 0  # a written 0 stays as written
        ]
    if t.kind == Kind.INDEPENDENT:
        return _independent_updates(grammar, t, counts, allowed & observable, w, alpha)
    if not observable[0]:
        return []
    return _count_update(t, counts[allowed[:, 0], 0], w[allowed[:, 0]], alpha)


def _share_unobservable(
    probs: FloatArray, old: FloatArray, observable: NDArray[np.bool_]
) -> FloatArray:
    """The fitted mass of the rules whose subtrees hold nothing observed, split between them
    as the old weights were.  Together they are seen (a scene without the observable options
    is evidence for them), but which of them fired, no scene tells: the parser picks the one
    whose mode scores best, which would otherwise take all their mass."""
    group = ~observable & (old > 0)
    if not group.any():
        return probs
    out = probs.copy()
    out[group] = probs[group].sum() * old[group] / old[group].sum()
    return out


def _or_probs(
    counts: NDArray[np.int64],
    allowed: NDArray[np.bool_],
    w: FloatArray,
    old: FloatArray,
    alpha: float,
) -> FloatArray | None:
    """Weighted rule frequencies, MAP under a Dirichlet(1 + alpha) prior on possible rules.

    Where max_nesting blocks some rules at a node, that node chose among the others only, with
    probabilities renormalised over them (ssgc.score); the MLE then has no closed form and is
    found by the minorise-maximise iteration for choices from subsets, which increases the
    likelihood at every step and is exact after one step when nothing is blocked.
    """
    if not w.sum() > 0:
        return None
    possible = old > 0
    chosen = np.argmax(counts, axis=1)
    n_k = np.bincount(chosen, weights=w, minlength=len(old)) + alpha * possible
    p = old / old.sum()
    full = np.all(allowed | ~possible, axis=1)
    partial = ~full
    for _ in range(MM_ROUNDS):
        denom = np.full(len(old), w[full].sum() + alpha * possible.sum())
        if np.any(partial):
            mass = allowed[partial] @ p
            denom += (w[partial] / mass) @ allowed[partial]
        new = np.where(possible, n_k / np.maximum(denom, 1e-300), 0.0)
        new /= new.sum()
        converged = np.max(np.abs(new - p)) < 1e-13
        p = new
        if converged or not np.any(partial):
            break
    return p


def _independent_updates(
    grammar: Grammar,
    t: NodeType,
    counts: NDArray[np.int64],
    allowed: NDArray[np.bool_],
    w: FloatArray,
    alpha: float,
) -> list[Update]:
    fired = (counts >= 1) & allowed
    seen = w @ allowed
    hits = w @ fired
    out = []
    for slot, rule_id in enumerate(t.rules):
        old = float(t.probs[slot])
        if seen[slot] <= 0 or old in (0.0, 1.0):
            continue
        p = (hits[slot] + alpha) / (seen[slot] + 2 * alpha)
        out.append(Update(grammar.rules[rule_id].path, {"p": float(p)}))
    return out


def _count_update(t: NodeType, n: NDArray[np.int64], w: FloatArray, alpha: float) -> list[Update]:
    """A `probs` law gets its weighted count frequencies, a geometric one its MLE `p`."""
    if t.count is None or not w.sum() > 0:
        return []
    old = t.count.probs
    hist = np.bincount(n, weights=w, minlength=old.size)[: old.size] + alpha * (old > 0)
    fitted = t.count.fit(hist)
    return [] if fitted is None else [Update(*fitted)]
