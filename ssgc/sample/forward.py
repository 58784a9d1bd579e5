"""Forward sampling (thesis Algorithm 1), vectorised over many scenes at once.

Instead of expanding one node at a time, the sampler expands a whole *level* of every tree in
the batch together: nodes of the frontier are grouped by type (the discrete choice of rules is
one vectorised draw per type) and the children are grouped by rule (one vectorised pose draw per
rule).  The Python loop runs over levels × (types + rules), never over nodes or scenes.

Reproducibility: scenes are drawn in chunks of `CHUNK` with a generator seeded by
``(seed, chunk index)``, so scene i depends only on the seed and i — asking for more scenes
extends the list without changing the first ones.

Recursion bounds: a rule whose child would exceed its type's `max_nesting` is *blocked*: it
never fires; an `or` renormalises over its unblocked rules (and produces nothing if none is
left), a blocked `repeat` produces no children.  `ssgc.score` applies the same rule, so the
sampler and the scorer define the same distribution.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import SsgError
from ssgc.ir import Grammar, Kind
from ssgc.rules import sample_children
from ssgc.score import unseen_edges
from ssgc.tree import Trees

CHUNK = 256
# Limits, so that a grammar whose trees are huge (nested repeats under a high `max_nesting`
# grow exponentially) is a message rather than a machine running out of memory.
MAX_LEVELS = 10_000  # tree depth
MAX_CHUNK_NODES = 4_000_000  # nodes of the trees drawn together (a chunk): ~320 MB of arrays


class TooLarge(SsgError):
    """The scenes drawn together would hold more than `MAX_CHUNK_NODES` nodes: a message for
    the user, which a caller drawing several scenes at once may instead answer by drawing
    fewer (`ssgc.sample.constrained`)."""


def sample_trees(grammar: Grammar, n: int, seed: int) -> tuple[Trees, NDArray[np.float64]]:
    """Draw `n` scene trees; returns them and each tree's score (`ssgc.score.score_trees`)."""
    if n < 0:
        raise ValueError(f"number of scenes must be >= 0, got {n}")
    batches, logps = [], []
    for chunk in range((n + CHUNK - 1) // CHUNK):
        trees, logp = sample_chunk(grammar, chunk_rng(seed, chunk))
        keep = min(CHUNK, n - chunk * CHUNK)
        if keep < CHUNK:
            trees = trees.tree(0) if keep == 1 else trees.first(keep)
            logp = logp[:keep]
        batches.append(trees)
        logps.append(logp)
    if not batches:
        return _empty(), np.zeros(0)
    return Trees.concatenate(batches), np.concatenate(logps)


def chunk_rng(seed: int, chunk: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFFFFFFFFFF, chunk])


def sample_chunk(
    grammar: Grammar, rng: np.random.Generator, size: int = CHUNK
) -> tuple[Trees, NDArray[np.float64]]:
    """Draw `size` trees with one generator: the level-by-level expansion from their roots."""
    tb = grammar.tables
    nest = np.zeros((size, tb.nesting_max.shape[0]), np.int64)
    if tb.nesting_slot[grammar.root] >= 0:
        nest[:, tb.nesting_slot[grammar.root]] = 1
    # Per node (accumulated level by level): scene, type, parent, rule, pose.
    scene = [np.arange(size)]
    ntype = [np.full(size, grammar.root, np.int64)]
    parent = [np.full(size, -1, np.int64)]
    rule = [np.full(size, -1, np.int64)]
    xyz = [np.broadcast_to(grammar.root_xyz, (size, 3)).copy()]
    quat = [np.broadcast_to(grammar.root_quat, (size, 4)).copy()]
    lp_scene: list[NDArray[np.int64]] = []
    lp_value: list[NDArray[np.float64]] = []
    for origin, logp_choice, level in grow(
        grammar, ntype[0], xyz[0], quat[0], nest, rng, MAX_CHUNK_NODES
    ):
        lp_scene.append(origin)
        lp_value.append(logp_choice)
        if level is None:
            break
        lp_scene.append(level["origin"])
        lp_value.append(level["lp"])
        scene.append(level["origin"])
        ntype.append(level["type"])
        parent.append(level["parent"])
        rule.append(level["rule"])
        xyz.append(level["xyz"])
        quat.append(level["quat"])
    logp = np.bincount(np.concatenate(lp_scene), np.concatenate(lp_value), minlength=size)
    trees = _group_by_scene(scene, ntype, parent, rule, xyz, quat, size)
    return trees, logp - unseen_edges(grammar, trees)  # the score (`ssgc.score`)


