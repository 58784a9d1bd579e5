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

A second kind of step, only where a derivation passes through a latent repeat/independent node
(a box tied to the root by `same`, holding one cup), cuts the *largest* such unit instead (the
box with its only cup) and leaves out attachments that would make a larger one (a cup into an
empty box): every candidate's step then cuts the same tree, so it is a heat-bath step too, and
the chain can open and close boxes; half the steps are of each kind.  With only the first, a
box's only cup could never leave it (count 0) and no box was ever proposed: the chain sat on
its start tree.

Derivations are proposed only where every pose follows from the object's and the slot's: fixed
rules down from the slot, at most one rule with a density, `same` rules up to the object (the
bundled sink grammar's latent nodes are all of the last kind); others are not proposed.
All proposals of all scenes are scored in one `score_trees` call per round.
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
from ssgc.rules import place_rotation, place_translation
from ssgc.score import score_trees
from ssgc.tree import Trees

MAX_DEPTH = 8  # longest derivation from a repeat/independent edge down to one object
SLOT_KINDS = (Kind.REPEAT, Kind.INDEPENDENT)
_NO_DRAW = np.random.default_rng(0)  # what `place_translation` takes; a fixed rule draws nothing


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


@dataclass(frozen=True)
class Derivation:
    """One way to hang one object under a slot edge, and where each node's pose comes from."""

    nodes: NDArray[np.int64]  # (k, 3): type, rule from its parent, local parent (-1: the slot)
    structure: tuple  # its shape (`_template_structure`), to recognise it in a tree
    at_object: NDArray[np.bool_]  # (k,) at the object's pose (joined to it by `same` rules)
    nested: bool  # a repeat/independent node lies between the slot and the object


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
    """Per (slot rule, observed type): the subtrees that put one object under that edge.

    A subtree is proposed only where every pose in it follows from the slot's pose and the
    object's: along the path down to the object, fixed rules (`same`, `offset`) from the slot,
    then at most one rule with a density, then `same` rules up from the object; nodes off the
    path hang by fixed rules.  Repeat/independent nodes on the path (a box pinned to the table,
    holding this one cup) make the derivation `nested`."""

    def __init__(self, grammar: Grammar) -> None:
        self.g = grammar
        self._cache: dict[tuple[int, int], list[Derivation]] = {}
        self._same = [_is_same(grammar, r) for r in range(len(grammar.rules))]
        self._point = [
            r.translation.point is not None and r.rotation.point is not None for r in grammar.rules
        ]
        self.slot = [t.kind in SLOT_KINDS for t in grammar.types]
        self.can_nest = any(
            d.nested
            for t in grammar.types
            if t.kind in SLOT_KINDS
            for r in t.rules
            for o in range(len(grammar.types))
            if grammar.types[o].observed and grammar.types[o].kind == Kind.TERMINAL
            for d in self.of(r, o)
        )

    def of(self, rule: int, obs_type: int) -> list[Derivation]:
        key = (rule, obs_type)
        if key not in self._cache:
            child = self.g.rules[rule].child
            free = not self._point[rule]
            self._cache[key] = [
                self._derivation(nodes, obj)
                for nodes, obj in self._chain(child, rule, obs_type, MAX_DEPTH, free)
            ]
        return self._cache[key]

    def structures(self, rule: int, obs_type: int, nested: bool) -> set[tuple]:
        """The shapes of the derivations `of(rule, obs_type)` (the nested ones if `nested`)."""
        return {d.structure for d in self.of(rule, obs_type) if nested or not d.nested}

    def placed(
        self,
        d: Derivation,
        slot_xyz: NDArray[np.float64],
        slot_quat: NDArray[np.float64],
        xyz: NDArray[np.float64],
        quat: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The poses of `d`'s nodes under a slot at (slot_xyz, slot_quat), its object at
        (xyz, quat): the object's for the nodes tied to it, the others by their fixed rules."""
        k = len(d.nodes)
        out_x, out_q = np.repeat(xyz[None], k, 0), np.repeat(quat[None], k, 0)
        for i in np.flatnonzero(~d.at_object).tolist():
            up, r = int(d.nodes[i, 2]), int(d.nodes[i, 1])
            px, pq = (slot_xyz, slot_quat) if up < 0 else (out_x[up], out_q[up])
            if self._same[r]:
                out_x[i], out_q[i] = px, pq
                continue
            rule = self.g.rules[r]
            out_x[i] = place_translation(rule.translation, px[None], pq[None], _NO_DRAW)[0][0]
            out_q[i] = place_rotation(rule.rotation, pq[None], _NO_DRAW)[0][0]
        return out_x, out_q

    def _derivation(self, nodes: list[tuple[int, int, int]], obj: int) -> Derivation:
        """The object and the nodes joined to it by `same` rules take its pose; the others
        follow their parents by fixed rules (`_chain` admits no other)."""
        at_object = np.zeros(len(nodes), bool)
        at_object[obj] = True
        i, tied, nested = obj, True, False
        while i > 0:  # up the path; node 0 hangs from the slot
            tied = tied and self._same[nodes[i][1]]
            i = nodes[i][2]
            at_object[i] = tied
            nested |= self.slot[nodes[i][0]]
        return Derivation(
            np.array(nodes, np.int64).reshape(-1, 3),
            _template_structure(tuple(nodes)),
            at_object,
            nested,
        )

    def _chain(self, t: int, rule: int, obs: int, depth: int, free: bool) -> list[tuple[list, int]]:
        """Subtrees rooted at type t (reached by `rule`) holding exactly one object, of `obs`.
        `free`: a rule with a density is already on the path, so only `same` rules follow."""
        nt = self.g.types[t]
        if t == obs:
            return [([(t, rule, -1)], 0)] if nt.kind == Kind.TERMINAL else []
        if nt.observed or depth == 0 or nt.kind == Kind.TERMINAL:
            return []
        out: list[tuple[list, int]] = []
        rules = list(nt.rules)
        for i, r in enumerate(rules):
            if free and not self._same[r]:
                continue
            if nt.never_fires(i):
                continue
            rest: list[list[list[tuple[int, int, int]]]] = []
            if nt.kind == Kind.AND:  # one child holds the object, the others are empty
                rest = [self._empty(self.g.rules[q].child, q, depth - 1) for q in rules if q != r]
            below = free or not self._point[r]
            for sub, obj in self._chain(self.g.rules[r].child, r, obs, depth - 1, below):
                for combo in product(*rest):
                    nodes = [(t, rule, -1), *_shift(sub, 1)]
                    for part in combo:
                        nodes += _shift(part, len(nodes))
                    out.append((nodes, obj + 1))
        return out

    def _empty(self, t: int, rule: int, depth: int) -> list[list[tuple[int, int, int]]]:
        """Subtrees rooted at type t without any object (repeat/independent: nothing fired),
        placed by fixed rules only."""
        nt = self.g.types[t]
        if nt.observed or depth < 0 or not self._point[rule]:
            return []
        if nt.kind in (*SLOT_KINDS, Kind.TERMINAL):
            return [[(t, rule, -1)]]
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
    xyz: list[NDArray[np.float64]]  # per candidate: its nodes' positions, (k, 3)
    quat: list[NDArray[np.float64]]  # per candidate: its nodes' rotations, (k, 4)
    stay: int = -1  # which candidate is the current tree (-1: none; -2: two look alike)


class _Chain:
    """One scene's chain: its current tree and how to propose around it."""

    def __init__(self, grammar: Grammar, tree: Trees, rng: np.random.Generator) -> None:
        self.g, self.rng = grammar, rng
        self.movable = np.array(
            [t.observed and t.kind == Kind.TERMINAL for t in grammar.types], bool
        )
        self.slot_type = np.isin(grammar.tables.type_kind, [int(k) for k in SLOT_KINDS])
        self.observed = grammar.tables.type_observed
        self.set_tree(tree)

    def set_tree(self, tree: Trees) -> None:
        """Move to `tree`; its signature is computed when it is first needed."""
        self.tree = tree
        self._key: bytes | None = None
        self.parent = tree.parent.tolist()
        self.kids = _children(self.parent)

    @property
    def key(self) -> bytes:
        if self._key is None:
            self._key = signature(self.g, self.tree)
        return self._key

    def propose(self, derivations: Derivations) -> _Step | None:
        """The candidates of one Gibbs step (the current tree among them), or None to stay.
        Where the grammar has nested derivations, half the steps cut the largest unit (module
        docstring), the others the smallest."""
        tree = self.tree
        objects = np.flatnonzero((tree.parent >= 0) & self.movable[tree.type])
        if len(objects) == 0:
            return None
        largest = derivations.can_nest and bool(self.rng.random() < 0.5)
        o = int(objects[self.rng.integers(len(objects))])
        a = self._largest_unit(o, derivations) if largest else self._smallest_unit(o, derivations)
        if a is None:
            return None
        unit, obs_type, home_rule = _structure(tree, a, self.kids), int(tree.type[o]), tree.rule[a]
        keep = np.ones(len(tree), bool)
        keep[_subtree(a, self.kids)] = False
        rest = _subset(tree, keep)
        home = int(np.count_nonzero(keep[: self.parent[a]]))
        around = _Rest(rest, self.observed) if largest else None
        step = _Step(rest, [], [], [], [])
        for p in np.flatnonzero(self.slot_type[rest.type]).tolist():
            for r in self.g.types[int(rest.type[p])].rules:
                for d in derivations.of(r, obs_type):
                    if d.nested and not largest:
                        continue
                    if around is not None and around.grows(p, d, derivations, obs_type):
                        continue  # that tree's largest unit would be bigger than d
                    if p == home and r == home_rule and d.structure == unit:
                        # two look-alike derivations: recompute the key whatever is chosen
                        step.stay = len(step.slots) if step.stay == -1 else -2
                    xyz, quat = derivations.placed(
                        d, rest.xyz[p], rest.quat[p], tree.xyz[o], tree.quat[o]
                    )
                    step.slots.append(p)
                    step.nodes.append(d.nodes)
                    step.xyz.append(xyz)
                    step.quat.append(quat)
        return step

    def _smallest_unit(self, o: int, derivations: Derivations) -> int | None:
        """The subtree hanging from the nearest repeat/independent node above `o`, if it holds
        nothing but `o` in a shape `derivations` proposes."""
        types, parent, a = self.tree.type.tolist(), self.parent, o
        while parent[a] >= 0 and not self.slot_type[types[parent[a]]]:
            a = parent[a]
        if parent[a] < 0:
            return None
        shapes = derivations.structures(int(self.tree.rule[a]), types[o], nested=False)
        return a if _structure(self.tree, a, self.kids) in shapes else None

    def _largest_unit(self, o: int, derivations: Derivations) -> int | None:
        """The highest subtree above `o` that hangs from a repeat/independent node, holds no
        other observed node, and has a shape `derivations` proposes (nested ones too)."""
        tree, x, best = self.tree, o, None
        types = tree.type.tolist()
        while self.parent[x] >= 0:
            p = self.parent[x]
            shapes = derivations.structures(int(tree.rule[x]), types[o], nested=True)
            if self.slot_type[types[p]] and _structure(tree, x, self.kids) in shapes:
                best = x
            if np.count_nonzero(self.observed[tree.type[_subtree(p, self.kids)]]) > 1:
                break
            x = p
        return best


class _Rest:
    """A cut tree, as the largest-unit step asks about it: which candidates would make a unit
    larger than their derivation (then that tree's step would cut elsewhere)."""

    def __init__(self, rest: Trees, observed: NDArray[np.bool_]) -> None:
        self.rest = rest
        self.parent = rest.parent.tolist()
        self.kids = _children(self.parent)
        self.holds = observed[rest.type].copy()  # its subtree holds an observed node
        for i in np.flatnonzero(self.holds).tolist():
            j = self.parent[i]
            while j >= 0 and not self.holds[j]:
                self.holds[j] = True
                j = self.parent[j]

    def grows(self, p: int, d: Derivation, derivations: Derivations, obs_type: int) -> bool:
        """Whether some empty subtree around slot `p`, with `d` added under p, is itself a
        unit: hanging from a repeat/independent node, of a shape `derivations` proposes."""
        rest, y = self.rest, p
        while y >= 0 and not self.holds[y]:
            up = self.parent[y]
            if up >= 0 and derivations.slot[int(rest.type[up])]:
                shape = list(_structure(rest, y, self.kids))
                own = (int(rest.type[p]), int(rest.rule[p]))
                shape.remove((*own, len(self.kids[p])))
                shape = sorted([*shape, (*own, len(self.kids[p]) + 1), *d.structure])
                if tuple(shape) in derivations.structures(int(rest.rule[y]), obs_type, True):
                    return True
            y = up
        return False


def _children(parent: list[int]) -> list[list[int]]:
    kids: list[list[int]] = [[] for _ in parent]
    for i, p in enumerate(parent):
        if p >= 0:
            kids[p].append(i)
    return kids


def _subtree(root: int, kids: list[list[int]]) -> list[int]:
    out, stack = [], [root]
    while stack:
        i = stack.pop()
        out.append(i)
        stack += kids[i]
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


def _candidates(steps: list[_Step]) -> Trees:
    """Every candidate tree of every step as one batch (one scene per candidate): the cut
    tree repeated, each copy with its derivation appended at its poses (`Derivations.placed`)."""
    fields: dict[str, list[NDArray]] = {k: [] for k in ("type", "parent", "rule", "xyz", "quat")}
    sizes = []
    offset = 0
    for st in steps:
        n0 = len(st.rest)
        for slot, local, xyz, quat in zip(st.slots, st.nodes, st.xyz, st.quat, strict=True):
            k = len(local)
            fields["type"] += [st.rest.type, local[:, 0]]
            fields["rule"] += [st.rest.rule, local[:, 1]]
            rest_parent = np.where(st.rest.parent >= 0, st.rest.parent + offset, -1)
            new_parent = np.where(local[:, 2] >= 0, local[:, 2] + n0, slot) + offset
            fields["parent"] += [rest_parent, new_parent]
            fields["xyz"] += [st.rest.xyz, xyz]
            fields["quat"] += [st.rest.quat, quat]
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
    n0 = len(rest)
    parent = np.where(local[:, 2] >= 0, local[:, 2] + n0, step.slots[j])
    return Trees(
        scene=np.zeros(n0 + len(local), np.int64),
        type=np.concatenate([rest.type, local[:, 0]]),
        parent=np.concatenate([rest.parent, parent]),
        rule=np.concatenate([rest.rule, local[:, 1]]),
        xyz=np.concatenate([rest.xyz, step.xyz[j]]),
        quat=np.concatenate([rest.quat, step.quat[j]]),
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
