"""Physical evidence for `ssg explain` beyond overlaps: objects that float, and objects that go
through their container's floor or walls (docs/explain.md, "Support, floor and walls").

Real scenes are settled: a dish lies on the bin floor or on other dishes, and inside the bin.
A grammar says where its container's floor and walls are with an `inside_box` constraint with
`geometry: true` (docs/constraints.md): the box, in the frame of the container type, that the
listed types' whole geometries must lie in.  For each object of those types this module reads

- how far its geometry reaches *below the box's floor* (min z) or *beyond its walls* (the x and
  y faces): "goes 5.0 cm through the floor of DishBin #0";
- how far it *floats*: its lowest point's height above the floor, or, when that is positive,
  its distance to the nearest object whose geometry reaches lower than its own lowest point
  (under the grammar's `non_penetration` geometries; without that constraint, the height alone),
  whichever is smaller: "floats 4.0 cm above anything under it".

Each kind of finding gets nats from how rare it is among the objects of real scenes, an
exponential tail P(D >= d) = rate * exp(-(d - tolerance) / mean) for d above a tolerance (as
overlaps do: ssgc/overlaps.py), so an object's evidence is -log rate + (d - tolerance) / mean.
The tails are the constraint's (`floating:`, `outside:`; ssgc/tails.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ssgc.constraints.penetration import NonPenetration
from ssgc.constraints.pose import InsideBox
from ssgc.constraints.shapes import frame_extents
from ssgc.geometry import quat_to_matrix
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.tails import FLOATING, OUTSIDE, TOLERANCE, Tail
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# The tolerance and the sink defaults live in ssgc/tails.py; a grammar's `inside_box` gives its
# own tails (`floating:`, `outside:`), `ssg fit` measures them (ssgc/fit/tails.py).
__all__ = [
    "FLOATING",
    "OUTSIDE",
    "TOLERANCE",
    "Finding",
    "Tail",
    "findings",
    "judged",
    "nats",
    "sentence",
]


@dataclass(frozen=True)
class Finding:
    """Object `obj` (a scene index) floats, or goes through the floor or a wall of the
    container object `container` (a scene index, -1 when it is not an object), by `distance`
    metres, under the `inside_box` constraint `constraint`."""

    kind: str  # "floats", "floor" or "wall"
    constraint: str
    obj: int
    container: int
    distance: float


def _posed_tree(scene: Scene, tree: Trees, obj_of: IntArray) -> Trees:
    """The tree with each observed node at its object's pose (the poses constraints judge)."""
    xyz, quat = tree.xyz.copy(), tree.quat.copy()
    seen = np.flatnonzero(obj_of >= 0)
    xyz[seen], quat[seen] = scene.xyz[obj_of[seen]], scene.quat[obj_of[seen]]
    return replace(tree, xyz=xyz, quat=quat)


def _lowest(box: InsideBox, batch: Trees, nodes: IntArray) -> FloatArray:
    """World height of each node's lowest geometry point."""
    assert box.shapes is not None
    lo, _ = frame_extents(box.shapes, batch.type[nodes], quat_to_matrix(batch.quat[nodes]))
    return batch.xyz[nodes, 2] + lo[:, 2]


def _gaps_below(grammar: Grammar, batch: Trees, nodes: IntArray, lowest: FloatArray) -> FloatArray:
    """Each node's distance to the nearest object whose geometry reaches lower than the node's
    own lowest point, under the grammar's `non_penetration` geometries (inf: none)."""
    out = np.full(len(nodes), np.inf)
    checks = [c for c in grammar.constraints if isinstance(c, NonPenetration)]
    if not checks or len(nodes) < 2:
        return out
    low = np.full(len(batch), np.inf)
    low[nodes] = lowest
    at = np.full(len(batch), -1)
    at[nodes] = np.arange(len(nodes))
    flat = replace(batch, parent=np.full(len(batch), -1))  # every pair, carried or not
    for c in checks:
        assert c.pairs_of is not None
        i, j = c.pairs_of.pairs(flat)
        for a, b in ((i, j), (j, i)):  # b lies under a: reaches lower than a's lowest point
            keep = (at[a] >= 0) & (low[b] < low[a] - TOLERANCE)
            # FCL's distance for every such pair: the bounding spheres' gap, which the
            # constraint takes for far pairs, is a lower bound (23 cm above read 9.4 cm)
            dist = c.distances_of(flat, a[keep], b[keep], exact=True)
            np.minimum.at(out, at[a[keep]], np.maximum(dist, 0.0))
    return out


