"""Which rules the data can say something about: a static analysis of the grammar.

The parser puts a latent node at its best pose.  For a latent node with observed nodes below,
that pose is pinned by what is observed; for one with nothing observed at or below it, it is
simply the mode of its own law, and a fit to those poses shrinks the law onto its mode (the
variance floor, the concentration cap), while a tree with the node always scores above one
without (a density at its mode against nothing), so its `independent` probability or its
count law goes to the largest count.  No scene carries evidence about any of this: whether
such a subtree exists, and where, changes nothing that is observed.  So the M-step
(`ssgc.fit.mstep`) leaves the laws of such subtrees as written (docs/fitting.md 4.1).

A rule is *observable* when some tree of the grammar puts an observed node at or below its
child.  That is decided on the grammar, not on the parses: on the compiled grammar (so the
types an `observation` section adds count like any other), over the states (type, nesting
depth of every type with `max_nesting`) the grammar can reach, since a rule blocked by
`max_nesting` at some depth makes nothing there.  Rules that can never fire (weight or
probability 0, a count law that puts all its mass on 0) make nothing either.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ssgc.ir import Grammar, Kind, NodeType
from ssgc.laws.base import Frame
from ssgc.node_states import child_states, root_state
from ssgc.tree import Trees

# Reachable (type, depths) states beyond which nesting is ignored: the analysis then only
# adds paths, so it may call a rule observable that is not (and fit it, as before).
MAX_STATES = 100_000


def observable_rules(grammar: Grammar) -> NDArray[np.bool_]:
    """(rules,) whether some tree holds an observed node at or below the rule's child."""
    edges = _state_edges(grammar, nesting=True)
    if edges is None:  # too many nesting states: the type graph alone
        edges = _state_edges(grammar, nesting=False)
    assert edges is not None
    parent, rule, child, observed = edges
    holds = observed.copy()
    while True:  # a state holds an observed node if it is one, or a child state holds one
        grown = holds.copy()
        grown[parent[holds[child]]] = True
        if np.array_equal(grown, holds):
            break
        holds = grown
    out = np.zeros(len(grammar.rules), bool)
    out[rule[holds[child]]] = True
    return out


def pose_observable_rules(grammar: Grammar) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(rules,) twice: whether the position, and the rotation, a rule gives its child can move
    an observed pose.  An observed child's can; a latent child's only through a rule of its
    own that reads it: a child position in its frame or offset from it (`Frame.WORLD_OFFSET`,
    `Frame.PARENT`) reads its position, one in its frame reads its rotation too, and a
    child rotation in its frame (`Frame.PARENT`) reads its rotation.  A latent node placed by
    a pinned or boxed law, whose children are all placed in world coordinates, was put at
    the law's mode by the parser, and its law shrank onto it (a variance of 0.05 fitted to
    1e-6 in one iteration); the data say nothing about where it is.  Type-level, ignoring
    `max_nesting`: it may call a law observable that is not, never the other way."""
    observed = np.array([t.observed for t in grammar.types], bool)
    parent = np.array([r.parent for r in grammar.rules], np.int64).reshape(-1)
    child = np.array([r.child for r in grammar.rules], np.int64).reshape(-1)
    t_frame = np.array([int(r.translation.frame) for r in grammar.rules], np.int64)
    r_frame = np.array([int(r.rotation.frame) for r in grammar.rules], np.int64)
    reads_position = t_frame != Frame.WORLD
    turns_position, turns_rotation = t_frame == Frame.PARENT, r_frame == Frame.PARENT
    position, rotation = observed.copy(), observed.copy()
    while True:  # a type's pose matters if a rule of its own reads it for a pose that does
        pos, rot = position.copy(), rotation.copy()
        pos[parent[reads_position & position[child]]] = True
        rot[parent[(turns_position & position[child]) | (turns_rotation & rotation[child])]] = True
        if np.array_equal(pos, position) and np.array_equal(rot, rotation):
            return position[child], rotation[child]
        position, rotation = pos, rot


def _state_edges(
    grammar: Grammar, nesting: bool
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]] | None:
    """(parent state, rule, child state) of every rule that can fire in a reachable state
    (`ssgc.node_states`; a `repeat` whose count is 0 for sure fires none), and whether each
    state's type is observed; None past `MAX_STATES`."""
    start = root_state(grammar, nesting)
    index = {start: 0}
    queue = [start]
    edges: list[tuple[int, int, int]] = []
    while queue:
        state = queue.pop()
        if not _can_fire(grammar.types[state[0]]):
            continue
        for rid, next_state in child_states(grammar, state):
            if next_state not in index:
                if len(index) >= MAX_STATES:
                    return None
                index[next_state] = len(index)
                queue.append(next_state)
            edges.append((index[state], rid, index[next_state]))
    table = np.array(edges, np.int64).reshape(-1, 3)
    observed = np.array([grammar.types[t].observed for t, _ in index], bool)
    return table[:, 0], table[:, 1], table[:, 2], observed


def _can_fire(node: NodeType) -> bool:
    """A `repeat` whose count law is 0 for sure makes no children."""
    if node.kind != Kind.REPEAT:
        return True
    return node.count is not None and bool(np.any(node.count.probs[1:] > 0))


def unobserved_nodes(trees: Trees, observable: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Nodes at or below the child of a rule whose subtree can hold no observed node
    (`observable_rules`): where the parser put them says nothing about the data, so
    neither their edges nor their own choices are counted (docs/fitting.md 4.1)."""
    if observable.all():
        return np.zeros(len(trees), bool)
    own = (trees.rule >= 0) & ~observable[np.maximum(trees.rule, 0)]
    hidden = own.copy()
    above = trees.parent.copy()
    while np.any(above >= 0):  # one step up per round, for every node at once
        up = above >= 0
        hidden[up] |= own[above[up]]
        above[up] = trees.parent[above[up]]
    return hidden
