"""The pose-instantiated unroll written the plain way, one instance at a time (the loop that
`ssgc.parse.posed._Unroll` replaced with array operations): an oracle for
tests/test_posed_unroll.py, which requires both to give the same instances in the same order."""

from __future__ import annotations

import numpy as np

from ssgc.geometry import quat_multiply, quat_rotate
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.parse.ip import implied_set_poses
from ssgc.parse.posed import FREE_CHILD, Restriction, Unrolled
from ssgc.parse.proposals import Candidates
from ssgc.parse.supertree import Supertree


def reference_unroll(
    grammar: Grammar, st: Supertree, cand: Candidates, restrict: Restriction | None = None
) -> Unrolled:
    """Breadth first: instance i's children by rule slot, then by copy or candidate index."""
    restrict = restrict or {}
    tb = grammar.tables
    node, parent, slot, cand_k, top = [0], [-1], [-1], [0], [0]
    xyz, quat = [np.asarray(grammar.root_xyz, float)], [np.asarray(grammar.root_quat, float)]

    def add(n: int, p: int, s: int, x: np.ndarray, q: np.ndarray, k: int) -> None:
        fixed = st.set_of[n] == st.set_of[node[p]]
        top.append(top[p] if fixed else len(node))
        node.append(n)
        parent.append(p)
        slot.append(s)
        cand_k.append(k)
        xyz.append(np.asarray(x, float))
        quat.append(np.asarray(q, float))

    def allowed(i: int, n: int, rule: int, e: int) -> list[int]:
        everything = list(range(len(cand.xyz[e])))
        own = int(st.set_of[n])
        if own not in restrict:
            return everything
        slots, assignment = restrict[own]
        cols = [j for j, s in enumerate(slots) if s == (n, rule)]
        if not cols:
            return everything
        named = assignment[cand_k[top[i]], cols]
        if np.any(named == FREE_CHILD):
            return everything
        return sorted({int(k) for k in named if k >= 0})

    i = 0
    while i < len(node):
        n = node[i]
        rules_seen: list[int] = []
        for c in st.children[n]:
            if int(st.rule[c]) not in rules_seen:
                rules_seen.append(int(st.rule[c]))
        for s, r in enumerate(rules_seen):
            copies = [c for c in st.children[n] if st.rule[c] == r]
            if st.set_of[copies[0]] == st.set_of[n]:
                x = xyz[i] + quat_rotate(quat[i], tb.point_xyz[r])
                q = quat_multiply(quat[i], tb.point_quat[r])
                for c2 in copies:
                    add(c2, i, s, x, q, cand_k[i])
            else:
                e = int(st.set_of[copies[0]])
                for k in allowed(i, n, r, e):
                    add(copies[0], i, s, cand.xyz[e][k], cand.quat[e][k], k)
        i += 1
    return Unrolled(
        np.asarray(node, np.int64),
        np.asarray(parent, np.int64),
        np.asarray(slot, np.int64),
        np.asarray(cand_k, np.int64),
        np.asarray(top, np.int64),
        np.asarray(xyz).reshape(-1, 3),
        np.asarray(quat).reshape(-1, 4),
    )


def reference_candidates(grammar: Grammar, st: Supertree, scene: Scene) -> Candidates:
    """The observed-implied candidate poses, one supertree node at a time (the loop that
    `ssgc.parse.posed.candidate_poses` replaced), deduplicated by `Candidates.add`."""
    cand = Candidates(
        [np.zeros((0, 3)) for _ in range(st.n_sets)], [np.zeros((0, 4)) for _ in range(st.n_sets)]
    )
    for n, _, t, q in implied_set_poses(grammar, st, scene):
        cand.add(int(st.set_of[n]), t.reshape(-1, 3), q.reshape(-1, 4))
    root_set = int(st.set_of[0])
    cand.xyz[root_set] = grammar.root_xyz.reshape(1, 3).copy()
    cand.quat[root_set] = grammar.root_quat.reshape(1, 4).copy()
    return cand