LEVEL_KEYS = ("origin", "type", "parent", "rule", "xyz", "quat", "nest", "lp")


def grow(
    grammar: Grammar,
    f_type: NDArray[np.int64],
    f_xyz: NDArray[np.float64],
    f_quat: NDArray[np.float64],
    f_nest: NDArray[np.int64],
    rng: np.random.Generator,
    max_nodes: int | None = None,
) -> Iterator[tuple[NDArray[np.int64], NDArray[np.float64], dict[str, NDArray] | None]]:  # type: ignore[type-arg]
    """Forward-sample the subtrees below a frontier of nodes, level by level: whole trees
    (`sample_chunk`, the frontier being their roots) and RJMCMC's regrown subtrees alike.

    Yields, per level, (each frontier node's origin, the log-probability of its rule choice,
    the new level or None when nothing fired).  A level holds per new node its `origin` (the
    first frontier's node it descends from), `type`, `parent`, `rule`, pose, `nest` and `lp`
    (its pose's log-density).  Node ids run in level order: the first frontier is
    0..F-1, the next level's nodes F, F+1, ...  `max_nodes` caps the nodes drawn in all."""
    tb = grammar.tables
    origin = ids = np.arange(len(f_type))
    scenes = len(f_type)  # drawn together, one per frontier node (for the too-large message)
    cur_type, cur_xyz, cur_quat, nest = f_type, f_xyz, f_quat, f_nest
    total, depth = len(f_type), 0
    while len(cur_type):
        depth += 1
        if depth > MAX_LEVELS:
            raise SsgError.single(
                f"grammar '{grammar.name}' makes trees deeper than {MAX_LEVELS} levels, "
                "too deep to sample; lower its `max_nesting` bounds",
                grammar.file,
            )
        budget = None if max_nodes is None else max_nodes - total
        fires, logp_choice = _choose_rules(grammar, cur_type, nest, rng, budget, scenes=scenes)
        new: dict[str, list[NDArray]] = {k: [] for k in LEVEL_KEYS}  # type: ignore[type-arg]
        for rid, where in fires:
            xyz, quat, lp = sample_children(grammar, rid, cur_xyz[where], cur_quat[where], rng)
            child = tb.rule_child[rid]
            c_nest = nest[where].copy()
            if tb.nesting_slot[child] >= 0:
                c_nest[:, tb.nesting_slot[child]] += 1
            new["origin"].append(origin[where])
            new["type"].append(np.full(len(where), child, np.int64))
            new["parent"].append(ids[where])
            new["rule"].append(np.full(len(where), rid, np.int64))
            new["xyz"].append(xyz)
            new["quat"].append(quat)
            new["nest"].append(c_nest)
            new["lp"].append(lp)
        if not new["type"]:
            yield origin, logp_choice, None
            return
        level = {k: np.concatenate(v) for k, v in new.items()}
        yield origin, logp_choice, level
        ids = ids[-1] + 1 + np.arange(len(level["type"]))  # the frontier is never empty here
        total += len(ids)
        origin, cur_type, cur_xyz = level["origin"], level["type"], level["xyz"]
        cur_quat, nest = level["quat"], level["nest"]


