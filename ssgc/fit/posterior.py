"""The posterior E-step: trees drawn from P(T | scene), not only the best parses.

Top-N EM weighs each scene's N best trees by their softmax.  When a scene has many more
trees than N, that is the posterior *near its mode*, and the fit drifts toward what the mode
prefers (issue 13: the sink's count laws, off by up to a factor of five).  Here each scene
gets a Markov chain over its parse trees, started from its best parse, whose stationary law is
the exact posterior `P(T | scene) ∝ exp(score(T))` (`ssgc.score.score_trees`).

The move (a Gibbs step on one observed object): pick an observed object `o` uniformly; cut out
its *unit*, the subtree hanging from the nearest repeat/independent node above `o` (the edge a
count law or a firing probability governs, so the rest stays a valid partial tree); then put
`o` back, by every derivation the grammar allows, under every repeat/independent node of what
is left, and choose one of these trees with probability proportional to exp(score).  The cut
tree is the same for the old tree and every new one, so the set of choices is too, and the
step leaves the posterior invariant (heat-bath: the acceptance probability is 1).  Units that
hold other objects (a plate with dishes on it) are not cut: the step then keeps the tree; the
dishes move off first, one at a time, so every tree remains reachable.

Exact for dependency-style grammars, where every latent pose is pinned by an object through
`same` rules (the bundled sink grammar): a derivation whose latent nodes are not pinned that way
is not proposed.  All proposals of all scenes are scored in one `score_trees` call per round.
Seeds are per (seed, iteration, scene), so results do not depend on `--jobs` or `--resume`.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from itertools import product
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaln

from ssgc.ir import Grammar, Kind
from ssgc.parse.parser import tree_signature
from ssgc.score import score_trees
from ssgc.tree import Trees

MAX_DEPTH = 8  # longest derivation from a repeat/independent edge down to one object
SLOT_KINDS = (Kind.REPEAT, Kind.INDEPENDENT)

# A derivation: nodes (type, rule from its parent, local parent index; -1: the slot node),
# node 0 hangs from the slot; `obj` is the local index of the observed object.
Template = tuple[tuple[tuple[int, int, int], ...], int]


@dataclass(frozen=True)
class McmcSettings:
    """How long each scene's chain runs (rounds: one Gibbs step per scene)."""

    samples: int = 100  # rounds whose trees are kept
    burn_in: int = 50  # rounds run first and dropped


@dataclass
class Posterior:
    """Every scene's sampled trees, deduplicated, with weights summing to 1 per scene."""

    trees: Trees
    weights: NDArray[np.float64]
    draws: list[Trees]  # per kept round, one tree per scene: complete-data draws
    topn_mass: list[float] = field(default_factory=list)  # per scene: sampled mass on top-N


def _is_same(grammar: Grammar, rule: int) -> bool:
    """A rule that puts its child exactly at its parent's pose (`same` in both parts)."""
    r = grammar.rules[rule]
    t, q = r.translation.point, r.rotation.point
    return (
        t is not None
        and q is not None
        and bool(np.allclose(t, 0.0))
        and bool(np.allclose(np.abs(q[0]), 1.0))
    )


