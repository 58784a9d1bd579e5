"""Exact rejection sampling under constraints, in stages that stop drawing a doomed candidate.

Plain rejection draws a whole tree (structure and poses) from P(T) and keeps it when every
constraint holds; the kept trees are exactly P(T | constraints).  This module makes the same
accept/reject decision for each candidate, but draws as little of the candidate as decides it:

1. **Structure of the relevant part.**  Only nodes of types from which a structurally
   constrained type can be reached are expanded (no poses).  Other nodes stay *pending*: they
   can never add or remove a constrained node, so the structural margins are final; they
   are followed level by level (`Watch`, ssgc/sample/watch.py).  Three exact proposals make
   fewer candidates fail here (`count_proposals`, `forced_rules`, `chain_proposal`:
   ssgc/sample/proposals.py); a proposed chain's links above its root wait for step 3.
2. **Poses of that part**, for the candidates whose structure passed, drawn from the
   grammar's own rules depth by depth (`pose_stage`).  Pose margins are minima over nodes or
   pairs, so they can only fall when more nodes are added: a partial tree that already
   violates one is rejected, judged on the terms with a freshly posed node.
3. **The rest**: pending nodes of the survivors are expanded (structure first), then posed
   depth by depth as in 2, every pose constraint judging the terms with a node of the rest.

Every random choice of a candidate is drawn from the grammar's law given what was drawn
before (subtrees are independent given their root's pose, so the order does not matter),
except the proposals, which multiply the probability of every accepted tree by one constant
(the chain proposal after its 1/K coin);
and a candidate is kept iff its complete tree satisfies every constraint: the kept candidates
are i.i.d. draws of P(T | C).  A rejected structure is never reused with new poses: that would
sample structures by P(S) instead of P(S) P(poses ok | S) (thesis 2.7.3; docs/constraints.md).

Everything is vectorised over a batch of candidates; the Python loops run over tree levels,
types and rules.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint
from ssgc.constraints.structural import chain_runs
from ssgc.ir import Grammar, Kind
from ssgc.node_states import State, child_states, root_state, subtree_total
from ssgc.rules import sample_children
from ssgc.sample.forward import MAX_CHUNK_NODES, MAX_LEVELS, _choose_rules
from ssgc.sample.proposals import ChainProposal, chain_proposal, count_proposals, forced_rules
from ssgc.sample.watch import Watch, is_watched, relevant_types
from ssgc.score import unseen_edges
from ssgc.tree import Trees

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
# The pose stage judges partial trees after every depth of poses while judging pays: once a
# judgement rejects fewer than this share of the candidates it judged, the following depths
# are posed first and judged together.  (Cost only: the verdicts are the same either way.)
SKIP_BELOW = 0.05
# The pose stage compacts its store once fewer than this share of the candidates in it are
# still alive.  (Cost only.)
COMPACT_BELOW = 0.5
# Candidates drawn together are as many as fill this share of `MAX_CHUNK_NODES` with their
# expected nodes (`largest_batch`): the rest is headroom for the spread of their sizes.
NODE_SHARE = 0.5
# `expected_nodes` gives up beyond this many kinds of node (a type with nesting depths).
MAX_NODE_KINDS = 100_000


@dataclass
class Nodes:
    """A level-major node store of many candidate trees (parents before children).

    Poses are absent (None) until the structure stage is over and the store is compacted to
    the surviving candidates."""

    scene: IntArray
    type: IntArray
    parent: IntArray
    rule: IntArray
    depth: IntArray
    nest: IntArray  # (N, B) nesting depth of every bounded type
    force: IntArray  # links of the chain proposal's forced chain a node must still make
    n_scenes: int
    xyz: FloatArray | None = None
    quat: FloatArray | None = None

    def extend(self, levels: list[dict[str, NDArray]]) -> None:  # type: ignore[type-arg]
        if not levels:
            return
        for key in levels[0]:
            setattr(self, key, np.concatenate([getattr(self, key), *(lv[key] for lv in levels)]))

    def extend_kept(
        self,
        levels: list[dict[str, NDArray]],
        keep_scene: NDArray[np.bool_],
        pending: IntArray,  # type: ignore[type-arg]
    ) -> IntArray:
        """`extend` and `compact` in one pass: only the kept candidates' nodes are copied."""
        masks = [keep_scene[self.scene]] + [keep_scene[lv["scene"]] for lv in levels]
        keep = np.concatenate(masks)
        new = np.cumsum(keep) - 1
        new[~keep] = -1
        for key in ("scene", "type", "parent", "rule", "depth", "nest", "force"):
            parts = [getattr(self, key)[masks[0]]]
            parts += [lv[key][m] for lv, m in zip(levels, masks[1:], strict=True)]
            setattr(self, key, np.concatenate(parts))
        self.parent = np.where(self.parent >= 0, new[np.maximum(self.parent, 0)], -1)
        pending = new[pending]
        return pending[pending >= 0]

    def compact(self, keep_scene: NDArray[np.bool_], pending: IntArray) -> IntArray:
        """Keep only the nodes of the kept candidates (scene ids unchanged); returns the
        kept pending nodes, renumbered."""
        return renumber(self.keep(keep_scene), pending)

    def keep(self, keep_scene: NDArray[np.bool_]) -> IntArray:
        """Keep only the nodes of the kept candidates (scene ids unchanged); returns each old
        node's new number (-1: dropped)."""
        idx = np.flatnonzero(keep_scene[self.scene])
        new = np.full(len(self.type), -1, np.int64)
        new[idx] = np.arange(len(idx))
        par = self.parent[idx]
        self.parent = np.where(par >= 0, new[np.maximum(par, 0)], -1)
        for key in ("scene", "type", "rule", "depth", "nest", "force"):
            setattr(self, key, getattr(self, key)[idx])
        if self.xyz is not None and self.quat is not None:
            self.xyz, self.quat = self.xyz[idx], self.quat[idx]
        return new


