"""The physical tails of `ssg explain`, measured on a fit's dataset (docs/fitting.md, "What is
fitted"; docs/explain.md, "Overlaps" and "Support, floor and walls").

`ssg explain` turns an overlap, a float or a dish through the bin's floor into nats with an
exponential tail per constraint (ssgc/tails.py): how many of a real scene's objects have such a
finding, and how large findings are.  The defaults were measured once on the real sink scenes;
a fit measures them on its own scenes, each scene's best parse, with the same code explain
uses (`ssgc.overlaps.overlaps`, `ssgc.support.findings`), and writes them into the grammar's
`non_penetration` (`tail:`) and `inside_box` with `geometry: true` (`floating:`, `outside:`)
constraints.  Constraints are not laws: this changes no fitted number.

The estimator, per constraint and kind of finding, over the objects the constraint judges
(objects of its types; for a box, those in its frame that the parse observes):

- rate = max(objects with a finding, 1) / objects: a share of the dataset's objects, never 0
  (no finding at all counts as fewer than one in N, as the sink defaults do);
- mean = the exponential's mean estimated from the median size of the findings, median / ln 2,
  floored at the tolerance (1 cm): for overlaps an object's summed depth (the D of its tail),
  for floating and going outside each finding's distance beyond the tolerance.  The median, not
  the average, so that a few gross outliers of the data (two dishes of sink scene 76 lie 1.2 m
  outside the bin) do not flatten the tail (the average gave 36 cm for `outside` on the sink
  scenes; overlaps, which have no such outliers, give nearly the same either way).  The floor:
  a handful of small findings cannot show a steeper tail than that, and the shapes are guesses
  of the real ones a few millimetres off.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ssgc.constraints.penetration import NonPenetration
from ssgc.constraints.pose import InsideBox
from ssgc.explain import blocks, match_objects
from ssgc.fit.writeback import Update
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.overlaps import overlaps
from ssgc.support import findings, judged
from ssgc.tails import TOLERANCE, Tail
from ssgc.tree import Trees

KEYS = {"floats": "floating", "floor": "outside", "wall": "outside"}  # finding kind -> key


@dataclass
class Measured:
    """One constraint's tail (`key`: tail, floating or outside) as measured on a dataset."""

    constraint: str
    key: str
    objects: int = 0  # objects the constraint judges, over the dataset
    found: int = 0  # of them, those with a finding
    sizes: list[float] = field(
        default_factory=list
    )  # each finding's size (m; overlaps: per object)

    def tail(self) -> Tail | None:
        """The estimator of the module docstring; None when the dataset has no such object."""
        if self.objects == 0:
            return None
        mean = float(np.median(self.sizes) / np.log(2)) if self.sizes else 0.0
        return Tail(rate=max(self.found, 1) / self.objects, mean=max(mean, TOLERANCE))

    def to_json(self) -> dict[str, object]:
        tail = self.tail()
        return {
            "constraint": self.constraint,
            "key": self.key,
            "objects": self.objects,
            "found": self.found,
            "rate": None if tail is None else tail.rate,
            "mean": None if tail is None else tail.mean,
        }


def measure_tails(
    grammar: Grammar, scenes: Sequence[Scene], trees: Sequence[Trees | None]
) -> list[Measured]:
    """Each physical tail of the grammar's constraints, measured on the scenes' best parses
    (`trees[k]` of scene k; None: the scene had no parse and is left out)."""
    out = _tallies(grammar)
    if not out:
        return []
    for scene, tree in zip(scenes, trees, strict=True):
        if tree is not None and len(scene):
            _measure_scene(grammar, scene, tree, out)
    return list(out.values())


def has_tails(grammar: Grammar) -> bool:
    """Whether the grammar has a constraint with a physical tail to measure: the fit says it
    measures them only then (a grammar without constraints gets nothing written)."""
    return bool(_tallies(grammar))


def _tallies(grammar: Grammar) -> dict[tuple[str, str], Measured]:
    """An empty tally per (constraint, key) of every tail the grammar's constraints have."""
    out: dict[tuple[str, str], Measured] = {}
    for c in grammar.constraints:
        if isinstance(c, NonPenetration):
            out[c.name, "tail"] = Measured(c.name, "tail")
        elif isinstance(c, InsideBox) and c.shapes is not None:
            for key in ("floating", "outside"):
                out[c.name, key] = Measured(c.name, key)
    return out


def _measure_scene(
    grammar: Grammar, scene: Scene, tree: Trees, out: dict[tuple[str, str], Measured]
) -> None:
    """Add one scene's objects and findings to the tallies."""
    obj_of = match_objects(grammar, scene, tree)
    checks = [c for c in grammar.constraints if isinstance(c, NonPenetration)]
    found = overlaps(grammar, scene, tree, blocks(grammar, tree), obj_of) if checks else []
    for c in checks:
        assert c.pairs_of is not None
        depth = np.zeros(len(scene))
        for v in found:
            if v.constraint == c.name:
                depth[[v.a, v.b]] += v.depth
        m = out[c.name, "tail"]
        m.objects += int(np.count_nonzero(c.pairs_of.types[scene.types]))
        m.found += int(np.count_nonzero(depth > 0))
        m.sizes += depth[depth > 0].tolist()
    counts = judged(grammar, scene, tree, obj_of)
    for name, n in counts.items():
        out[name, "floating"].objects += n
        out[name, "outside"].objects += n
    seen: set[tuple[str, str, int]] = set()
    for f in findings(grammar, scene, tree, obj_of):
        m = out[f.constraint, KEYS[f.kind]]
        m.sizes.append(f.distance - TOLERANCE)
        if (f.constraint, m.key, f.obj) not in seen:
            seen.add((f.constraint, m.key, f.obj))
            m.found += 1


def tail_updates(grammar: Grammar, measured: list[Measured]) -> list[Update]:
    """The write-back of the measured tails: `{rate, mean}` under each constraint's key."""
    path = {c.name: c.path for c in grammar.constraints}
    out = []
    for m in measured:
        tail = m.tail()
        if tail is not None:
            out.append(Update(path[m.constraint], {m.key: {"rate": tail.rate, "mean": tail.mean}}))
    return out
