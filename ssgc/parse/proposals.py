"""Pose proposals for latent equivalent sets (thesis 3.5.1).

A set that can be active without any observed node (a `Pair` formation centre in a
constituency grammar) has no pose to read off the scene, so the integer program chooses among
*proposed* poses.  Proposals are made bottom-up, children before parents:

- rule inversion from one child: the pose that puts one candidate child exactly at the mode of
  its rule (the mean offset, the Bingham mode);
- rule inversion from two children: the average of two such poses, for every pair of candidate
  children on two child slots (two rules, or two copies of a `repeat`);
- top-down: the mode of the set's own rule at each known parent pose, and a few draws from it.

Every proposal made from children is then moved, with scipy, to the pose that maximises the
log-densities of its parent rule and the children it was made from (`ssgc.parse.poses`), so for
a latent node with at most two children the proposal made from its true children is already its
best pose given them.  Refinement of the whole tree afterwards handles the rest.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.geometry import (
    quat_angle,
    quat_between,
    quat_canonical,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
)
from ssgc.ir import Grammar
from ssgc.laws.base import POS_TOL, ROT_TOL, Frame
from ssgc.laws.position_box import BoxTranslation
from ssgc.laws.rotation_revolute import RevoluteRotation
from ssgc.parse import hard_laws
from ssgc.parse.clock import check_deadline, past
from ssgc.parse.poses import PoseEdges, maximize_independent
from ssgc.parse.supertree import Supertree
from ssgc.rules import sample_children

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
MAX_PAIRS = 2000  # two-child proposals per set, the most consistent ones first
TOP_DOWN_PARENTS = 20  # parent poses whose rule mode is proposed
TOP_DOWN_SAMPLES = 8  # draws from the set's own rule


def latent_sets(st: Supertree) -> NDArray[np.bool_]:
    """Sets that can be active without an observed node (the root's set has a known pose)."""
    latent = ~st.always_observed
    latent[st.set_of[0]] = False
    return latent


@dataclass
class Candidates:
    """Candidate poses of every set's top node: observed-implied poses and proposals."""

    xyz: list[FloatArray]
    quat: list[FloatArray]

    def add(self, e: int, xyz: FloatArray, quat: FloatArray) -> None:
        """Append poses to set e, skipping any already there (within the pose tolerances)."""
        xyz, quat = xyz.reshape(-1, 3), quat.reshape(-1, 4)
        n_old = len(self.xyz[e])
        groups = pose_groups(np.vstack([self.xyz[e], xyz]), np.vstack([self.quat[e], quat]))
        # a new pose is kept unless it matches an old one or an earlier new one: it must be
        # the first of its group, and no group with an earlier first pose may be near it
        own = groups.of[n_old:]
        shadowed = np.zeros(len(groups.first), bool)
        shadowed[groups.b] = True
        keep = (groups.first[own] == n_old + np.arange(len(xyz))) & ~shadowed[own]
        self.xyz[e] = np.vstack([self.xyz[e], xyz[keep]])
        self.quat[e] = np.vstack([self.quat[e], quat[keep]])


GROUP_GRID = 1e-9  # poses whose coordinates round to one multiple of this are one pose


@dataclass(frozen=True)
class PoseGroups:
    """Poses that agree to GROUP_GRID (position and sign-canonical quaternion), numbered in
    the order of their first pose, and the pairs of distinct groups within the tolerances.

    Why: N objects at one pose (a chain with zero offsets) are N²/2 pairs within the
    tolerances, which took minutes and gigabytes; one group stands for all of them, and only
    the pairs between distinct nearby poses are compared.  GROUP_GRID is a thousand times
    finer than POS_TOL and ROT_TOL, so a group's poses are within the tolerances of each
    other, and a pose's neighbours are those of its group's first pose, up to 2e-9 at the
    tolerance's edge."""

    of: IntArray  # the group of each pose
    first: IntArray  # the first pose of each group, increasing
    a: IntArray  # near groups: group a's first pose comes before group b's
    b: IntArray


def pose_groups(xyz: FloatArray, quat: FloatArray) -> PoseGroups:
    """Group the poses; see `PoseGroups`."""
    key = np.rint(np.hstack([xyz, quat_canonical(quat)]) / GROUP_GRID)
    # rows sorted by every column (stable: a run's first row is its earliest pose), runs
    # numbered in sorted order, then renumbered by their first pose; no `np.unique(axis=0)`,
    # whose structured-array comparison numpy turns a Ctrl-C into an error of its own in
    order = np.lexsort(key.T[::-1])
    starts = np.ones(len(key), bool)
    starts[1:] = np.any(key[order][1:] != key[order][:-1], axis=1)
    run = np.empty(len(key), np.int64)
    run[order] = np.cumsum(starts) - 1
    first = order[starts]  # each run's earliest pose, runs in sorted order
    by_first = np.argsort(first)
    renumber = np.empty_like(by_first)
    renumber[by_first] = np.arange(len(by_first))
    of = run
    first = first[by_first]
    a, b = near_earlier(xyz[first], 0)
    near = quat_angle(quat[first[a]], quat[first[b]]) <= ROT_TOL
    return PoseGroups(renumber[of], first, a[near], b[near])


def cross_pairs(groups: PoseGroups) -> tuple[IntArray, IntArray]:
    """Every pair of poses (i < j) in two distinct groups within the tolerances."""
    if not len(groups.a):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(groups.of, kind="stable")
    counts = np.bincount(groups.of, minlength=len(groups.first))
    starts = np.cumsum(counts) - counts
    na, nb = counts[groups.a], counts[groups.b]
    pair = np.repeat(np.arange(len(na)), na * nb)
    k = np.arange(len(pair)) - np.repeat(np.cumsum(na * nb) - na * nb, na * nb)
    x = order[starts[groups.a][pair] + k // nb[pair]]
    y = order[starts[groups.b][pair] + k % nb[pair]]
    return np.minimum(x, y), np.maximum(x, y)


def earlier_count(group: IntArray, value: IntArray) -> IntArray:
    """How many earlier rows have the same group and the same (non-negative) value."""
    key = group.astype(np.int64) * (int(value.max(initial=0)) + 1) + value
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    run_start = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    lengths = np.diff(np.r_[run_start, len(key)])
    count = np.empty(len(key), np.int64)
    count[order] = np.arange(len(key)) - np.repeat(run_start, lengths)
    return count


# A generic unit direction: positions within POS_TOL are within POS_TOL along it, and poses
# that share a coordinate (clipped onto a box face, on an axis) still spread out along it.
_SWEEP = np.array([1.0, np.sqrt(2.0), np.sqrt(3.0)]) / np.sqrt(6.0)
NEAR_PAIRS_CHUNK = 1 << 20  # candidate pairs compared at once
ALL_PAIRS_UP_TO = 4096  # pairs below which every pair is compared (no sort)


def near_earlier(all_xyz: FloatArray, n_old: int) -> tuple[IntArray, IntArray]:
    """Pairs (i, j): position i of `all_xyz` lies within POS_TOL of new position j (row
    n_old + j) and comes before it.

    Why not all pairs: a wide `repeat` of a 1,000-object scene adds a thousand poses to each of
    a thousand sets, and comparing every pair took a minute.  Sorted along one direction, only
    the poses in a 2·POS_TOL window of each new one are compared: O(n log n) unless many poses
    share one position."""
    new_xyz = all_xyz[n_old:]
    if len(all_xyz) * len(new_xyz) <= ALL_PAIRS_UP_TO:  # small: one broadcast is quicker
        near = np.linalg.norm(all_xyz[:, None, :] - new_xyz[None, :, :], axis=2) <= POS_TOL
        earlier = np.arange(len(all_xyz))[:, None] < (n_old + np.arange(len(new_xyz)))[None, :]
        i, j = np.nonzero(near & earlier)
        return i.astype(np.int64), j.astype(np.int64)
    s = all_xyz @ _SWEEP
    order = np.argsort(s, kind="stable")
    sorted_s = s[order]
    new_s = s[n_old:]
    lo = np.searchsorted(sorted_s, new_s - 2 * POS_TOL, "left")
    counts = np.searchsorted(sorted_s, new_s + 2 * POS_TOL, "right") - lo
    ends = np.cumsum(counts)
    out_i, out_j = [], []
    start = 0
    while start < len(new_s):  # chunks of at most NEAR_PAIRS_CHUNK pairs (or one new pose)
        base = ends[start - 1] if start else 0
        stop = max(int(np.searchsorted(ends, base + NEAR_PAIRS_CHUNK, "right")), start + 1)
        j = np.repeat(np.arange(start, stop), counts[start:stop])
        first = np.repeat(ends[start:stop] - counts[start:stop], counts[start:stop])
        i = order[np.repeat(lo[start:stop], counts[start:stop]) + np.arange(len(j)) - first + base]
        keep = (i < n_old + j) & (
            np.linalg.norm(all_xyz[i] - all_xyz[n_old + j], axis=1) <= POS_TOL
        )
        out_i.append(i[keep])
        out_j.append(j[keep])
        start = stop
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_i), np.concatenate(out_j)


def rotation_mode(grammar: Grammar, r: int) -> FloatArray | None:
    """The most likely child rotation relative to its parent, or None if not parent-relative."""
    law = grammar.rules[r].rotation
    return law.mode() if law.frame == Frame.PARENT else None


def translation_mode(grammar: Grammar, r: int) -> tuple[FloatArray, Frame]:
    """The most likely child position, in the frame its rule's law is written in."""
    law = grammar.rules[r].translation
    return law.mode(), law.frame


def child_mode(
    grammar: Grammar, r: int, parent_xyz: FloatArray, parent_quat: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The mode of rule r's child pose at each parent pose (top-down proposals)."""
    centre, frame = translation_mode(grammar, r)
    if frame == Frame.PARENT:
        xyz = parent_xyz + quat_rotate(parent_quat, centre)
    elif frame == Frame.WORLD_OFFSET:
        xyz = parent_xyz + centre
    else:
        xyz = np.broadcast_to(centre, parent_xyz.shape).copy()
    law = grammar.rules[r].rotation
    mode = law.mode()
    if mode is None:  # every rotation is as likely: keep the parent's
        quat = parent_quat.copy()
    elif law.frame == Frame.PARENT:
        quat = quat_multiply(parent_quat, mode)
    else:
        quat = np.broadcast_to(mode, parent_quat.shape).copy()
    return xyz, quat


def revolute_arc(grammar: Grammar, r: int) -> tuple[FloatArray, float, float] | None:
    """(axis, lo, hi) of rule r's revolute rotation law, None for any other law."""
    law = grammar.rules[r].rotation
    if not isinstance(law, RevoluteRotation):
        return None
    return np.asarray(law.axis, float), float(law.revolute.lo), float(law.revolute.hi)


def _clip_angle(alpha: FloatArray, lo: float, hi: float) -> FloatArray:
    """Each angle moved into [lo, hi] (modulo 2π), to the nearer end when outside."""
    rel = np.mod(alpha - lo, 2 * np.pi)
    width = hi - lo
    past = rel - width  # how far beyond hi; 2π - rel: how far before lo
    rel = np.where(rel <= width, rel, np.where(past <= 2 * np.pi - rel, width, 0.0))
    return lo + rel


def onto_arc(
    parent_quat: FloatArray,
    arc: tuple[FloatArray, float, float],
    quat: FloatArray,
    aligns: tuple[tuple[FloatArray, FloatArray], ...] = (),
) -> FloatArray:
    """Rotations parent ∘ Ra(α), α in the arc's range, one per row: the first of `aligns`
    (vector in the rotated frame, its world direction) that fixes α decides it (the rotation
    about the axis that takes one onto the other, Paden–Kahan's first subproblem); where none
    does (a vector along the axis), the rotation closest to `quat`.

    Why: a latent pose whose own rule is revolute has density zero off its arc, and a proposal
    made from its children (or averaged from two) is almost never on it; Newton cannot reach
    the arc from outside, where every step is -inf.  A child placed by a revolute law about
    axis b needs the pose to map b onto the child's b; a child at a fixed offset m from a
    pinned position needs it to map m onto the child's direction."""
    a, lo, hi = arc
    n = len(quat)
    pq = np.broadcast_to(parent_quat, (n, 4))
    # closest: <p ∘ (cos h, sin h a), q> = A cos h + B sin h, largest in |.| at h = atan2(B, A)
    pa = quat_multiply(pq, np.r_[0.0, a])
    alpha = 2 * np.arctan2(np.sum(pa * quat, axis=1), np.sum(pq * quat, axis=1))
    decided = np.zeros(n, bool)
    for vec_from, vec_to in aligns:
        b = np.broadcast_to(vec_from, (n, 3))
        w = quat_rotate(quat_conjugate(pq), vec_to)  # Ra(α) b = w in the parent's frame
        b_perp = b - np.outer(b @ a, a)
        w_perp = w - np.outer(w @ a, a)
        turn = np.arctan2(np.cross(b_perp, w_perp) @ a, np.sum(b_perp * w_perp, axis=1))
        ok = (np.linalg.norm(b_perp, axis=1) > 1e-6) & (np.linalg.norm(w_perp, axis=1) > 1e-6)
        ok &= ~decided
        alpha = np.where(ok, turn, alpha)
        decided |= ok
    alpha = _clip_angle(alpha, lo, hi)
    half = 0.5 * alpha[:, None]
    return quat_multiply(pq, np.hstack([np.cos(half), np.sin(half) * a]))


def known_parent(grammar: Grammar, st: Supertree, cand: Candidates, e: int):  # type: ignore[no-untyped-def]
    """The pose of set e's parent node, at which the set's own rule is scored: None if the rule
    ignores its parent (world frame), False if the parent's set has other than one pose."""
    top = int(st.set_top[e])
    rule = grammar.rules[int(st.rule[top])]
    if rule.translation.frame == Frame.WORLD and rule.rotation.frame == Frame.WORLD:
        return None
    p = int(st.parent[top])
    e_p = int(st.set_of[p])
    if len(cand.xyz[e_p]) != 1:
        return False
    tx, tq = cand.xyz[e_p][0], cand.quat[e_p][0]
    return tx + quat_rotate(tq, st.offset_xyz[p]), quat_multiply(tq, st.offset_quat[p])


class _SetProposer:
    """Proposals for one latent set e, from its child slots' candidates and its parent's."""

    def __init__(
        self,
        grammar: Grammar,
        st: Supertree,
        cand: Candidates,
        e: int,
        rng: np.random.Generator,
        deadline: float | None = None,
    ) -> None:
        self.g, self.st, self.cand, self.e, self.rng = grammar, st, cand, e, rng
        self.deadline = deadline
        self.top = int(st.set_top[e])
        self.slots = self._slots()
        self.prior = self._prior_parent()
        own_arc = revolute_arc(grammar, int(st.rule[self.top]))
        known = known_parent(grammar, st, cand, e) not in (None, False)
        self.arc = own_arc if known else None  # the own rule's arc about a known parent
        self.pinned_xyz, self.pinned_quat = self._pinned() if known else (None, None)
        self.pins = self._own_pins()
        self.target = self._aim_target()

    def _slots(self) -> list[tuple[int, int, int, int]]:
        """(member node, rule, child set, copies) for each rule leaving the set."""
        st = self.st
        seen: dict[tuple[int, int], list[int]] = {}
        for v in np.flatnonzero(st.set_of == self.e):
            for c in st.children[v]:
                if st.set_of[c] != self.e:
                    seen.setdefault((int(v), int(st.rule[c])), []).append(int(c))
        return [
            (v, r, int(st.set_of[kids[0]]), len(kids))
            for (v, r), kids in seen.items()
            if len(self.cand.xyz[st.set_of[kids[0]]])
        ]

    def _pinned(self) -> tuple[FloatArray | None, FloatArray | None]:
        """The position and the rotation the set's own rule fixes at its known parent (a
        fixed offset), each None when its law is not a point: proposals must sit there."""
        assert self.prior is not None
        r = int(self.st.rule[self.top])
        rule = self.g.rules[r]
        mx, mq = child_mode(self.g, r, self.prior[0][None], self.prior[1][None])
        return (
            mx[0] if rule.translation.point is not None else None,
            mq[0] if rule.rotation.point is not None else None,
        )

    def _prior_parent(self) -> tuple[FloatArray, FloatArray] | None:
        """The parent pose at which the set's own rule is scored during proposal refinement
        (any pose if the rule ignores its parent), or None if it is not known."""
        parent = known_parent(self.g, self.st, self.cand, self.e)
        if parent is None:
            return np.zeros(3), np.array([1.0, 0, 0, 0])
        return parent or None

    def _node_pose(self, n: int, top_xyz: FloatArray, top_quat: FloatArray):  # type: ignore[no-untyped-def]
        st = self.st
        return (
            top_xyz + quat_rotate(top_quat, st.offset_xyz[n]),
            quat_multiply(top_quat, st.offset_quat[n]),
        )

    def top_down(self) -> tuple[FloatArray, FloatArray]:
        st, g = self.st, self.g
        r = int(st.rule[self.top])
        p = int(st.parent[self.top])
        e_p = int(st.set_of[p])
        if len(self.cand.xyz[e_p]) == 0:
            return np.zeros((0, 3)), np.zeros((0, 4))
        px, pq = self._node_pose(
            p, self.cand.xyz[e_p][:TOP_DOWN_PARENTS], self.cand.quat[e_p][:TOP_DOWN_PARENTS]
        )
        mx, mq = child_mode(g, r, px, pq)
        pick = self.rng.integers(0, len(px), TOP_DOWN_SAMPLES)
        sx, sq, _ = sample_children(g, r, px[pick], pq[pick], self.rng)
        return np.vstack([mx, sx]), np.vstack([mq, sq])

    def invert(
        self, slot: tuple[int, int, int, int], child_xyz: FloatArray, child_quat: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Set-top poses that put each given child at the mode of the slot's rule."""
        v, r, _, _ = slot
        g = self.g
        default_xyz, default_quat = child_mode(
            g, int(self.st.rule[self.top]), *self._default_parent(len(child_xyz))
        )
        rel = rotation_mode(g, r)
        q_v = default_quat if rel is None else quat_multiply(child_quat, quat_conjugate(rel))
        if self.pinned_quat is not None:  # the set's own rule fixes its rotation
            q_v = quat_multiply(
                np.broadcast_to(self.pinned_quat, (len(child_xyz), 4)), self.st.offset_quat[v]
            )
        elif self.arc is not None:  # the set's own rule holds it to an arc: put it there
            q_top = quat_multiply(q_v, quat_conjugate(self.st.offset_quat[v]))
            q_top = self._onto_arc(q_top, slot, child_xyz, child_quat)
            q_v = quat_multiply(q_top, self.st.offset_quat[v])
        t_top, q_top = self._translation(slot, child_xyz, q_v, default_xyz)
        if self.pins is not None and self.pinned_quat is None and self.arc is None:
            t_top, q_top = self._onto_pins(child_xyz, t_top, q_top)
        if self.pinned_xyz is not None and self.pinned_quat is None and self.arc is None:
            q_top = self._onto_child_pins(((slot, child_xyz),), t_top, q_top)
        return t_top, q_top

    def _onto_child_pins(
        self,
        kids: tuple[tuple[tuple[int, int, int, int], FloatArray], ...],
        t_top: FloatArray,
        q_top: FloatArray,
    ) -> FloatArray:
        """Set-top rotations at a held position turned onto the pinned axes of the children's
        parent-frame Normals (`hard_laws.turn_onto_pins`), each child in turn, a few rounds
        where there are several.

        Why: inversion at a held position (a `same` link) kept the default rotation, which
        puts a child with `pin: [y]` off its pin (density zero): no proposal was feasible and
        the scene, sampled from the grammar, was `no_parse`."""
        pinned_kids = []
        for (v, r, _, _), child_xyz in kids:
            law = self.g.rules[r].translation
            free = getattr(law, "free", None)
            if law.frame == Frame.PARENT and free is not None and not np.all(free):
                pinned_kids.append((v, ~np.asarray(free, bool), law.offset, child_xyz))
        rounds = 1 if len(pinned_kids) <= 1 else hard_laws.CHILD_PIN_ROUNDS
        st = self.st
        for _ in range(rounds):
            for v, pinned, mean, child_xyz in pinned_kids:
                q_top = hard_laws.turn_set_onto_pin(
                    q_top, t_top, st.offset_xyz[v], st.offset_quat[v], child_xyz, pinned, mean
                )
        return q_top

    def _aim_target(self) -> FloatArray | None:
        """Where the rules above expect the set's position: the mode of the first rule up
        the chain of fixed translations (`same`, `offset`) that is not one, at its parent's
        pose where that is known (or in the world); None where no such mode is known.  The
        chain's offsets are left out: a guess to aim at, not a pose."""
        st, g, cand = self.st, self.g, self.cand
        e, root = self.e, int(st.set_of[0])
        while e != root:
            r = int(st.rule[st.set_top[e]])
            law = g.rules[r].translation
            parent = known_parent(g, st, cand, e)
            if law.point is None and law.frame == Frame.WORLD:
                return law.mode()
            if parent not in (None, False):
                return child_mode(g, r, parent[0][None], parent[1][None])[0][0]
            if law.point is None:
                return None
            e = int(st.set_of[st.parent[st.set_top[e]]])
        return cand.xyz[root][0] if len(cand.xyz[root]) == 1 else None

    def aimed(
        self, slot: tuple[int, int, int, int], child_xyz: FloatArray
    ) -> tuple[FloatArray, FloatArray] | None:
        """Set-top poses that put each child at the slot's fixed offset, the set turned so
        that it sits as near to `_aim_target` as the offset allows (then onto its own pins);
        None where the slot's rule is not a fixed offset under a free rotation.

        Why: such a child holds the set on a sphere about it, and rule inversion at the
        default rotation put it at an arbitrary point of that sphere, often metres from where
        the rules above want it (a chain L1 -same-> L2 -offset-> B under uniform rotations:
        150 nats below the sampled tree).  Refinement cannot walk the sphere from a tree the
        model did not pick (`no_parse`, or a shallower tree whose rotation is held)."""
        v, r, _, _ = slot
        law = self.g.rules[r].translation
        if self.target is None or self.pinned_quat is not None or self.arc is not None:
            return None
        if law.point is None or law.frame != Frame.PARENT or rotation_mode(self.g, r) is not None:
            return None
        arm = self.st.offset_xyz[v] + quat_rotate(self.st.offset_quat[v], law.point)
        if np.linalg.norm(arm) <= POS_TOL or not len(child_xyz):
            return None
        q_top = quat_between(np.broadcast_to(arm, child_xyz.shape), child_xyz - self.target)
        t_top = child_xyz - quat_rotate(q_top, arm)
        if self.pins is not None:
            t_top, q_top = self._onto_pins(child_xyz, t_top, q_top)
        return t_top, q_top

    def _own_pins(self) -> tuple[NDArray[np.bool_], FloatArray, FloatArray, FloatArray] | None:
        """The axes the set's own translation pins, where its frame puts them: (pinned,
        their values, the frame's origin, the frame's rotation); None without pinned axes,
        or when the frame's parent pose is not known."""
        law = self.g.rules[int(self.st.rule[self.top])].translation
        free = getattr(law, "free", None)
        if free is None or np.all(free) or self.prior is None or self.pinned_xyz is not None:
            return None
        origin, turn = self.prior
        if law.frame == Frame.WORLD:
            origin, turn = np.zeros(3), np.array([1.0, 0, 0, 0])
        elif law.frame == Frame.WORLD_OFFSET:
            turn = np.array([1.0, 0, 0, 0])
        return ~np.asarray(free, bool), np.asarray(law.offset, float), origin, turn

    def _onto_pins(
        self, child_xyz: FloatArray, t_top: FloatArray, q_top: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Set-top poses moved onto the own rule's pinned axes, the child kept where the
        inversion put it by turning the set about it: the set's vector u to the child keeps
        its length, its pinned components become what the pins ask, its free ones keep
        their direction.  Where no turn reaches (the child too far from the pinned line or
        plane, or at the set's own position) the pose is left as it was.

        Why: a latent set whose own Normal pins axes (`pin: [x, y]`) and whose child sits at
        a fixed offset was proposed at `child - R·offset`, off its pins, where its density is
        zero; refinement cannot step in from outside, and every sampled scene of such a
        grammar was `no_parse`."""
        assert self.pins is not None
        pinned, value, origin, turn = self.pins
        u = quat_rotate(quat_conjugate(turn), child_xyz - t_top)  # in the law's frame
        want = quat_rotate(quat_conjugate(turn), child_xyz - origin) - value  # pinned parts
        length2 = np.sum(u * u, axis=1)
        left2 = length2 - np.sum(np.where(pinned, want, 0.0) ** 2, axis=1)
        free_u = np.where(pinned, 0.0, u)
        free_norm = np.linalg.norm(free_u, axis=1)
        ok = (left2 >= 0) & (length2 > POS_TOL**2) & (free_norm > 1e-12)
        scale = np.sqrt(np.maximum(left2, 0.0)) / np.where(ok, free_norm, 1.0)
        new_u = np.where(pinned, want, free_u * scale[:, None])
        world_u = quat_rotate(turn, u)
        world_new = quat_rotate(turn, new_u)
        swing = quat_between(world_u, world_new)
        q_new = quat_multiply(swing, q_top)
        t_new = child_xyz - world_new
        return np.where(ok[:, None], t_new, t_top), np.where(ok[:, None], q_new, q_top)

    def _onto_arc(
        self,
        q_top: FloatArray,
        slot: tuple[int, int, int, int],
        child_xyz: FloatArray,
        child_quat: FloatArray,
    ) -> FloatArray:
        """`onto_arc` for this set, aligned with the slot's child: its revolute axis, or
        its fixed offset from the set's pinned position."""
        assert self.arc is not None and self.prior is not None
        v, r, _, _ = slot
        st, aligns = self.st, []
        child_arc = revolute_arc(self.g, r)
        if child_arc is not None:  # its axis in the top's frame, and in the world
            b = quat_rotate(st.offset_quat[v], child_arc[0])
            aligns.append((b, quat_rotate(child_quat, child_arc[0])))
        law = self.g.rules[r].translation
        anchor = self.pinned_xyz if self.pinned_xyz is not None else self._on_pins(child_xyz)
        if anchor is not None and law.point is not None and law.frame == Frame.PARENT:
            m = st.offset_xyz[v] + quat_rotate(st.offset_quat[v], law.point)
            aligns.append((m, child_xyz - anchor))
        return onto_arc(self.prior[1], self.arc, q_top, tuple(aligns))

    def _on_pins(self, child_xyz: FloatArray) -> FloatArray | None:
        """Where the set's own pins put it, as far as they say: each child's position with
        its pinned coordinates replaced by the pins' (in the law's frame); None without pins.
        A shelf pinned at x = y = 0 and turning about z: the turn that takes its book's fixed
        offset onto the book's direction from the z axis needs only the pinned x and y.
        Without it, such a set got no proposal on its pins, and every scene was `no_parse`."""
        if self.pins is None:
            return None
        pinned, value, origin, turn = self.pins
        local = quat_rotate(quat_conjugate(turn), child_xyz - origin)
        local = np.where(pinned, value, local)
        return origin + quat_rotate(turn, local)

    def _translation(
        self,
        slot: tuple[int, int, int, int],
        child_xyz: FloatArray,
        q_v: FloatArray,
        default_xyz: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """Set-top poses with member v at rotation q_v that put each child at the mode of the
        slot's translation law."""
        v, r, _, _ = slot
        centre, frame = translation_mode(self.g, r)
        if frame == Frame.PARENT:
            t_v = child_xyz - quat_rotate(q_v, centre)
        elif frame == Frame.WORLD_OFFSET:
            t_v = child_xyz - centre
        else:
            t_v = default_xyz
        q_top = quat_multiply(q_v, quat_conjugate(self.st.offset_quat[v]))
        if self.pinned_xyz is not None:  # the set's own rule fixes its position
            return np.broadcast_to(self.pinned_xyz, (len(q_top), 3)).copy(), q_top
        return t_v - quat_rotate(q_top, self.st.offset_xyz[v]), q_top

    def _at(self, slot: tuple[int, int, int, int], child_xyz: FloatArray, q_top: FloatArray):  # type: ignore[no-untyped-def]
        """The set-top positions, at rotation q_top, that put each child at its law's mode."""
        default_xyz, _ = child_mode(
            self.g, int(self.st.rule[self.top]), *self._default_parent(len(child_xyz))
        )
        q_v = quat_multiply(q_top, self.st.offset_quat[slot[0]])
        return self._translation(slot, child_xyz, q_v, default_xyz)[0]

    def _default_parent(self, n: int) -> tuple[FloatArray, FloatArray]:
        if self.prior is not None:
            return np.tile(self.prior[0], (n, 1)), np.tile(self.prior[1], (n, 1))
        return np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1))

    def propose(self) -> tuple[FloatArray, FloatArray]:
        xs, qs, edges = [], [], []
        singles = [self._children(s) for s in self.slots]
        for s, (cx, cq) in zip(self.slots, singles, strict=True):
            for tx, tq in filter(None, (self.invert(s, cx, cq), self.aimed(s, cx))):
                xs.append(tx)
                qs.append(tq)
                edges += [((s, cx[k], cq[k]),) for k in range(len(cx))]
        px, pq, pe = self._pairs(singles)
        xs.append(px)
        qs.append(pq)
        edges += pe
        x0 = np.vstack([np.zeros((0, 3)), *xs])
        q0 = np.vstack([np.zeros((0, 4)), *qs])
        if len(x0):
            x0, q0 = maximize_independent(
                self.g, self._edges(edges), x0, quat_normalize(q0), deadline=self.deadline
            )
        tx, tq = self.top_down()
        return np.vstack([x0, tx]), np.vstack([q0, tq])

    def _children(self, slot: tuple[int, int, int, int]) -> tuple[FloatArray, FloatArray]:
        e_c = slot[2]
        return self.cand.xyz[e_c], self.cand.quat[e_c]

    def _pairs(self, singles: list[tuple[FloatArray, FloatArray]]):  # type: ignore[no-untyped-def]
        """Two-child proposals: the averaged inversions of every pair of candidate children on
        two slots (a slot pairs with itself when its rule has several copies)."""
        found: list[tuple[float, FloatArray, FloatArray, tuple]] = []
        for a in range(len(self.slots)):
            for b in range(a, len(self.slots)):
                if a == b and self.slots[a][3] < 2:
                    continue
                found += self._slot_pairs(a, b, singles)
        found.sort(key=lambda f: f[0])
        found = found[:MAX_PAIRS]
        if not found:
            return np.zeros((0, 3)), np.zeros((0, 4)), []
        return (
            np.stack([f[1] for f in found]),
            np.stack([f[2] for f in found]),
            [f[3] for f in found],
        )

    def _slot_pairs(self, a: int, b: int, singles):  # type: ignore[no-untyped-def]
        (ax, aq), (bx, bq) = singles[a], singles[b]
        ta, qa = self.invert(self.slots[a], ax, aq)
        tb_, qb = self.invert(self.slots[b], bx, bq)
        i, j = np.meshgrid(np.arange(len(ax)), np.arange(len(bx)), indexing="ij")
        i, j = i.ravel(), j.ravel()
        distinct = (np.linalg.norm(ax[i] - bx[j], axis=1) > POS_TOL) | (
            quat_angle(aq[i], bq[j]) > ROT_TOL
        )
        if a == b:
            distinct &= i < j
        i, j = i[distinct], j[distinct]
        sign = np.where(np.sum(qa[i] * qb[j], axis=1) < 0, -1.0, 1.0)[:, None]
        q = quat_normalize(qa[i] + sign * qb[j])
        held_a = rotation_mode(self.g, self.slots[a][1]) is not None
        one_held = held_a != (rotation_mode(self.g, self.slots[b][1]) is not None)
        if one_held:  # the other slot's rotation is the default, not a guess: not averaged
            q = qa[i] if held_a else qb[j]
        t = 0.5 * (ta[i] + tb_[j])
        if self.pinned_quat is not None and len(q):  # the own rule fixes the rotation
            q = np.tile(self.pinned_quat, (len(q), 1))
        elif self.arc is not None and len(q):  # the average is off the arc: back onto it
            q = onto_arc(self.prior[1], self.arc, q)  # type: ignore[index]
        if (self.arc is not None or self.pinned_quat is not None) and len(q):
            t = 0.5 * (self._at(self.slots[a], ax[i], q) + self._at(self.slots[b], bx[j], q))
        elif self.pinned_xyz is not None and len(q):  # a held position, a free rotation
            kids = ((self.slots[a], ax[i]), (self.slots[b], bx[j]))
            q = self._onto_child_pins(kids, t, q)
        elif one_held and len(q):
            t = self._held_position((self.slots[a], ax[i]), (self.slots[b], bx[j]), q)
        disagreement = np.linalg.norm(ta[i] - tb_[j], axis=1) + quat_angle(qa[i], qb[j])
        sa, sb = self.slots[a], self.slots[b]
        return [
            (
                float(disagreement[k]),
                t[k],
                q[k],
                ((sa, ax[i[k]], aq[i[k]]), (sb, bx[j[k]], bq[j[k]])),
            )
            for k in range(len(i))
        ]

    def _held_position(
        self,
        kid_a: tuple[tuple[int, int, int, int], FloatArray],
        kid_b: tuple[tuple[int, int, int, int], FloatArray],
        q: FloatArray,
    ) -> FloatArray:
        """Set-top positions at rotations q for a pair of children: the one a fixed offset
        gives where exactly one of the two slots is a fixed offset, else the mean of both
        slots' modes.

        Why: a latent set whose rotation one child holds (`rotation: same`) and whose other
        child sits at a fixed offset under a free rotation (a chain of `offset` links) is
        exactly placed by the pair, and the average of the two inversions (one at the
        default rotation) put no proposal on the chain: `no_parse` three sets deep."""
        at = [self._at(slot, xyz, q) for slot, xyz in (kid_a, kid_b)]
        fixed = [self.g.rules[slot[1]].translation.point is not None for slot, _ in (kid_a, kid_b)]
        if fixed[0] != fixed[1]:
            return at[0] if fixed[0] else at[1]
        return 0.5 * (at[0] + at[1])

    def _edges(self, assigned: list[tuple]) -> PoseEdges:
        """Edges of each proposal's local problem: its children, and its own rule if the
        parent pose is known."""
        st = self.st
        rule, pb, pxyz, pquat, cb, cxyz, cquat = [], [], [], [], [], [], []
        for k, kids in enumerate(assigned):
            for (v, r, _, _), t, q in kids:
                rule.append(r)
                pb.append(k)
                pxyz.append(st.offset_xyz[v])
                pquat.append(st.offset_quat[v])
                cb.append(-1)
                cxyz.append(t)
                cquat.append(q)
            if self.prior is not None:
                rule.append(int(st.rule[self.top]))
                pb.append(-1)
                pxyz.append(self.prior[0])
                pquat.append(self.prior[1])
                cb.append(k)
                cxyz.append(np.zeros(3))
                cquat.append(np.array([1.0, 0, 0, 0]))
        return PoseEdges(
            rule=np.asarray(rule, np.int64),
            p_block=np.asarray(pb, np.int64),
            p_xyz=np.asarray(pxyz, float).reshape(-1, 3),
            p_quat=np.asarray(pquat, float).reshape(-1, 4),
            c_block=np.asarray(cb, np.int64),
            c_xyz=np.asarray(cxyz, float).reshape(-1, 3),
            c_quat=np.asarray(cquat, float).reshape(-1, 4),
        )


def add_proposals(
    grammar: Grammar,
    st: Supertree,
    cand: Candidates,
    rng: np.random.Generator,
    deadline: float | None = None,
    stop: float | None = None,
) -> None:
    """Propose poses for every latent set, children's sets first (sets are numbered top-down).

    Sets whose top nodes share a type and whose child slots have the same candidates (the
    copies of a `repeat`) get the same proposals, computed once.  Past the deadline, proposals
    are still made but no longer optimised; past `stop` (the parse's own deadline) it raises
    OutOfTime before the next set: unoptimised proposals of many sets still take a while.
    """
    memo: dict[tuple, tuple[FloatArray, FloatArray]] = {}
    for e in np.flatnonzero(latent_sets(st))[::-1]:
        check_deadline(stop)
        proposer = _SetProposer(grammar, st, cand, int(e), rng, deadline)
        parent_set = int(st.set_of[st.parent[st.set_top[e]]])
        key = (
            int(st.type[st.set_top[e]]),
            int(st.rule[st.set_top[e]]),
            cand.xyz[parent_set].tobytes(),
            tuple(
                (s[1], cand.xyz[s[2]].tobytes(), cand.quat[s[2]].tobytes()) for s in proposer.slots
            ),
        )
        if key not in memo:
            fresh = Candidates([np.zeros((0, 3))], [np.zeros((0, 4))])
            fresh.add(0, *proposer.propose())
            memo[key] = (fresh.xyz[0], fresh.quat[0])
        if len(cand.xyz[e]):
            cand.add(int(e), *memo[key])
        else:
            cand.xyz[e], cand.quat[e] = memo[key][0].copy(), memo[key][1].copy()
    for e in np.flatnonzero(latent_sets(st)):  # parents first: into their boxes
        _clip_into_box(grammar, st, cand, int(e))
    for e in np.flatnonzero(latent_sets(st)):  # parents first: onto their parents' pins
        _onto_parent_pins(grammar, st, cand, int(e))


PIN_PARENTS = 16  # parent poses whose pins a latent set's proposals are moved onto
PIN_OWN = 8  # of the set's own proposals, the first


def _onto_parent_pins(grammar: Grammar, st: Supertree, cand: Candidates, e: int) -> None:
    """Add set e's first proposals moved onto the pinned axes of its own parent-frame Normal
    at each of its latent parent's first poses that none of them is on: the position with
    its pinned components (in the parent's frame) replaced by the pins', and the rule's
    mode; the rotation kept.  Only for a set whose position no child's rule depends on: its
    proposals came from a default parent alone (elsewhere the extra poses only moved the
    search to other trees: a recursive pinned chain lost 34 nats).

    Why: proposals are made children first, so a set under a latent parent is proposed
    before its parent's poses exist, at a default parent; off the pins its density is zero
    at every real parent pose, and refinement cannot step onto a pin both ends of which
    move.  A recursive set pinned in its parent's y, whose parent's rotation an observed
    child holds (`rotation: same`), got only trees that turned the parent off that child."""
    top = int(st.set_top[e])
    r = int(st.rule[top])
    law = grammar.rules[r].translation
    free = getattr(law, "free", None)
    p = int(st.parent[top])
    e_p = int(st.set_of[p])
    if free is None or np.all(free) or law.frame != Frame.PARENT or not latent_sets(st)[e_p]:
        return
    if _children_place(grammar, st, e):  # its proposals already sit where its children say
        return
    bx, bq = cand.xyz[e_p][:PIN_PARENTS], cand.quat[e_p][:PIN_PARENTS]
    own_xyz, own_quat = cand.xyz[e][:PIN_OWN], cand.quat[e][:PIN_OWN]
    if not len(bx) or not len(own_xyz):
        return
    px = bx + quat_rotate(bq, st.offset_xyz[p])  # the parent node's poses
    pq = quat_multiply(bq, st.offset_quat[p])
    n_p, n_o = len(px), len(own_xyz)
    tpx, tpq = np.repeat(px, n_o, axis=0), np.repeat(pq, n_o, axis=0)
    local = quat_rotate(quat_conjugate(tpq), np.tile(own_xyz, (n_p, 1)) - tpx)
    off = np.abs(local - np.asarray(law.offset, float))
    on_pins = np.all(free | (off <= POS_TOL), axis=1).reshape(n_p, n_o)
    keep = np.repeat(~on_pins.any(axis=1), n_o)  # parents with no proposal on their pins
    tpx, tpq, local = tpx[keep], tpq[keep], local[keep]
    local = np.where(free, local, np.asarray(law.offset, float))
    moved = tpx + quat_rotate(tpq, local)
    mode = tpx + quat_rotate(tpq, np.broadcast_to(np.asarray(law.offset, float), tpx.shape))
    rot = np.tile(own_quat, (n_p, 1))[keep]
    cand.add(e, np.vstack([moved, mode]), np.vstack([rot, rot]))


def _children_place(grammar: Grammar, st: Supertree, e: int) -> bool:
    """Whether a rule from set e to a child outside it depends on e's position (any frame
    but the world's)."""
    for v in np.flatnonzero(st.set_of == e):
        for c in st.children[v]:
            law = grammar.rules[int(st.rule[c])].translation
            if st.set_of[c] != e and law.frame != Frame.WORLD:
                return True
    return False


BOX_PARENTS = 10  # parent poses whose box a latent set's proposals are clipped into
BOX_OWN = 20  # of the set's own proposals, the first


def _clip_into_box(grammar: Grammar, st: Supertree, cand: Candidates, e: int) -> None:
    """Add set e's first proposals moved into its own rule's box (around each of the first
    parent poses, for a box offset).

    Why: proposals are made from children, bottom-up, and the best pose given the children is
    often outside the box its parent's candidates allow; the model over proposals then has no
    tree at all (`no_parse`).  A clipped pose is feasible, and refinement optimises it."""
    top = int(st.set_top[e])
    law = grammar.rules[int(st.rule[top])].translation
    if not isinstance(law, BoxTranslation) or not len(cand.xyz[e]):
        return
    own_xyz, own_quat = cand.xyz[e][:BOX_OWN], cand.quat[e][:BOX_OWN]
    if law.frame == Frame.WORLD:
        cand.add(e, np.clip(own_xyz, law.box.lo, law.box.hi), own_quat)
        return
    p = int(st.parent[top])
    e_p = int(st.set_of[p])
    bx, bq = cand.xyz[e_p][:BOX_PARENTS], cand.quat[e_p][:BOX_PARENTS]
    if not len(bx):
        return
    px = bx + quat_rotate(bq, st.offset_xyz[p])  # the parent node's positions
    lo, hi = px[:, None, :] + law.box.lo, px[:, None, :] + law.box.hi
    clipped = np.clip(own_xyz[None, :, :], lo, hi).reshape(-1, 3)
    cand.add(e, clipped, np.tile(own_quat, (len(px), 1)))


HARD_PARENTS = 8  # parent poses a set's hard-law poses are solved at
HARD_CHILDREN = 12  # candidate children per slot used to solve them
HARD_COMBOS = 160  # combinations of children per parent pose (singles first, then pairs)
HARD_KEEP = 1  # poses kept per combination (the best)
HARD_PER_SET = 32  # poses added to a set per pass: the model over them grows like K^depth
HARD_PARENTS_EACH = 2  # parent poses at which one combination of children is solved
HARD_RELAYED = 64  # pairs of a child and a grandchild through a latent child (relays)
HARD_TRIOS = 24  # trios of children pinned in a set's frame, per slot (`_near_trios`)


def add_hard_poses(
    grammar: Grammar, st: Supertree, cand: Candidates, deadline: float | None = None
) -> None:
    """Add, for every latent set, poses that satisfy its hard laws exactly
    (`ssgc.parse.hard_laws`): at each of its parent's first candidate poses, with no child,
    one child or two children on its slots.  Sets are solved children first, then parents
    first, then children first again, so that a chain of latent sets passes its constraints
    both ways; each pass prefers the poses the previous passes solved.

    Why: rule inversion and Newton steps aim at soft laws' modes, and a scene whose latent
    poses are held by boxes, pins and revolute arcs from both sides gets no feasible proposal
    (`no_parse`), although the scene was sampled from the grammar."""
    solved: dict[int, FloatArray] = {}  # per set, how many leading candidates are solved
    order = np.flatnonzero(latent_sets(st))
    for sets in (order[::-1], order, order[::-1]):
        for e in sets:
            if deadline is not None and time.perf_counter() >= deadline:
                return
            xyz, quat = _hard_set(grammar, st, cand, int(e), solved, deadline)
            if len(xyz):
                n_old = len(cand.xyz[e])
                cand.add(int(e), xyz, quat)
                new = np.arange(n_old, len(cand.xyz[e]))
                solved[int(e)] = np.r_[solved.get(int(e), np.zeros(0, np.int64)), new]


def _preferred(cand: Candidates, e: int, solved: dict[int, FloatArray], n: int) -> IntArray:
    """The first n candidate indices of set e, solved poses first."""
    first = solved.get(e, np.zeros(0, np.int64)).astype(np.int64)
    rest = np.setdiff1d(np.arange(len(cand.xyz[e])), first, assume_unique=True)
    return np.r_[first, rest][:n].astype(np.int64)


def _hard_set(
    grammar: Grammar,
    st: Supertree,
    cand: Candidates,
    e: int,
    solved: dict[int, FloatArray],
    deadline: float | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Hard-law poses of set e; past `deadline` it returns those solved so far (one set's
    combinations take up to a tenth of a second: a check per set let a parse overrun)."""
    top = int(st.set_top[e])
    r0 = int(st.rule[top])
    p = int(st.parent[top])
    e_p = int(st.set_of[p])
    rule = grammar.rules[r0]
    world = rule.translation.frame == Frame.WORLD and rule.rotation.frame == Frame.WORLD
    parents: list[tuple[FloatArray | None, FloatArray | None]] = [(None, None)]
    if not world and len(cand.xyz[e_p]):
        k = _preferred(cand, e_p, solved, HARD_PARENTS)
        bx, bq = cand.xyz[e_p][k], cand.quat[e_p][k]
        px = bx + quat_rotate(bq, st.offset_xyz[p])
        pq = quat_multiply(bq, st.offset_quat[p])
        parents = list(zip(px, pq, strict=True))
        if latent_sets(st)[e_p]:  # its poses are guesses: solve from the children alone too
            parents.insert(0, (None, None))
    combos = _child_combos(grammar, st, cand, e, solved)
    inherited = _inherited_boxes(grammar, st, e)
    fallback = cand.quat[e][:4]
    xs, qs = [np.zeros((0, 3))], [np.zeros((0, 4))]
    # half the poses from pairs of children (jointly implied), half from one child or none;
    # each combination at no more than HARD_PARENTS_EACH parent poses
    relayed = [c for c in combos if len(c) > 1 and any(k[4] is not None for k in c)]
    pairs = [c for c in combos if len(c) > 1 and all(k[4] is None for k in c)]
    for group in (relayed, pairs, [c for c in combos if len(c) == 1] + [()]):
        found = 0
        for combo in group:
            if found >= HARD_PER_SET // 2 or past(deadline):
                break
            found_here = 0
            for p_xyz, p_quat in parents:
                if combo and found_here >= HARD_PARENTS_EACH:  # without children: all
                    break
                laws = hard_laws.empty_laws()
                laws.boxes += inherited
                hard_laws.add_parent_rule(laws, grammar, r0, p_xyz, p_quat)
                for v, r, c_xyz, c_quat, via in combo:
                    if via is None:
                        hard_laws.add_child_rule(
                            laws, grammar, r, st.offset_xyz[v], st.offset_quat[v], c_xyz, c_quat
                        )
                    else:  # a grandchild, through the latent child set `via` names
                        v2, r2 = via
                        hard_laws.add_grandchild_rule(
                            laws,
                            grammar,
                            r,
                            st.offset_quat[v],
                            r2,
                            st.offset_xyz[v2],
                            st.offset_quat[v2],
                            c_xyz,
                            c_quat,
                        )
                x, q = hard_laws.hard_poses(grammar, laws, fallback, HARD_KEEP)
                xs.append(x)
                qs.append(q)
                found_here += len(x)
            found += found_here
    return np.vstack(xs), np.vstack(qs)


def _inherited_boxes(grammar: Grammar, st: Supertree, e: int) -> list:  # type: ignore[type-arg]
    """World boxes on set e's position that come from above through zero offsets: a set placed
    at its parent's position (`same`, or `offset` [0, 0, 0], from a member at the parent set's
    top) whose parent set is placed by a `world_box` (or inherits one) lies in that box too.

    Why: solved from its children alone, such a set gets poses outside the box two levels up
    when its rotation (a revolute arc, say) moves its position; the box narrows the arc."""
    boxes = []
    zero = np.zeros(3)
    while True:
        top = int(st.set_top[e])
        p = int(st.parent[top])
        law = grammar.rules[int(st.rule[top])].translation
        if p < 0 or law.point is None or np.any(law.point != 0) or np.any(st.offset_xyz[p] != 0):
            return boxes
        e = int(st.set_of[p])
        if e == int(st.set_of[0]):
            return boxes
        up = grammar.rules[int(st.rule[st.set_top[e]])].translation
        if isinstance(up, BoxTranslation) and up.frame == Frame.WORLD:
            boxes.append((up.box.lo, up.box.hi, zero))


def _hard_rule(grammar: Grammar, r: int) -> bool:
    """Whether rule r ties its parent's pose to its child's by a hard law (a pin, an arc, a
    box offset, a pinned axis)."""
    tl, rl = grammar.rules[r].translation, grammar.rules[r].rotation
    rot = rl.frame == Frame.PARENT and (rl.point is not None or isinstance(rl, RevoluteRotation))
    pinned_axes = hasattr(tl, "free") and not np.all(tl.free)
    box = isinstance(tl, BoxTranslation) and tl.frame != Frame.WORLD
    return rot or tl.point is not None or box or (pinned_axes and tl.frame != Frame.WORLD)


def _turning_link(grammar: Grammar, r: int) -> bool:
    """Whether rule r turns its child with its parent by a fixed or revolute rotation, so that
    the child's arcs carry over to the parent (`hard_laws.add_grandchild_rule`)."""
    rl = grammar.rules[r].rotation
    return rl.frame == Frame.PARENT and (rl.point is not None or isinstance(rl, RevoluteRotation))


def _hard_grandchildren(grammar: Grammar, st: Supertree, e_c: int) -> list[tuple[int, int, int]]:
    """(member, rule, set) of the children of latent set e_c whose rule holds e_c's rotation
    (a fixed or revolute rotation), outside e_c."""
    out = []
    for v2 in np.flatnonzero(st.set_of == e_c):
        for c2 in st.children[v2]:
            r2 = int(st.rule[c2])
            if st.set_of[c2] != e_c and _turning_link(grammar, r2):
                out.append((int(v2), r2, int(st.set_of[c2])))
    return out


def _child_combos(
    grammar: Grammar, st: Supertree, cand: Candidates, e: int, solved: dict[int, FloatArray]
) -> list[tuple[tuple[int, int, FloatArray, FloatArray, Any], ...]]:
    """No child, each candidate child of each hard slot, then pairs on two slots (or two
    copies of one `repeat` slot), at most HARD_COMBOS in all."""
    slots: dict[tuple[int, int, Any], tuple[int, int]] = {}
    latent = latent_sets(st)
    for v in np.flatnonzero(st.set_of == e):
        for c in st.children[v]:
            r = int(st.rule[c])
            e_c = int(st.set_of[c])
            if e_c != e and _hard_rule(grammar, r):
                n = slots.get((int(v), r, None), (e_c, 0))[1]
                slots[(int(v), r, None)] = (e_c, n + 1)
            if e_c != e and latent[e_c] and _turning_link(grammar, r):
                for v2, r2, e_g in _hard_grandchildren(grammar, st, e_c):
                    slots.setdefault((int(v), r, (v2, r2)), (e_g, 1))
    singles = []
    for (v, r, via), (e_c, copies) in slots.items():
        k = _preferred(cand, e_c, solved, HARD_CHILDREN)
        if len(k):  # a child set with no candidate pose (yet) offers nothing to combine
            singles.append([(v, r, cand.xyz[e_c][i], cand.quat[e_c][i], via, copies) for i in k])
    own = [s for s in singles if s[0][4] is None]
    combos: list[tuple] = [()]  # the set's own children first, then grandchildren
    combos += [(c[:5],) for s in own + [s for s in singles if s[0][4] is not None] for c in s]
    for s in own:  # three children pinned on one plane fix it (`_many_pinned`)
        if _many_pinned(grammar, s):
            combos += [tuple(c[:5] for c in trio) for trio in _near_trios(s)]
    for a in range(len(own)):
        for b in range(a, len(own)):
            for i, ca in enumerate(own[a]):
                for cb in own[b][i + 1 :] if a == b else own[b]:
                    if a == b and ca[5] < 2:
                        break
                    combos.append((ca[:5], cb[:5]))
                    if len(combos) >= HARD_COMBOS:
                        return combos + _relayed_pairs(singles)
    return combos + _relayed_pairs(singles)


def _near_trios(slot: list[tuple]) -> list[tuple]:  # type: ignore[type-arg]
    """The HARD_TRIOS trios of a slot's candidate children whose positions lie closest
    together (least perimeter) first.  Any three points lie on a plane, so a trio of two
    shelves' boxes gives a pose too (a steep one); the children of one parent lie near it,
    so the near trios come first, and the cap keeps the number of combinations small."""
    trios = list(combinations(slot, 3))
    xyz = np.array([[c[2] for c in trio] for trio in trios]).reshape(-1, 3, 3)
    sides = np.linalg.norm(xyz - np.roll(xyz, 1, axis=1), axis=2).sum(axis=1)
    order = np.argsort(sides, kind="stable")[:HARD_TRIOS]
    return [trios[i] for i in order]


def _many_pinned(grammar: Grammar, slot: list[tuple]) -> bool:  # type: ignore[type-arg]
    """Whether a slot's candidate children, three at a time, are combinations of their own: a
    `repeat` of three or more copies whose rule pins axes in the parent's frame.

    Why: objects pinned on a latent surface lie on one plane, which three of them fix; from
    one or two children the surface was turned onto their planes only, the others missed
    theirs, and a shelf of three or four boxes sampled from the grammar had no parse.  Three
    at a time, not all at once: with two shelves, a trio of one shelf's boxes meets its plane
    exactly, and a mixed trio meets none (its poses are refused)."""
    tl = grammar.rules[slot[0][1]].translation
    pinned = tl.frame == Frame.PARENT and hasattr(tl, "free") and not np.all(tl.free)
    return pinned and min(slot[0][5], len(slot)) >= 3


def _relayed_pairs(singles: list[list[tuple]]) -> list[tuple]:  # type: ignore[type-arg]
    """Pairs of one child of the set and one grandchild through a latent child set, taken in
    turn from every such pair of slots (at most HARD_RELAYED): the child's arc and the
    grandchild's relay meet in isolated rotations (`hard_laws.relay_meets`)."""
    own = [s for s in singles if s[0][4] is None]
    via = [s for s in singles if s[0][4] is not None]
    streams = [  # not the linking child itself: its guessed pose already fixes the set
        [(ca[:5], cb[:5]) for ca in a for cb in b] for a in own for b in via if a[0][:2] != b[0][:2]
    ]
    out: list[tuple] = []  # type: ignore[type-arg]
    for k in range(max((len(x) for x in streams), default=0)):
        out += [x[k] for x in streams if k < len(x)]
        if len(out) >= HARD_RELAYED:
            return out[:HARD_RELAYED]
    return out