def renumber(new: IntArray, ids: IntArray) -> IntArray:
    """The nodes `ids` that were kept, by their new numbers (`Nodes.keep`)."""
    ids = new[ids]
    return ids[ids >= 0]


def expected_nodes(grammar: Grammar) -> float | None:
    """The mean number of nodes of a tree of P(T), its root included: what a candidate costs
    the node store when no constraint rejects it early.  Counted per kind of node (a type
    with the nesting depths of the bounded types, as in `ssgc.supertree_size`): a rule
    blocked by `max_nesting` never fires and an `or` renormalises over the others, as in
    `ssgc.sample.forward._choose_rules`.  None when there are more than `MAX_NODE_KINDS`
    kinds of node (the mean is then unknown, not infinite: every recursion is bounded)."""

    def mean_children(state: State) -> list[tuple[float, State]]:
        """(mean number of such children, child state) of every rule that can fire there."""
        node = grammar.types[state[0]]
        kids = child_states(grammar, state)
        if node.kind == Kind.REPEAT:
            assert node.count is not None
            weights = [node.count.mean] * len(kids)
        elif node.kind in (Kind.OR, Kind.INDEPENDENT):
            weights = [float(node.probs[grammar.rules[rid].index]) for rid, _ in kids]
        else:
            weights = [1.0] * len(kids)
        if node.kind == Kind.OR and kids:  # renormalised over the rules not blocked
            total = sum(weights)
            weights = [w / total for w in weights]
        return [(w, kid) for w, (_, kid) in zip(weights, kids, strict=True)]

    return subtree_total(root_state(grammar), mean_children, MAX_NODE_KINDS)


def largest_batch(grammar: Grammar) -> int | None:
    """The most candidates to draw together: as many as fill `NODE_SHARE` of
    `MAX_CHUNK_NODES` with their expected nodes (`expected_nodes`), at least one.  The node
    store holds every candidate of a batch, so a grammar of 300-object scenes is drawn in
    batches of about 6,600 candidates rather than refused.  None: no bound is known (a
    batch that overflows anyway raises `TooLarge`, and the caller draws fewer)."""
    mean = expected_nodes(grammar)
    if mean is None:
        return None
    return max(1, int(NODE_SHARE * MAX_CHUNK_NODES / mean))


