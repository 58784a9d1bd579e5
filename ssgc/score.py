"""Scoring a scene tree: its log-probability under the grammar (thesis Eq. 2.1).

A pure function of (grammar, trees), vectorised over every node of every tree in the batch:
the discrete term of each parent (which rules fired, Table 2.3.1 node kinds) is computed for
all nodes at once from a (node × rule slot) child-count matrix, and the continuous term of
each edge comes from `ssgc.rules`.  A tree the grammar cannot produce scores -inf;
`explain` says why, for messages.

A tree's score integrates out the poses of its *unseen* nodes — nodes with no observed node at
or below them.  Every pose law is a normalised density, so each such node's edge integrates to
1 and drops out, exactly: what is left is the probability of the tree's structure and the
density of the poses a scene can show.  Parses maximise it; samplers record it, explanations
and fits use it.  `marginal=False` gives Eq. 2.1 as written, every pose's density included.  At its
mode a Normal of variance 0.01 has density e^4.15 per node, so under Eq. 2.1 an empty latent
node placed at its mode raised a tree's score, and parses added such nodes (docs/parsing.md,
"What a parse maximises").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import quat_angle
from ssgc.ir import Grammar, Kind
from ssgc.rules import POS_TOL, ROT_TOL, rotation_log_density, translation_log_density
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class NodeTerms:
    """Per-node parts of the score; a tree's score is the sum over its nodes."""

    choice: FloatArray  # log P(this node's set of fired rules)
    edge: FloatArray  # log p(this node's pose | its parent's pose, its rule); 0 for roots
    valid: NDArray[np.bool_]  # False where the structure is impossible (the term is -inf)


def score_trees(grammar: Grammar, trees: Trees, marginal: bool = True) -> FloatArray:
    """Log-probability of each tree in the batch (-inf for trees the grammar cannot produce);
    `marginal`: with the poses of unseen nodes integrated out (the module's docstring)."""
    terms = node_terms(grammar, trees, marginal)
    total = np.bincount(trees.scene, terms.choice + terms.edge, minlength=trees.n_scenes)
    invalid = np.bincount(trees.scene, ~terms.valid, minlength=trees.n_scenes) > 0
    invalid |= _roots(trees) != 1  # a tree of no nodes summed to 0: probability 1
    return np.where(invalid, -np.inf, total)


def _roots(trees: Trees) -> NDArray[np.int64]:
    return np.bincount(trees.scene[trees.parent < 0], minlength=trees.n_scenes)


def seen_nodes(grammar: Grammar, trees: Trees) -> NDArray[np.bool_]:
    """Nodes with an observed node at or below them: the nodes whose poses a scene can show
    (directly, or through where its observed descendants lie)."""
    seen = grammar.tables.type_observed[trees.type].copy()
    up = np.flatnonzero(seen)
    while len(up):  # one level per round, each round only the nodes newly seen
        parent = trees.parent[up]
        parent = np.unique(parent[parent >= 0])
        up = parent[~seen[parent]]
        seen[up] = True
    return seen


def unseen_edges(grammar: Grammar, trees: Trees) -> FloatArray:
    """Per tree, the log-densities of its unseen nodes' poses: what a sampler, which draws
    every pose, takes off its Eq. 2.1 sum to record the tree's score (`marginal`)."""
    out = np.zeros(trees.n_scenes)
    maybe = _maybe_unseen(grammar)  # a shortcut: the sink's trees never have such a node
    if len(trees) == 0 or not maybe[trees.type, np.maximum(trees.rule, 0)].any():
        return out
    unseen = np.flatnonzero(~seen_nodes(grammar, trees) & (trees.parent >= 0))
    if len(unseen):
        r, p = trees.rule[unseen], trees.parent[unseen]
        edge = translation_log_density(
            grammar, r, trees.xyz[p], trees.quat[p], trees.xyz[unseen]
        ) + rotation_log_density(grammar, r, trees.quat[p], trees.quat[unseen])
        out += np.bincount(trees.scene[unseen], edge, minlength=trees.n_scenes)
    return out


def _maybe_unseen(grammar: Grammar) -> NDArray[np.bool_]:
    """(types, rules): whether a node of this type, made by this rule, might be unseen and
    carry a density: a latent type that some expansion leaves with nothing observed, under a
    rule with a translation or rotation that is not fixed.  A fixed point over the types that
    may say yes too often, never no wrongly: a rule to a type with `max_nesting` may be
    blocked at some depth, and then makes nothing, so such a child counts as holding nothing
    (an `and` whose one child was bounded said no, and sampled scenes kept the density of a
    node they do not show in their `log_prob`)."""
    bounded = np.array([t.max_nesting is not None for t in grammar.types], bool)
    can = ~grammar.tables.type_observed.copy()
    while True:  # from "every latent type can" down to the greatest fixed point
        empty = can | bounded
        new = np.array(
            [
                t.can_hold_nothing(
                    [(grammar.rules[r].index, bool(empty[grammar.rules[r].child])) for r in t.rules]
                )
                for t in grammar.types
            ],
            bool,
        )
        if np.array_equal(new, can):
            break
        can = new
    free = np.array(
        [r.translation.point is None or r.rotation.point is None for r in grammar.rules] or [False]
    )
    return can[:, None] & free[None, :]


