"""Why a scene scores what it scores: −log p of its best parse, split over objects and rules.

Also callable: `ssgc.explain(grammar, scene, time_limit=None)` is `ssgc.api.explain`, which
takes `ssgc.load_grammar`'s grammar and an API scene and explains the scene's best parse as
`ssg explain` does; this module's own `explain(grammar, scene, tree=None, **parse)` takes the
compiled grammar (`ssgc.ir.Grammar`) and the library's scene.

Two numbers per object, for two questions (docs/explain.md):

* **share** — its exact part of −log p (thesis Eq. 2.1).  Every term of the score belongs to a
  node; a node's terms go to the observed objects of its *block* (the nodes joined to it by
  fixed rules, which share one pose), else to the observed objects of its subtree, else to its
  parent's owners, split equally (the clutter set's to the clutter objects below it, though it
  shares the root's pose; an unseen node's pose is integrated out: its edge has no term).
  So an edge's placement density goes to the object it places, a latent node's terms and
  count/choice terms to the objects below it, and the shares sum to −log p exactly.
* **unusual** — the ranking key: how much the score would improve if only this object were
  different.  For its pose, the best rigid move of its block (a shift, a turn), scored on every
  edge the block touches: the edge that places it and the edges to the objects it places.  A
  misplaced plate thus explains its misplaced-looking children (one move fixes all of them),
  while a child's own move fixes only its edge; the latent nodes between an object and its
  nearest observed ancestor, whose poses no scene shows, may move with it (a cup whose latent
  slot is misplaced gains the slot's move).  Under the grammar this gain is about half a
  χ² with 3 degrees of freedom per move (mean ≈ 1.5 nats) for any object, so objects compare.
  Discrete terms add their surprise over their expectation (−log P − entropy, when positive).
  Two other views of the same question can rank it higher: the *slot surprise* (an unusual
  choice among placing rules) and the *type gain* (the scene with the object of another type).
  Where the grammar declares `non_penetration`, overlaps with objects the tree does not relate
  add their nats too (`overlap_reasons`); where it declares a container (`inside_box` with
  `geometry: true`), so do objects that float or go through its floor or walls
  (`support_reasons`, ssgc/support.py).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from ssgc.constraints.penetration import NonPenetration
from ssgc.distributions.uniform import UNIFORM_SO3_LOG_DENSITY
from ssgc.errors import Diagnostic, SsgError
from ssgc.geometry import quat_angle, quat_conjugate, quat_multiply, quat_rotate
from ssgc.io.scene import Scene
from ssgc.ir import Grammar, Kind
from ssgc.laws.base import POS_TOL, ROT_TOL, Context, Deviation, Frame, percent
from ssgc.observation import clutter_nodes
from ssgc.overlaps import overlaps
from ssgc.rules import (
    rotation_coordinates,
    rotation_log_density,
    sample_children,
    translation_coordinates,
    translation_log_density,
)
from ssgc.score import node_terms, score_trees, seen_nodes
from ssgc.support import findings as support_findings
from ssgc.support import nats as support_nats
from ssgc.support import sentence as support_sentence
from ssgc.tree import Trees

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
MC_DRAWS = 4000  # draws per rule for expected log-densities and rotation percentiles
# A rotation percentile from fewer of the law's own draws than this (P < 0.25%) is estimated
# from uniform rotations instead (`_Expectations.percentile`): a handful of hits is no number.
TAIL_HITS = 10
UNIFORM_DRAWS = 20000  # uniform rotations for those: about 3% relative error at P = 1e-5
# The least percentile a text prints, as a bound ("< 2.2e-306%"): a tail too far out for a
# float (a position 54σ off, a rotation of log p < -745) underflows to 0, which no finite
# density has; the smallest normal float is above the true value then.
PERCENTILE_FLOOR = float(np.finfo(np.float64).tiny)
# Seconds all of one explanation's re-parses may take together when no time limit is given
# (docs/explain.md "Cost"): enough for every object of the real sink scenes.
EXPLAIN_BUDGET_S = 30.0
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
# nats: a type gain below this is no evidence that the object is of another type.  The text
# shows gains to 0.1 nats, so a smaller one would read "+0.0 nats"; and swapping between
# equally likely models leaves rounding noise (1e-14) that must not count as a gain.
TYPE_GAIN_MIN = 0.05


@dataclass
class Reason:
    """One score term as it bears on one object."""

    rule: str  # the rule (edges) or the node type (count/choice)
    kind: str  # position | rotation | count | choice
    log_prob: float  # the whole term
    share: float  # this object's part of −log p from the term
    excess: float  # −log p of the term minus its expectation under the grammar
    sigma: float | None  # Mahalanobis distance (Normal positions)
    percentile: float | None  # P(a draw of the law is no more likely than this)
    text: str
    percentile_bound: bool = False  # the percentile is only an upper bound (a rare rotation)

    def to_json(self) -> dict[str, Any]:
        bound = {"percentile_bound": True} if self.percentile_bound else {}
        return {
            "rule": self.rule,
            "kind": self.kind,
            "log_prob": self.log_prob,
            "share": self.share,
            "excess": self.excess,
            "sigma": self.sigma,
            "percentile": self.percentile,
            "text": self.text,
        } | bound


@dataclass
class ObjectExplanation:
    index: int  # position in the scene's objects
    type: str
    share: float
    unusual: float
    pose_gain: float
    reasons: list[Reason] = field(default_factory=list)
    slot_surprise: float = 0.0  # placement by an `or` of placing rules vs. its expectation
    overlap: float = 0.0  # nats for overlapping objects the tree does not relate (overlaps.py)
    support: float = 0.0  # nats for floating or going through floor or walls (support.py)
    unexplained: bool = False  # the best parse leaves it to clutter (`observation: clutter`)
    type_gain: float | None = None  # log p gained as its best other type (None: none tried)
    better_type: str | None = None  # that type

    @property
    def label(self) -> str:
        return f"{self.type} #{self.index}"

    def __repr__(self) -> str:  # the dataclass's lists every reason and rule share
        return (
            f"ObjectExplanation({self.label}, unusual={self.unusual:.3g}, share={self.share:.3g})"
        )

    @property
    def type_evidence(self) -> float:
        """The type gain as evidence for `unusual` and the text: 0 unless another type fits
        better by at least TYPE_GAIN_MIN (rounding noise and ties are no reason)."""
        if self.type_gain is None or self.type_gain < TYPE_GAIN_MIN:
            return 0.0
        return self.type_gain

    def to_json(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "type": self.type,
            "share": self.share,
            "unusual": self.unusual,
            "pose_gain": self.pose_gain,
            "slot_surprise": self.slot_surprise,
            "overlap": self.overlap,
            "support": self.support,
            "unexplained": self.unexplained,
            "type_gain": self.type_gain,
            "better_type": self.better_type,
            "reasons": [r.to_json() for r in self.reasons],
        }


@dataclass
class Reparses:
    """What the per-object re-parses did within the explanation's budget: an object whose
    re-parse was cut short or skipped keeps the gain found so far (at least its local pose
    repair's), so its rank may be lower than with more time."""

    budget_s: float
    parsed: int = 0  # re-parses that ran to their end
    cut: list[int] = field(default_factory=list)  # objects whose re-parse hit the time limit
    skipped: list[int] = field(default_factory=list)  # objects not re-parsed: budget spent

    @property
    def status(self) -> str:
        """`complete` when every re-parse ran to its end, else `budget_exhausted`."""
        return "budget_exhausted" if self.cut or self.skipped else "complete"

    def best_score(self, parser: Any, changed: Scene, o: int, time_limit: float) -> float:
        """The best parse's log-probability of `changed` (object o moved or retyped; -inf if
        no parse), the parse noted as cut short or run to its end."""
        try:
            result = parser.parse(changed, top=1, time_limit=time_limit)
        except SsgError:  # e.g. a retyped object the grammar cannot hold more of
            return -np.inf
        if result.timed_out_in:
            self.cut.append(o)
        else:
            self.parsed += 1
        return result.parses[0].score if result.parses else -np.inf

    def to_json(self) -> dict[str, Any]:
        return {
            "status": self.status,
            "budget_s": self.budget_s,
            "parsed": self.parsed,
            "cut": sorted(set(self.cut)),
            "skipped": sorted(set(self.skipped)),
        }


@dataclass
class Explanation:
    scene: str
    log_prob: float
    objects: list[ObjectExplanation]  # most unusual first
    rules: list[dict[str, Any]]  # each rule's (or node type's) share, largest first
    unattributed: float = 0.0  # −log p of a scene without objects (nothing to attribute it to)
    reparse: Reparses | None = None  # the per-object re-parses (None: explained without)
    status: str = ""  # the best parse's: optimal or feasible ("" when explained without one)
    gap: float | None = None  # a `feasible` parse's relative gap to the bound, when known

    def __repr__(self) -> str:  # the dataclass's would print every object and rule
        first = f", most unusual {self.objects[0].label}" if self.objects else ""
        return (
            f"Explanation(scene={self.scene!r}, log_prob={self.log_prob:.4g}, "
            f"{len(self.objects)} objects{first})"
        )

    @property
    def nats_per_object(self) -> float | None:
        """−log p per observed object: comparable between scenes of different sizes.  None
        for a scene without objects, which has nothing to divide its −log p among."""
        if not self.objects:
            return None
        return -self.log_prob / len(self.objects)

    def to_json(self) -> dict[str, Any]:
        return (
            ({"status": self.status} if self.status else {})
            | ({"gap": self.gap} if self.status == "feasible" else {})
            | {
                "scene": self.scene,
                "log_prob": self.log_prob,
                "neg_log_prob": -self.log_prob,
                "nats_per_object": self.nats_per_object,
                "unattributed": self.unattributed,
                "objects": [o.to_json() for o in self.objects],
                "rules": [dict(r) for r in self.rules],  # the caller's: edits stay there
            }
            | ({} if self.reparse is None else {"reparse": self.reparse.to_json()})
        )

    def text(self, limit: int | None = None) -> str:
        """The explanation in words: the `limit` most unusual objects and rules (all: None),
        a line for those left out, and one for a parse not proven best (`status` feasible)."""
        if limit is not None and (
            isinstance(limit, bool) or not isinstance(limit, int | np.integer) or limit < 0
        ):
            raise ValueError(f"limit must be a whole number >= 0 or None, got {limit!r}")
        per = self.nats_per_object
        per_text = "no objects" if per is None else f"{per:.3f} per object"
        lines = [
            f"scene '{self.scene}': −log p = {-self.log_prob:.3f} ({per_text}); most unusual first:"
        ]
        if self.status == "feasible":  # a tree with its exact score, but maybe not the best
            gap = "" if self.gap is None else f"; relative gap to the bound {self.gap:.3g}"
            lines.append(f"  (feasible: the best parse found, not proven best{gap})")
        for o in self.objects[:limit]:
            clutter = " UNEXPLAINED (clutter)," if o.unexplained else ""
            lines.append(f"  {o.label}:{clutter} unusual {o.unusual:.2f}, share {o.share:.3f}")
            if o.type_evidence > 0:
                lines.append(
                    f"    would fit its place better as a {o.better_type} (+{o.type_gain:.1f} nats)"
                )
            shown = sorted(o.reasons, key=lambda r: -r.excess)[:3]
            texts = [r.text for r in shown]
            for r in shown:  # two rules' same words (two revolute laws above) name their rules
                said = f"{r.text} ({r.rule})" if texts.count(r.text) > 1 else r.text
                lines.append(f"    {said}")
        rest = self.objects[len(self.objects) if limit is None else limit :]
        lines += _more_line(len(rest), sum(o.share for o in rest), "object")
        if self.reparse is not None and self.reparse.status != "complete":
            r = self.reparse
            lines.append(
                f"(re-parse budget of {r.budget_s:.1f} s spent: {len(set(r.cut + r.skipped))} "
                "object(s) ranked on their local pose repair alone; raise --time-limit)"
            )
        if self.rules:
            lines.append("rules by share of −log p:")
            for r in self.rules[:limit]:
                lines.append(f"  {r['rule']} ({r['kind']}, {r['terms']} term(s)): {r['share']:.3f}")
            rest_rules = self.rules[len(self.rules) if limit is None else limit :]
            lines += _more_line(len(rest_rules), sum(r["share"] for r in rest_rules), "rule")
        return "\n".join(lines)


def _more_line(n: int, nats: float, what: str) -> list[str]:
    """The line for the n objects or rules `Explanation.text` leaves out, with their part of
    −log p: the listed shares then still add up to it, and the reader knows the list goes on."""
    if n == 0:
        return []
    return [f"  … and {n} more {what}(s) ({nats:.3f} nats of −log p; the JSON lists all)"]


def explain(grammar: Grammar, scene: Scene, tree: Trees | None = None, **parse: Any) -> Explanation:
    """Explain a scene's best parse (parsed here unless `tree` is given; `parse` goes to
    `Parser.parse`, e.g. time_limit).  Raises `UnexplainedScene` when there is no parse; for a
    scene no tree contains, with the diagnosis (`diagnose`) that names the objects to blame."""
    from ssgc.parse.parser import Parser

    parser = Parser(grammar)
    t0 = time.perf_counter()
    if tree is None:
        tree = best_tree(grammar, scene, parser, **parse)
    budget = reparse_budget(parse.get("time_limit"), time.perf_counter() - t0)
    return explain_tree(grammar, scene, tree, parser, budget)


def reparse_budget(time_limit: float | None, spent: float) -> float:
    """Seconds left for an explanation's re-parses: what a per-scene time limit leaves after
    the `spent` seconds of the base parse, or EXPLAIN_BUDGET_S without a limit."""
    if time_limit is None:
        return EXPLAIN_BUDGET_S
    return max(time_limit - spent, 0.0)


class UnexplainedScene(SsgError):
    """No parse, so nothing to explain: `status` is `infeasible` (proven: `diagnosis` names
    the objects and rules to blame) or `no_parse` (none found, e.g. within the time limit).
    An `SsgError`, with `ssg explain`'s exit code for that status."""

    def __init__(
        self, message: str, status: str, diagnosis: Diagnosis | None = None, phase: str = ""
    ) -> None:
        from ssgc.parse.parser import exit_code

        # the exit code `ssg explain` gives the scene: a no_parse the time limit caused is 4
        code = exit_code([{"status": status, "phase": phase}])
        super().__init__([Diagnostic(message)], code)
        self.message = message
        self.status = status
        self.diagnosis = diagnosis
        self.phase = phase  # for no_parse: the step that gave up (SceneParses.phase)

    def __reduce__(self) -> tuple[type[UnexplainedScene], tuple[str, str, Diagnosis | None, str]]:
        """Pickled (and copied) as its own arguments: an exception is rebuilt from its `args`,
        one string here, so explaining in a process pool broke the pool."""
        return type(self), (self.message, self.status, self.diagnosis, self.phase)


def best_tree(grammar: Grammar, scene: Scene, parser: Any = None, **parse: Any) -> Trees:
    return best_parse(grammar, scene, parser, **parse)[0]


def best_parse(
    grammar: Grammar, scene: Scene, parser: Any = None, **parse: Any
) -> tuple[Trees, str, float | None]:
    """The scene's best tree, the parse's status (optimal or feasible) and its relative gap
    (None when not computed); `UnexplainedScene` when there is none."""
    from ssgc.parse.parser import Parser

    parser = parser or Parser(grammar)
    result = parser.parse(scene, top=1, **parse)
    if result.parses:
        gap = float(result.parses[0].gap)
        return result.parses[0].tree, result.status, gap if np.isfinite(gap) else None
    if result.status != "infeasible":
        raise UnexplainedScene(result.message, result.status, phase=result.phase)
    d = diagnose(grammar, scene, parser, time_limit=parse.get("time_limit") or 30.0)
    raise UnexplainedScene(d.message, result.status, d)


def explain_tree(
    grammar: Grammar,
    scene: Scene,
    tree: Trees,
    parser: Any = None,
    time_limit: float | None = None,
) -> Explanation:
    """Explain one tree of the scene (its observed nodes are the scene's objects).

    With a `parser`, each object's repaired pose is also tried by parsing the scene again with
    that one object moved (so other objects may change parent: a flipped plate whose cups had
    to move to a far plate gets the credit for the whole mess); its pose gain is then the
    better of the two.  `time_limit` is the seconds all those re-parses may take together
    (default EXPLAIN_BUDGET_S); what they did is `Explanation.reparse`."""
    terms = _terms(grammar, tree)
    obj_of = match_objects(grammar, scene, tree)
    owners = ownership(grammar, tree, obj_of, len(scene))
    expect = _Expectations(grammar)
    objects = [
        ObjectExplanation(int(o), grammar.types[scene.types[o]].name, 0.0, 0.0, 0.0)
        for o in range(len(scene))
    ]
    for term in terms:
        w = owners.of(term)
        excess = -term["log_prob"] - expect.term(term)
        text = _sentence(grammar, scene, tree, obj_of, term, expect)
        for o in np.flatnonzero(w):
            share = -float(w[o]) * term["log_prob"]
            objects[o].share += share
            objects[o].reasons.append(
                Reason(
                    term["rule"],
                    term["kind"],
                    term["log_prob"],
                    share,
                    excess,
                    term.get("sigma"),
                    term.get("percentile"),
                    text,
                    term.get("percentile_bound", False),
                )
            )
            if term["kind"] in ("count", "choice"):
                objects[o].unusual += float(w[o]) * max(0.0, excess)
    log_prob = float(sum(t["log_prob"] for t in terms))
    budget = EXPLAIN_BUDGET_S if time_limit is None else time_limit
    reparse = None if parser is None else Reparses(budget)
    deadline = time.perf_counter() + budget
    for o, fix in pose_gains(grammar, tree, obj_of).items():
        gain = fix.gain
        if reparse is not None and gain > 0:
            found = _reparsed_gain(parser, scene, o, fix, log_prob, deadline, reparse)
            gain = max(gain, found)
        objects[o].pose_gain = gain
        objects[o].unusual += gain
    for o, surprise in slot_surprises(grammar, tree, terms, obj_of, owners, expect).items():
        objects[o].slot_surprise = surprise
    retyped = type_gains(grammar, scene, tree, obj_of, log_prob, parser, deadline, reparse)
    for o, fix in retyped.items():
        objects[o].type_gain = fix.gain
        objects[o].better_type = grammar.types[fix.type].name
    for o in objects:  # the evidence that the object is not what or where the grammar expects
        o.unusual = max(o.unusual, o.slot_surprise, o.type_evidence)
    for o, (nats, reasons) in overlap_reasons(grammar, scene, tree, obj_of).items():
        objects[o].overlap = nats
        objects[o].unusual += nats  # evidence from contact, apart from the grammar's densities
        objects[o].reasons += reasons
    for o, (nats, reasons) in support_reasons(grammar, scene, tree, obj_of).items():
        objects[o].support = nats
        objects[o].unusual += nats  # evidence from physics, like the overlaps
        objects[o].reasons += reasons
    for o in unexplained_objects(grammar, scene, tree):
        objects[o].unexplained = True
    unattributed = -log_prob if len(scene) == 0 else 0.0
    # what the grammar leaves unexplained comes first, then the most unusual
    objects.sort(key=lambda o: (not o.unexplained, -o.unusual, -o.share, o.index))
    return Explanation(scene.name, log_prob, objects, _rule_shares(terms), unattributed, reparse)


def slot_surprise_nodes(grammar: Grammar, tree: Trees) -> list[tuple[int, int]]:
    """(`or` node, chosen child) pairs where the `or` chooses how to place its child: the
    chosen rule is not fixed, so the choice and the placement are one mixture law."""
    top = blocks(grammar, tree)
    kids = np.flatnonzero(tree.parent >= 0)
    out = []
    for c in kids:
        i = int(tree.parent[c])
        if grammar.types[tree.type[i]].kind == Kind.OR and top[c] != top[i]:
            out.append((i, int(c)))
    return out


def slot_surprises(
    grammar: Grammar,
    tree: Trees,
    terms: list[dict[str, Any]],
    obj_of: IntArray,
    owners: Owners,
    expect: _Expectations,
) -> dict[int, float]:
    """Each object's *slot surprise*: −log of its `or` choice and placement together (one
    draw of the mixture the `or` defines: right side up, upside down, on its side, ...) minus
    the mixture's expected −log p, so 0 is a typical draw.  Calibrated per slot, it compares
    objects whose rules have laws of different widths; and unlike the pose repair, which only
    looks for a better pose under the rule that placed the object, it sees an object that the
    parse had to put in an unlikely branch (a flipped dish in the catch-all "any rotation")."""
    out: dict[int, float] = {}
    pairs = slot_surprise_nodes(grammar, tree)
    if not pairs:
        return out
    choice = dict.fromkeys((i for i, _ in pairs), 0.0)  # the `or` node's choice term
    placement = dict.fromkeys((c for _, c in pairs), 0.0)  # the chosen child's edge terms
    for t in terms:
        if t["kind"] == "choice" and t["node"] in choice:
            choice[t["node"]] += t["log_prob"]
        elif t["kind"] in ("position", "rotation") and t["node"] in placement:
            placement[t["node"]] += t["log_prob"]
    for i, c in pairs:
        surprise = -(choice[i] + placement[c]) - expect.mixture(int(tree.type[i]))
        w = owners.placement[c]  # the owners of the placement the `or` chose
        for o in np.flatnonzero(w):
            out[int(o)] = max(out.get(int(o), -np.inf), float(w[o]) * surprise)
    return out


def overlap_reasons(
    grammar: Grammar, scene: Scene, tree: Trees, obj_of: IntArray
) -> dict[int, tuple[float, list[Reason]]]:
    """Each overlapping object's nats and a reason per overlap it takes part in
    (`ssgc.overlaps`: the grammar's `non_penetration` constraints, pairs of which neither
    carries the other).  An object's overlap depths under one constraint add up to D; their
    nats are −log of how rare so much overlap is among the objects of real scenes, the
    constraint's exponential tail P(D ≥ d) = rate · exp(−d / mean) (its `tail:`, else the sink
    default: ssgc/tails.py; docs/explain.md, "Overlaps"), summed over the constraints."""
    found = overlaps(grammar, scene, tree, blocks(grammar, tree), obj_of)
    if not found:
        return {}
    tails = {c.name: c.tail for c in grammar.constraints if isinstance(c, NonPenetration)}
    depth = {name: np.zeros(len(scene)) for name in tails}  # per constraint and object
    for v in found:
        depth[v.constraint][[v.a, v.b]] += v.depth
    nats = {name: np.where(d > 0, tails[name].nats(d), 0.0) for name, d in depth.items()}
    names = [f"{grammar.types[t].name} #{o}" for o, t in enumerate(scene.types)]
    out: dict[int, tuple[float, list[Reason]]] = {}
    for v in found:
        for me, other in ((v.a, v.b), (v.b, v.a)):
            text = (
                f"overlaps {names[other]} by {100 * v.depth:.1f} cm, though neither carries "
                f"the other ({v.constraint})"
            )
            c = v.constraint  # the object's nats under c, split by depth
            part = float(v.depth / depth[c][me] * nats[c][me])
            reason = Reason(c, "overlap", -part, 0.0, part, None, None, text)
            out.setdefault(me, (sum(float(n[me]) for n in nats.values()), []))[1].append(reason)
    return out


def support_reasons(
    grammar: Grammar, scene: Scene, tree: Trees, obj_of: IntArray
) -> dict[int, tuple[float, list[Reason]]]:
    """Each object's nats and reasons for floating or going through its container's floor or
    walls (`ssgc.support`): the sum of its findings' nats (each −log of how rare so much is
    among real objects), split over its reasons (docs/explain.md, "Support, floor and walls")."""
    names = [f"{grammar.types[t].name} #{o}" for o, t in enumerate(scene.types)]
    out: dict[int, tuple[float, list[Reason]]] = {}
    for f in support_findings(grammar, scene, tree, obj_of):
        part = support_nats(grammar, f)
        reason = Reason(
            f.constraint, f.kind, -part, 0.0, part, None, None, support_sentence(f, names)
        )
        nats, reasons = out.get(f.obj, (0.0, []))
        out[f.obj] = (nats + part, [*reasons, reason])
    return out


def _reparsed_gain(
    parser: Any,
    scene: Scene,
    o: int,
    fix: Repair,
    log_prob: float,
    deadline: float,
    record: Reparses,
) -> float:
    """The best score gain over the repair's poses of object o, the scene parsed again, each
    parse bounded by what is left before `deadline` (noted in `record`)."""
    best = 0.0
    for xyz_o, quat_o in fix.poses[:2]:
        left = deadline - time.perf_counter()
        if left <= 0:
            record.skipped.append(o)
            break
        xyz, quat = scene.xyz.copy(), scene.quat.copy()
        xyz[o], quat[o] = xyz_o, quat_o
        moved = Scene(scene.name, scene.types, xyz, quat, metadata=scene.metadata)
        best = max(best, record.best_score(parser, moved, o, left) - log_prob)
    return best


# ------------------------------------------------------------------ terms ---


def _terms(grammar: Grammar, tree: Trees) -> list[dict[str, Any]]:
    """Every non-zero term of the tree's score: edges split into position and rotation.  An
    unseen node's edge has none: the scorer integrates its pose out (docs/conventions.md,
    "Unseen nodes"), so an empty latent node with a pose law of its own says nothing."""
    nt = node_terms(grammar, tree)
    out: list[dict[str, Any]] = []
    child = np.flatnonzero((tree.parent >= 0) & seen_nodes(grammar, tree))
    r, p = tree.rule[child], tree.parent[child]
    lt = translation_log_density(grammar, r, tree.xyz[p], tree.quat[p], tree.xyz[child])
    lr = rotation_log_density(grammar, r, tree.quat[p], tree.quat[child])
    for k, i in enumerate(child):
        rule = int(r[k])
        name = grammar.rule_name(rule)
        if grammar.rules[rule].translation.point is None:
            out.append(
                {
                    "node": int(i),
                    "kind": "position",
                    "rule": name,
                    "rid": rule,
                    "log_prob": float(lt[k]),
                }
            )
        if grammar.rules[rule].rotation.point is None:
            out.append(
                {
                    "node": int(i),
                    "kind": "rotation",
                    "rule": name,
                    "rid": rule,
                    "log_prob": float(lr[k]),
                }
            )
    for i in np.flatnonzero(nt.choice != 0):
        t = grammar.types[tree.type[i]]
        kind = "count" if t.kind == Kind.REPEAT else "choice"
        out.append({"node": int(i), "kind": kind, "rule": t.name, "log_prob": float(nt.choice[i])})
    # the edge terms recomputed here must be the scorer's (one definition of the score)
    assert np.allclose(lt + lr, nt.edge[child], atol=1e-9, equal_nan=True)
    assert np.allclose(np.sum(nt.edge), np.sum(nt.edge[child]), atol=1e-9, equal_nan=True)
    return out


def _rule_shares(terms: list[dict[str, Any]]) -> list[dict[str, Any]]:
    acc: dict[tuple[str, str], list[float]] = {}
    for t in terms:
        kind = "placement" if t["kind"] in ("position", "rotation") else t["kind"]
        acc.setdefault((t["rule"], kind), []).append(-t["log_prob"])
    rows = [
        {"rule": rule, "kind": kind, "share": float(sum(v)), "terms": len(v)}
        for (rule, kind), v in acc.items()
    ]
    return sorted(rows, key=lambda r: -r["share"])


# -------------------------------------------------------------- ownership ---


def match_objects(grammar: Grammar, scene: Scene, tree: Trees) -> IntArray:
    """For each tree node, the scene object it is (-1 for latent nodes and an implicit root),
    matched per type by pose (nodes of a parse sit exactly on their objects)."""
    obj_of = np.full(len(tree), -1, np.int64)
    observed = grammar.tables.type_observed[tree.type]
    for t in np.unique(scene.types):
        nodes = np.flatnonzero(observed & (tree.type == t))
        objs = np.flatnonzero(scene.types == t)
        if len(nodes) == 0:
            continue
        cost = np.linalg.norm(tree.xyz[nodes][:, None] - scene.xyz[objs][None], axis=2)
        cost = cost + quat_angle(tree.quat[nodes][:, None], scene.quat[objs][None])
        rows, cols = linear_sum_assignment(cost)
        obj_of[nodes[rows]] = objs[cols]
    return obj_of


def unexplained_objects(grammar: Grammar, scene: Scene, tree: Trees) -> list[int]:
    """The scene's objects that `tree` leaves to clutter (their indices, in scene order)."""
    obj_of = match_objects(grammar, scene, tree)
    return sorted(int(o) for o in obj_of[clutter_nodes(grammar, tree) & (obj_of >= 0)])


def blocks(grammar: Grammar, tree: Trees) -> IntArray:
    """Each node's block top: nodes joined by rules fixed in translation and rotation share a
    pose, so they are one thing that moves together."""
    rigid = [_rigid(grammar, r) for r in range(len(grammar.rules))]
    top = np.arange(len(tree))
    for i in range(len(tree)):  # parents come first
        r = tree.rule[i]
        if r >= 0 and rigid[r]:
            top[i] = top[tree.parent[i]]
    return top


@dataclass
class Owners:
    """Who owns each node's terms: (nodes, objects) weights, each row summing to 1 (when the
    scene has objects).  Two matrices, because a node's placement and its choice can belong
    to different objects: an observed `or` node keeps its own placement, while its choice is
    about the child it chose (docs/explain.md, "share", rule 1 and its exception)."""

    placement: FloatArray  # a node's position and rotation terms
    choice: FloatArray  # its count or choice term

    def of(self, term: dict[str, Any]) -> FloatArray:
        """The weights over the objects of one term of `_terms`."""
        edge = term["kind"] in ("position", "rotation")
        return (self.placement if edge else self.choice)[term["node"]]


def ownership(grammar: Grammar, tree: Trees, obj_of: IntArray, n_objects: int) -> Owners:
    """Who owns each node's terms (module docstring), with the `or` exception: a choice is
    about the child it chose, so when that child has a pose of its own (an `or` whose rules
    place dishes right side up or upside down), the choice goes to the child's owners, not to
    whatever object shares the `or` node's pose (the bin).  A latent `or` node's placement
    follows its choice (its terms go to the object it chose); an `or` node whose block holds
    an observed object keeps its placement: that object is what the placement places."""
    top = blocks(grammar, tree)
    clutter = np.array([grammar.types[t].synthetic == "clutter" for t in tree.type], bool)
    w, observed = _block_owners(tree, obj_of, n_objects, top, clutter)
    choice = w.copy()
    is_or = np.array([grammar.types[t].kind == Kind.OR for t in tree.type])
    kids = np.flatnonzero((tree.parent >= 0) & is_or[np.maximum(tree.parent, 0)])
    for c in kids[::-1]:  # children before parents: chains of `or`s
        i = tree.parent[c]
        if top[c] != top[i] and w[c].any():
            choice[i] = w[c]
            if not observed[i]:
                w[i] = w[c]
    return Owners(w, choice)


def _block_owners(
    tree: Trees, obj_of: IntArray, n_objects: int, top: IntArray, clutter: NDArray[np.bool_]
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Rules 1-3 of docs/explain.md ("share"): each node's (nodes, objects) weights, and
    whether its block holds an observed object (the `or` exception keeps such a placement).
    The `clutter` nodes (the clutter set and its objects) go by rule 2 first: the clutter set
    shares the root's pose, and with it an observed root's block when the root has no noise,
    yet its count is about the clutter objects, not the root."""
    n = len(tree)
    w = np.zeros((n, n_objects))
    if n_objects == 0:
        return w, np.zeros(n, bool)
    below = np.zeros((n, n_objects), bool)  # objects in each node's subtree
    has = obj_of >= 0
    below[np.flatnonzero(has), obj_of[has]] = True
    for i in range(n - 1, 0, -1):
        if tree.parent[i] >= 0:
            below[tree.parent[i]] |= below[i]
    in_block = np.zeros((n, n_objects), bool)
    in_block[top[np.flatnonzero(has)], obj_of[has]] = True
    for i in range(n):
        own = in_block[top[i]]
        if clutter[i] or not own.any():
            own = below[i]
        if own.any():
            w[i] = own / own.sum()
        elif tree.parent[i] >= 0:
            w[i] = w[tree.parent[i]]
        else:
            w[i] = 1.0 / n_objects
    return w, in_block[top].any(axis=1)


# ------------------------------------------------------------ pose repair ---


@dataclass
class Repair:
    """Rigid moves of one object's block that raise the tree's score: the best gain, and the
    object's pose after each move (best first; a shift alone, a turn alone, both)."""

    gain: float
    poses: list[tuple[FloatArray, FloatArray]]


def pose_gains(grammar: Grammar, tree: Trees, obj_of: IntArray) -> dict[int, Repair]:
    """For each object: how much the tree's score rises when it moves to the best of a few
    candidate poses (`_object_moves`), the latent nodes between it and its nearest observed
    ancestor allowed to move with it."""
    top = blocks(grammar, tree)
    seen = seen_nodes(grammar, tree)
    out: dict[int, Repair] = {}
    for b in np.unique(top[obj_of >= 0]):
        moves = _object_moves(grammar, tree, obj_of, top, seen, int(b))
        for m in np.flatnonzero((top == b) & (obj_of >= 0)):
            poses = [(xyz[m], quat[m]) for _, xyz, quat in moves]
            out[int(obj_of[m])] = Repair(moves[0][0] if moves else 0.0, poses)
    return out


def _object_moves(
    grammar: Grammar, tree: Trees, obj_of: IntArray, top: IntArray, seen: NDArray[np.bool_], b: int
) -> list[tuple[float, FloatArray, FloatArray]]:
    """Moves of block b that raise the score, best first: (gain, every node's pose after it).
    The block moves rigidly (`_block_gain`); and, since no scene shows a latent node's pose,
    the latent blocks above it up to its nearest observed ancestor (`_latent_ancestors`) may
    move too: each such chain rigidly with the block (a slot that places its cup at its own
    position: the cup alone cannot move), scored on every edge the chain touches (its own
    placement, and the other children it carries, which stay), then the block re-placed on
    the moved chain.  Each move is a pose of the tree, so its gain is a true rise of the
    score: a lower bound of the best the object's move can give."""
    members = np.flatnonzero(top == b)
    moves = [
        (gain, *_moved(tree, members, b, shift, turn))
        for shift, turn, gain in _block_gain(grammar, tree, members, b, seen)
    ]
    carried = members
    for a in _latent_ancestors(tree, obj_of, top, b):
        carried = np.r_[carried, np.flatnonzero(top == a)]
        for shift, turn, gain in _block_gain(grammar, tree, carried, a, seen)[:1]:
            xyz, quat = _moved(tree, carried, a, shift, turn)
            moves.append((gain, xyz, quat))
            there = replace(tree, xyz=xyz, quat=quat)
            for shift2, turn2, gain2 in _block_gain(grammar, there, members, b, seen)[:1]:
                moves.append((gain + gain2, *_moved(there, members, b, shift2, turn2)))
    return sorted(moves, key=lambda m: -m[0])


def _latent_ancestors(tree: Trees, obj_of: IntArray, top: IntArray, b: int) -> list[int]:
    """The tops of the latent blocks above block b, nearest first, up to its nearest observed
    ancestor's block or the root's (whose pose the grammar fixes)."""
    out = []
    p = tree.parent[b]
    while p >= 0:
        a = int(top[p])
        if tree.parent[a] < 0 or np.any(obj_of[top == a] >= 0):
            break
        out.append(a)
        p = tree.parent[a]
    return out


def _moved(
    tree: Trees, members: IntArray, top: int, shift: FloatArray, turn: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Every node's pose after `members` turn about the top node's position, then shift."""
    xyz, quat = tree.xyz.copy(), tree.quat.copy()
    x0 = tree.xyz[top]
    for m in members:
        xyz[m] = x0 + quat_rotate(turn, tree.xyz[m] - x0) + shift
        quat[m] = quat_multiply(turn, tree.quat[m])
    return xyz, quat


def _block_gain(
    grammar: Grammar, tree: Trees, members: IntArray, top: int, seen: NDArray[np.bool_]
) -> list[tuple[FloatArray, FloatArray, float]]:
    """Rigid moves (shift, turn, gain) of a block that raise the score, best first.  None for
    the block of the tree's root: the grammar fixes the root's pose (docs/grammar.md, `root`),
    so moving it would make the tree impossible, however much its children's edges gain.  (An
    observed root with `observation: noise` is a noisy child of its own `~node`: it has a
    parent, and its pose gain is its noise edge's.)  The edges to unseen children, whose
    poses the score integrates out, are not scored."""
    if tree.parent[top] < 0:
        return []
    inside = np.zeros(len(tree), bool)
    inside[members] = True
    kids = np.flatnonzero((tree.parent >= 0) & ~inside & inside[np.maximum(tree.parent, 0)] & seen)
    edges = np.r_[[top], kids].astype(np.int64)
    shifts, turns = [np.zeros(3)], [IDENTITY]
    x0, q0 = tree.xyz[top], tree.quat[top]
    p, r = tree.parent[top], int(tree.rule[top])
    shifts.append(_mode_position(grammar, r, tree.xyz[p], tree.quat[p]) - x0)
    mode = _mode_rotation(grammar, r, tree.quat[p])
    if mode is not None:
        turns.append(quat_multiply(mode, quat_conjugate(q0)))
    for c in kids:
        p, r = tree.parent[c], int(tree.rule[c])
        frame = grammar.rules[r].translation.frame
        if frame == Frame.WORLD_OFFSET:
            shifts.append(tree.xyz[c] - _mode_u(grammar, r) - tree.xyz[p])
        elif frame == Frame.PARENT:
            shifts.append(
                tree.xyz[c] - quat_rotate(tree.quat[p], _mode_u(grammar, r)) - tree.xyz[p]
            )
        rel = _rel_mode(grammar, r)
        if rel is not None and grammar.rules[r].rotation.frame != Frame.WORLD:
            want = quat_multiply(tree.quat[c], quat_conjugate(rel))  # parent rotation wanted
            turns.append(quat_multiply(want, quat_conjugate(tree.quat[p])))
    if len(shifts) > 2:
        shifts.append(np.mean(shifts[1:], axis=0))
    d = np.array(shifts)
    rq = np.array(turns)
    # shifts alone, turns alone, and the best turn after the best shift: (K, 3) and (K, 4)
    shift = np.r_[d, np.zeros((len(rq), 3))]
    turn = np.r_[np.tile(IDENTITY, (len(d), 1)), rq]
    s = _moved_scores(grammar, tree, members, top, edges, shift, turn)
    best_d, best_r = int(np.argmax(s[: len(d)])), len(d) + int(np.argmax(s[len(d) :]))
    s2 = _moved_scores(grammar, tree, members, top, edges, np.tile(d[best_d], (len(rq), 1)), rq)
    moves = [(d[best_d], IDENTITY, s[best_d]), (np.zeros(3), turn[best_r], s[best_r])]
    moves.append((d[best_d], rq[int(np.argmax(s2))], float(np.max(s2))))
    moves = [(a, b, float(v) - float(s[0])) for a, b, v in moves]
    moves = [m for m in moves if np.isfinite(m[2]) and m[2] > 0]
    return sorted(moves, key=lambda m: -m[2])


def _moved_scores(
    grammar: Grammar,
    tree: Trees,
    members: IntArray,
    top: int,
    edges: IntArray,
    shift: FloatArray,
    turn: FloatArray,
) -> FloatArray:
    """Score of the touched edges for K rigid moves of the block: turn about the top node's
    position, then shift."""
    k = len(shift)
    xyz = np.repeat(tree.xyz[None], k, axis=0)
    quat = np.repeat(tree.quat[None], k, axis=0)
    x0 = tree.xyz[top]
    for m in members:
        xyz[:, m] = x0 + quat_rotate(turn, np.broadcast_to(tree.xyz[m] - x0, (k, 3))) + shift
        quat[:, m] = quat_multiply(turn, np.broadcast_to(tree.quat[m], (k, 4)))
    p = tree.parent[edges]
    r = np.tile(tree.rule[edges], k)
    px, pq = xyz[:, p].reshape(-1, 3), quat[:, p].reshape(-1, 4)
    cx, cq = xyz[:, edges].reshape(-1, 3), quat[:, edges].reshape(-1, 4)
    lp = translation_log_density(grammar, r, px, pq, cx) + rotation_log_density(grammar, r, pq, cq)
    return np.nan_to_num(lp.reshape(k, -1).sum(axis=1), nan=-np.inf)


def _mode_u(grammar: Grammar, r: int) -> FloatArray:
    """The most likely position of a rule's child in the rule's own coordinates."""
    mode = grammar.rules[r].translation.mode()
    return np.zeros(3) if mode is None else np.array(mode, float)


def _mode_position(grammar: Grammar, r: int, pxyz: FloatArray, pquat: FloatArray) -> FloatArray:
    frame = grammar.rules[r].translation.frame
    u = _mode_u(grammar, r)
    if frame == Frame.WORLD:
        return u
    if frame == Frame.PARENT:
        return pxyz + quat_rotate(pquat, u)
    return pxyz + u


def _rel_mode(grammar: Grammar, r: int) -> FloatArray | None:
    """The most likely rotation of a rule's child in the rule's coordinates (None: no mode)."""
    mode = grammar.rules[r].rotation.mode()
    return None if mode is None else np.array(mode, float)


def _mode_rotation(grammar: Grammar, r: int, pquat: FloatArray) -> FloatArray | None:
    rel = _rel_mode(grammar, r)
    if rel is None or grammar.rules[r].rotation.frame == Frame.WORLD:
        return rel
    return quat_multiply(pquat, rel)


# ------------------------------------------------------------ type repair ---

RETYPE_TIME = 60.0  # s, wall clock: the default bound of each parse of a retyped scene


@dataclass
class TypeFix:
    """The best other type for one object: how much the scene's best log-probability would
    rise with it (negative: every other type fits worse) and how that was found ("swap": the
    same tree with the object's leaf swapped; "parse": the scene parsed again)."""

    gain: float
    type: int
    how: str


def type_gains(
    grammar: Grammar,
    scene: Scene,
    tree: Trees,
    obj_of: IntArray,
    log_prob: float,
    parser: Any = None,
    deadline: float | None = None,
    record: Reparses | None = None,
) -> dict[int, TypeFix]:
    """For each object: the best score of the scene with that object of another type, minus
    the tree's.  An object given a wrong type sits where its *true* type belongs (a mug at a
    plate's pose, with cups resting on it): retyping it back restores the scene, while an
    unchanged object's best other type fits no better (gain ≤ 0, up to model choices that are
    more probable than its own).  Types that swap into the tree in place (another leaf of the
    same `or`: another model of the same category) are scored on the tree; other types are
    tried by parsing the scene again (with a `parser`), one type per group of interchangeable
    types (`retype_groups`).  Those parses share the explanation's re-parse budget (until
    `deadline`, each at most RETYPE_TIME) and are noted in `record`."""
    found = _swap_scores(grammar, tree, obj_of)
    how = {o: dict.fromkeys(s, "swap") for o, s in found.items()}
    if parser is not None:
        end = time.perf_counter() + RETYPE_TIME * len(scene) if deadline is None else deadline
        record = Reparses(end - time.perf_counter()) if record is None else record
        for o in range(len(scene)):
            if _is_root_object(grammar, scene, o):
                continue
            done = set(found.get(o, {}))
            for t in _reparse_candidates(grammar, parser, scene, o, done):
                left = min(end - time.perf_counter(), RETYPE_TIME)
                if left <= 0:
                    record.skipped.append(o)
                    break
                score = _retyped_score(parser, scene, o, t, left, record)
                if np.isfinite(score):
                    found.setdefault(o, {})[t] = score
                    how.setdefault(o, {})[t] = "parse"
    out: dict[int, TypeFix] = {}
    for o, scores in found.items():
        best = max(scores, key=lambda t: scores[t])
        if np.isfinite(scores[best]):
            out[o] = TypeFix(float(scores[best] - log_prob), best, how[o][best])
    return out


def _is_root_object(grammar: Grammar, scene: Scene, o: int) -> bool:
    """Object o is the grammar's observed root, which every tree holds at its fixed pose.  A
    scene without it parses with an implicit root at no cost (docs/parsing.md), so retyping it
    would only weigh "one more object at the root's pose" against "nothing": not a question
    about its type."""
    return bool(grammar.tables.type_observed[grammar.root] and scene.types[o] == grammar.root)


def _swap_scores(grammar: Grammar, tree: Trees, obj_of: IntArray) -> dict[int, dict[int, float]]:
    """Score of the tree with one object's leaf swapped for a leaf of another type that its
    parent `or` could have chosen instead (all swaps scored as one batch).  Rules of the `or`
    that produce the object's own type (a mixture's components, as in `gmm`) are no other
    type: the parse already chose the best of them."""
    tb = grammar.tables
    n = len(tree)
    has_kids = np.zeros(n, bool)
    has_kids[tree.parent[tree.parent >= 0]] = True
    swaps: list[tuple[int, int, int]] = []  # (node, rule, type)
    for m in np.flatnonzero((obj_of >= 0) & ~has_kids & (tree.parent >= 0)):
        p = tree.parent[m]
        if tb.type_kind[tree.type[p]] != Kind.OR:
            continue
        for r in tb.type_rules[tree.type[p]]:
            if r < 0 or r == tree.rule[m]:
                continue
            c = tb.rule_child[r]
            if c == tree.type[m]:  # the same type by another rule: not another type
                continue
            if tb.type_observed[c] and np.all(tb.type_rules[c] < 0):  # another observed leaf
                swaps.append((int(m), int(r), int(c)))
    if not swaps:
        return {}
    k = len(swaps)
    node, rule, kind = (np.array(v, np.int64) for v in zip(*swaps, strict=True))
    types = np.tile(tree.type, (k, 1))
    rules = np.tile(tree.rule, (k, 1))
    types[np.arange(k), node] = kind
    rules[np.arange(k), node] = rule
    shift = (np.arange(k) * n)[:, None]
    parents = np.where(tree.parent >= 0, tree.parent + shift, -1)
    batch = Trees(
        scene=np.repeat(np.arange(k), n),
        type=types.ravel(),
        parent=parents.ravel(),
        rule=rules.ravel(),
        xyz=np.tile(tree.xyz, (k, 1)),
        quat=np.tile(tree.quat, (k, 1)),
        n_scenes=k,
    )
    scores = score_trees(grammar, batch)
    out: dict[int, dict[int, float]] = {}
    for (m, _, c), s in zip(swaps, scores, strict=True):
        per = out.setdefault(int(obj_of[m]), {})
        per[c] = max(per.get(c, -np.inf), float(s))
    return out


def retype_groups(grammar: Grammar) -> list[list[int]]:
    """Observed types grouped by the node types whose rules produce them (in `sink_detailed`:
    the three plate models, the three bowls, the three mugs, the bin), each group's most
    probable member first.  Members of a group differ only by which leaf their parent chose,
    so parsing with the first one stands for the group (the others are a swap away)."""
    tb = grammar.tables
    groups: dict[tuple[int, ...], list[int]] = {}
    for t in np.flatnonzero(tb.type_observed):
        producers = tuple(sorted(set(tb.rule_parent[tb.rule_child == t].tolist())))
        groups.setdefault(producers, []).append(int(t))
    return [sorted(g, key=lambda t: -_best_rule_prob(grammar, t)) for g in groups.values()]


def _best_rule_prob(grammar: Grammar, t: int) -> float:
    """The largest probability with which a rule that produces type t fires at its parent."""
    tb = grammar.tables
    best = 0.0
    for r in np.flatnonzero(tb.rule_child == t):
        parent = grammar.types[tb.rule_parent[r]]
        if parent.kind in (Kind.OR, Kind.INDEPENDENT):
            best = max(best, float(parent.probs[tb.rule_index[r]]))
        else:
            best = 1.0
    return best


def _reparse_candidates(
    grammar: Grammar, parser: Any, scene: Scene, o: int, done: set[int]
) -> list[int]:
    """The types to try object o as by parsing: each group's first member, unless it is the
    object's own type, a type already scored by a swap, or one the scene cannot hold more of."""
    counts = np.bincount(scene.types, minlength=len(grammar.types))
    counts[scene.types[o]] -= 1
    out = []
    for group in retype_groups(grammar):
        t = group[0]
        if t == scene.types[o] or t in done or counts[t] + 1 > parser.capacity[t]:
            continue
        out.append(t)
    return out


def _retyped_score(
    parser: Any, scene: Scene, o: int, t: int, time_limit: float, record: Reparses
) -> float:
    """The best parse's log-probability of the scene with object o of type t (-inf if none)."""
    types = scene.types.copy()
    types[o] = t
    retyped = Scene(scene.name, types, scene.xyz, scene.quat, metadata=scene.metadata)
    return record.best_score(parser, retyped, o, time_limit)


# ----------------------------------------------------- expectations, words ---


class _Expectations:
    """Expected log-probability of each term under the grammar, and rotation percentiles, by
    Monte Carlo from each rule's own sampler (seeded: the same numbers every run)."""

    def __init__(self, grammar: Grammar) -> None:
        self.g = grammar
        self.draws: dict[int, tuple[FloatArray, FloatArray]] = {}
        self.uniform_draws: dict[int, FloatArray] = {}

    def rule(self, r: int) -> tuple[FloatArray, FloatArray]:
        if r not in self.draws:
            rng = np.random.default_rng([7, r])
            n = MC_DRAWS
            px, pq = np.zeros((n, 3)), np.tile(IDENTITY, (n, 1))
            xyz, quat, _ = sample_children(self.g, r, px, pq, rng)
            rr = np.full(n, r)
            self.draws[r] = (
                translation_log_density(self.g, rr, px, pq, xyz),
                rotation_log_density(self.g, rr, pq, quat),
            )
        return self.draws[r]

    def term(self, term: dict[str, Any]) -> float:
        """E[−log p] of the term's law."""
        if term["kind"] in ("position", "rotation"):
            lt, lr = self.rule(term["rid"])
            return -float(np.mean(lt if term["kind"] == "position" else lr))
        return _entropy(self.g, term["rule"])

    def mixture(self, type_id: int) -> float:
        """E[−log p] of an `or` node's choice and its chosen rule's placement together: the
        choice's entropy plus each rule's expected −log density, weighted by its probability."""
        t = self.g.types[type_id]
        probs = np.asarray(t.probs, float) / np.sum(t.probs)
        expected = _entropy(self.g, t.name)
        for p, r in zip(probs, t.rules, strict=True):
            if p > 0:
                lt, lr = self.rule(r)
                expected -= p * float(np.mean(lt + lr))
        return expected

    def uniform(self, r: int) -> FloatArray:
        """Rule r's rotation log-density at UNIFORM_DRAWS uniform rotations (seeded)."""
        if r not in self.uniform_draws:
            rng = np.random.default_rng([11, r])
            n = UNIFORM_DRAWS
            quat = rng.normal(size=(n, 4))
            quat /= np.linalg.norm(quat, axis=1)[:, None]
            pq = np.tile(IDENTITY, (n, 1))
            self.uniform_draws[r] = rotation_log_density(self.g, np.full(n, r), pq, quat)
        return self.uniform_draws[r]

    def percentile(self, r: int, log_prob: float) -> tuple[float, bool]:
        """P(a draw of rule r's rotation law is no more likely than `log_prob`), and whether
        the number is only an upper bound.  Where at least TAIL_HITS of the law's own draws
        lie there, their share.  Rarer, uniform rotations weighted by the law's density
        (importance sampling): in that tail each weight is at most exp(log_prob)·π², so the
        estimate is good exactly where the plain one counts no draw.  Beyond every uniform
        draw too (the law's least likely rotations), the bound exp(log_prob)·π²: the law's
        density is at most exp(log_prob) there, on a set of volume at most π² (SO(3)'s)."""
        hits = self.rule(r)[1] <= log_prob + 1e-12
        if np.sum(hits) >= TAIL_HITS:
            return float(np.mean(hits)), False
        lu = self.uniform(r)
        tail = lu <= log_prob + 1e-12
        estimate = float(np.sum(np.exp(lu[tail] - UNIFORM_SO3_LOG_DENSITY))) / len(lu)
        if estimate > 0:
            return estimate, False
        bound = np.exp(log_prob - UNIFORM_SO3_LOG_DENSITY)  # 0 below exp(-745): floored
        return float(np.clip(bound, PERCENTILE_FLOOR, 1.0)), True


def _entropy(grammar: Grammar, type_name: str) -> float:
    t = next(t for t in grammar.types if t.name == type_name)
    if t.kind == Kind.REPEAT and t.count is not None:
        p = np.asarray(t.count.probs)
    elif t.kind == Kind.OR:
        p = np.asarray(t.probs) / np.sum(t.probs)
    elif t.kind == Kind.INDEPENDENT:
        p = np.asarray(t.probs)
        q = p[(p > 0) & (p < 1)]
        return float(-np.sum(q * np.log(q) + (1 - q) * np.log1p(-q)))
    else:
        return 0.0
    p = p[p > 0]
    return float(-np.sum(p * np.log(p)))


def _name(grammar: Grammar, tree: Trees, obj_of: IntArray, node: int) -> str:
    """A node as a user knows it: the object of its block, else its type (the clutter set by
    its type too: it shares the root's pose, but the root does not place clutter objects)."""
    top = blocks(grammar, tree)
    t = grammar.types[tree.type[node]]
    if t.synthetic == "clutter":
        return t.name
    same = np.flatnonzero((top == top[node]) & (obj_of >= 0))
    if not len(same) and t.synthetic == "node":  # an observed root's own node: that object
        twin = grammar.type_ids[t.name.split(":", 1)[1]]
        same = np.flatnonzero((tree.type == twin) & (obj_of >= 0))
    if len(same):
        o = same[0]
        return f"{grammar.types[tree.type[o]].name} #{obj_of[o]}"
    return t.name


def _sentence(
    grammar: Grammar,
    scene: Scene,
    tree: Trees,
    obj_of: IntArray,
    term: dict[str, Any],
    expect: _Expectations,
) -> str:
    i, kind, lp = term["node"], term["kind"], term["log_prob"]
    if kind == "position":
        return _position_words(grammar, tree, obj_of, term)
    if kind == "rotation":
        return _rotation_words(grammar, tree, obj_of, term, expect)
    t = grammar.types[tree.type[i]]
    kids = np.flatnonzero(tree.parent == i)
    if kind == "count":
        tail = _discrete_tail(np.asarray(t.count.probs) if t.count else np.ones(1), len(kids))
        term["percentile"] = tail
        return (
            f"{t.name} holds {len(kids)} (P = {np.exp(lp):.3g}; {percent(tail)} of counts as rare)"
        )
    chosen = ", ".join(grammar.types[tree.type[c]].name for c in kids) or "nothing"
    if t.kind == Kind.OR and len(kids) == 1:
        probs = np.asarray(t.probs) / np.sum(t.probs)
        term["percentile"] = _discrete_tail(
            probs, int(grammar.tables.rule_index[tree.rule[kids[0]]])
        )
    verb = "is a" if t.kind == Kind.OR else "makes"  # an `or` picks one; `independent` a subset
    return f"{t.name} {verb} {chosen} (P = {np.exp(lp):.3g})"


def _discrete_tail(probs: FloatArray, k: int) -> float:
    """P(an outcome no more likely than outcome k)."""
    if k >= len(probs):
        return 0.0
    return float(np.sum(probs[probs <= probs[k] + 1e-15]))


def _position_words(grammar: Grammar, tree: Trees, obj_of: IntArray, term: dict[str, Any]) -> str:
    i, r = term["node"], term["rid"]
    p = tree.parent[i]
    u = translation_coordinates(
        grammar, np.array([r]), tree.xyz[p][None], tree.quat[p][None], tree.xyz[i][None]
    )[0]
    ctx = Context(_name(grammar, tree, obj_of, int(p)), lambda lp: float("nan"))
    d = grammar.rules[r].translation.describe_deviation(u, term["log_prob"], ctx)
    if d.percentile is not None and d.percentile < PERCENTILE_FLOOR:  # 0 after an underflow
        term["percentile_bound"] = True
        d = _bounded(replace(d, percentile=PERCENTILE_FLOOR), percent(d.percentile))
    return _worded(d, term)


def _rotation_words(
    grammar: Grammar, tree: Trees, obj_of: IntArray, term: dict[str, Any], expect: _Expectations
) -> str:
    i, r = term["node"], term["rid"]
    p = tree.parent[i]
    rel = rotation_coordinates(grammar, np.array([r]), tree.quat[p][None], tree.quat[i][None])[0]
    ctx = Context(_name(grammar, tree, obj_of, int(p)), lambda lp: expect.percentile(r, lp)[0])
    d = grammar.rules[r].rotation.describe_deviation(rel, term["log_prob"], ctx)
    if d.percentile is not None and expect.percentile(r, term["log_prob"])[1]:
        term["percentile_bound"] = True  # say so: "< 3.7e-40% likely"
        d = _bounded(d, percent(d.percentile))
    return _worded(d, term)


def _bounded(d: Deviation, mark: str) -> Deviation:
    """The law's words with its percentile, written `mark` there, read as an upper bound."""
    bound = percent(d.percentile or 0.0)
    text = d.text.replace(mark, f"< {bound}", 1) if mark in d.text else f"{d.text} (< {bound})"
    return replace(d, text=text)


def _worded(d: Deviation, term: dict[str, Any]) -> str:
    """The law's words for a term; its sigma and percentile join the term."""
    if d.sigma is not None:
        term["sigma"] = d.sigma
    if d.percentile is not None:
        term["percentile"] = d.percentile
    return d.text


# ------------------------------------------------ scenes with no parse at all ---


@dataclass
class Diagnosis:
    """Why no tree explains a scene: objects whose removal lets the rest parse, and why the
    rules that could have produced each fail.  When no removal helps, `objects` are those the
    grammar never produces or no rule can place where they are (`_unplaceable`); empty when
    nothing is found in time."""

    scene: str
    objects: list[int]  # the smallest set found, best first (else the objects to blame)
    reasons: dict[int, list[str]]
    alternatives: list[list[int]]  # other sets of the same size that also work
    message: str

    def to_json(self) -> dict[str, Any]:
        return {  # copies: editing the document must not change the diagnosis
            "objects": list(self.objects),
            "reasons": {str(k): list(v) for k, v in self.reasons.items()},
            "alternatives": [list(a) for a in self.alternatives],
            "message": self.message,
        }


# Seconds of a diagnosis's time limit (at most a tenth of it) kept for the per-object reasons
# when no removal helps: they parse nothing, so a second covers scenes of many objects.
REASONS_S = 1.0
SHOWN = 5  # objects a message of the per-object reasons names; the JSON's `reasons` has all


def diagnose(
    grammar: Grammar,
    scene: Scene,
    parser: Any = None,
    time_limit: float = 30.0,
    max_removed: int = 2,
) -> Diagnosis:
    """Find few objects whose removal makes the scene parseable (the parser as a black box:
    every object alone, then pairs, within `time_limit` seconds), and say for each why the
    rules that could produce it cannot.  Among several single objects that work, the one whose
    removal leaves the most probable rest comes first.  When none works, name the objects no
    rule can place where they are: a scene whose every pose is a few mm off is still to blame
    on its objects, though removing two of them does not help."""
    from ssgc.parse.parser import Parser

    parser = parser or Parser(grammar)
    t_end = time.perf_counter() + time_limit
    names = [f"{grammar.types[t].name} #{o}" for o, t in enumerate(scene.types)]
    need = grammar.required_root
    if need is not None and not np.any(scene.types == need):
        return _without_root(grammar, scene, names)
    never = [o for o in range(len(scene)) if parser.capacity[scene.types[o]] == 0]
    reserve = min(REASONS_S, 0.1 * time_limit)
    found, cut = _removals(parser, scene, never, max_removed, t_end - reserve)
    if not found:
        deadline = max(t_end, time.perf_counter() + reserve)
        return _no_removal_helps(grammar, scene, parser, never, max_removed, deadline, cut)
    found.sort(key=lambda f: -f[0])
    _, drop, tree = found[0]
    kept = np.setdiff1d(np.arange(len(scene)), drop)
    reasons = {o: _why_not(grammar, scene, o, tree, kept, parser, drop) for o in drop}
    parts = [f"{names[o]} ({'; '.join(reasons[o][:3])})" for o in drop]
    message = (
        f"scene '{scene.name}': no tree of the grammar contains all its objects; "
        + _rest_words(grammar, scene, names, drop)
        + " it parses. "
        + " ".join(parts)
    )
    if len(found) > 1:
        message += (
            " (also parses "
            + "; ".join(_rest_words(grammar, scene, names, f[1]) for f in found[1:6])
            + ")"
        )
    message += _hint(grammar, [r for o in drop for r in reasons[o]])
    return Diagnosis(scene.name, drop, reasons, [f[1] for f in found[1:]], message)


def _removals(
    parser: Any, scene: Scene, never: list[int], max_removed: int, t_end: float
) -> tuple[list[tuple[float, list[int], Trees]], bool]:
    """The smallest sets of objects (with those the grammar never produces) whose removal
    lets the rest parse, each with the rest's best score and tree: every object alone, then
    pairs, up to `max_removed`, until `t_end`.  Also whether the search was cut short: a
    set not tried by `t_end`, or a rest whose parse gave up unproven (`no_parse`), so that
    none found is no proof that no removal helps."""
    import itertools

    found: list[tuple[float, list[int], Trees]] = []
    base, cut = set(never), False
    for k in range(0, max_removed + 1):
        for extra in itertools.combinations([o for o in range(len(scene)) if o not in base], k):
            left = t_end - time.perf_counter()
            if left <= 0:
                cut = True
                break
            drop = sorted(base | set(extra))
            if not drop:
                continue
            rest = _without(scene, drop)  # a required root set aside is implied at its pose
            limit = max(0.5, min(left, 10.0))
            result = parser.parse(rest, top=1, time_limit=limit, imply_root=True)
            if result.parses:
                found.append((result.parses[0].score, drop, result.parses[0].tree))
            cut |= not result.parses and result.status != "infeasible"
        if found:
            break
    return found, cut


def _rest_words(grammar: Grammar, scene: Scene, names: list[str], drop: list[int]) -> str:
    """What the scene that parses is, set against this one: "without Mug #4".  A required
    root set aside is not removed (a scene without it is refused) but implied at its pose
    (`Parser.parse(imply_root=True)`), so it reads "with DishBin #0 at the root's pose (0.50,
    0.00, 0.00)"."""
    implied = _implied_root(grammar, scene, drop)
    parts = []
    if implied is not None:
        fixed = _fixed_pose(
            grammar, int(scene.types[implied]), scene.xyz[implied], scene.quat[implied]
        )
        x, y, z = grammar.root_xyz if fixed is None else fixed[0]
        parts.append(f"with {names[implied]} at the root's pose ({x:.2f}, {y:.2f}, {z:.2f})")
    removed = [names[o] for o in drop if o != implied]
    if removed:
        parts.append("without " + " and ".join(removed))
    return " and ".join(parts)


def _implied_root(grammar: Grammar, scene: Scene, drop: list[int]) -> int | None:
    """The object of the required root's type among `drop` that the parse of the rest implies
    at its pose (none of that type is kept), else None."""
    need = grammar.required_root
    if need is None:
        return None
    dropped = [o for o in drop if scene.types[o] == need]
    kept = np.count_nonzero(scene.types == need) - len(dropped)
    return dropped[0] if dropped and kept == 0 else None


def _no_removal_helps(
    grammar: Grammar,
    scene: Scene,
    parser: Any,
    never: list[int],
    max_removed: int,
    deadline: float,
    cut: bool,
) -> Diagnosis:
    """The diagnosis when no removal lets the rest parse: the objects the grammar never
    produces, those off the pose it fixes, those no rule can place where they are (the first
    SHOWN in the message), and the count laws the scene has too few objects for."""
    names = [f"{grammar.types[t].name} #{o}" for o, t in enumerate(scene.types)]
    message = (
        f"scene '{scene.name}': no tree of the grammar contains this scene's objects, and "
        + (
            f"removing up to {max_removed} object(s) was not tried to the end (the time limit, "
            "or a rest whose parse gave up unproven)"
            if cut
            else f"removing up to {max_removed} object(s) does not help"
        )
    )
    if never:
        message += "; never produced by the grammar: " + ", ".join(names[o] for o in never)
    off = _off_root(grammar, scene)
    if off:
        message += "; off the pose the grammar fixes: " + ", ".join(
            f"{names[o]} ({why})" for o, why in off.items()
        )
    others = [o for o in range(len(scene)) if o not in never and o not in off]
    placed, unexamined = _unplaceable(grammar, scene, others, deadline)
    message += _unplaceable_words(names, placed, unexamined)
    few = _too_few(grammar, scene)
    if few:
        message += "; " + "; ".join(f"{names[o]}: {why}" for o, why in few.items())
    try:  # too many objects (of types it makes): any of them may go, so none is named
        parser.check_capacity(_without(scene, never))
    except SsgError as exc:
        message += "; " + "; ".join(d.message for d in exc.diagnostics)
    message += _hint(grammar, [*off.values(), *(r for rs in placed.values() for r in rs)])
    reasons = {o: [why] for o, why in off.items()} | placed
    for o, why in few.items():
        reasons.setdefault(o, []).append(why)
    objects = sorted({*never, *off, *placed})
    return Diagnosis(scene.name, objects, reasons, [], message)


# a node that could fire a rule (`_firing_nodes`): type, xyz, quat, name, children it holds
Node = tuple[int, FloatArray, FloatArray, str, int]


def _unplaceable_words(names: list[str], placed: dict[int, list[str]], unexamined: int) -> str:
    """The message's part for `_unplaceable`: the first SHOWN objects, each with its two
    closest reasons, then how many more (a scene of many objects keeps a readable line)."""
    if not placed and not unexamined:
        return ""
    shown = [f"{names[o]} ({'; '.join(why[:2])})" for o, why in list(placed.items())[:SHOWN]]
    words = ""
    if placed:
        words = "; no rule can place these where they are: " + ", ".join(shown)
    if len(placed) > SHOWN:
        words += f", and {len(placed) - SHOWN} more (the diagnosis's reasons list all)"
    if unexamined:
        words += f"; {unexamined} object(s) not examined within the time limit"
    return words


def _unplaceable(
    grammar: Grammar, scene: Scene, objects: list[int], deadline: float
) -> tuple[dict[int, list[str]], int]:
    """Of `objects`, those no rule can place where they are, whatever the rest of the tree:
    every rule that could produce one (directly or through fixed rules) refuses its pose from
    every node that could fire it here — the root at its pose and the other objects, with the
    nodes fixed rules tie to them — each with its reasons, closest first (`_rule_failures`).
    An object some rule accepts is not named, nor one a latent node could place (its pose is
    unknown without a tree), nor one whose pose the grammar fixes (`_off_root` names those).
    Also how many objects `deadline` left unexamined."""
    blocks = [
        _node_block(grammar, int(t), x, q, f"{grammar.types[t].name} #{o}")
        for o, (t, x, q) in enumerate(zip(scene.types, scene.xyz, scene.quat, strict=True))
    ]
    root = _node_block(grammar, grammar.root, grammar.root_xyz, grammar.root_quat, "")
    named: dict[int, list[str]] = {}
    for k, o in enumerate(objects):
        if time.perf_counter() > deadline:
            return named, len(objects) - k
        if _fixed_pose(grammar, int(scene.types[o]), scene.xyz[o], scene.quat[o]) is not None:
            continue
        nodes: dict[tuple[Any, ...], Node] = {}  # one pose of one type is one node
        for d, block in [*enumerate(blocks), (-1, root)]:
            for key, node in block.items():
                if d != o:
                    nodes.setdefault(key, node)
        failures, placeable = _rule_failures(grammar, scene, o, list(nodes.values()))
        if failures and not placeable:
            named[o] = [why for _, why in failures]
    return named, 0


def _node_block(
    grammar: Grammar, t: int, x: FloatArray, q: FloatArray, name: str
) -> dict[tuple[Any, ...], Node]:
    """A node of type t at (x, q) and the nodes fixed rules tie to it above and below (a
    latent table top the root holds fixed), as nodes that could fire a rule when no tree is
    known, keyed by type and position.  Named `name` (its object), else by type and position."""
    block: dict[tuple[Any, ...], Node] = {}
    for vt, vx, vq in _fixed_ancestors(grammar, t, x, q):
        for ct, cx, cq in [(vt, vx, vq), *_fixed_descendants(grammar, vt, vx, vq)]:
            where = f"{grammar.types[ct].name} at ({cx[0]:.2f}, {cx[1]:.2f}, {cx[2]:.2f})"
            block.setdefault((int(ct), *np.round(cx, 6)), (int(ct), cx, cq, name or where, 0))
    return block


def _fixed_descendants(
    grammar: Grammar, t: int, x: FloatArray, q: FloatArray
) -> list[tuple[int, FloatArray, FloatArray]]:
    """(type, xyz, quat) of the nodes fixed rules tie below a node of type t at (x, q), as
    `_fixed_ancestors` goes up: they share its pose, so they are there whenever it is."""
    tb = grammar.tables
    todo, out = [(t, x, q)], []
    while todo and len(out) < 64:
        vt, vx, vq = todo.pop()
        for r in np.flatnonzero(tb.rule_parent == vt):
            if _rigid(grammar, int(r)):
                rule = grammar.rules[int(r)]
                cx = vx + quat_rotate(vq, rule.translation.point)
                child = (int(tb.rule_child[r]), cx, quat_multiply(vq, rule.rotation.point))
                out.append(child)
                todo.append(child)
    return out


SMALL_M, SMALL_DEG = 0.05, 10.0  # offsets a sensor's error could explain


def _without_root(grammar: Grammar, scene: Scene, names: list[str]) -> Diagnosis:
    """A scene without the root its grammar requires: no removal helps, so name the objects
    that lie where the root is (within what a sensor's error could explain): the root given
    another type is the likely story (a detector's wrong label keeps the pose)."""
    from ssgc.parse.parser import missing_root

    off = np.linalg.norm(scene.xyz - grammar.root_xyz, axis=1)
    turn = np.degrees(quat_angle(scene.quat, np.broadcast_to(grammar.root_quat, scene.quat.shape)))
    at = [int(o) for o in np.flatnonzero((off <= SMALL_M) & (turn <= SMALL_DEG))]
    assert grammar.required_root is not None
    root = grammar.types[grammar.required_root].name
    reasons = {
        o: [f"lies at the pose of the missing {root} ({100 * off[o]:.1f} cm, {turn[o]:.1f}° off)"]
        for o in at
    }
    message = missing_root(grammar, scene.name) + "; "
    if at:
        message += " and ".join(names[o] for o in at) + f" lies where the {root} is: "
        message += f"a {root} given another type?"
    else:
        message += f"no object lies where the {root} is"
    return Diagnosis(scene.name, at, reasons, [], message)


def _too_few(grammar: Grammar, scene: Scene) -> dict[int, str]:
    """The objects whose count law needs more than the scene has: a `repeat` type whose
    least count k > 0 needs k children that each make at least one object, while the scene's
    other objects of the types a child can make are fewer (no removal can help then: the
    diagnosis names the law instead)."""
    least = _least_objects(grammar)
    out = {}
    for o, t in enumerate(scene.types):
        node = grammar.types[t]
        if node.kind != Kind.REPEAT or node.count is None or not node.rules:
            continue
        k = int(np.argmax(np.asarray(node.count.probs) > 0))
        child = grammar.rules[node.rules[0]].child
        makes = _made_types(grammar, child)
        have = int(np.sum(np.isin(scene.types, makes))) - int(t in makes)
        if k > 0 and least[child] > 0 and have < k * least[child]:
            what = "none" if have == 0 else f"only {have} object(s) it could hold"
            out[o] = (
                f"{node.name} holds at least {k} {grammar.types[child].name} (its count law), "
                f"and the scene has {what}"
            )
    return out


def _least_objects(grammar: Grammar) -> IntArray:
    """Per type, the fewest observed objects a node of it makes (itself included): a fixed
    point from below, so a lower bound even for recursive types."""
    least = grammar.tables.type_observed.astype(np.int64)
    for _ in range(len(grammar.types)):
        new = np.array(
            [
                t.least_observed(
                    [(i, int(least[grammar.rules[r].child])) for i, r in enumerate(t.rules)]
                )
                for t in grammar.types
            ],
            np.int64,
        )
        if np.array_equal(new, least):
            break
        least = new
    return least


def _made_types(grammar: Grammar, t: int) -> list[int]:
    """The observed types a node of type t can make, itself included."""
    seen, todo = {t}, [t]
    while todo:
        for r in grammar.types[todo.pop()].rules:
            c = grammar.rules[r].child
            if c not in seen:
                seen.add(c)
                todo.append(c)
    return [c for c in seen if grammar.tables.type_observed[c]]


def _hint(grammar: Grammar, reasons: list[str]) -> str:
    """What in the grammar language would let such a scene parse, when the grammar lacks it:
    sensor noise for small offsets from exact placements, clutter for unknown objects."""
    spec = grammar.observation
    hints = []
    small = False
    for r in reasons:
        m = re.search(r"(pinned axis \w|fixed offset|fixed position) off by ([-+0-9.e]+) m", r)
        d = re.search(r"fixed rotation off by ([0-9.e+-]+)°", r)
        small |= bool(m and abs(float(m.group(2))) <= SMALL_M)
        small |= bool(d and float(d.group(1)) <= SMALL_DEG)
    if small and (spec is None or not spec.noise):
        hints.append(
            "poses from a sensor are never exact: an `observation: noise` section tolerates "
            "such offsets"
        )
    if any("never produces" in r for r in reasons) and (spec is None or spec.clutter is None):
        hints.append("an `observation: clutter` section lets objects stay unexplained")
    if not hints:
        return ""
    return " Hint: " + "; ".join(hints) + " (docs/grammar.md, section 9)."


def _without(scene: Scene, drop: list[int]) -> Scene:
    keep = np.setdiff1d(np.arange(len(scene)), drop)
    return Scene(
        scene.name,
        scene.types[keep],
        scene.xyz[keep],
        scene.quat[keep],
        metadata=tuple(scene.metadata[i] for i in keep) if scene.metadata else (),
    )


def _why_not(
    grammar: Grammar,
    scene: Scene,
    o: int,
    tree: Trees,
    kept: IntArray,
    parser: Any,
    drop: list[int],
) -> list[str]:
    """Why each rule that could produce object o fails from each node that could have fired
    it, closest candidates first: the nodes of the other objects' best tree, and the other
    removed objects (a plate removed with the spoon it lacks is the spoon's parent to try)."""
    t = int(scene.types[o])
    if parser.capacity[t] == 0:
        return [f"the grammar never produces a {grammar.types[t].name}"]
    nodes = _firing_nodes(grammar, scene, tree, kept, [d for d in drop if d != o])
    out, _ = _rule_failures(grammar, scene, o, nodes)
    fixed = _root_offset(grammar, scene, o)
    if fixed is not None:  # no rule can place it: the grammar fixes its pose at the root's
        return [fixed, *[s for _, s in out]]
    return [s for _, s in out] or [f"no rule produces a {grammar.types[t].name}"]


def _rule_failures(
    grammar: Grammar,
    scene: Scene,
    o: int,
    nodes: list[Node],
) -> tuple[list[tuple[float, str]], bool]:
    """Why each rule that could produce object o (directly or through fixed rules) fails from
    the two of `nodes` closest to it that could fire it, closest first, with their distances;
    and whether o could be placed after all: some rule and node accept its pose, or a rule has
    no node here to fire it (a latent parent, whose pose only a tree would tell)."""
    tb = grammar.tables
    t = int(scene.types[o])
    out: list[tuple[float, str]] = []
    placeable = False
    for vt, x, q in _fixed_ancestors(grammar, t, scene.xyz[o], scene.quat[o]):
        for r in np.flatnonzero(tb.rule_child == vt):
            if _rigid(grammar, int(r)):
                continue
            parents = [n for n in nodes if n[0] == tb.rule_parent[r]]
            rule = grammar.rule_name(int(r))
            if len(parents) == 0:
                placeable = True
                out.append(
                    (
                        np.inf,
                        f"{rule}: no {grammar.types[tb.rule_parent[r]].name} among "
                        "the other objects' tree to fire it",
                    )
                )
                continue
            rr = np.full(len(parents), r)
            px = np.array([n[1] for n in parents])
            pq = np.array([n[2] for n in parents])
            xs, qs = np.tile(x, (len(parents), 1)), np.tile(q, (len(parents), 1))
            lt = translation_log_density(grammar, rr, px, pq, xs)
            lr = rotation_log_density(grammar, rr, pq, qs)
            placeable |= bool(np.any(np.isfinite(lt) & np.isfinite(lr)))
            u = translation_coordinates(grammar, rr, px, pq, xs)
            dist = np.linalg.norm(xs - px, axis=1)
            for k in np.argsort(dist)[:2]:
                _, _, _, name, held = parents[k]
                what = _failure(grammar, int(r), u[k], lt[k], lr[k], pq[k], q, held)
                out.append((float(dist[k]), f"{rule} from {name}: {what}"))
    out.sort(key=lambda x: x[0])
    return out, placeable


def _firing_nodes(
    grammar: Grammar, scene: Scene, tree: Trees, kept: IntArray, others: list[int]
) -> list[tuple[int, FloatArray, FloatArray, str, int]]:
    """(type, xyz, quat, name, children held) of each node that could fire a rule: the
    nodes of the kept objects' tree (an object's node named as it, a latent one by its type
    and position), then the other removed objects and the nodes fixed rules tie to them."""
    out = []
    for i in range(len(tree)):
        same = np.flatnonzero(
            (scene.types[kept] == tree.type[i])
            & (np.linalg.norm(scene.xyz[kept] - tree.xyz[i], axis=1) < 1e-6)
        )
        x, y, z = tree.xyz[i]
        name = (
            f"{grammar.types[tree.type[i]].name} #{kept[same[0]]}"
            if len(same)
            else f"{grammar.types[tree.type[i]].name} at ({x:.2f}, {y:.2f}, {z:.2f})"
        )
        held = int(np.sum(tree.parent == i))
        out.append((int(tree.type[i]), tree.xyz[i], tree.quat[i], name, held))
    for d in others:
        name = f"{grammar.types[scene.types[d]].name} #{d}"
        for vt, x, q in _fixed_ancestors(grammar, int(scene.types[d]), scene.xyz[d], scene.quat[d]):
            out.append((int(vt), x, q, name, 0))
    return out


def _off_root(grammar: Grammar, scene: Scene) -> dict[int, str]:
    """The objects off the pose the grammar fixes for them (`_root_offset`), and by how much:
    when no removal lets the scene parse (the root is not implied when the grammar's root is
    `observation: clutter`'s `~scene`), they are still the likely cause."""
    out = {}
    for o in range(len(scene)):
        fixed = _fixed_pose(grammar, int(scene.types[o]), scene.xyz[o], scene.quat[o])
        if fixed is not None and (fixed[1] > POS_TOL or np.radians(fixed[2]) > ROT_TOL):
            out[o] = _fixed_offset_words(grammar, int(scene.types[o]), fixed)
    return out


def _fixed_pose(
    grammar: Grammar, t: int, xyz: FloatArray, quat: FloatArray
) -> tuple[FloatArray, float, float] | None:
    """Where the grammar fixes an object of type t at (xyz, quat) when it is the root or tied
    to the root by fixed rules (the bin under `observation: clutter`'s `~scene`): that
    position, and how far (m) and how much turned (°) the object is from that pose.  None
    when no chain of fixed rules leads from the root to it."""
    for vt, x, q in _fixed_ancestors(grammar, t, xyz, quat):
        if vt == grammar.root:  # (x, q): the root's pose, were the object where it is
            turn = quat_multiply(grammar.root_quat, quat_conjugate(q))
            want_x = grammar.root_xyz + quat_rotate(turn, xyz - x)
            angle = quat_angle(quat, quat_multiply(turn, quat))
            return want_x, float(np.linalg.norm(xyz - want_x)), float(np.degrees(angle))
    return None


def _root_offset(grammar: Grammar, scene: Scene, o: int) -> str | None:
    """Why object o cannot be where it is when the grammar fixes its pose (`_fixed_pose`):
    no rule places it, so how far it lies from that pose, worded as the fixed laws word
    theirs ("fixed rotation off by 3°"), so that `_hint` offers noise for a small offset."""
    fixed = _fixed_pose(grammar, int(scene.types[o]), scene.xyz[o], scene.quat[o])
    return None if fixed is None else _fixed_offset_words(grammar, int(scene.types[o]), fixed)


def _fixed_offset_words(grammar: Grammar, t: int, fixed: tuple[FloatArray, float, float]) -> str:
    """`_fixed_pose`'s answer for an object of type t, in words."""
    (x, y, z), off, angle = fixed
    what = "the grammar's root"
    if t != grammar.root:
        what = "tied to the grammar's root by fixed rules"
    where = f"{what}, fixed at ({x:.2f}, {y:.2f}, {z:.2f})"
    parts = [f"fixed position off by {off:.3g} m"] if off > POS_TOL else []
    parts += [f"fixed rotation off by {angle:.3g}°"] if np.radians(angle) > ROT_TOL else []
    return f"{where}: " + (", ".join(parts) if parts else "it lies there")


def _rigid(grammar: Grammar, r: int) -> bool:
    """A rule fixed in translation and rotation: its child moves with its parent."""
    rule = grammar.rules[r]
    return rule.translation.point is not None and rule.rotation.point is not None


def _fixed_ancestors(grammar: Grammar, t: int, x: FloatArray, q: FloatArray):  # type: ignore[no-untyped-def]
    """(type, xyz, quat) of the object and of every node that fixed rules would tie to it."""
    tb = grammar.tables
    todo, seen = [(t, x, q)], 0
    while todo and seen < 64:
        vt, vx, vq = todo.pop()
        seen += 1
        yield vt, vx, vq
        for r in np.flatnonzero(tb.rule_child == vt):
            if _rigid(grammar, int(r)):
                rule = grammar.rules[int(r)]
                pq = quat_multiply(vq, quat_conjugate(rule.rotation.point))
                px = vx - quat_rotate(pq, rule.translation.point)
                todo.append((int(tb.rule_parent[r]), px, pq))


def _failure(
    grammar: Grammar,
    r: int,
    u: FloatArray,
    lt: float,
    lr: float,
    pq: FloatArray,
    q: FloatArray,
    held: int,
) -> str:
    """Why rule r cannot place a child at rotation q from a parent (rotation pq, holding
    `held` children) that puts it at u in the rule's coordinates."""
    rule = grammar.rules[r]
    if not np.isfinite(lt):
        return rule.translation.describe_violation(u)
    if not np.isfinite(lr):
        rel = rotation_coordinates(grammar, np.array([r]), pq[None], q[None])[0]
        return rule.rotation.describe_violation(rel)
    t = grammar.types[rule.parent]
    if t.kind == Kind.REPEAT and t.count is not None and held >= t.count.largest:
        return f"its pose is possible, but {t.name} already holds its maximum of {held}"
    return (
        f"its pose is possible (log p {lt + lr:.3g}); the grammar's counts or structure "
        "cannot take it together with the rest"
    )