def roots(grammar: Grammar, size: int) -> Nodes:
    tb = grammar.tables
    nest = np.zeros((size, tb.nesting_max.shape[0]), np.int64)
    if tb.nesting_slot[grammar.root] >= 0:
        nest[:, tb.nesting_slot[grammar.root]] = 1
    return Nodes(
        scene=np.arange(size),
        type=np.full(size, grammar.root, np.int64),
        parent=np.full(size, -1, np.int64),
        rule=np.full(size, -1, np.int64),
        depth=np.zeros(size, np.int64),
        nest=nest,
        force=np.zeros(size, np.int64),
        n_scenes=size,
    )


def grow(
    grammar: Grammar,
    nodes: Nodes,
    start: IntArray,
    expand: NDArray[np.bool_],
    rng: np.random.Generator,
    logp: FloatArray,
    watch: Watch | None = None,
    levels: list[dict[str, NDArray]] | None = None,  # type: ignore[type-arg]
    counts_in: dict[int, tuple[int, int | None]] | None = None,
    forced: frozenset[int] = frozenset(),
    chain: ChainProposal | None = None,
) -> IntArray:
    """Expand the nodes `start` level by level, only nodes whose type is in `expand`, without
    poses (the pose stages draw them).  Adds the log-probability of every choice to `logp`
    (per scene).  A `watch` sees every level and may kill candidates (their nodes stop
    growing).  Returns the nodes left unexpanded (pending).  With `levels`, the new nodes are
    put there, not in the store (for `Nodes.extend_kept`).  `counts_in` restricts `repeat`
    counts (`count_proposals`), `forced` makes `independent` rules fire (`forced_rules`),
    `chain` forces one chain of each candidate to its constraint's length (`chain_proposal`)."""
    tb = grammar.tables
    kind = tb.type_kind
    f_id = start
    f = {
        "scene": nodes.scene[f_id],
        "type": nodes.type[f_id],
        "nest": nodes.nest[f_id],
        "depth": nodes.depth[f_id],
        "force": nodes.force[f_id],
    }
    if watch is not None:
        watch.start(f["type"], f["scene"])
    pending = []
    keep_levels = levels is not None
    levels = levels if levels is not None else []
    next_id = len(nodes.type)
    nest_step = nesting_steps(grammar)
    for _ in range(MAX_LEVELS):
        nonterminal = kind[f["type"]] != Kind.TERMINAL
        live = nonterminal & expand[f["type"]]
        if watch is not None:
            live &= watch.alive[f["scene"]]
        pending.append(f_id[nonterminal & ~live])
        if not np.any(live):
            break
        f_id = f_id[live]
        f = {k: v[live] for k, v in f.items()}
        if watch is not None:
            watch.select(live)
        budget = MAX_CHUNK_NODES - next_id  # memory bound, as in forward sampling
        must = None if chain is None else chain.must(f["force"])
        biased = frozenset() if chain is None else frozenset([chain.repeat])
        fires, lp = _choose_rules(
            grammar,
            f["type"],
            f["nest"],
            rng,
            budget,
            counts_in,
            forced,
            biased,
            must,
            scenes=nodes.n_scenes,
        )
        logp += np.bincount(f["scene"], lp, minlength=len(logp))
        if not fires:
            break
        level, at = _next_level(grammar, fires, f, f_id, nest_step, chain, rng)
        levels.append(level)
        f_id = next_id + np.arange(len(at))
        next_id += len(at)
        f = {k: level[k] for k in f}
        if watch is not None:
            watch.step(at, level["type"], level["scene"], f["type"])
    if not keep_levels:
        nodes.extend(levels)
    return np.concatenate(pending) if pending else np.zeros(0, np.int64)


