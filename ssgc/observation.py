"""The observation model: sensor noise on observed poses, and clutter (issue 16, item 4).

The grammar of a document describes the true scene; a perception system reports each object's
pose with some error and adds objects no grammar explains.  A grammar's `observation` section
(docs/grammar.md, section 9) says how much, and this module turns the compiled grammar into
the grammar *of what is observed*, so that the sampler, the scorer and the parser need no
change:

- **Noise** (per observed type: a standard deviation of each position coordinate, and of the
  rotation angle about each axis).  Every rule between two observed poses gets the law of the
  *observed* relative pose: its own law convolved with the noise of both ends.  A Normal's
  covariance grows by the noise variance (a pinned axis becomes a Normal of the noise's
  spread), a fixed offset becomes a Normal about it, a Bingham's concentration c about each
  axis becomes c·k/(c + k) with k = 2/σ² the noise's own, a fixed rotation a Bingham about it
  and a full revolute joint a Bingham that keeps the turn free and the axis tilted by the
  noise.  The noise of the parent's end adds its rotation's lever arm (|mean offset|·σ_rot)
  to a parent-frame translation.  This is the exact marginal P(o | rest) for an edge whose
  parent pose is exact (the root, or a type without noise) and a first-order one otherwise
  (siblings' shared parent error is treated as independent).  A box translation and a
  revolute range short of the full circle are not widened (their convolutions are laws ssgc
  does not have); the compiler warns about each rule that noise reaches there.  An observed
  root with noise gets its own node at the grammar's root pose (type `~node:NAME`), of which
  the observed object is a noisy child.
- **Clutter**: a new root (type `~scene`, at the grammar's root pose) holds the grammar's root
  by a fixed rule and a set `~clutter` of at most `max` clutter objects: their number Poisson
  with the total rate (truncated), each one of a type chosen in proportion to its rate,
  uniform in a world box and in rotation.  An object the best parse puts there is
  *unexplained*.  Clutter types are the grammar's observed terminal types or new names.

Laws this module creates are `fixed` (`ssg fit` keeps them as written: it fits the laws of a
grammar without noise).  Scores of a grammar with noise are densities over the observed poses:
a pinned axis or a fixed offset with noise contributes a log-density instead of 0, so scores
compare between grammars with the same observation model only.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from math import lgamma, log
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from ssgc import dsl
from ssgc.distributions.bingham import Bingham
from ssgc.distributions.discrete import CountLaw
from ssgc.distributions.normal import Normal
from ssgc.distributions.uniform import UniformBox
from ssgc.ir import Grammar, Kind, Loc, NodeType, Rule
from ssgc.laws.base import MIN_WIDTH, Frame, PoseLaw, frozen
from ssgc.laws.counts import ProbsCount
from ssgc.laws.fixed import FixedRotation, FixedTranslation
from ssgc.laws.position_box import BoxTranslation, narrow_box
from ssgc.laws.position_normal import NormalTranslation, Spread
from ssgc.laws.rotation_bingham import MAX_CONCENTRATION, BinghamRotation, Form
from ssgc.laws.rotation_revolute import RevoluteRotation
from ssgc.laws.rotation_uniform import UniformRotation

if TYPE_CHECKING:
    from ssgc.tree import Trees

LOC: Loc = ("observation",)
SCENE, CLUTTER = "~scene", "~clutter"
NODE_PREFIX, CLUTTER_PREFIX = "~node:", "~clutter:"


class Report(Protocol):
    def error(self, loc: Loc, message: str) -> None: ...

    def warn(self, loc: Loc, message: str) -> None: ...


@dataclass(frozen=True)
class Noise:
    """One type's noise: σ of each position coordinate (m), of each rotation angle (rad)."""

    position: float = 0.0
    rotation: float = 0.0

    def __bool__(self) -> bool:
        return self.position > 0 or self.rotation > 0

    @staticmethod
    def worst(noises: list[Noise]) -> Noise:
        return Noise(
            max([n.position for n in noises], default=0.0),
            max([n.rotation for n in noises], default=0.0),
        )


@dataclass
class Observed:
    """The grammar's parts as the observation model leaves them."""

    types: list[NodeType]
    rules: list[Rule]
    root: int
    ids: dict[str, int]