class Derivations:
    """Per (slot rule, observed type): the subtrees that put one object under that edge."""

    def __init__(self, grammar: Grammar) -> None:
        self.g = grammar
        self._cache: dict[tuple[int, int], list[Template]] = {}

    def of(self, rule: int, obs_type: int) -> list[Template]:
        key = (rule, obs_type)
        if key not in self._cache:
            child = self.g.rules[rule].child
            self._cache[key] = [
                (tuple(nodes), obj) for nodes, obj in self._chain(child, rule, obs_type, MAX_DEPTH)
            ]
        return self._cache[key]

    def _chain(self, t: int, rule: int, obs: int, depth: int) -> list[tuple[list, int]]:
        """Subtrees rooted at type t (reached by `rule`) holding exactly one object, of `obs`."""
        nt = self.g.types[t]
        if t == obs:
            return [([(t, rule, -1)], 0)] if nt.kind == Kind.TERMINAL else []
        if nt.observed or depth == 0 or nt.kind in (*SLOT_KINDS, Kind.TERMINAL):
            return []
        out: list[tuple[list, int]] = []
        rules = list(nt.rules)
        if nt.kind == Kind.OR:
            for r, p in zip(rules, nt.probs, strict=True):
                if p > 0 and _is_same(self.g, r):
                    for sub, obj in self._chain(self.g.rules[r].child, r, obs, depth - 1):
                        out.append(([(t, rule, -1), *_shift(sub, 1)], obj + 1))
            return out
        if not all(_is_same(self.g, q) for q in rules):
            return []
        for r in rules:  # AND: one child holds the object, the others are empty
            rest = [self._empty(self.g.rules[q].child, q, depth - 1) for q in rules if q != r]
            for sub, obj in self._chain(self.g.rules[r].child, r, obs, depth - 1):
                for combo in product(*rest):
                    nodes = [(t, rule, -1)]
                    nodes += _shift(sub, len(nodes))
                    at = 1 + obj
                    for part in combo:
                        nodes += _shift(part, len(nodes))
                    out.append((nodes, at))
        return out

    def _empty(self, t: int, rule: int, depth: int) -> list[list[tuple[int, int, int]]]:
        """Subtrees rooted at type t without any object (repeat/independent: nothing fired)."""
        nt = self.g.types[t]
        if nt.observed or depth < 0:
            return []
        if nt.kind in (*SLOT_KINDS, Kind.TERMINAL):
            return [[(t, rule, -1)]]
        if not all(_is_same(self.g, q) for q in nt.rules):
            return []
        kids = [(q, self._empty(self.g.rules[q].child, q, depth - 1)) for q in nt.rules]
        if nt.kind == Kind.OR:
            return [[(t, rule, -1), *_shift(s, 1)] for _, subs in kids for s in subs]
        out = []
        for combo in product(*[subs for _, subs in kids]):
            nodes = [(t, rule, -1)]
            for part in combo:
                nodes += _shift(part, len(nodes))
            out.append(nodes)
        return out


def _shift(nodes: list[tuple[int, int, int]], by: int) -> list[tuple[int, int, int]]:
    """A subtree's local nodes appended at position `by`, its root under local node 0."""
    return [(t, r, (p + by) if p >= 0 else 0) for t, r, p in nodes]


def _structure(tree: Trees, root: int, kids: list[list[int]]) -> tuple:
    out = []
    stack = [root]
    while stack:
        i = stack.pop()
        out.append((int(tree.type[i]), int(tree.rule[i]), len(kids[i])))
        stack += kids[i]
    return tuple(sorted(out))


def _template_structure(nodes: tuple[tuple[int, int, int], ...]) -> tuple:
    n_kids = Counter(p for _, _, p in nodes)
    return tuple(sorted((t, r, n_kids.get(i, 0)) for i, (t, r, _) in enumerate(nodes)))


class _Chain:
    """One scene's chain: its current tree and how to propose around it."""

    def __init__(self, grammar: Grammar, tree: Trees, rng: np.random.Generator) -> None:
        self.g, self.tree, self.rng = grammar, tree, rng
        self.key = tree_signature(grammar, tree)
        self.stay = -1  # which proposal of the last step is the current tree
        self.movable = np.array(
            [t.observed and t.kind == Kind.TERMINAL for t in grammar.types], bool
        )

    def propose(self, derivations: Derivations) -> list[Trees]:
        """The trees of one Gibbs step (the current tree among them), or [] to stay."""
        tree, g = self.tree, self.g
        objects = np.flatnonzero((tree.parent >= 0) & self.movable[tree.type])
        if len(objects) == 0:
            return []
        o = int(self.rng.choice(objects))
        kinds = g.tables.type_kind
        a = o
        while tree.parent[a] >= 0 and kinds[tree.type[tree.parent[a]]] not in SLOT_KINDS:
            a = int(tree.parent[a])
        if tree.parent[a] < 0:
            return []
        kids: list[list[int]] = [[] for _ in range(len(tree))]
        for i in range(1, len(tree)):
            if tree.parent[i] >= 0:
                kids[tree.parent[i]].append(i)
        unit = _structure(tree, a, kids)
        templates = derivations.of(int(tree.rule[a]), int(tree.type[o]))
        known = [_template_structure(n) for n, _ in templates]
        if unit not in known:
            return []  # the unit holds more than o: keep the tree this step
        keep = np.ones(len(tree), bool)
        stack = [a]
        while stack:
            i = stack.pop()
            keep[i] = False
            stack += kids[i]
        rest = _subset(tree, keep)
        obs_type = int(tree.type[o])
        home = int(np.cumsum(keep)[tree.parent[a]] - 1)
        out = []
        self.stay = -1
        for p in np.flatnonzero(np.isin(kinds[rest.type], [int(k) for k in SLOT_KINDS])):
            for r in g.types[int(rest.type[p])].rules:
                for nodes, _ in derivations.of(r, obs_type):
                    if p == home and r == tree.rule[a] and _template_structure(nodes) == unit:
                        # two look-alike derivations: recompute the key whatever is chosen
                        self.stay = len(out) if self.stay == -1 else -2
                    out.append(_attach(rest, int(p), nodes, tree.xyz[o], tree.quat[o]))
        return out