def _next_level(
    grammar: Grammar,
    fires: list[tuple[int, IntArray]],
    f: dict[str, NDArray],  # type: ignore[type-arg]
    f_id: IntArray,
    nest_step: IntArray,
    chain: ChainProposal | None,
    rng: np.random.Generator,
) -> tuple[dict[str, NDArray], IntArray]:  # type: ignore[type-arg]
    """The children of the frontier `f` (node ids `f_id`) made by the rules that fire, as
    arrays over the new level: everything follows from the frontier position `at` of each
    child's parent and the rule that made it.  Returns the level and `at`."""
    tb = grammar.tables
    at = np.concatenate([where for _, where in fires])
    rid = np.repeat([r for r, _ in fires], [len(where) for _, where in fires])
    child = tb.rule_child[rid]
    level = {
        "scene": f["scene"][at],
        "type": child,
        "nest": f["nest"][at] + nest_step[child],
        "depth": f["depth"][at] + 1,
        "parent": f_id[at],
        "rule": rid,
    }
    if chain is None:
        level["force"] = np.zeros(len(at), np.int64)
    else:
        level["force"] = chain.child_force(f["force"], at, rid, rng)
    return level, at


def nesting_steps(grammar: Grammar) -> IntArray:
    """(types, bounded types): what a child of each type adds to the nesting counters."""
    tb = grammar.tables
    step = np.zeros((len(grammar.types), tb.nesting_max.shape[0]), np.int64)
    bounded = np.flatnonzero(tb.nesting_slot >= 0)
    step[bounded, tb.nesting_slot[bounded]] = 1
    return step


def pose_stage(
    grammar: Grammar,
    nodes: Nodes,
    constraints: list[Constraint],
    alive: NDArray[np.bool_],
    rng: np.random.Generator,
    logp: FloatArray,
    stats: _Stats,
    todo: IntArray,
) -> IntArray | None:
    """Draw the poses of the nodes `todo` (their ancestors posed or among them) of the
    candidates `alive`, depth by depth, judging the pose constraints on the partial trees
    (every posed node) after each depth that posed nodes they read; `alive` is updated in
    place.  A pose margin is a minimum over nodes or pairs, so the nodes posed so far can
    only lower it when more are added: a partial tree that fails is a candidate that fails,
    and the deeper nodes of a candidate already rejected are never drawn (in the dimsum
    table, two stacks' bottom trays that overlap reject the candidate before any tray above
    them gets a pose; a teapot on a stack, before the plates).  Constraints whose evaluation
    is costly (`progressive` False: FCL) are judged once, after the last depth.

    When most of the candidates in the store have been rejected, the store is compacted to
    the others (views and draws cost what the store holds); the map from old to new node
    numbers is returned then (None if the store was not compacted)."""
    moved: IntArray | None = None
    if not len(todo):
        return moved
    n_rules = len(grammar.rules) + 1
    depth = nodes.depth[todo]
    if np.all(depth[1:] >= depth[:-1]):
        order = todo  # level-major already (the structure stage's store): runs of one rule
    else:
        order = todo[np.argsort(depth * n_rules + nodes.rule[todo], kind="stable")]
    stored = np.count_nonzero(alive)  # candidates with nodes in the store
    waiting = np.zeros(len(nodes.type), bool)  # not posed yet: left out of the views
    waiting[order] = True
    fresh = np.zeros(len(nodes.type), bool)  # posed since the last judgement
    cuts, depth_of_cut = _runs(nodes, order, n_rules)
    early = [c for c in constraints if c.progressive]
    reads = {c.name: c.reads(len(grammar.types)) for c in early}
    touched = {c.name: np.zeros(len(alive), bool) for c in early}
    rate = 1.0  # share of the judged candidates the last judgement rejected
    start = 0
    while start < len(cuts) - 1:
        d = depth_of_cut[start]
        stop = start
        while stop < len(cuts) - 1 and depth_of_cut[stop] == d:
            stop += 1
        runs = [
            order[a:b] for a, b in zip(cuts[start:stop], cuts[start + 1 : stop + 1], strict=True)
        ]
        posed = _draw_runs(grammar, nodes, runs, alive, rng, logp)
        start = stop
        if posed:
            new = np.concatenate(posed)
            waiting[new] = False
            fresh[new] = True
            for c in early:
                touched[c.name][nodes.scene[new[reads[c.name][nodes.type[new]]]]] = True
        if not early:
            continue
        # Judging costs a pass over the partial trees: after a judgement that rejected few,
        # the next depths are posed first and judged together (always after the last one).
        if rate < SKIP_BELOW and start < len(cuts) - 1:
            continue
        judged = _judge_partial(nodes, early, touched, alive, fresh, waiting, stats)
        if judged is None:
            continue
        rate = judged
        fresh[:] = False
        if np.count_nonzero(alive) < COMPACT_BELOW * stored and start < len(cuts) - 1:
            new = nodes.keep(alive)
            moved = new if moved is None else np.where(moved >= 0, new[moved], -1)
            order = renumber(new, order[cuts[start] :])
            cuts, depth_of_cut = _runs(nodes, order, n_rules)
            start = 0
            waiting = np.zeros(len(nodes.type), bool)
            waiting[order] = True
            fresh = np.zeros(len(nodes.type), bool)
            stored = np.count_nonzero(alive)
    for c in constraints:
        if not c.progressive and np.any(alive):
            whole = view(nodes, alive, waiting=waiting)
            alive &= stats.judge(c, c.margin(whole), alive)
    return moved