def apply(
    spec: dsl.ObservationSpec | None,
    types: list[NodeType],
    rules: list[Rule],
    root: int,
    ids: dict[str, int],
    report: Report,
) -> Observed:
    """The grammar of observed scenes (module docstring); unchanged without `observation`."""
    out = Observed(list(types), list(rules), root, dict(ids))
    if spec is None:
        return out
    noise = _noise_of_types(spec, out, report)
    if any(noise.values()):
        _widen(out, noise, root, report)
        if noise.get(root):
            _observe_root(out, noise[root])
    if spec.clutter is not None:
        _add_clutter(spec.clutter, out, report)
    return out


def check(
    spec: dsl.ObservationSpec | None,
    types: list[NodeType],
    rules: list[Rule],
    ids: dict[str, int],
    report: Report,
) -> None:
    """Report the errors `apply` would, without building anything: for a grammar with errors
    elsewhere, whose types and rules cannot be turned into the grammar of observed scenes,
    but whose type names, observed flags and rule lists still tell what the section gets
    wrong (docs/grammar.md, section 6: one run reports what every stage can still check)."""
    if spec is None:
        return
    g = Observed(list(types), list(rules), -1, dict(ids))  # a copy: new clutter types go here
    _noise_of_types(spec, g, report)
    if spec.clutter is not None:
        _clutter_kinds(spec.clutter, g, report)


def true_nodes(g: Observed, types: list[NodeType], root: int | None) -> dict[int, int]:
    """{the root type: its true node's type} when `apply` gave an observed root noise (the
    root's rules moved to `~node:NAME`, the root type a noisy leaf under `~scene`), else {}:
    what a constraint naming the root refers to (`ssgc.constraints.build`)."""
    if root is None:
        return {}
    node = g.ids.get(NODE_PREFIX + types[root].name)
    if node is None or g.types[node].synthetic != "node":
        return {}
    return {root: node}


# ------------------------------------------------------------------------- noise ---


def _noise_of_types(spec: dsl.ObservationSpec, g: Observed, report: Report) -> dict[int, Noise]:
    """Each observed type's noise (its own entry, else `default`), checked and located."""
    default = spec.noise.get("default")
    own: dict[int, Noise] = {}
    for name, n in spec.noise.items():
        loc = (*LOC, "noise", name)
        if name == "default" and name not in g.ids:
            continue
        tid = g.ids.get(name)
        if tid is None or not g.types[tid].observed:
            what = "not a type of this grammar" if tid is None else "not an observed type"
            hint = _observed_like(name, g) if tid is None else ""
            report.error(loc, f"noise of '{name}': {what}{hint} (noise is on observed poses)")
            continue
        own[tid] = _noise(n, loc, report)
    base = _noise(default, (*LOC, "noise", "default"), report) if default else Noise()
    return {t.id: own.get(t.id, base) for t in g.types if t.observed}