def findings(grammar: Grammar, scene: Scene, tree: Trees, obj_of: IntArray) -> list[Finding]:
    """Every object that floats or goes through its container's floor or walls by more than
    TOLERANCE, under the grammar's `inside_box` constraints with `geometry: true`."""
    boxes = [c for c in grammar.constraints if isinstance(c, InsideBox) and c.shapes is not None]
    if not boxes or len(scene) == 0:
        return []
    batch = _posed_tree(scene, tree, obj_of)
    out: list[Finding] = []
    for box in boxes:
        nodes, gaps = _judged(box, batch, obj_of)
        if not len(nodes):
            continue
        container = _containers(box, batch, nodes, obj_of)
        with np.errstate(invalid="ignore"):
            floor = np.nan_to_num(-gaps[:, 2], nan=0.0)
            wall = np.nan_to_num(np.nanmax(-gaps[:, [0, 1, 3, 4]], axis=1), nan=0.0)
            height = np.nan_to_num(gaps[:, 2], nan=0.0)
        above = np.flatnonzero(height > TOLERANCE)
        floats = np.zeros(len(nodes))
        if len(above):
            below = _gaps_below(grammar, batch, nodes, _lowest(box, batch, nodes))
            floats[above] = np.minimum(height[above], below[above])
        for kind, depth in (("floor", floor), ("wall", wall), ("floats", floats)):
            for k in np.flatnonzero(depth > TOLERANCE):
                o, c = int(obj_of[nodes[k]]), int(container[k])
                out.append(Finding(kind, box.name, o, c, float(depth[k])))
    return sorted(out, key=lambda f: -f.distance)


def _judged(box: InsideBox, batch: Trees, obj_of: IntArray) -> tuple[IntArray, FloatArray]:
    """The nodes the box judges (of its types, with its frame, observed) and their face gaps."""
    nodes, _, ok, gaps = box.face_gaps(batch)
    keep = ok & (obj_of[nodes] >= 0)
    return nodes[keep], gaps[keep]


def judged(grammar: Grammar, scene: Scene, tree: Trees, obj_of: IntArray) -> dict[str, int]:
    """How many of the scene's objects each `inside_box` constraint with `geometry: true`
    judges: the objects its findings are a share of (`ssg fit` measures the tails with it)."""
    boxes = [c for c in grammar.constraints if isinstance(c, InsideBox) and c.shapes is not None]
    batch = _posed_tree(scene, tree, obj_of)
    return {box.name: len(_judged(box, batch, obj_of)[0]) for box in boxes}


def _containers(box: InsideBox, batch: Trees, nodes: IntArray, obj_of: IntArray) -> IntArray:
    """Each node's container object (its nearest ancestor of the box's frame type), or -1."""
    from ssgc.constraints.base import nearest_ancestor

    if box.frame is None:
        return np.full(len(nodes), -1)
    anc = nearest_ancestor(batch.parent, batch.type, box.frame, nodes)
    return np.where(anc >= 0, obj_of[np.maximum(anc, 0)], -1)


def nats(grammar: Grammar, finding: Finding) -> float:
    """How rare so much of this finding is among the objects of real scenes: the tail its
    `inside_box` constraint gives (`floating:` or `outside:`), beyond the tolerance."""
    box = next(c for c in grammar.constraints if c.name == finding.constraint)
    tail = box.floating if finding.kind == "floats" else box.outside
    return float(tail.nats(finding.distance - TOLERANCE))


def sentence(finding: Finding, names: list[str]) -> str:
    cm = f"{100 * finding.distance:.1f} cm"
    if finding.kind == "floats":
        return f"floats {cm} above anything under it ({finding.constraint})"
    where = "the floor" if finding.kind == "floor" else "a wall"
    of = f" of {names[finding.container]}" if finding.container >= 0 else ""
    return f"goes {cm} through {where}{of} ({finding.constraint})"
