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

import hashlib
import time
from collections import Counter
from dataclasses import dataclass, field
from itertools import product
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaln

from ssgc.ir import Grammar, Kind
from ssgc.parse.poses import free_blocks
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
    draws: list[Trees]  # some kept rounds, one tree per scene each: complete-data draws
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
        self._same_rules: dict[int, bool] = {}
        self._arrays: dict[tuple[int, int], list[tuple[NDArray[np.int64], tuple]]] = {}

    def of(self, rule: int, obs_type: int) -> list[Template]:
        key = (rule, obs_type)
        if key not in self._cache:
            child = self.g.rules[rule].child
            self._cache[key] = [
                (tuple(nodes), obj) for nodes, obj in self._chain(child, rule, obs_type, MAX_DEPTH)
            ]
        return self._cache[key]

    def _same(self, rule: int) -> bool:
        if rule not in self._same_rules:
            self._same_rules[rule] = _is_same(self.g, rule)
        return self._same_rules[rule]

    def structures(self, rule: int, obs_type: int) -> set[tuple]:
        """The shapes (`_structure`) of the derivations `of(rule, obs_type)`."""
        return {structure for _, structure in self.arrays(rule, obs_type)}

    def arrays(self, rule: int, obs_type: int) -> list[tuple[NDArray[np.int64], tuple]]:
        """The derivations `of(rule, obs_type)` as (k, 3) arrays, with their shapes."""
        key = (rule, obs_type)
        if key not in self._arrays:
            self._arrays[key] = [
                (np.array(nodes, np.int64).reshape(-1, 3), _template_structure(nodes))
                for nodes, _ in self.of(rule, obs_type)
            ]
        return self._arrays[key]

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
                if p > 0 and self._same(r):
                    for sub, obj in self._chain(self.g.rules[r].child, r, obs, depth - 1):
                        out.append(([(t, rule, -1), *_shift(sub, 1)], obj + 1))
            return out
        if not all(self._same(q) for q in rules):
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
        if not all(self._same(q) for q in nt.rules):
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


def signature(grammar: Grammar, tree: Trees) -> bytes:
    """What makes two trees of a scene different, as `ssgc.parse.parser.tree_signature`
    (types, rules, the poses of nodes tied to observations; children unordered), with each
    node's own part packed by numpy: the chain needs one per move, and this is its hot spot.
    Signatures from here compare only with signatures from here."""
    top, tops = free_blocks(grammar, tree)
    latent = np.isin(top, tops)
    pose = np.round(np.concatenate([tree.xyz, np.abs(tree.quat)], axis=1), 6) + 0.0
    pose[latent] = 0.0
    ids = np.stack([tree.type, tree.rule, latent.astype(np.int64)], axis=1)
    own = [a.tobytes() + b.tobytes() for a, b in zip(ids, pose, strict=True)]
    parent = tree.parent.tolist()
    kids: list[list[bytes]] = [[] for _ in own]
    key = b""
    for i in range(len(own) - 1, -1, -1):  # children first
        key = hashlib.blake2b(own[i] + b"".join(sorted(kids[i])), digest_size=20).digest()
        if parent[i] >= 0:
            kids[parent[i]].append(key)
    return key


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


@dataclass
class _Step:
    """One chain's Gibbs step: the cut tree and every way to put the object back."""

    rest: Trees
    slots: list[int]  # per candidate: the node of `rest` it hangs from
    nodes: list[NDArray[np.int64]]  # per candidate: its derivation, (k, 3) local nodes
    xyz: NDArray[np.float64]
    quat: NDArray[np.float64]
    stay: int  # which candidate is the current tree (-1: none; -2: two look alike)


