"""`--method rjmcmc`: Metropolis-Hastings over whole trees (structure and poses) whose
stationary law is P(T | every constraint holds), many chains in lockstep.

Moves, one of each per sweep (`RjSettings.moves`), every chain at once:

- **subtree**: pick a non-terminal node uniformly, redraw everything below it from the
  grammar (its rule choices, counts and poses, given its pose and nesting depths).  The
  proposal is P(new subtree | node) / |T|, the target P(T) 1[C(T)], and P(rest) cancels, so
  the acceptance probability is min(1, |T| / |T'|) 1[C(T')], with |T| the number of
  non-terminal nodes.  The dimension changes with the subtree: this is the reversible jump,
  with the grammar itself as the proposal for the new dimensions (no Jacobian: the new
  values are drawn, not transformed).
- **structure (birth/death)**: pick a site uniformly among the tree's M sites (a `repeat`
  node, or one rule of an `independent` node); at a `repeat` node with k children, add a
  child drawn with its whole subtree from the grammar (probability 1/2) or remove one of the
  k children, uniformly, with its subtree; at an `independent` rule, remove the child if it
  is there, else draw it.  The drawn subtree's density cancels, so the acceptance
  probability is min(1, P(k') / P(k) · M / M') 1[C(T')] (P the count law, or p and 1 - p).
  One object comes or goes at a time, so the number of objects mixes far faster than by
  regrowing a whole group, which must then fit at once.
- **translation (prior)**: pick a node whose translation law is not a point, redraw its local
  translation from its law (descendants move along); accepted iff every constraint holds.
- **translation (random walk)**: a Gaussian step in the unconstrained coordinates of
  `ssgc.sample.lawspace` (so the step never leaves a law's support); accepted with
  min(1, p(z') / p(z)) 1[C].
- **rotation (prior)**: as for translations, for a node whose rotation law is not a point.

A chain starts from an exact draw of P(T | C) when staged rejection finds one within
`start_candidates` candidates, else from a draw of P(T).  Initialisation, never output: until
it first satisfies every constraint, a chain targets P(T) exp(-Σ_C min(C, 0)² / (2 ε²))
instead (same moves), which leads it into the feasible set; from then on it never leaves
it.  Burn-in is then decided by diagnostics on the per-type node counts across the chains
(`ssgc.sample.diagnostics`: the drift of their mean between the halves of the window,
split-R̂ and bulk ESS), not by a fixed number of sweeps; see `rjmcmc_batch`.  Every move
leaves P(T | C) invariant (`tests/test_rjmcmc_kernel.py` checks each one against exact
rejection), so the chains' law tends to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.base import Constraint
from ssgc.ir import Grammar, Kind
from ssgc.rules import sample_children
from ssgc.sample.chains import ChainOutcome, Judge
from ssgc.sample.diagnostics import Summary, summary
from ssgc.sample.forward import TooLarge, grow, sample_chunk
from ssgc.sample.lawspace import Coords
from ssgc.sample.poses import choose, local_poses, world_poses
from ssgc.sample.staged import check_deadline, largest_batch, rejection_batch
from ssgc.score import nesting_counts
from ssgc.tree import Trees

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
MOVES = ("subtree", "structure", "translation", "walk", "rotation")


@dataclass(frozen=True)
class RjSettings:
    min_sweeps: int = 100  # after every chain is feasible, before convergence is first checked
    max_sweeps: int = 600  # in all (initialisation included)
    check_every: int = 10  # sweeps between convergence checks
    drift: float = 3.0  # burn-in is over when no count statistic's mean drifts by more
    # standard errors than this between the halves of the window
    rhat: float = 1.5  # ... and every count statistic's split-R̂ is at most this
    ess: float = 400.0  # ... and every count statistic's bulk ESS over all chains is this
    start_candidates: int = 16384  # staged-rejection budget for exact starting states
    eps: float = 1e-3  # penalty scale before a chain is first feasible
    walk: float = 0.3  # random-walk step in the unconstrained coordinates
    moves: tuple[str, ...] = MOVES  # the moves of a sweep, in order


SETTINGS = RjSettings()


def rjmcmc_batch(
    grammar: Grammar,
    constraints: list[Constraint],
    size: int,
    rng: np.random.Generator,
    deadline: float | None = None,
    settings: RjSettings = SETTINGS,
) -> ChainOutcome:
    """Run `size` chains; keep the final states of the chains that are burnt in.

    Initialisation (not output): chains that start infeasible follow the penalised target
    until every chain is feasible (or half of `max_sweeps` is spent).  From that sweep t0,
    the per-type node counts of every chain are recorded at every sweep, and every
    `check_every` sweeps (from `min_sweeps` on) the window of the last half of the sweeps
    since t0 is diagnosed over the chains feasible throughout it: burn-in is over when no
    count's mean over the chains drifts by more than `drift` standard errors between the
    window's halves, every count's split-R̂ is at most `rhat` and its bulk ESS at least
    `ess` (`ssgc.sample.diagnostics`; docs/constraints.md says why these bounds), else at
    `max_sweeps`.  A chain is reported if it was feasible throughout that window (a chain
    that became feasible later has not burnt in); every scene records the diagnostics."""
    s = settings
    judge = Judge(constraints)
    trees = _starts(grammar, constraints, size, rng, s.start_candidates, deadline)
    chain = Chains(grammar, constraints, trees, s)
    watch = CountWatch(grammar)
    since = np.where(chain.feasible, 0, -1)  # sweeps since each chain was first feasible
    t0, done, diag = None, 0, None
    while done < s.max_sweeps:
        chain.sweep(rng)
        done += 1
        since = np.where(chain.feasible, since + 1, -1)
        check_deadline(deadline)
        if t0 is None and (chain.feasible.all() or done >= s.max_sweeps // 2):
            t0 = done
        if t0 is None:
            continue
        watch.record(chain.trees)
        run = done - t0 + 1
        if run >= s.min_sweeps and run % s.check_every == 0:
            diag = watch.diagnose(since >= run - run // 2)
            if diag.drift <= s.drift and diag.rhat <= s.rhat and diag.ess >= s.ess:
                break
    run = 0 if t0 is None else done - t0 + 1
    burnt = since >= run - run // 2 if t0 is not None else np.zeros(size, bool)
    if diag is None and run >= 4:
        diag = watch.diagnose(burnt)
    ok = judge.judge(judge.margins(chain.trees), burnt)
    stats = {f"{m}_acceptance": chain.accepted[m] / done for m in s.moves}
    stats["sweeps"] = np.full(size, done, float)
    stats["feasible_sweeps"] = since.astype(float)
    known = diag is not None and np.isfinite([diag.rhat, diag.drift]).all()
    stats["diagnosed"] = np.full(size, float(known))  # else too few chains or sweeps
    for k in ("rhat", "ess", "drift"):
        stats[k] = np.full(size, getattr(diag, k) if known else 0.0)
    return judge.outcome(grammar, chain.trees, ok, size, stats)


class CountWatch:
    """The statistics the burn-in is judged on: each chain's number of nodes of every
    non-root type and in all, recorded once per sweep."""

    def __init__(self, grammar: Grammar) -> None:
        self.n_types = len(grammar.types)
        self.history: list[FloatArray] = []

    def record(self, trees: Trees) -> None:
        key = trees.scene * (self.n_types + 1) + trees.type
        per = np.bincount(key, minlength=trees.n_scenes * (self.n_types + 1))
        per = per.reshape(trees.n_scenes, self.n_types + 1).astype(float)
        per[:, -1] = per[:, :-1].sum(axis=1)
        self.history.append(per)

    def diagnose(self, chains: NDArray[np.bool_]) -> Summary:
        """The diagnostics of the recorded window's last half, for the given chains (too
        few chains or draws: nothing is known, the worst values)."""
        h = np.stack(self.history[len(self.history) // 2 :])[:, chains]
        if h.shape[1] < 4 or h.shape[0] < 4:
            return Summary(rhat=float("inf"), ess=0.0, drift=float("inf"))
        return summary(h)


def _starts(
    grammar: Grammar,
    constraints: list[Constraint],
    size: int,
    rng: np.random.Generator,
    budget: int,
    deadline: float | None,
) -> Trees:
    """Starting states: as many exact draws of P(T | C) as staged rejection finds within
    `budget` candidates (a chain started there is in its stationary law from the start), the
    rest draws of P(T).  The candidates are drawn in batches the node store holds
    (`largest_batch`; a batch that overflows it anyway is drawn again halved), until the
    budget is spent or every chain has its start: scenes of 250 objects start from batches
    of about 8,000 candidates, not one of 16,384 that no store holds."""
    found: list[Trees] = []
    have = spent = 0
    largest = largest_batch(grammar)
    batch = budget if largest is None else largest
    while spent < budget and have < size:
        part = min(batch, budget - spent)
        try:
            exact = rejection_batch(grammar, constraints, part, rng, deadline).trees
        except TooLarge:
            if part == 1:
                raise
            batch = part // 2
            continue
        spent += part
        have += exact.n_scenes
        found.append(exact)
    k = min(size, have)
    parts = [Trees.concatenate(found).first(k)] if k else []
    if k < size:
        parts.append(sample_chunk(grammar, rng, size - k)[0])
    return Trees.concatenate(parts)


class Chains:
    """The current trees of every chain and the moves on them."""

    def __init__(
        self, grammar: Grammar, constraints: list[Constraint], trees: Trees, s: RjSettings
    ) -> None:
        self.grammar, self.constraints, self.s = grammar, constraints, s
        self.trees = trees
        self.n = trees.n_scenes
        self.terminal = np.array([t.kind == Kind.TERMINAL for t in grammar.types])
        self.pen, self.feasible = self._score(trees)
        self.accepted = {m: np.zeros(self.n) for m in MOVES}

    def _score(self, trees: Trees) -> tuple[FloatArray, NDArray[np.bool_]]:
        pen = np.zeros(trees.n_scenes)
        ok = np.ones(trees.n_scenes, bool)
        for c in self.constraints:
            m = c.margin(trees)
            ok &= m >= 0
            short = np.where(np.isnan(m), -np.inf, np.minimum(m, 0.0))
            pen += np.where(np.isfinite(short), short**2 / (2 * self.s.eps**2), np.inf)
        return pen, ok

    def _accept(
        self, name: str, new: Trees, log_ratio: FloatArray, rng: np.random.Generator
    ) -> None:
        """Metropolis-Hastings with the hard target for feasible chains, soft before."""
        pen, ok = self._score(new)
        soft = np.where(np.isfinite(pen), self.pen - pen, -np.inf)
        hard = np.where(ok, 0.0, -np.inf)
        log_a = log_ratio + np.where(self.feasible, hard, np.where(np.isinf(self.pen), 0.0, soft))
        take = np.log(rng.random(self.n)) < log_a
        self.trees = choose(self.trees, new, take)
        self.pen = np.where(take, pen, self.pen)
        self.feasible = np.where(take, ok, self.feasible)
        self.accepted[name] += take

    def sweep(self, rng: np.random.Generator) -> None:
        """One of each move of the settings, in order."""
        for m in self.s.moves:
            getattr(self, f"{m}_move")(rng)

    # ------------------------------------------------------------------ the moves ---

    def subtree_move(self, rng: np.random.Generator) -> None:
        t = self.trees
        inner = ~self.terminal[t.type]
        chosen = _pick(t.scene[inner], np.flatnonzero(inner), self.n, rng)
        has = chosen >= 0
        new = regrow(self.grammar, t, chosen, rng)
        before = np.bincount(t.scene[inner], minlength=self.n)
        inner_new = ~self.terminal[new.type]
        after = np.bincount(new.scene[inner_new], minlength=self.n)
        log_ratio = np.where(
            has, np.log(np.maximum(before, 1)) - np.log(np.maximum(after, 1)), -np.inf
        )
        self._accept("subtree", new, log_ratio, rng)

    def structure_move(self, rng: np.random.Generator) -> None:
        """Birth or death of one child: a site (a `repeat` node, or one rule of an
        `independent` node) is picked uniformly among the tree's M sites.  At a `repeat`
        node with k children, a birth (probability 1/2) adds a child and its subtree drawn
        from the grammar, a death removes one of the k children (uniformly) with its subtree;
        at an `independent` rule the child is removed if present, else drawn.  The drawn
        subtree's density cancels against the target's, so the acceptance probability is
        min(1, P(k') / P(k) · M / M') 1[C(T')], P the count law (or p and 1 - p)."""
        t = self.trees
        site_node, site_slot = sites(self.grammar, t)
        if not len(site_node):  # no `repeat` node or `independent` rule in any tree: no move
            return
        pick = _pick(t.scene[site_node], np.arange(len(site_node)), self.n, rng)
        has = pick >= 0
        v = np.where(has, site_node[np.maximum(pick, 0)], -1)
        slot = np.where(has, site_slot[np.maximum(pick, 0)], 0)
        step = _structure_step(self.grammar, t, v, slot, rng)
        new = _apply_step(self.grammar, t, v, step, rng)
        before = np.bincount(t.scene[site_node], minlength=self.n)
        after = np.bincount(new.scene[sites(self.grammar, new)[0]], minlength=self.n)
        log_ratio = step.log_ratio + np.log(np.maximum(before, 1)) - np.log(np.maximum(after, 1))
        self._accept("structure", new, np.where(has, log_ratio, -np.inf), rng)

    def _pose_nodes(self, part: str) -> NDArray[np.bool_]:
        t = self.trees
        movable = np.array([getattr(r, part).point is None for r in self.grammar.rules] + [False])
        return movable[np.where(t.rule >= 0, t.rule, -1)]

    def translation_move(self, rng: np.random.Generator) -> None:
        self._redraw("translation", rng)

    def rotation_move(self, rng: np.random.Generator) -> None:
        self._redraw("rotation", rng)

    def _redraw(self, part: str, rng: np.random.Generator) -> None:
        """Redraw one node's local translation or rotation per chain from its law."""
        t = self.trees
        mask = self._pose_nodes(part)
        chosen = _pick(t.scene[mask], np.flatnonzero(mask), self.n, rng)
        at = chosen[chosen >= 0]
        u, r = local_poses(self.grammar, t)
        local = u if part == "translation" else r
        rules = t.rule[at]
        for rid in np.unique(rules):
            law = getattr(self.grammar.rules[rid], part)
            where = at[rules == rid]
            local[where] = law.sample(rng, len(where))[0]
        new = world_poses(self.grammar, t, u, r)
        self._accept(
            part if part == "rotation" else "translation",
            new,
            np.where(chosen >= 0, 0.0, -np.inf),
            rng,
        )

    def walk_move(self, rng: np.random.Generator) -> None:
        """A Gaussian step on one node's free coordinates, symmetric in z."""
        t = self.trees
        coords = Coords.of(self.grammar, t.rule)
        mask = coords.free.any(axis=1)
        chosen = _pick(t.scene[mask], np.flatnonzero(mask), self.n, rng)
        at = chosen[chosen >= 0]
        u, r = local_poses(self.grammar, t)
        z = coords.to_z(u)
        z_new = z.copy()
        z_new[at] += self.s.walk * rng.standard_normal((len(at), 3))
        z_new = np.where(coords.free, z_new, z)
        new = world_poses(self.grammar, t, coords.to_u(z_new, u), r)
        log_ratio = coords.log_density(z_new, t.scene, self.n) - coords.log_density(
            z, t.scene, self.n
        )
        self._accept("walk", new, np.where(chosen >= 0, log_ratio, -np.inf), rng)


def _pick(scene: IntArray, nodes: IntArray, n: int, rng: np.random.Generator) -> IntArray:
    """One of `nodes` per tree, uniformly (-1 for a tree with none)."""
    count = np.bincount(scene, minlength=n)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    k = np.floor(rng.random(n) * count).astype(np.int64)
    out = np.full(n, -1, np.int64)
    has = count > 0
    order = np.argsort(scene, kind="stable")
    out[has] = nodes[order[start[has] + k[has]]]
    return out


def below(trees: Trees, target: IntArray) -> NDArray[np.bool_]:
    """Nodes strictly below each tree's `target` node (one per tree, -1: none)."""
    desc = np.zeros(len(trees), bool)
    goal = np.where(target >= 0, target, -2)
    anc = trees.parent.copy()
    live = np.flatnonzero(anc >= 0)
    while len(live):
        desc[live[anc[live] == goal[trees.scene[live]]]] = True
        anc[live] = trees.parent[anc[live]]
        live = live[anc[live] >= 0]
    return desc


def splice(
    trees: Trees,
    keep: NDArray[np.bool_],
    new: dict[str, NDArray],  # type: ignore[type-arg]
    attach: IntArray,
) -> Trees:
    """The kept nodes of `trees` plus a block of new nodes (`new`: scene, type, rule, xyz,
    quat, parent, in level order), new node j hanging below the old node attach[j] when
    new["parent"][j] < 0, else below new node new["parent"][j].  A tree's kept nodes keep
    their order and its new nodes follow them, so parents stay before children."""
    keep_idx = np.flatnonzero(keep)
    n_keep = len(keep_idx)
    old_pos = np.full(len(trees), -1, np.int64)
    old_pos[keep_idx] = np.arange(n_keep)
    par = new["parent"]
    parent_new = np.where(par < 0, old_pos[np.maximum(attach, 0)], n_keep + par)
    scene_all = np.concatenate([trees.scene[keep_idx], new["scene"]])
    kept_parent = trees.parent[keep_idx]
    parent_all = np.concatenate(
        [np.where(kept_parent >= 0, old_pos[np.maximum(kept_parent, 0)], -1), parent_new]
    )
    order = np.argsort(scene_all, kind="stable")
    pos = np.empty(len(order), np.int64)
    pos[order] = np.arange(len(order))
    parent_all = np.where(parent_all >= 0, pos[np.maximum(parent_all, 0)], -1)
    cat = np.concatenate
    return Trees(
        scene=scene_all[order],
        type=cat([trees.type[keep_idx], new["type"]])[order],
        parent=parent_all[order],
        rule=cat([trees.rule[keep_idx], new["rule"]])[order],
        xyz=cat([trees.xyz[keep_idx], new["xyz"]])[order],
        quat=cat([trees.quat[keep_idx], new["quat"]])[order],
        n_scenes=trees.n_scenes,
    )


def regrow(grammar: Grammar, trees: Trees, chosen: IntArray, rng: np.random.Generator) -> Trees:
    """Every tree with the subtree below its `chosen` node (-1: none) redrawn from the
    grammar, given that node's pose and nesting depths."""
    c = chosen[chosen >= 0]
    desc = below(trees, chosen)
    nest = nesting_counts(grammar, trees)[c]
    new = _grow(grammar, trees.type[c], trees.xyz[c], trees.quat[c], nest, rng)
    f = len(c)
    par = new["parent"]
    attach = np.where(par < f, c[np.minimum(par, f - 1)] if f else par, -1)
    new["parent"] = np.where(par < f, -1, par - f)
    new["scene"] = trees.scene[c][new["root"]] if f else np.zeros(0, np.int64)
    return splice(trees, ~desc, new, attach)


def sites(grammar: Grammar, trees: Trees) -> tuple[IntArray, IntArray]:
    """Where a child can be born or die: (node, rule slot) of every `repeat` node and every
    rule of an `independent` node, except rules that max_nesting blocks there."""
    tb = grammar.tables
    rules = tb.type_rules[trees.type]  # (N, K), -1 padded
    kind = tb.type_kind[trees.type]
    ok = (rules >= 0) & ((kind == Kind.REPEAT) | (kind == Kind.INDEPENDENT))[:, None]
    if tb.nesting_max.shape[0] and ok.any():
        nest = nesting_counts(grammar, trees)
        slot = np.where(rules >= 0, tb.nesting_slot[tb.rule_child[np.maximum(rules, 0)]], -1)
        lim = tb.nesting_max[np.maximum(slot, 0)]
        depth = np.take_along_axis(nest, np.maximum(slot, 0), axis=1)
        ok &= ~((slot >= 0) & (depth >= lim))
    node, k = np.nonzero(ok)
    return node.astype(np.int64), k.astype(np.int64)


@dataclass(frozen=True)
class Step:
    """A proposed birth or death per tree: `born` the rule of the new child (-1: none),
    `dies` the child to remove (-1: none), and log P(k') / P(k) of the change."""

    born: IntArray
    dies: IntArray
    log_ratio: FloatArray


def _structure_step(
    grammar: Grammar, trees: Trees, v: IntArray, slot: IntArray, rng: np.random.Generator
) -> Step:
    """Choose birth or death at each tree's site (node v, rule slot)."""
    tb = grammar.tables
    n = trees.n_scenes
    has = v >= 0
    vv = np.maximum(v, 0)
    t = trees.type[vv]
    rule = tb.type_rules[t, slot]
    repeat = tb.type_kind[t] == Kind.REPEAT
    # the children of each site: nodes whose parent is the site's node, by the site's rule
    child = np.flatnonzero(trees.parent >= 0)
    s = trees.scene[child]
    mine = has[s] & (trees.parent[child] == v[s]) & (trees.rule[child] == rule[s])
    child, s = child[mine], s[mine]
    k = np.bincount(s, minlength=n)
    birth = np.where(repeat, rng.random(n) < 0.5, k == 0)
    dies = np.full(n, -1, np.int64)
    which = np.floor(rng.random(n) * np.maximum(k, 1)).astype(np.int64)
    first = np.concatenate([[0], np.cumsum(k)[:-1]])
    death = has & ~birth & (k > 0)
    dies[death] = child[np.argsort(s, kind="stable")][first[death] + which[death]]
    born = np.where(has & birth, rule, -1)
    width = tb.count_logp.shape[1]
    k2 = np.where(birth, k + 1, k - 1)

    def count_lp(c: IntArray) -> FloatArray:
        inside = (c >= 0) & (c < width)
        return np.where(inside, tb.count_logp[t, np.clip(c, 0, width - 1)], -np.inf)

    with np.errstate(invalid="ignore"):
        lp_rep = count_lp(k2) - count_lp(k)
    lp_p, lp_q = tb.type_logp[t, slot], tb.type_log1mp[t, slot]
    with np.errstate(invalid="ignore"):
        lp_ind = np.where(birth, lp_p - lp_q, lp_q - lp_p)
    log_ratio = np.where(repeat, lp_rep, lp_ind)
    # a step to a tree the grammar cannot make (a count beyond the law's support) is none
    ok = has & ((born >= 0) | (dies >= 0)) & (log_ratio > -np.inf)
    return Step(np.where(ok, born, -1), np.where(ok, dies, -1), np.where(ok, log_ratio, -np.inf))


def _apply_step(
    grammar: Grammar, trees: Trees, v: IntArray, step: Step, rng: np.random.Generator
) -> Trees:
    """The trees with each step's child removed (with its subtree) or drawn (with a subtree
    drawn from the grammar below it)."""
    tb = grammar.tables
    gone = below(trees, step.dies)
    gone[step.dies[step.dies >= 0]] = True
    bs = np.flatnonzero(step.born >= 0)  # trees with a birth
    at, rid = v[bs], step.born[bs]
    xyz, quat = np.zeros((len(bs), 3)), np.zeros((len(bs), 4))
    for r in np.unique(rid):
        w = np.flatnonzero(rid == r)
        xyz[w], quat[w], _ = sample_children(
            grammar, int(r), trees.xyz[at[w]], trees.quat[at[w]], rng
        )
    ctype = tb.rule_child[rid]
    nest = nesting_counts(grammar, trees)[at]
    slot = tb.nesting_slot[ctype]
    nest[np.flatnonzero(slot >= 0), slot[slot >= 0]] += 1
    grown = _grow(grammar, ctype, xyz, quat, nest, rng)
    f = len(bs)
    new = {
        "scene": np.concatenate([bs, bs[grown["root"]]]),
        "type": np.concatenate([ctype, grown["type"]]),
        "rule": np.concatenate([rid, grown["rule"]]),
        "xyz": np.concatenate([xyz, grown["xyz"]]),
        "quat": np.concatenate([quat, grown["quat"]]),
        "parent": np.concatenate([np.full(f, -1, np.int64), grown["parent"]]),
    }
    attach = np.concatenate([at, np.full(len(grown["type"]), -1, np.int64)])
    return splice(trees, ~gone, new, attach)


def _grow(
    grammar: Grammar,
    f_type: IntArray,
    f_xyz: FloatArray,
    f_quat: FloatArray,
    f_nest: IntArray,
    rng: np.random.Generator,
) -> dict[str, NDArray]:  # type: ignore[type-arg]
    """The subtrees below a frontier of nodes (`ssgc.sample.forward.grow`), all levels
    together: node ids as there, `root` the frontier node each new node descends from."""
    out: dict[str, list[NDArray]] = {
        k: [] for k in ("type", "parent", "rule", "xyz", "quat", "root")
    }  # type: ignore[type-arg]
    for _, _, level in grow(grammar, f_type, f_xyz, f_quat, f_nest, rng):
        if level is None:
            break
        for k in out:
            out[k].append(level["origin" if k == "root" else k])
    empty = {
        "type": (0,),
        "parent": (0,),
        "rule": (0,),
        "root": (0,),
        "xyz": (0, 3),
        "quat": (0, 4),
    }
    return {
        k: np.concatenate(v)
        if v
        else np.zeros(empty[k], float if k in ("xyz", "quat") else np.int64)
        for k, v in out.items()
    }