def _judge_partial(
    nodes: Nodes,
    early: list[Constraint],
    touched: dict[str, NDArray[np.bool_]],
    alive: NDArray[np.bool_],
    fresh: NDArray[np.bool_],
    waiting: NDArray[np.bool_],
    stats: _Stats,
) -> float | None:
    """Judge the progressive constraints on the partial trees of the candidates whose nodes
    they read were posed (`touched`, cleared here), updating `alive` in place.  Returns the
    share of those candidates rejected (None: no candidate to judge)."""
    among = np.logical_or.reduce(list(touched.values())) & alive
    if not np.any(among):
        return None
    partial = view(nodes, among, fresh=fresh, waiting=waiting)  # one for every constraint
    before = int(np.count_nonzero(among))
    fresh_here = partial.fresh
    assert fresh_here is not None
    for c in early:
        judged = touched[c.name] & alive
        if np.any(judged):
            # trees an earlier constraint just rejected are not looked at again
            partial.fresh = fresh_here & alive[partial.scene]
            alive &= stats.judge(c, c.margin(partial), judged)
        touched[c.name][:] = False
    return 1.0 - np.count_nonzero(among & alive) / before


def _runs(nodes: Nodes, order: IntArray, n_rules: int) -> tuple[IntArray, IntArray]:
    """Where the nodes `order` (sorted by depth, then rule) change depth or rule: the runs
    whose poses one call of the rule's sampler draws, and each run's depth.  No nodes, no
    runs: every candidate that had nodes left to pose was rejected."""
    if len(order) == 0:
        return np.zeros(1, np.int64), np.zeros(0, np.int64)
    key = nodes.depth[order] * n_rules + nodes.rule[order]
    cuts = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
    return cuts, nodes.depth[order[cuts[:-1]]]


def _draw_runs(
    grammar: Grammar,
    nodes: Nodes,
    runs: list[IntArray],
    alive: NDArray[np.bool_],
    rng: np.random.Generator,
    logp: FloatArray,
) -> list[IntArray]:
    """Draw the poses of each run's nodes of the candidates `alive` (one rule per run, their
    parents posed), adding their log-densities to `logp`; returns the nodes posed."""
    assert nodes.xyz is not None and nodes.quat is not None
    posed = []
    for run in runs:
        idx = run[alive[nodes.scene[run]]]
        if not len(idx):
            continue
        par = nodes.parent[idx]
        xyz, quat, lp = sample_children(
            grammar, int(nodes.rule[idx[0]]), nodes.xyz[par], nodes.quat[par], rng
        )
        nodes.xyz[idx], nodes.quat[idx] = xyz, quat
        logp += np.bincount(nodes.scene[idx], lp, minlength=len(logp))
        posed.append(idx)
    return posed


@dataclass
class View:
    """The nodes of some candidates, renumbered, in the shape constraints read."""

    scene: IntArray
    type: IntArray
    parent: IntArray
    xyz: FloatArray
    quat: FloatArray
    n_scenes: int
    index: IntArray  # position of each node in the store
    depth: IntArray  # of each node (lineal pairs are found by walking up from the deeper)
    # Nodes posed since the view's trees were last judged (None: all).  Their trees passed
    # on the older nodes, so a constraint may judge only the terms that involve a fresh node.
    fresh: NDArray[np.bool_] | None = None