def node_terms(grammar: Grammar, trees: Trees, marginal: bool = True) -> NodeTerms:
    """`marginal`: an unseen node's edge is 0, its pose integrated out (the module's
    docstring); a pose its law cannot produce still makes the tree impossible."""
    n = len(trees)
    valid = _structure_valid(grammar, trees)
    # Only trust the rule/type tables on nodes whose parent link is consistent.
    rule = np.where(valid & (trees.rule >= 0), trees.rule, -1)
    child = np.flatnonzero(rule >= 0)
    r, p = rule[child], trees.parent[child]

    counts, exists, blocked = fired_slots(grammar, trees, rule)
    choice, ok = _choice_terms(grammar, trees.type, counts, exists, blocked)

    edge = np.zeros(n)
    if len(child):
        edge[child] = translation_log_density(
            grammar, r, trees.xyz[p], trees.quat[p], trees.xyz[child]
        ) + rotation_log_density(grammar, r, trees.quat[p], trees.quat[child])
    valid &= ok & np.isfinite(edge) & np.isfinite(choice)
    if marginal:
        edge = np.where(seen_nodes(grammar, trees), edge, 0.0)
    return NodeTerms(choice=np.where(ok, choice, -np.inf), edge=edge, valid=valid)


def fired_slots(
    grammar: Grammar, trees: Trees, rule: NDArray[np.int64] | None = None
) -> tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]]:
    """(nodes, rule slots) arrays: how often each rule of the node's type fired at the node,
    whether the slot is a rule at all, and whether max_nesting blocks it there.

    The scorer turns them into each node's discrete term and the fitter into rule frequencies,
    so both count the same way.  `rule` overrides the trees' rules (-1 to leave an edge out).
    """
    tb = grammar.tables
    rule = trees.rule if rule is None else rule
    child = np.flatnonzero(rule >= 0)
    width, n = tb.type_rules.shape[1], len(trees)
    slots = trees.parent[child] * width + tb.rule_index[rule[child]]
    counts = np.bincount(slots, minlength=n * width).reshape(n, width)
    exists = tb.type_rules[trees.type] >= 0
    return counts, exists, _blocked(grammar, trees) & exists


def _structure_valid(grammar: Grammar, trees: Trees) -> NDArray[np.bool_]:
    """Each node's rule must belong to its parent's type and produce its type; roots at x_root."""
    tb = grammar.tables
    n_rules = len(grammar.rules)
    is_root = trees.parent < 0
    known = (trees.rule >= 0) & (trees.rule < n_rules)
    r = np.where(known, trees.rule, 0)
    parent_type = trees.type[np.maximum(trees.parent, 0)]
    ok_child = known.copy()
    if n_rules:  # a grammar of one terminal root has no rule tables to look in
        ok_child &= (tb.rule_parent[r] == parent_type) & (tb.rule_child[r] == trees.type)
    ok_root = (
        (trees.type == grammar.root)
        & (np.linalg.norm(trees.xyz - grammar.root_xyz, axis=1) <= POS_TOL)
        & (quat_angle(trees.quat, grammar.root_quat) <= ROT_TOL)
    )
    return np.where(is_root, ok_root, ok_child)


def nesting_counts(grammar: Grammar, trees: Trees) -> NDArray[np.int64]:
    """(nodes, bounded types): how many nodes of each bounded type lie on the path to the root."""
    tb = grammar.tables
    n_bounded = tb.nesting_max.shape[0]
    out = np.zeros((len(trees), n_bounded), np.int64)
    if n_bounded == 0:
        return out
    own = np.zeros((len(grammar.types), n_bounded), np.int64)
    bounded_types = np.flatnonzero(tb.nesting_slot >= 0)
    own[bounded_types, tb.nesting_slot[bounded_types]] = 1
    # path sums by pointer doubling: after k rounds, out[v] sums the 2**k nodes nearest v on
    # its path and jump[v] is the next node past them, so a chain of 10,000 nodes takes 14
    # rounds (walking up one node per round, as before, took 10,000 rounds over every node)
    out[:] = own[trees.type]
    jump = np.asarray(trees.parent, np.int64).copy()
    while np.any(jump >= 0):
        has = np.flatnonzero(jump >= 0)
        out[has] += out[jump[has]]
        jump[has] = jump[jump[has]]
    return out