class _Chain:
    """One scene's chain: its current tree and how to propose around it."""

    def __init__(self, grammar: Grammar, tree: Trees, rng: np.random.Generator) -> None:
        self.g, self.rng = grammar, rng
        self.movable = np.array(
            [t.observed and t.kind == Kind.TERMINAL for t in grammar.types], bool
        )
        self.slot_type = np.isin(grammar.tables.type_kind, [int(k) for k in SLOT_KINDS])
        self.set_tree(tree)

    def set_tree(self, tree: Trees) -> None:
        """Move to `tree`; its signature is computed when it is first needed."""
        self.tree = tree
        self._key: bytes | None = None
        self.parent = tree.parent.tolist()
        self.kids: list[list[int]] = [[] for _ in range(len(tree))]
        for i, p in enumerate(self.parent):
            if p >= 0:
                self.kids[p].append(i)

    @property
    def key(self) -> bytes:
        if self._key is None:
            self._key = signature(self.g, self.tree)
        return self._key

    def propose(self, derivations: Derivations) -> _Step | None:
        """The candidates of one Gibbs step (the current tree among them), or None to stay."""
        tree, g = self.tree, self.g
        objects = np.flatnonzero((tree.parent >= 0) & self.movable[tree.type])
        if len(objects) == 0:
            return None
        o = int(objects[self.rng.integers(len(objects))])
        types, parent = tree.type.tolist(), self.parent
        a = o
        while parent[a] >= 0 and not self.slot_type[types[parent[a]]]:
            a = parent[a]
        if parent[a] < 0:
            return None
        unit = _structure(tree, a, self.kids)
        obs_type, home_rule = types[o], int(tree.rule[a])
        if unit not in derivations.structures(home_rule, obs_type):
            return None  # the unit holds more than o: keep the tree this step
        keep = np.ones(len(tree), bool)
        stack = [a]
        while stack:
            i = stack.pop()
            keep[i] = False
            stack += self.kids[i]
        rest = _subset(tree, keep)
        home = int(np.count_nonzero(keep[: parent[a]]))
        step = _Step(rest, [], [], tree.xyz[o], tree.quat[o], -1)
        for p in np.flatnonzero(self.slot_type[rest.type]).tolist():
            for r in g.types[int(rest.type[p])].rules:
                for local, structure in derivations.arrays(r, obs_type):
                    if p == home and r == home_rule and structure == unit:
                        # two look-alike derivations: recompute the key whatever is chosen
                        step.stay = len(step.slots) if step.stay == -1 else -2
                    step.slots.append(p)
                    step.nodes.append(local)
        return step


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


def _candidates(steps: list[_Step]) -> Trees:
    """Every candidate tree of every step as one batch (one scene per candidate): the cut
    tree repeated, each copy with its derivation appended, at the object's pose (the
    derivation's rules below the slot edge are all `same`)."""
    fields: dict[str, list[NDArray]] = {k: [] for k in ("type", "parent", "rule", "xyz", "quat")}
    sizes = []
    offset = 0
    for st in steps:
        n0 = len(st.rest)
        for slot, local in zip(st.slots, st.nodes, strict=True):
            k = len(local)
            fields["type"] += [st.rest.type, local[:, 0]]
            fields["rule"] += [st.rest.rule, local[:, 1]]
            rest_parent = np.where(st.rest.parent >= 0, st.rest.parent + offset, -1)
            new_parent = np.where(local[:, 2] >= 0, local[:, 2] + n0, slot) + offset
            fields["parent"] += [rest_parent, new_parent]
            fields["xyz"] += [st.rest.xyz, np.repeat(st.xyz[None], k, 0)]
            fields["quat"] += [st.rest.quat, np.repeat(st.quat[None], k, 0)]
            sizes.append(n0 + k)
            offset += n0 + k
    return Trees(
        scene=np.repeat(np.arange(len(sizes)), sizes),
        n_scenes=len(sizes),
        **{k: np.concatenate(v) for k, v in fields.items()},
    )