def view(
    nodes: Nodes,
    keep_scene: NDArray[np.bool_],
    fresh: NDArray[np.bool_] | None = None,
    waiting: NDArray[np.bool_] | None = None,
) -> View:
    """The nodes of the candidates `keep_scene`, except those `waiting` for their poses;
    `fresh` (per node of the store) marks the nodes posed since the trees were last judged."""
    keep = keep_scene[nodes.scene]
    if waiting is not None:
        keep &= ~waiting
    idx = np.flatnonzero(keep)
    new = np.full(len(nodes.type), -1, np.int64)
    new[idx] = np.arange(len(idx))
    par = nodes.parent[idx]
    assert nodes.xyz is not None and nodes.quat is not None
    return View(
        scene=nodes.scene[idx],
        type=nodes.type[idx],
        parent=np.where(par >= 0, new[np.maximum(par, 0)], -1),
        xyz=nodes.xyz[idx],
        quat=nodes.quat[idx],
        n_scenes=nodes.n_scenes,
        index=idx,
        depth=nodes.depth[idx],
        fresh=None if fresh is None else fresh[idx],
    )


@dataclass
class Outcome:
    """One batch of candidates: which were kept, and what the constraints said."""

    trees: Trees  # the kept candidates, in candidate order
    logp: FloatArray
    margins: dict[str, FloatArray]  # per constraint, for the kept trees
    evaluated: dict[str, int]  # candidates each constraint was evaluated on
    rejected: dict[str, int]  # candidates it rejected
    best: dict[str, float]  # the largest margin among the candidates it rejected
    drawn: int


class OutOfTime(Exception):
    """The deadline passed during an attempt (checked between its stages)."""


def check_deadline(deadline: float | None) -> None:
    if deadline is not None and time.monotonic() > deadline:
        raise OutOfTime


def rejection_batch(
    grammar: Grammar,
    constraints: list[Constraint],
    size: int,
    rng: np.random.Generator,
    deadline: float | None = None,
) -> Outcome:
    """Draw `size` candidates in stages; keep those that satisfy every constraint."""
    # The verdict does not depend on the order (every constraint must hold); the cost does.
    pose = sorted((c for c in constraints if c.kind != "structure"), key=lambda c: c.rank)
    stats = _Stats([c.name for c in constraints])
    nodes = roots(grammar, size)
    logp = np.zeros(size)
    restricted = count_proposals(grammar, constraints)
    chain = chain_proposal(grammar, constraints, restricted)
    # The proposed chains' trays above their roots are grown with the rest (stage 3), for
    # the candidates whose roots' poses pass, when no other structural constraint needs them.
    late = (
        chain
        if chain is not None
        and not relevant_types(grammar, [c for c in constraints if c.name != chain.constraint])[
            chain.chain_type
        ]
        else None
    )
    batch = _Batch(grammar, constraints, pose, nodes, logp, rng, stats)
    pending, alive = _structure_stage(batch, restricted, chain, late)
    check_deadline(deadline)
    pending, read = _pose_stage_partial(batch, alive, pending)
    check_deadline(deadline)
    _rest_stage(batch, alive, pending, read, chain, late)
    full = view(nodes, alive)
    margins = {c.name: c.margin(full) for c in constraints}
    trees = _as_trees(nodes, alive)
    kept = np.flatnonzero(alive)
    return Outcome(
        trees=trees,
        logp=logp[kept] - unseen_edges(grammar, trees),  # the score (`ssgc.score`)
        margins={k: v[kept] for k, v in margins.items()},
        evaluated=stats.evaluated,
        rejected=stats.rejected,
        best=stats.best,
        drawn=size,
    )


@dataclass
class _Batch:
    """What the stages of one batch share: the grammar and the constraints (`pose`: those on
    poses, cheapest first), the candidates' node store and log-probabilities, the random
    stream and the constraints' tallies."""

    grammar: Grammar
    constraints: list[Constraint]
    pose: list[Constraint]
    nodes: Nodes
    logp: FloatArray
    rng: np.random.Generator
    stats: _Stats