def _subset(tree: Trees, keep: NDArray[np.bool_]) -> Trees:
    new_index = np.cumsum(keep) - 1
    parent = tree.parent[keep]
    parent = np.where(parent >= 0, new_index[np.maximum(parent, 0)], -1)
    n = int(keep.sum())
    return Trees(
        scene=np.zeros(n, np.int64),
        type=tree.type[keep],
        parent=parent,
        rule=tree.rule[keep],
        xyz=tree.xyz[keep],
        quat=tree.quat[keep],
        n_scenes=1,
    )


def _attach(
    rest: Trees, slot: int, nodes: tuple[tuple[int, int, int], ...], xyz: NDArray, quat: NDArray
) -> Trees:
    """`rest` with a derivation hung from node `slot`; every new node at the object's pose
    (the derivation's rules below the slot edge are all `same`)."""
    n0, k = len(rest), len(nodes)
    local = np.array(nodes, np.int64).reshape(k, 3)
    parent = np.where(local[:, 2] >= 0, local[:, 2] + n0, slot)
    return Trees(
        scene=np.zeros(n0 + k, np.int64),
        type=np.concatenate([rest.type, local[:, 0]]),
        parent=np.concatenate([rest.parent, parent]),
        rule=np.concatenate([rest.rule, local[:, 1]]),
        xyz=np.concatenate([rest.xyz, np.broadcast_to(xyz, (k, 3))]),
        quat=np.concatenate([rest.quat, np.broadcast_to(quat, (k, 4))]),
        n_scenes=1,
    )


def sample_posterior(
    grammar: Grammar,
    starts: list[Trees],
    settings: McmcSettings,
    seed: int,
    iteration: int,
    top_signatures: list[set[bytes]] | None = None,
    deadline: float | None = None,
) -> Posterior | None:
    """Run every scene's chain from its start tree; keep `samples` rounds after `burn_in`.
    None if `deadline` (a `time.monotonic()` value) passes first."""
    derivations = Derivations(grammar)
    chains = [
        _Chain(grammar, t, np.random.default_rng([seed, iteration, i]))
        for i, t in enumerate(starts)
    ]
    counts: list[Counter[bytes]] = [Counter() for _ in chains]
    examples: list[dict[bytes, Trees]] = [{} for _ in chains]
    draws: list[Trees] = []
    for rnd in range(settings.burn_in + settings.samples):
        if deadline is not None and time.monotonic() >= deadline:
            return None
        _round(grammar, chains, derivations)
        if rnd < settings.burn_in:
            continue
        draws.append(Trees.concatenate([c.tree for c in chains]))
        for i, c in enumerate(chains):
            counts[i][c.key] += 1
            examples[i].setdefault(c.key, c.tree)
    trees, weights, mass = [], [], []
    for i, cnt in enumerate(counts):
        total = sum(cnt.values())
        for key, n in cnt.items():
            trees.append(examples[i][key])
            weights.append(n / total)
        if top_signatures is not None:
            mass.append(sum(n for key, n in cnt.items() if key in top_signatures[i]) / total)
    return Posterior(Trees.concatenate(trees), np.asarray(weights), draws, mass)


