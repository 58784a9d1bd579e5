"""Poses at one place are compared as one group (`ssgc.parse.proposals.PoseGroups`), and
nesting depths are path sums by pointer doubling (`ssgc.score.nesting_counts`).

Both replaced work that grew with the square of a scene: a chain grammar with 9,805 objects at
one pose made 48 million pose pairs within the tolerances, and `ssg parse --time-limit 5` ran
past 120 s; walking up one node per round over every node took 10,000 rounds for that chain.
The answers must stay exactly those of comparing every pair and of walking every path."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as hs

import ssgc.parse.proposals as proposals
from ssgc.compile import compile_text
from ssgc.geometry import quat_angle
from ssgc.laws.base import POS_TOL, ROT_TOL
from ssgc.parse.posed import _first_distinct
from ssgc.parse.proposals import Candidates
from ssgc.score import nesting_counts
from ssgc.tree import Trees


def _poses(rng: np.random.Generator, n: int, sites: int, moved: float, jitter: float):
    """Poses at a few sites: some exact copies of a site, some moved by jitter·POS_TOL (or
    turned by jitter·ROT_TOL); 0.3 stays within the tolerances of its site, 3 does not."""
    site = rng.integers(0, sites, n)
    xyz = rng.normal(size=(sites, 3))[site]
    quat = np.eye(4)[rng.integers(0, 2, sites)][site]
    move = rng.random(n) < moved
    xyz[move] += rng.normal(size=(int(move.sum()), 3)) / np.sqrt(3) * POS_TOL * jitter
    turn = rng.random(n) < moved
    quat[turn, 3] += rng.normal(size=int(turn.sum())) * 0.5 * ROT_TOL * jitter
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return xyz, quat


def _same_pose(xyz: np.ndarray, quat: np.ndarray) -> np.ndarray:
    close = np.linalg.norm(xyz[:, None] - xyz[None], axis=2) <= POS_TOL
    return close & (quat_angle(quat[:, None], quat[None]) <= ROT_TOL)


@settings(max_examples=120, deadline=None)
@given(
    n=hs.integers(0, 40),
    sites=hs.integers(1, 4),
    moved=hs.sampled_from([0.0, 0.3, 0.7]),
    jitter=hs.sampled_from([0.3, 3.0]),
    nodes=hs.integers(1, 3),
    objects=hs.integers(1, 6),
    held=hs.booleans(),
    seed=hs.integers(0, 2**31),
)
def test_grouped_poses_keep_what_every_pair_compared_keeps(
    n, sites, moved, jitter, nodes, objects, held, seed
):
    """Exact copies (one group) mixed with poses moved within or beyond the tolerances
    (other groups, compared pairwise): the kept poses are those of the definition in
    `_first_distinct`, computed here over every pair."""
    rng = np.random.default_rng(seed)
    xyz, quat = _poses(rng, n, sites, moved, jitter)
    node = np.sort(rng.integers(0, nodes, n))
    obj = rng.integers(0, objects, n)
    keep = _first_distinct(xyz, quat, obj, node if held else None, None)
    same = _same_pose(xyz, quat)
    one_node = node[:, None] == node[None]
    rank = [int((same[:j, j] & one_node[:j, j]).sum()) for j in range(n)]

    def shares(i: int, j: int) -> bool:
        if held:
            return bool(same[i, j] and not one_node[i, j] and rank[i] == rank[j])
        return bool(same[i, j] and obj[i] == obj[j])

    assert keep.tolist() == [j for j in range(n) if not any(shares(i, j) for i in range(j))]


@settings(max_examples=120, deadline=None)
@given(
    n_old=hs.integers(0, 15),
    n_new=hs.integers(0, 15),
    sites=hs.integers(1, 4),
    moved=hs.sampled_from([0.0, 0.3, 0.7]),
    jitter=hs.sampled_from([0.3, 3.0]),
    seed=hs.integers(0, 2**31),
)
def test_candidates_add_keeps_what_every_pair_compared_keeps(
    n_old, n_new, sites, moved, jitter, seed
):
    """A new pose is added unless an old pose or an earlier new one is within both
    tolerances of it; old poses are never dropped."""
    rng = np.random.default_rng(seed)
    xyz, quat = _poses(rng, n_old + n_new, sites, moved, jitter)
    c = Candidates([xyz[:n_old].copy()], [quat[:n_old].copy()])
    c.add(0, xyz[n_old:], quat[n_old:])
    same = _same_pose(xyz, quat)
    kept = list(range(n_old)) + [j for j in range(n_old, n_old + n_new) if not same[:j, j].any()]
    np.testing.assert_array_equal(c.xyz[0], xyz[kept])
    np.testing.assert_array_equal(c.quat[0], quat[kept])


def test_many_objects_at_one_pose_are_not_compared_pair_by_pair(monkeypatch):
    """20,000 poses at one place (five nodes, 4,000 each; then 20,000 objects): the pairwise
    comparison sees one pose per group, and the answer is still the definition's — as many
    candidates as one node has poses there, or one per object."""
    seen: list[int] = []
    real = proposals.near_earlier

    def spy(all_xyz, n_old):
        seen.append(len(all_xyz))
        return real(all_xyz, n_old)

    monkeypatch.setattr(proposals, "near_earlier", spy)
    n = 20_000
    xyz = np.tile([0.3, -0.2, 0.1], (n, 1))
    quat = np.tile([0.0, 0.6, 0.8, 0.0], (n, 1))
    node = np.repeat(np.arange(5), n // 5)
    keep = _first_distinct(xyz, quat, np.arange(n), node, None)
    np.testing.assert_array_equal(keep, np.arange(n // 5))
    keep = _first_distinct(xyz, quat, np.arange(n) % 7, None, None)
    np.testing.assert_array_equal(keep, np.arange(7))
    c = Candidates([xyz[:1].copy()], [quat[:1].copy()])
    c.add(0, xyz, quat)
    assert len(c.xyz[0]) == 1
    assert seen == [1, 1, 1]


CYCLE = """
grammar: cycle
root: {type: R, pose: {xyz: [0, 0, 0]}}
types:
  R: {observed: true, and: [{child: A}]}
  A: {observed: true, max_nesting: 5, or: [{child: B, p: 0.5}, {child: C, p: 0.5}]}
  B: {observed: true, max_nesting: 3, independent: [{child: A, p: 0.7}]}
  C: {observed: true}