def _choose_rules(
    grammar: Grammar,
    f_type: NDArray[np.int64],
    nest: NDArray[np.int64],
    rng: np.random.Generator,
    budget: int | None = None,
    counts_in: dict[int, tuple[int, int | None]] | None = None,
    forced: frozenset[int] = frozenset(),
    biased: frozenset[int] = frozenset(),
    must: tuple[NDArray[np.bool_], int, int] | None = None,
    scenes: int = CHUNK,
) -> tuple[list[tuple[int, NDArray[np.int64]]], NDArray[np.float64]]:
    """Which rules fire at each frontier node: [(rule id, frontier positions)], log-probs.

    More than `budget` children in all is an error (`TooLarge`, naming the `scenes` drawn
    together), found before they take any memory.
    `counts_in` {type: (lo, hi)} draws the count of those `repeat` types from their law
    restricted to [lo, hi] (the constrained sampler's proposal, `ssgc.sample.staged`); the
    log-probabilities stay those of the unrestricted law.  Likewise the `independent` rules in
    `forced` always fire (where not blocked), with their log-probability log p.  The
    restricted counts of the `repeat` types in `biased` are drawn size-biased (weight k), and
    `must` = (mask over the frontier, `or` type, rule index) makes the masked nodes of that
    type choose that rule (with its log-probability), for the chain proposal of
    `ssgc.sample.staged`; the caller guarantees no rule of those nodes is blocked.
    """
    tb = grammar.tables
    fires: list[tuple[int, NDArray[np.int64]]] = []
    logp = np.zeros(len(f_type))
    produced = 0

    def spend(children: int) -> None:
        nonlocal produced
        produced += children
        if budget is not None and produced > budget:
            what = "one scene" if scenes == 1 else f"{scenes:,} scenes (drawn together)"
            raise TooLarge.single(
                f"grammar '{grammar.name}' makes scenes too large to sample: {what} would "
                f"hold more than {MAX_CHUNK_NODES:,} nodes; lower its counts or `max_nesting` "
                "bounds",
                grammar.file,
            )

    for t in np.flatnonzero(np.bincount(f_type, minlength=len(grammar.types))):  # unique, fast
        node = grammar.types[t]
        if node.kind == Kind.TERMINAL:
            continue
        sel = np.flatnonzero(f_type == t)
        rules = np.asarray(node.rules)
        blocked = blocked_rules(grammar, rules, nest[sel])
        if node.kind == Kind.AND:
            spend(int(blocked.size - np.count_nonzero(blocked)))
            fires += [(int(r), sel[~blocked[:, k]]) for k, r in enumerate(rules)]
        elif node.kind == Kind.OR:
            choice, live, lp = _choose_or(node.probs, blocked, rng)
            if must is not None and must[1] == t:
                fix = must[0][sel]
                choice[fix], live[fix], lp[fix] = must[2], True, tb.type_logp[t, must[2]]
            logp[sel] = lp
            spend(int(np.count_nonzero(live)))
            fires += [(int(r), sel[live & (choice == k)]) for k, r in enumerate(rules)]
        elif node.kind == Kind.INDEPENDENT:
            fire = rng.random((len(sel), len(rules))) < node.probs
            if forced:
                fire |= np.isin(rules, list(forced))
            fire &= ~blocked
            term = np.where(fire, tb.type_logp[t, : len(rules)], tb.type_log1mp[t, : len(rules)])
            logp[sel] = np.sum(np.where(blocked, 0.0, term), axis=1)
            spend(int(np.count_nonzero(fire)))
            fires += [(int(r), sel[fire[:, k]]) for k, r in enumerate(rules)]
        else:  # REPEAT
            if counts_in is not None and t in counts_in:
                lo, hi = counts_in[t]
                counts = _restricted_counts(node.count.probs, lo, hi, rng, len(sel), t in biased)
            else:
                counts = node.count.sample(rng, len(sel))
            counts[blocked[:, 0]] = 0
            logp[sel] = np.where(blocked[:, 0], 0.0, node.count.log_prob(counts))
            spend(int(counts.sum()))
            fires.append((int(rules[0]), np.repeat(sel, counts)))
    return [(r, w) for r, w in fires if len(w)], logp