def log_orders(grammar: Grammar, trees: Trees) -> NDArray[np.float64]:
    """Per tree of the batch: the sum over its repeat nodes of log c!, c their children.

    `score_trees` is the probability of one *ordered* draw of a repeat node's c children, but
    a scene is a set of objects: every one of the c! orders gives the same set and the same
    tree.  The factor differs between trees that nest an object and trees that do not
    (moving a dish from a bin of k into an empty bowl divides it by k), so weighing trees
    without it favours nesting (issue 13).  Both E-steps of `ssg fit` add it.
    """
    kinds = grammar.tables.type_kind
    child = trees.parent >= 0
    under_repeat = child & (kinds[trees.type[np.maximum(trees.parent, 0)]] == Kind.REPEAT)
    counts = np.bincount(trees.parent[under_repeat], minlength=len(trees))
    per_node = gammaln(counts + 1.0)
    return np.bincount(trees.scene, per_node, minlength=trees.n_scenes)


def posterior_scores(grammar: Grammar, trees: Trees) -> NDArray[np.float64]:
    """log P(T, scene) for trees whose repeat children are unordered: the tree score plus,
    per repeat node with c children, log c! (`log_orders`)."""
    return score_trees(grammar, trees) + log_orders(grammar, trees)


def _round(grammar: Grammar, chains: list[_Chain], derivations: Derivations) -> None:
    """One Gibbs step in every chain, all proposals scored in one batch."""
    proposals = [c.propose(derivations) for c in chains]
    flat = [t for ps in proposals for t in ps]
    if not flat:
        return
    scores = posterior_scores(grammar, Trees.concatenate(flat))
    at = 0
    for c, ps in zip(chains, proposals, strict=True):
        s = scores[at : at + len(ps)]
        at += len(ps)
        if not ps or not np.isfinite(s).any():
            continue
        w = np.exp(s - s.max())
        pick = int(c.rng.choice(len(ps), p=w / w.sum()))
        c.tree = ps[pick]
        if pick != c.stay:
            c.key = tree_signature(grammar, c.tree)


def spread(updates_per_draw: list[list[Any]]) -> dict[str, dict[str, float]]:
    """Per discrete parameter (a `p` or a `probs` entry): mean and standard deviation of its
    estimate across complete-data draws (one sampled tree per scene)."""
    values: dict[str, list[float]] = {}
    for updates in updates_per_draw:
        for u in updates:
            where = ".".join(str(k) for k in u.path)
            for key, v in u.values.items():
                if key == "p" and isinstance(v, float):
                    values.setdefault(f"{where}.p", []).append(v)
                elif key == "probs" and isinstance(v, list):
                    for j, x in enumerate(v):
                        values.setdefault(f"{where}.probs[{j}]", []).append(float(x))
    return {
        k: {"mean": float(np.mean(v)), "std": float(np.std(v))}
        for k, v in values.items()
        if len(v) == len(updates_per_draw)
    }


def posterior_e_step(
    grammar: Grammar,
    scene_trees: list[list[Trees]],
    settings: McmcSettings,
    fit_settings: Any,
    ties: Any,
    seed: int,
    iteration: int,
    spread_draws: int = 20,
    deadline: float | None = None,
) -> tuple[Trees, NDArray[np.float64], dict[str, Any]] | None:
    """The sampled trees and weights for the M-step, and what the report says about them.

    `scene_trees[i]` are scene i's top-N parses, best first (the chain starts at the best).
    None if `deadline` passed before the chains finished.  The report has the mean share of
    the sampled posterior that the top-N trees carry, the scenes where it is below one half,
    and each discrete parameter's spread across draws.
    """
    from ssgc.fit.mstep import m_step  # the public entry; imported here to keep imports light

    tops = [{tree_signature(grammar, t) for t in trees} for trees in scene_trees]
    starts = [t[0] for t in scene_trees]
    post = sample_posterior(grammar, starts, settings, seed, iteration, tops, deadline)
    if post is None:
        return None
    picks = np.unique(np.linspace(0, len(post.draws) - 1, min(spread_draws, len(post.draws))))
    per_draw = [
        m_step(grammar, post.draws[int(k)], np.ones(len(scene_trees)), fit_settings, ties)
        for k in picks
    ]
    mass = np.asarray(post.topn_mass)
    report: dict[str, Any] = {
        "samples": settings.samples,
        "burn_in": settings.burn_in,
        "topn_mass_mean": float(mass.mean()),
        "scenes_topn_mass_below_half": int(np.sum(mass < 0.5)),
        "spread": spread(per_draw),
    }
    if mass.mean() < 0.5:
        report["warning"] = (
            f"the top-N trees carry {mass.mean():.0%} of the sampled posterior on average: "
            "top-N EM would be biased here"
        )
    return post.trees, post.weights, report