"""


def _walked(grammar, trees: Trees) -> np.ndarray:
    """Nesting counts by walking up every path, one node per round (the old way)."""
    tb = grammar.tables
    own = np.zeros((len(grammar.types), tb.nesting_max.shape[0]), np.int64)
    bounded = np.flatnonzero(tb.nesting_slot >= 0)
    own[bounded, tb.nesting_slot[bounded]] = 1
    out = np.zeros((len(trees), own.shape[1]), np.int64)
    for v in range(len(trees)):
        a = v
        while a >= 0:
            out[v] += own[trees.type[a]]
            a = int(trees.parent[a])
    return out


@settings(max_examples=60, deadline=None)
@given(
    n=hs.integers(1, 300), roots=hs.integers(1, 5), chain=hs.booleans(), seed=hs.integers(0, 2**31)
)
def test_nesting_counts_are_the_sums_along_every_path(n, roots, chain, seed):
    """Forests in any node order (parents after children too), deep chains included."""
    grammar = compile_text(CYCLE)
    rng = np.random.default_rng(seed)
    roots = min(roots, n)
    parent = np.full(n, -1, np.int64)
    for v in range(roots, n):
        parent[v] = v - 1 if chain else rng.integers(0, v)
    perm = rng.permutation(n)
    inverse = np.argsort(perm)
    parent = np.where(parent[perm] >= 0, inverse[parent[perm]], -1)
    trees = Trees(
        scene=np.zeros(n, np.int64),
        type=rng.integers(0, len(grammar.types), n),
        parent=parent,
        rule=np.full(n, -1, np.int64),
        xyz=np.zeros((n, 3)),
        quat=np.tile([1.0, 0, 0, 0], (n, 1)),
        n_scenes=1,
    )
    np.testing.assert_array_equal(nesting_counts(grammar, trees), _walked(grammar, trees))