def _choose_or(
    probs: NDArray[np.float64], blocked: NDArray[np.bool_], rng: np.random.Generator
) -> tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.float64]]:
    """One rule per node of an `or` type, with its blocked rules' weights set to 0: (choice,
    whether any rule was left, log-probability).  Nodes with no blocked rule (most of them)
    share one cumulative sum; the result is the same as one row of weights per node."""
    n, m = blocked.shape
    u = rng.random(n)
    choice = np.zeros(n, np.int64)
    lp = np.zeros(n)
    live = np.ones(n, bool)
    partial = blocked.any(axis=1)
    free = np.flatnonzero(~partial)
    if len(free):
        cum = np.cumsum(probs)
        uu = u[free] * cum[-1]
        choice[free] = np.minimum((cum <= uu[:, None]).sum(axis=1), m - 1)
        with np.errstate(divide="ignore"):
            lp[free] = np.log(probs / cum[-1])[choice[free]]
    some = np.flatnonzero(partial)
    if len(some):
        weights = np.where(blocked[some], 0.0, probs)
        total = weights.sum(axis=1)
        cum2 = np.cumsum(weights, axis=1)
        uu = u[some] * total
        c = np.minimum((cum2 <= uu[:, None]).sum(axis=1), m - 1)
        ok = total > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            lp[some] = np.where(ok, np.log(weights[np.arange(len(some)), c] / total), 0.0)
        choice[some], live[some] = c, ok
    return choice, live, lp


def _restricted_counts(
    probs: NDArray[np.float64],
    lo: int,
    hi: int | None,
    rng: np.random.Generator,
    n: int,
    size_biased: bool = False,
) -> NDArray[np.int64]:
    """`n` counts of the law `probs` (P(count = k) = probs[k]) conditioned on lo <= k <= hi;
    `size_biased`: of the law k * probs[k] so conditioned."""
    k = np.arange(len(probs))
    weights = np.where((k >= lo) & (k <= (len(probs) if hi is None else hi)), probs, 0.0)
    if size_biased:
        weights = weights * k
    cum = np.cumsum(weights)
    if cum[-1] <= 0:  # no count in range (validation refuses such bounds): all rejected
        return np.zeros(n, np.int64)
    u = rng.random(n) * cum[-1]
    # u can round up to cum[-1] (probabilities as small as 5e-324): the last count with weight
    last = int(np.flatnonzero(weights > 0)[-1])
    return np.minimum(np.searchsorted(cum, u, side="right"), last).astype(np.int64)


def blocked_rules(
    grammar: Grammar, rules: NDArray[np.int64], nest: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """(nodes, rules) mask of rules whose child would exceed its type's max_nesting."""
    tb = grammar.tables
    slot = tb.nesting_slot[tb.rule_child[rules]]
    bounded = slot >= 0
    out = np.zeros((nest.shape[0], len(rules)), bool)
    if np.any(bounded):
        out[:, bounded] = nest[:, slot[bounded]] >= tb.nesting_max[slot[bounded]]
    return out


def _group_by_scene(scene, ntype, parent, rule, xyz, quat, size):  # type: ignore[no-untyped-def]
    """Reorder level-major nodes into scene-major order, keeping parents before children."""
    s = np.concatenate(scene)
    order = np.argsort(s, kind="stable")
    new_index = np.empty_like(order)
    new_index[order] = np.arange(len(order))
    p = np.concatenate(parent)[order]
    return Trees(
        scene=s[order],
        type=np.concatenate(ntype)[order],
        parent=np.where(p >= 0, new_index[np.maximum(p, 0)], -1),
        rule=np.concatenate(rule)[order],
        xyz=np.concatenate(xyz)[order],
        quat=np.concatenate(quat)[order],
        n_scenes=size,
    )


def _empty() -> Trees:
    z = np.zeros(0, np.int64)
    return Trees(z, z, z, z, np.zeros((0, 3)), np.zeros((0, 4)), 0)