def _structure_stage(
    batch: _Batch,
    restricted: dict[int, tuple[int, int | None]],
    chain: ChainProposal | None,
    late_chain: ChainProposal | None,
) -> tuple[IntArray, NDArray[np.bool_]]:
    """Stage 1: grow the structure that structural constraints depend on, judging it as it
    grows (the chain proposal's trays too, unless they are left to stage 3: `late_chain`).
    Returns the pending nodes and the candidates alive."""
    grammar, constraints, nodes, rng, stats = (
        batch.grammar,
        batch.constraints,
        batch.nodes,
        batch.rng,
        batch.stats,
    )
    size = nodes.n_scenes
    forced = forced_rules(grammar, constraints)
    relevant = relevant_types(grammar, constraints)
    watched = constraints
    if late_chain is not None:
        relevant[late_chain.chain_type] = False
        watched = [c for c in constraints if c.name != late_chain.constraint]
    watch = Watch(grammar, watched, size, stats, chain)
    levels: list[dict[str, NDArray]] = []  # type: ignore[type-arg]
    pending = grow(
        grammar,
        nodes,
        np.arange(size),
        relevant,
        rng,
        batch.logp,
        watch,
        levels,
        restricted,
        forced,
        chain,
    )
    watch.finish()
    alive = watch.alive
    if chain is not None and late_chain is None:  # keep a candidate with probability 1/K
        _keep_one_in_k(chain, watch.tall, alive, rng, stats)
    pending = nodes.extend_kept(levels, alive, pending)
    for c in constraints:  # registered structural kinds that Watch does not follow
        if c.kind == "structure" and not is_watched(c) and np.any(alive):
            alive &= stats.judge(c, c.margin(nodes), alive)
    return pending, alive


def _pose_stage_partial(
    batch: _Batch, alive: NDArray[np.bool_], pending: IntArray
) -> tuple[IntArray, NDArray[np.bool_]]:
    """Stage 2: the poses of stage 1's structure, depth by depth, with the pose constraints
    judged on the partial trees.  Returns the pending nodes (renumbered) and which types the
    pose constraints read."""
    grammar, nodes = batch.grammar, batch.nodes
    nodes.xyz = np.broadcast_to(grammar.root_xyz, (len(nodes.type), 3)).copy()
    nodes.quat = np.broadcast_to(grammar.root_quat, (len(nodes.type), 4)).copy()
    # Pending nodes that no pose constraint reads get their poses with the rest (stage 3):
    # they are not needed to judge the partial trees, and most candidates die first.
    read = np.zeros(len(grammar.types), bool)
    for c in batch.pose:
        read |= c.reads(len(grammar.types))
    deferred = np.zeros(len(nodes.type), bool)
    deferred[pending[~read[nodes.type[pending]] & (nodes.parent[pending] >= 0)]] = True
    todo = np.flatnonzero((nodes.parent >= 0) & ~deferred)
    _judge_roots(batch, alive)
    moved = pose_stage(grammar, nodes, batch.pose, alive, batch.rng, batch.logp, batch.stats, todo)
    return (pending if moved is None else renumber(moved, pending)), read


def _judge_roots(batch: _Batch, alive: NDArray[np.bool_]) -> None:
    """Judge the progressive pose constraints that read the root's type on the roots alone,
    updating `alive` in place.  A root is posed when its tree is made, never by `pose_stage`,
    which judges only the terms with a freshly posed node: without this, the root's own terms
    (an `inside_box` or `upright` listing its type) were never judged."""
    grammar, nodes = batch.grammar, batch.nodes
    early = [c for c in batch.pose if c.progressive and c.reads(len(grammar.types))[grammar.root]]
    if not early:
        return
    roots_alone = view(nodes, alive, waiting=nodes.parent >= 0)
    for c in early:
        if np.any(alive):
            alive &= batch.stats.judge(c, c.margin(roots_alone), alive)