def _blocked(grammar: Grammar, trees: Trees) -> NDArray[np.bool_]:
    """(nodes, rule slots): rules that cannot fire at this node because of max_nesting."""
    tb = grammar.tables
    nest = nesting_counts(grammar, trees)
    rules = tb.type_rules[trees.type]  # (N, K), -1 padded
    if nest.shape[1] == 0:  # (also when the grammar has no rules at all)
        return np.zeros(rules.shape, bool)
    slot = np.where(rules >= 0, tb.nesting_slot[tb.rule_child[np.maximum(rules, 0)]], -1)
    depth_here = np.take_along_axis(nest, np.maximum(slot, 0), axis=1)
    return (slot >= 0) & (depth_here >= tb.nesting_max[np.maximum(slot, 0)])


def _choice_terms(
    grammar: Grammar,
    ntype: NDArray[np.int64],
    counts: NDArray[np.int64],
    exists: NDArray[np.bool_],
    blocked: NDArray[np.bool_],
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Discrete log-probability of each node's fired rules, and whether that set is possible."""
    tb = grammar.tables
    kind = tb.type_kind[ntype]
    allowed = exists & ~blocked
    total = counts.sum(axis=1)
    logp = tb.type_logp[ntype]
    log1mp = tb.type_log1mp[ntype]
    out = np.zeros(len(ntype))
    ok = np.ones(len(ntype), bool)

    ok[kind == Kind.TERMINAL] = total[kind == Kind.TERMINAL] == 0

    is_and = kind == Kind.AND
    ok[is_and] = np.all(counts[is_and] == allowed[is_and], axis=1)

    is_or = kind == Kind.OR
    if np.any(is_or):
        c, a, lp = counts[is_or], allowed[is_or], logp[is_or]
        # rules of weight 0 never fire: with every other rule blocked the node makes nothing,
        # with probability 1, as the sampler draws it (docs/grammar.md 3.4)
        any_allowed = (a & np.isfinite(lp)).any(axis=1)
        chosen = np.argmax(c, axis=1)
        one_allowed = (c.sum(axis=1) == 1) & a[np.arange(len(c)), chosen]
        ok[is_or] = np.where(any_allowed, one_allowed, c.sum(axis=1) == 0)
        with np.errstate(divide="ignore", invalid="ignore"):  # (-inf - -inf: not one_allowed)
            log_mass = np.log(np.sum(np.where(a, np.exp(lp), 0.0), axis=1))
            out[is_or] = np.where(one_allowed, lp[np.arange(len(c)), chosen] - log_mass, 0.0)

    is_ind = kind == Kind.INDEPENDENT
    if np.any(is_ind):
        c, a = counts[is_ind], allowed[is_ind]
        ok[is_ind] = np.all(c <= a, axis=1)  # at most once, never when blocked
        term = np.where(c >= 1, logp[is_ind], log1mp[is_ind])
        out[is_ind] = np.sum(np.where(a, term, 0.0), axis=1)

    is_rep = kind == Kind.REPEAT
    if np.any(is_rep):
        c, a, t = counts[is_rep, 0], allowed[is_rep, 0], ntype[is_rep]
        ok[is_rep] = np.where(a, c <= tb.count_max[t], c == 0)
        clipped = np.minimum(c, tb.count_logp.shape[1] - 1)
        out[is_rep] = np.where(a, tb.count_logp[t, clipped], 0.0)
    out = np.where(ok, out, -np.inf)
    return out, ok & np.isfinite(out)


def explain(grammar: Grammar, trees: Trees) -> list[str]:
    """Human-readable reasons why a single tree scores -inf (empty if it is possible)."""
    terms = node_terms(grammar, trees)
    roots = int(_roots(trees).sum())
    reasons = []
    if roots != 1:
        reasons.append(f"the tree has {roots} roots; a scene's tree has one, the grammar's root")
    for i in np.flatnonzero(~terms.valid):
        name = grammar.types[trees.type[i]].name
        if trees.parent[i] < 0:
            reasons.append(f"node {i} ({name}) is a root but is not the grammar's root at its pose")
        elif not np.isfinite(terms.edge[i]):
            rule = grammar.rule_name(int(trees.rule[i])) if trees.rule[i] >= 0 else "?"
            reasons.append(f"node {i} ({name}): its pose is impossible under rule {rule}")
        elif not np.isfinite(terms.choice[i]):
            reasons.append(f"node {i} ({name}): its set of children is impossible")
        else:
            reasons.append(f"node {i} ({name}): not produced by a rule of its parent's type")
    return reasons