def _attach(step: _Step, j: int) -> Trees:
    """Candidate j of a step as a tree of its own."""
    rest, local = step.rest, step.nodes[j]
    n0, k = len(rest), len(local)
    parent = np.where(local[:, 2] >= 0, local[:, 2] + n0, step.slots[j])
    return Trees(
        scene=np.zeros(n0 + k, np.int64),
        type=np.concatenate([rest.type, local[:, 0]]),
        parent=np.concatenate([rest.parent, parent]),
        rule=np.concatenate([rest.rule, local[:, 1]]),
        xyz=np.concatenate([rest.xyz, np.repeat(step.xyz[None], k, 0)]),
        quat=np.concatenate([rest.quat, np.repeat(step.quat[None], k, 0)]),
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
    draws: int = 20,
) -> Posterior | None:
    """Run every scene's chain from its start tree; keep `samples` rounds after `burn_in`,
    and `draws` of them, evenly spaced, as complete-data draws (one tree per scene).
    None if `deadline` (a `time.monotonic()` value) passes first."""
    derivations = Derivations(grammar)
    chains = [
        _Chain(grammar, t, np.random.default_rng([seed, iteration, i]))
        for i, t in enumerate(starts)
    ]
    counts: list[Counter[bytes]] = [Counter() for _ in chains]
    examples: list[dict[bytes, Trees]] = [{} for _ in chains]
    picks = set(np.linspace(0, settings.samples - 1, min(draws, settings.samples)).astype(int))
    kept: list[Trees] = []
    for rnd in range(settings.burn_in + settings.samples):
        if deadline is not None and time.monotonic() >= deadline:
            return None
        _round(grammar, chains, derivations)
        if rnd < settings.burn_in:
            continue
        if rnd - settings.burn_in in picks:
            kept.append(Trees.concatenate([c.tree for c in chains]))
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
    return Posterior(Trees.concatenate(trees), np.asarray(weights), kept, mass)


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
    """One Gibbs step in every chain, all candidates of all chains scored in one batch."""
    steps = [c.propose(derivations) for c in chains]
    moving = [(c, st) for c, st in zip(chains, steps, strict=True) if st and len(st.slots) > 1]
    if not moving:
        return  # a step with one candidate keeps the tree
    scores = posterior_scores(grammar, _candidates([st for _, st in moving]))
    at = 0
    for c, st in moving:
        s = scores[at : at + len(st.slots)]
        at += len(st.slots)
        if not np.isfinite(s).any():
            continue
        w = np.exp(s - s.max())
        pick = int(c.rng.choice(len(s), p=w / w.sum()))
        if pick != st.stay:
            c.set_tree(_attach(st, pick))


SPREAD_KEYS = ("p", "probs", "mean", "variance")


def spread(updates_per_draw: list[list[Any]]) -> dict[str, dict[str, float]]:
    """Per fitted number (a `p`, every entry of a `probs`, a mean or variance component; not
    the rotation laws, whose fits would be most of the E-step's time): mean and standard
    deviation of its estimate across complete-data draws (one sampled tree per scene).  A
    number the M-step sets in only some draws (an outcome no sampled tree uses) is left out."""
    values: dict[str, list[float]] = {}
    for updates in updates_per_draw:
        for u in updates:
            where = ".".join(str(k) for k in u.path)
            for key in SPREAD_KEYS:
                v = u.values.get(key)
                if isinstance(v, (int, float)):
                    values.setdefault(f"{where}.{key}", []).append(float(v))
                elif isinstance(v, list | tuple) and all(
                    isinstance(x, int | float) or x is None for x in v
                ):  # None: kept as written (an impossible count, a pinned axis)
                    for j, x in enumerate(v):
                        if x is not None:
                            values.setdefault(f"{where}.{key}[{j}]", []).append(float(x))
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

    tops = [{signature(grammar, t) for t in trees} for trees in scene_trees]
    starts = [t[0] for t in scene_trees]
    post = sample_posterior(
        grammar, starts, settings, seed, iteration, tops, deadline, draws=spread_draws
    )
    if post is None:
        return None
    per_draw = [
        m_step(grammar, draw, np.ones(len(scene_trees)), fit_settings, ties, rotations=False)
        for draw in post.draws
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