def _rest_stage(
    batch: _Batch,
    alive: NDArray[np.bool_],
    pending: IntArray,
    read: NDArray[np.bool_],
    chain: ChainProposal | None,
    late_chain: ChainProposal | None,
) -> None:
    """Stage 3: the rest of each surviving tree: its structure (with the trays of
    `late_chain`, the chain proposal when stage 1 left them), then its poses (and the
    deferred ones) depth by depth, judged on the partial trees as in stage 2 (its nodes
    passed, so only the terms with a node of the rest are new)."""
    grammar, nodes, rng, logp, stats = (
        batch.grammar,
        batch.nodes,
        batch.rng,
        batch.logp,
        batch.stats,
    )
    size = nodes.n_scenes
    pending = nodes.compact(alive, pending)
    late = pending[~read[nodes.type[pending]] & (nodes.parent[pending] >= 0)]
    grown_from = len(nodes.type)
    grow(grammar, nodes, pending, np.ones(len(grammar.types), bool), rng, logp, chain=chain)
    if late_chain is not None and np.any(alive):
        (c,) = [c for c in batch.constraints if c.name == late_chain.constraint]
        alive &= stats.judge(c, c.margin(nodes), alive)
        run = chain_runs(nodes.type, nodes.parent, late_chain.chain_type)
        tall = np.bincount(nodes.scene[run == late_chain.length], minlength=size)
        _keep_one_in_k(late_chain, tall, alive, rng, stats)
    grown = len(nodes.type) - grown_from
    nodes.xyz = np.concatenate([nodes.xyz, np.zeros((grown, 3))])
    nodes.quat = np.concatenate([nodes.quat, np.zeros((grown, 4))])
    todo = np.r_[late, np.arange(grown_from, len(nodes.type))]
    pose_stage(grammar, nodes, batch.pose, alive, rng, logp, stats, todo)


def _keep_one_in_k(
    chain: ChainProposal,
    tall: IntArray,
    alive: NDArray[np.bool_],
    rng: np.random.Generator,
    stats: _Stats,
) -> None:
    """The chain proposal's coin: keep each candidate with probability 1/K, K (`tall`) its
    number of chains at least the proposal's length (>= 1: one is forced)."""
    assert np.all(tall[alive] >= 1), "the proposal forces one chain"
    unlucky = alive & (rng.random(len(alive)) * tall >= 1)
    stats.rejected[chain.constraint] += int(np.count_nonzero(unlucky))
    alive &= ~unlucky


class _Stats:
    def __init__(self, names: list[str]) -> None:
        self.evaluated = dict.fromkeys(names, 0)
        self.rejected = dict.fromkeys(names, 0)
        self.best = dict.fromkeys(names, -np.inf)
        self.seen: dict[str, NDArray[np.bool_]] = {}

    def count(self, name: str, margin: FloatArray) -> None:
        """Candidates judged by `name` with these margins (negative: rejected)."""
        bad = margin < 0
        self.evaluated[name] += len(margin)
        self.rejected[name] += int(bad.sum())
        if np.any(bad):
            self.best[name] = max(self.best[name], float(margin[bad].max()))

    def judge(
        self, c: Constraint, margin: FloatArray, among: NDArray[np.bool_]
    ) -> NDArray[np.bool_]:
        """Which candidates `c` lets through (`margin` >= 0).  Pose constraints judge a
        candidate several times (partial trees, then the complete one): it counts as evaluated
        the first time, as rejected the time it fails."""
        ok = margin >= 0
        bad = among & ~ok
        seen = self.seen.setdefault(c.name, np.zeros(len(among), bool))
        self.evaluated[c.name] += int(np.count_nonzero(among & ~seen))
        seen |= among
        self.rejected[c.name] += int(np.count_nonzero(bad))
        if np.any(bad):
            self.best[c.name] = max(self.best[c.name], float(margin[bad].max()))
        return ok | ~among


def _as_trees(nodes: Nodes, keep: NDArray[np.bool_]) -> Trees:
    """The kept candidates as a `Trees` batch: grouped by tree, parents before children."""
    assert nodes.xyz is not None and nodes.quat is not None, "poses are drawn first"
    every = Trees(
        nodes.scene, nodes.type, nodes.parent, nodes.rule, nodes.xyz, nodes.quat, nodes.n_scenes
    )
    return every.select(keep)