def _observed_like(name: str, g: Observed) -> str:
    """A "did you mean" for a misspelt noise type, as a misspelt child or constraint type
    gets one: the closest observed type's name, if any is close."""
    import difflib

    observed = [t.name for t in g.types if t.observed]
    close = difflib.get_close_matches(name, observed, n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _noise(n: dsl.NoiseSpec, loc: Loc, report: Report) -> Noise:
    rotation = np.deg2rad(n.rotation_deg)
    if rotation > 0 and 2.0 / rotation**2 > MAX_CONCENTRATION:
        least = np.ceil(np.rad2deg(np.sqrt(2.0 / MAX_CONCENTRATION)) * 1e4) / 1e4  # 0.8103
        report.error(
            (*loc, "rotation_deg"),
            f"rotation noise must be 0 or at least {least:.4f}° (a Bingham concentration "
            f"of at most {MAX_CONCENTRATION:g}), got {n.rotation_deg:g}°",
        )
        rotation = 0.0
    return Noise(float(n.position), float(rotation))


def _is_fixed(rule: Rule) -> bool:
    return rule.translation.point is not None and rule.rotation.point is not None


def _components(n_types: int, joins: list[Rule]) -> list[int]:
    """Connected components of the types joined by `joins` (union-find): the types that
    share one pose, as far as type-level analysis tells."""
    parent = list(range(n_types))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for r in joins:
        parent[find(r.parent)] = find(r.child)
    return [find(a) for a in range(n_types)]


def _widen(g: Observed, noise: dict[int, Noise], root: int, report: Report) -> None:
    """Replace each rule between observed poses by the law of the observed relative pose.

    The root's own node is at the grammar's root pose exactly (`_observe_root`), so the root
    type's noise does not reach the rules it fires.  A rule whose box or revolute range the
    noise would widen but does not (`_kept_sharp`) is warned about."""
    n_types = len(g.types)
    fixed = [r for r in g.rules if _is_fixed(r)]
    into_noisy = [r for r in fixed if noise.get(r.child)]
    # A fixed rule into a noisy observed child keeps the child's pose tied to its parent's
    # unless the parent's pose is always an observed pose already: then two observed poses
    # are joined, and the noise must be on that rule.
    tied = _tied_types(g, {r.id for r in into_noisy}, root)
    loose = _inexact_blocks(
        g, fixed, into_noisy, {r.id for r in into_noisy if tied[r.parent]}, noise
    )
    comp = _components(n_types, [r for r in fixed if r.id not in loose])
    members: dict[int, list[Noise]] = {}
    for t, n in noise.items():
        if t != root:
            members.setdefault(comp[t], []).append(n)
    block = [Noise.worst(members.get(comp[t], [])) for t in range(n_types)]
    for r in g.rules:
        if _is_fixed(r) and r.id not in loose:
            continue
        child, parent = block[r.child], block[r.parent]
        if child or parent:
            _warn_kept_sharp(g, r, child, parent, report)
            g.rules[r.id] = dataclasses.replace(
                r,
                translation=_noisy_translation(r.translation, child, parent),
                rotation=_noisy_rotation(r.rotation, child, parent),
            )


def _tied_types(g: Observed, loose_candidates: set[int], root: int) -> list[bool]:
    """Which types always share their pose with an observed node or the root's (exact) pose:
    observed types, and types that every rule producing them places by a fixed rule from such
    a type (rules in `loose_candidates` do not count: they may get noise); the root type's
    own node needs no rule.  Type-level and sound: an `or` above two kinds of object does not
    make either kind tied to the other.  A latent root counted as untied lost the noise of an
    observed child at a fixed offset from it, and gave that noise to its other rules.

    The largest such set (start from every type and drop those that fail, until none does):
    a fixed rule from a type to itself keeps it tied, since every node of it is entered from
    a tied one first (a fixed `L -> L` made L untied, and its observed child lost its noise)."""
    into: dict[int, list[Rule]] = {}
    for r in g.rules:
        into.setdefault(r.child, []).append(r)
    tied = [True] * len(g.types)
    changed = True
    while changed:
        changed = False
        for t in range(len(g.types)):
            rules = into.get(t, [])
            now = g.types[t].observed or (
                (bool(rules) or t == root)
                and all(
                    _is_fixed(r) and r.id not in loose_candidates and tied[r.parent] for r in rules
                )
            )
            if tied[t] and not now:
                tied[t], changed = False, True
    return tied


def _inexact_blocks(
    g: Observed, fixed: list[Rule], into_noisy: list[Rule], loose: set[int], noise: dict[int, Noise]
) -> set[int]:
    """`loose` and the fixed rules into noisy observed children that must carry the noise
    themselves, though their parent is not tied, because their block would not be exact: it
    holds two observed nodes at once (their poses would stay exactly related: a lamp fixed on
    a latent base fixed on a table was infeasible 3 mm off), or an observed member with
    rotation noise lies at an offset within it (the noise on the rule that places the block
    swung the member on that lever: 8.7σ for 10° on 0.5 m).  Their parents become latent
    poses the parser places.  The alternatives of an `or` are one at a time: the three plate
    models under `TerminalPlate` in `sink` stay one block."""
    loose = set(loose)
    while True:
        joins = [r for r in fixed if r.id not in loose]
        comp = _components(len(g.types), joins)
        many = {comp[t] for t, n in enumerate(_observed_at_once(g, joins)) if n > 1}
        turned = {comp[t] for t, n in noise.items() if n.rotation > 0}
        lever = {comp[r.child] for r in joins if np.any(np.asarray(r.translation.point) != 0)}
        bad = many | (turned & lever)
        more = {r.id for r in into_noisy if r.id not in loose and comp[r.child] in bad}
        if not more:
            return loose
        loose |= more


def _observed_at_once(g: Observed, joins: list[Rule]) -> list[int]:
    """Per type, how many observed nodes a node of it holds together with the nodes `joins`
    (fixed rules) tie to it, capped at 2: itself if observed, plus its tied children's: all of
    an `and`'s and `independent`'s, the most of an `or`'s, and a `repeat`'s child times its
    largest count.  The least fixed point from 0, so a tied `or` that loops to itself counts
    what it ends in."""
    tied: dict[int, list[Rule]] = {}
    for r in joins:
        tied.setdefault(r.parent, []).append(r)
    count = [0] * len(g.types)
    changed = True
    while changed:
        changed = False
        for t, node in enumerate(g.types):
            kids = [count[r.child] for r in tied.get(t, [])]
            if node.kind == Kind.OR:
                below = max(kids, default=0)
            elif node.kind == Kind.REPEAT and node.count is not None:
                below = max(kids, default=0) * node.count.largest
            else:
                below = sum(kids)
            now = min(2, int(node.observed) + below)
            if now > count[t]:
                count[t], changed = now, True
    return count


def _position_variance(law: PoseLaw, child: Noise, parent: Noise) -> float:
    """The noise variance of each coordinate of the relative position `law` places."""
    if law.frame == Frame.WORLD:
        var = child.position**2
    else:
        var = child.position**2 + parent.position**2
    if law.frame == Frame.PARENT and isinstance(law, NormalTranslation | FixedTranslation):
        var += (float(np.linalg.norm(law.offset)) * parent.rotation) ** 2
    return var


def _rotation_variance(law: PoseLaw, child: Noise, parent: Noise) -> float:
    """The noise variance of each angle of the relative rotation `law` places."""
    return child.rotation**2 + (parent.rotation**2 if law.frame != Frame.WORLD else 0.0)


def _kept_sharp(r: Rule, child: Noise, parent: Noise) -> list[str]:
    """The parts of rule `r` that noise reaches but does not widen: a box translation and a
    revolute range keep their edges (`_noisy_translation`, `_noisy_rotation`).

    Widening them exactly would take a new law, a box convolved with a Normal (per axis a
    difference of two normal CDFs), which the parser would have to place latent nodes by and
    bound; ssgc has none, so such a rule places an observed object only inside its range (to
    1e-6 m or rad), with noise as without, and `ssg validate` says so (docs/grammar.md 9)."""
    parts = []
    t, q = r.translation, r.rotation
    if isinstance(t, BoxTranslation) and _position_variance(t, child, parent) > 0:
        parts.append("box translation")
    if (
        isinstance(q, RevoluteRotation)
        and not q.revolute.is_full_circle
        and _rotation_variance(q, child, parent) > 0
    ):
        parts.append("revolute range")
    return parts


def _warn_kept_sharp(g: Observed, r: Rule, child: Noise, parent: Noise, report: Report) -> None:
    """One warning for a rule whose box or revolute range noise does not widen, at the first
    of them."""
    parts = _kept_sharp(r, child, parent)
    if not parts:
        return
    at = r.translation.path if parts[0] == "box translation" else r.rotation.path
    them = "them" if len(parts) > 1 else "it"
    report.warn(
        at,
        f"noise does not widen this rule's {' and '.join(parts)}: it places {_placed(g, r)} "
        f"only within {them} (to 1e-6 m, 1e-6 rad), as without noise (docs/grammar.md, "
        "section 9)",
    )


def _placed(g: Observed, r: Rule) -> str:
    """What rule `r` places, in a warning's words: a latent child is named as such (it was
    called "an observed Slot"), since the noise reaches it from the observed nodes it holds."""
    child = g.types[r.child]
    if child.observed:
        return f"an observed {child.name}"
    return f"a {child.name}, whose observed nodes are noisy,"


def _noisy_translation(law: PoseLaw, child: Noise, parent: Noise) -> PoseLaw:
    """`law` convolved with the position noise of the relative pose it places."""
    var = _position_variance(law, child, parent)
    if var <= 0:
        return law
    if isinstance(law, FixedTranslation):
        cov = np.zeros((3, 3))
        key, spread = "parent_normal_offset", Spread.ISOTROPIC
    elif isinstance(law, NormalTranslation):
        cov = np.zeros((3, 3))
        free = np.flatnonzero(law.free)
        cov[np.ix_(free, free)] = law.normal.cov
        key, spread = law.key, law.spread
    else:  # a box is a support, uniform: its edges stay sharp (docs/grammar.md, section 9)
        return law
    return NormalTranslation(
        key=key,
        frame=law.frame,
        path=law.path,
        fixed=True,
        offset=law.offset,
        free=frozen(np.ones(3, bool)),
        normal=Normal(np.asarray(law.offset, float), cov + var * np.eye(3)),
        spread=spread,
    )


def _noisy_rotation(law: PoseLaw, child: Noise, parent: Noise) -> PoseLaw:
    """`law` with its concentration combined with the rotation noise's (module docstring)."""
    var = _rotation_variance(law, child, parent)
    if var <= 0 or isinstance(law, UniformRotation):
        return law
    k = 2.0 / var  # the concentration of a Bingham whose angle about an axis has variance var
    if isinstance(law, FixedRotation):
        bingham = Bingham.from_mode(law.offset, min(k, MAX_CONCENTRATION))
        key = "parent_bingham"
    elif isinstance(law, BinghamRotation):
        c = np.asarray(law.bingham.concentration, float)
        combined = np.minimum(c * k / (c + k), MAX_CONCENTRATION)
        bingham, key = Bingham(law.bingham.M, -combined), law.key
    elif isinstance(law, RevoluteRotation) and law.revolute.is_full_circle:
        bingham, key = _revolute_bingham(law.axis, min(k, MAX_CONCENTRATION)), "parent_bingham"
    else:  # a revolute range keeps its axis exact
        return law
    return BinghamRotation(
        key=key, frame=law.frame, path=law.path, fixed=True, bingham=bingham, form=Form.RAW
    )


def _revolute_bingham(axis: np.ndarray, k: float) -> Bingham:
    """A Bingham free along the turns about `axis` ({(cos φ/2, sin φ/2 · axis)}, a plane of
    quaternions) and of concentration k across it: the axis tilts by the noise."""
    plane = np.zeros((4, 2))
    plane[0, 0] = 1.0
    plane[1:, 1] = axis / np.linalg.norm(axis)
    full, _ = np.linalg.qr(np.hstack([plane, np.eye(4)]))
    m = np.column_stack([plane, full[:, 2:4]])
    return Bingham(m, [0.0, 0.0, -k, -k])


def _observe_root(g: Observed, noise: Noise) -> None:
    """An observed root with noise: its rules move to its own node `~node:NAME` at the root
    pose, and the observed object is a noisy child of that node (under a new root)."""
    old = g.types[g.root]
    node = _new_type(g, NODE_PREFIX + old.name, "node", old.kind, old.rules, old.probs)
    node = dataclasses.replace(node, count=old.count, fixed=old.fixed, path=old.path)
    g.types[node.id] = node
    for rid in old.rules:
        g.rules[rid] = dataclasses.replace(g.rules[rid], parent=node.id)
    g.types[old.id] = dataclasses.replace(
        old, kind=Kind.TERMINAL, rules=(), probs=frozen(np.zeros(0)), count=None
    )
    scene = _scene_root(g, hold=False)
    _add_rule(g, scene, node.id, _same_t(), _same_r())
    exact = Noise()
    _add_rule(
        g,
        scene,
        old.id,
        _noisy_translation(_same_t(), noise, exact),
        _noisy_rotation(_same_r(), noise, exact),
    )


# ----------------------------------------------------------------------- clutter ---


def _clutter_kinds(spec: dsl.ClutterSpec, g: Observed, report: Report) -> list[int] | None:
    """The type of each clutter rate (new types for new names), None after an error: the
    region and every rate are checked, so that one run reports all their errors."""
    loc = (*LOC, "clutter")
    lo, hi = np.asarray(spec.region.min, float), np.asarray(spec.region.max, float)
    ok = not np.any(hi <= lo)
    if not ok:
        report.error((*loc, "region", "max"), "the clutter region needs max > min on every axis")
    elif np.any(hi - lo < MIN_WIDTH):  # a box: its faces have the same tolerance
        i = int(np.argmax(hi - lo < MIN_WIDTH))
        report.error((*loc, "region", "max", i), narrow_box(float(hi[i] - lo[i]), "xyz"[i]))
        ok = False
    kinds: list[int] = []
    for name, _rate in spec.rates.items():
        tid = _clutter_type(name, g, (*loc, "rates", name), report)
        if tid is not None:
            kinds.append(tid)
    return kinds if ok and len(kinds) == len(spec.rates) else None


def _add_clutter(spec: dsl.ClutterSpec, g: Observed, report: Report) -> None:
    """The set `~clutter` under the scene root (module docstring)."""
    loc = (*LOC, "clutter")
    kinds = _clutter_kinds(spec, g, report)
    if kinds is None:
        return
    lo, hi = np.asarray(spec.region.min, float), np.asarray(spec.region.max, float)
    rates = np.array(list(spec.rates.values()), float)
    total = float(rates.sum())
    counts = np.arange(spec.max + 1)
    log_poisson = counts * log(total) - np.array([lgamma(n + 1) for n in counts])
    probs = np.exp(log_poisson - log_poisson.max())
    count = ProbsCount(law=CountLaw(probs / probs.sum()), path=(*loc, "max"))
    scene = _scene_root(g)
    one = _new_type(g, CLUTTER_PREFIX + "object", "clutter", Kind.OR, (), rates / total)
    for tid in kinds:
        _add_rule(g, one.id, tid, _same_t(), _same_r())
    clutter = _new_type(g, CLUTTER, "clutter", Kind.REPEAT, (), np.ones(0))
    g.types[clutter.id] = dataclasses.replace(clutter, count=count)
    box = BoxTranslation(
        key="world_box",
        frame=Frame.WORLD,
        path=(*loc, "region"),
        fixed=True,
        box=UniformBox(lo, hi),
    )
    uniform = UniformRotation(key="uniform", frame=Frame.WORLD, path=(*loc, "region"), fixed=True)
    _add_rule(g, clutter.id, one.id, box, uniform)
    _add_rule(g, scene, clutter.id, _same_t(), _same_r())


def _clutter_type(name: str, g: Observed, loc: Loc, report: Report) -> int | None:
    """The type a clutter rate names: an observed terminal type, or a new one."""
    tid = g.ids.get(name)
    if tid is None:
        return _new_type(g, name, "", Kind.TERMINAL, (), np.zeros(0), observed=True).id
    t = g.types[tid]
    if not t.observed or t.rules:
        what = "is not observed" if not t.observed else "has rules of its own"
        report.error(loc, f"clutter of type '{name}': the type {what}; clutter objects are leaves")
        return None
    return tid


# ----------------------------------------------------------------------- helpers ---


def _scene_root(g: Observed, hold: bool = True) -> int:
    """The `~scene` root (made on first use), holding the grammar's root by a fixed rule
    (unless not `hold`: an observed root with noise is held by a noisy rule instead)."""
    if SCENE in g.ids:
        return g.ids[SCENE]
    old = g.root
    scene = _new_type(g, SCENE, "scene", Kind.AND, (), np.ones(0))
    g.root = scene.id
    if hold:
        _add_rule(g, scene.id, old, _same_t(), _same_r())
    return scene.id


def _new_type(
    g: Observed,
    name: str,
    role: str,
    kind: Kind,
    rules: tuple[int, ...],
    probs: np.ndarray,
    observed: bool = False,
) -> NodeType:
    t = NodeType(
        id=len(g.types),
        name=name,
        kind=kind,
        observed=observed,
        rules=tuple(rules),
        probs=frozen(probs),
        fixed=True,
        path=LOC,
        synthetic=role,
    )
    g.types.append(t)
    g.ids[name] = t.id
    return t


def _add_rule(g: Observed, parent: int, child: int, t: PoseLaw, r: PoseLaw) -> None:
    p = g.types[parent]
    rule = Rule(len(g.rules), parent, len(p.rules), child, t, r, LOC)  # type: ignore[arg-type]
    g.rules.append(rule)
    probs = p.probs
    if p.kind in (Kind.AND, Kind.REPEAT):
        probs = np.ones(len(p.rules) + 1)
    g.types[parent] = dataclasses.replace(p, rules=(*p.rules, rule.id), probs=frozen(probs))


def _same_t() -> FixedTranslation:
    return FixedTranslation(key="same", frame=Frame.PARENT, path=LOC, offset=frozen(np.zeros(3)))


def _same_r() -> FixedRotation:
    return FixedRotation(
        key="same", frame=Frame.PARENT, path=LOC, offset=frozen([1.0, 0.0, 0.0, 0.0])
    )


# -------------------------------------------------------------------- reading trees ---


def clutter_nodes(grammar: Grammar, tree: Trees) -> NDArray[np.bool_]:
    """Which nodes of a tree are clutter objects (placed by the clutter set)."""
    role = np.array([t.synthetic for t in grammar.types])
    parent_type = tree.type[np.maximum(tree.parent, 0)]
    return (
        (tree.parent >= 0)
        & (role[parent_type] == "clutter")
        & grammar.tables.type_observed[tree.type]
    )
