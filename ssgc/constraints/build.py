"""The `constraints:` section of a grammar document → constraint objects, with every check.

Called once by `ssgc.compile.Compiler.run`; messages go through the compiler, so they are
located (file:line:col) like every other grammar error.  Besides names (types, frames), it
flags constraints that no tree can satisfy: count bounds outside what the grammar can
produce, boxes narrower than an object's keep-out disc, frames an object can lack.
"""

from __future__ import annotations

import sys
from functools import cache
from typing import Any

import numpy as np

from ssgc import dsl
from ssgc.constraints.base import Constraint, Loc, builder_for, pair_table, register, type_mask
from ssgc.constraints.penetration import NonPenetration
from ssgc.constraints.pose import Clearance, InsideBox, Upright
from ssgc.constraints.shapes import (
    Extents,
    ShapeError,
    bounding_radius,
    closed_surface,
    collision_shape,
    extents_of,
    geometry_origin,
    keep_out_radius,
    solid_of,
)
from ssgc.constraints.structural import Children, Count, LongestChain
from ssgc.ir import Kind, NodeType, Rule
from ssgc.tails import FLOATING, OUTSIDE, OVERLAP, Tail

MAX_STATES = 200_000  # feasibility of count bounds is checked only below this many states
AXIS = {"x": 0, "y": 1, "z": 2}


def build_constraints(
    compiler: Any,
    types: list[NodeType],
    rules: list[Rule],
    root: int | None,
    sound: bool,
    n_types: int,
    true: dict[int, int] | None = None,
) -> tuple[Constraint, ...]:
    """Lower and check every constraint.  `sound`: the grammar itself had no error, so its
    recursion is bounded and the can-never-hold checks may explore it.  `n_types`: how many
    types the compiled grammar has (more than `types` when its observation adds some, which
    no constraint names); the constraints' per-type tables cover them all.  `true`: {a root
    type the observation gives noise: its true node's type} (`observation.true_nodes`): a
    constraint that names the root is about the world, so it means that true node — its
    frame, its children, its pose (the root type is never a rule's child, so no other node
    has it; docs/constraints.md).  Names are checked on the grammar as written."""
    b = _Builder(compiler, types, rules, root if sound else None, n_types, true or {})
    out = []
    for name, spec in compiler.doc.constraints.items():
        c = b.build(name, spec, ("constraints", name))
        if c is not None:
            out.append(c)
    _check_together(compiler, out)
    return tuple(out)


def _check_together(compiler: Any, constraints: list[Constraint]) -> None:
    """Two range constraints on one number (the count of a type, the children of a type, the
    longest chain of a type) whose ranges do not meet can never hold together: rejection
    sampling then ran for ever without a word (`count: {min: 3}` with `count: {max: 2}`)."""
    seen: dict[tuple[Any, ...], tuple[str, int, int | None]] = {}
    for c in constraints:
        if isinstance(c, Count | LongestChain):
            key: tuple[Any, ...] = (c.word, c.type_id)
        elif isinstance(c, Children):
            key = (c.word, c.of, c.child)
        else:
            continue
        lo, hi = c.lo, c.hi  # type: ignore[attr-defined]
        if key in seen:
            first, first_lo, first_hi = seen[key]
            lo, hi = max(lo, first_lo), _least(hi, first_hi)
            if hi is not None and lo > hi:
                compiler.error(
                    c.path,
                    f"can never hold together with '{first}': their ranges of the same "
                    f"{c.word} meet nowhere (together, at least {lo} and at most {hi})",
                )
        seen[key] = (c.name if key not in seen else seen[key][0], lo, hi)


def _least(a: int | None, b: int | None) -> int | None:
    return b if a is None else a if b is None else min(a, b)


def _tail(spec: dsl.TailC | None, default: Tail) -> Tail:
    """The grammar's tail, or the sink default where it gives none (ssgc/tails.py)."""
    return default if spec is None else Tail(rate=spec.rate, mean=spec.mean)


class _Builder:
    def __init__(
        self,
        compiler: Any,
        types: list[NodeType],
        rules: list[Rule],
        root: int | None,
        n_types: int,
        true: dict[int, int],
    ):
        self.c = compiler
        self.types = types
        self.rules = rules
        self.root = root
        self.n = n_types  # the length of every per-type table
        self.true = true  # `true_nodes`

    def node(self, tid: int) -> int:
        """The type that nodes of the written type `tid` have in trees of the compiled grammar:
        for a root the observation gives noise, its true node's (`true_nodes`).  Names are
        checked on the grammar as written, where the root's rules are its own, so that the
        checks hold for the true node; the constraints' tables are indexed by this."""
        return self.true.get(tid, tid)

    def mask(self, ids: list[int]) -> Any:
        """The constraint's per-type mask of the written types `ids`."""
        return type_mask([self.node(t) for t in ids], self.n)

    # ----------------------------------------------------------------- names ---

    def type_id(self, name: str, loc: Loc, what: str = "type") -> int | None:
        tid = self.c.ids.get(name)
        if tid is None:
            self.c.unknown_type(loc, name, what)
        return tid

    def type_ids(self, names: list[str], loc: Loc) -> list[int] | None:
        known, ok = self.known_ids(names, loc)
        return known if ok else None

    def known_ids(self, names: list[str], loc: Loc) -> tuple[list[int], bool]:
        """The ids of the names that are types, and whether all are: a constraint with an
        unknown name is still checked on its known ones, so one run reports its other
        mistakes too (its frame, its box, its radii)."""
        ids = [self.type_id(n, (*loc, i)) for i, n in enumerate(names)]
        return [int(i) for i in ids if i is not None], all(i is not None for i in ids)

    def misshapen(self, t: int) -> bool:
        """Whether type `t`'s geometry has a shape error, said already: a check of its shape
        gives up without a follow-on error (`Compiler.misshapen`)."""
        return self.types[t].name in self.c.misshapen

    def at(self, loc: Loc, names: list[str], t: int) -> Loc:
        """Where type `t` is written in the constraint's list `names` at `loc`: a message
        about one type points at its name, not at the list."""
        name = self.types[t].name
        return (*loc, names.index(name)) if name in names else loc

    def frame(self, name: str, loc: Loc, listed: list[int]) -> int | bool | None:
        """None for the world, a type id, or False after an error."""
        if name == "world":
            return None
        tid = self.type_id(name, loc, "frame type")
        if tid is None:
            return False
        for t in listed:
            why = self.without_frame(t, tid)
            if why is not None:
                self.c.error(loc, why)
                return False
        return self.node(tid)

    def without_frame(self, t: int, frame: int) -> str | None:
        """Why a node of type `t` can occur with no `frame` node above it, or None.  Clutter
        objects (the observation's `clutter.rates`) hang under `~clutter`, below no type of
        the grammar: sampling drops every scene that has one, as it would any node without
        its frame.  The rules are followed only for a sound grammar (`reachable_avoiding`)."""
        what, where = self.types[t].name, self.types[frame].name
        lacks = "so it has no frame to be checked in"
        if self.clutter_most(what):
            return (
                f"a clutter '{what}' (observation.clutter.rates) has no '{where}' above it, {lacks}"
            )
        if self.root is None or not self.reachable_avoiding(t, frame):
            return None
        own = " (its frame is a proper ancestor, never itself)" if t == frame else ""
        return f"a '{what}' can occur without a '{where}' above it, {lacks}{own}"

    def reachable_avoiding(self, target: int, avoid: int) -> bool:
        """Can a `target` node occur with no `avoid` node among its proper ancestors?  A
        frame is the nearest proper ancestor of its type (`nearest_ancestor`): the root has
        none, and a type that is its own frame needs another of itself above it, so the
        node reached is never checked against `avoid`, only the nodes on the way to it."""
        assert self.root is not None
        if self.root == target:
            return True
        if self.root == avoid:
            return False
        seen, stack = {self.root}, [self.root]
        while stack:
            for rid in self.types[stack.pop()].rules:
                child = self.rules[rid].child
                if child == target:
                    return True
                if child != avoid and child not in seen:
                    seen.add(child)
                    stack.append(child)
        return False

    # ----------------------------------------------------------------- build ---

    def build(self, name: str, spec: Any, loc: Loc) -> Constraint | None:
        """The registered builder of the entry's one key (`ssgc.constraints.base.register`)."""
        word = next(iter(type(spec).model_fields))
        return builder_for(word)(self, name, getattr(spec, word), (*loc, word))

    def bounds(self, spec: Any, loc: Loc, possible: tuple[int, int] | None, what: str) -> bool:
        """min <= max, and [min, max] meets what the grammar can produce."""
        if spec.max is not None and spec.min > spec.max:
            self.c.error((*loc, "max"), f"max {spec.max} is below min {spec.min}")
            return False
        if possible is None:
            return True
        lo, hi = possible
        if spec.min > hi:
            self.c.error(
                (*loc, "min"),
                f"can never hold: {what} is at most {hi} in any tree, min is {spec.min}",
            )
            return False
        if spec.max is not None and spec.max < lo:
            self.c.error(
                (*loc, "max"),
                f"can never hold: {what} is at least {lo} in every tree, max is {spec.max}",
            )
            return False
        return True

    def count(self, name: str, s: dsl.CountC, loc: Loc) -> Constraint | None:
        t = self.type_id(s.type, (*loc, "type"))
        if t is None:
            return None
        possible = self.count_range(lambda tt: int(tt == t))
        if possible is not None:  # clutter objects of the type count too, as sampling does
            possible = (possible[0], possible[1] + self.clutter_most(s.type))
        if not self.bounds(s, loc, possible, f"the number of '{s.type}' nodes"):
            return None
        return Count(name, loc, type_id=self.node(t), lo=s.min, hi=s.max)

    def clutter_most(self, name: str) -> int:
        """The most clutter objects of type `name` a scene holds (the observation's `max`
        when `name` has a clutter rate): the grammar's rules never make them, yet a `count`
        counts them (a `count: {min: 2}` that clutter could meet was refused)."""
        observation = self.c.doc.observation
        clutter = None if observation is None else observation.clutter
        return clutter.max if clutter is not None and name in clutter.rates else 0

    def chain(self, name: str, s: dsl.ChainC, loc: Loc) -> Constraint | None:
        t = self.type_id(s.type, (*loc, "type"))
        if t is None:
            return None
        node = self.types[t]
        direct = any(self.rules[r].child == t for r in node.rules)
        top = (node.max_nesting or 1) if direct else 1
        present = self.count_range(lambda tt: int(tt == t))
        possible = None if present is None else (min(1, present[0]), top if present[1] else 0)
        if not self.bounds(s, loc, possible, f"the longest chain of '{s.type}'"):
            return None
        return LongestChain(name, loc, type_id=self.node(t), lo=s.min, hi=s.max)

    def children(self, name: str, s: dsl.ChildrenC, loc: Loc) -> Constraint | None:
        of = self.type_id(s.of, (*loc, "of"))
        child = self.type_id(s.child, (*loc, "child")) if s.child is not None else None
        if of is None or (s.child is not None and child is None):
            return None

        def produced(tt: int) -> tuple[int, int]:  # children of a node of type `of`
            return (0, 0) if tt != of else self.child_range(of, child)

        possible = self.count_range(lambda tt: 0, per_node=produced)
        what = f"the number of children of '{s.of}' nodes"
        if not self.bounds(s, loc, possible, what):
            return None
        nodes = self.count_range(lambda tt: int(tt == of))
        single = nodes is not None and nodes[1] <= 1
        child = None if child is None else self.node(child)
        return Children(name, loc, of=self.node(of), child=child, lo=s.min, hi=s.max, single=single)

    # ---------------------------------------------------------------- radii ---

    def radii(
        self, ids: list[int], given: dict[str, float], loc: Loc, needed: bool, names: list[str]
    ) -> Any:
        r = np.zeros(self.n)
        ok = True
        # with a misspelt name in `types` (said already), a radius for the type it meant is
        # not a second mistake
        all_known = {self.types[i].name for i in ids} >= set(names)
        for key, value in given.items():
            t = self.type_id(key, (*loc, "radius", key))
            if t is None:
                ok = False
            elif t not in ids:
                if all_known:
                    self.c.error(
                        (*loc, "radius", key), f"'{key}' is not one of this constraint's types"
                    )
                ok = False
            else:
                r[self.node(t)] = value
        if needed:
            for t in ids:
                tname = self.types[t].name
                if tname in given:
                    continue
                if self.misshapen(t):
                    ok = False
                    continue
                try:
                    r[self.node(t)] = keep_out_radius(self.types[t].geometry, self.c.base_dir)
                except ShapeError as exc:
                    self.c.error(
                        self.at((*loc, "types"), names, t),
                        f"no keep-out radius for '{tname}': {exc}; give it under `radius`",
                    )
                    ok = False
        return r if ok else None

    def exempt(self, pairs: list[list[str]], loc: Loc) -> Any:
        """The table of exempt pairs; None after reporting every unknown name in them."""
        ids = []
        ok = True
        for k, (a, b) in enumerate(pairs):
            ta = self.type_id(a, (*loc, "exempt", k, 0))
            tb = self.type_id(b, (*loc, "exempt", k, 1))
            if ta is None or tb is None:
                ok = False
                continue
            ids.append((self.node(ta), self.node(tb)))
        return pair_table(ids, self.n) if ok else None

    # ----------------------------------------------------------------- pose ---

    def inside_box(self, name: str, s: dsl.InsideBoxC, loc: Loc) -> Constraint | None:
        """Every independent mistake of the entry is reported (its names, frame, radii, box,
        geometry, tails) before it is given up; only the keep-out width, which needs both a
        sound box and sound radii, waits for them."""
        ids, known = self.known_ids(s.types, (*loc, "types"))
        frame = self.frame(s.frame, (*loc, "frame"), ids)
        r = self.radii(ids, s.radius, loc, s.keep_out, s.types)
        lo = np.array([np.nan if v is None else v for v in s.min])
        hi = np.array([np.nan if v is None else v for v in s.max])
        box = True
        for axis in range(3):
            if s.min[axis] is not None and s.max[axis] is not None and lo[axis] > hi[axis]:
                self.c.error((*loc, "max", axis), f"box max is below min on the {'xyz'[axis]} axis")
                box = False
        ok = known and frame is not False and r is not None and box
        fits = s.keep_out and r is not None and box
        if fits and not self.keep_out_fits(ids, r, lo, hi, loc, s.types):
            ok = False
        if not s.keep_out:
            r = np.zeros(self.n)
        shapes = self.extents(ids, loc, s.types) if s.geometry else None
        if s.geometry and shapes is None:
            ok = False
        for key in ("floating", "outside"):
            if getattr(s, key) is not None and not s.geometry:
                self.c.error(
                    (*loc, key),
                    f"`{key}` calibrates the floor and walls that only `geometry: true` "
                    "declares; add `geometry: true` or remove it",
                )
                ok = False
        if not ok:
            return None
        return InsideBox(
            name,
            loc,
            types=self.mask(ids),
            frame=frame,
            lo=lo,
            hi=hi,
            radius=r,
            shapes=shapes,
            floating=_tail(s.floating, FLOATING),
            outside=_tail(s.outside, OUTSIDE),
        )

    def keep_out_fits(
        self, ids: list[int], r: Any, lo: Any, hi: Any, loc: Loc, names: list[str]
    ) -> bool:
        """Whether every type's keep-out disc fits in the box's narrowest horizontal width;
        each type that does not is named."""
        width = np.nanmin(np.where(np.isnan(hi - lo), np.inf, hi - lo)[:2])
        fits = True
        for t in ids:
            across = 2 * r[self.node(t)]
            if across > width:
                self.c.error(
                    self.at((*loc, "types"), names, t),
                    f"can never hold: the box is {width:g} m wide, narrower than the "
                    f"keep-out disc of '{self.types[t].name}' ({across:g} m across)",
                )
                fits = False
        return fits

    def extents(self, ids: list[int], loc: Loc, names: list[str]) -> Extents | None:
        """The `Extents` of the types' geometries; every listed type must have one (each
        that has none is named)."""
        if any(self.misshapen(t) for t in ids):
            return None
        missing = [t for t in ids if self.types[t].geometry is None]
        for t in missing:
            where = self.at((*loc, "types"), names, t)
            self.c.error(where, f"'{self.types[t].name}' has no geometry to keep inside")
        if missing:
            return None
        try:
            geometries: list[Any] = [None] * self.n
            for t in ids:
                geometries[self.node(t)] = self.types[t].geometry
            return extents_of(geometries, self.c.base_dir)
        except ShapeError as exc:
            self.c.error((*loc, "types"), f"cannot bound the geometry: {exc}")
            return None

    def clearance(self, name: str, s: dsl.ClearanceC, loc: Loc) -> Constraint | None:
        ids = self.type_ids(s.types, (*loc, "types"))
        if ids is None:
            return None
        r = self.radii(ids, s.radius, loc, True, s.types)
        ex = self.exempt(s.exempt, loc)
        if r is None or ex is None:
            return None
        return Clearance(
            name,
            loc,
            types=self.mask(ids),
            radius=r,
            exempt=ex,
            exempt_ancestors=s.exempt_ancestors,
        )

    def upright(self, name: str, s: dsl.UprightC, loc: Loc) -> Constraint | None:
        ids, known = self.known_ids(s.types, (*loc, "types"))
        frame = self.frame(s.frame, (*loc, "frame"), ids)  # checked even after a bad name
        if not known or frame is False:
            return None
        return Upright(
            name,
            loc,
            types=self.mask(ids),
            axis=AXIS[s.axis],
            frame=frame,
            frame_axis=AXIS[s.frame_axis],
            max_angle=float(np.radians(s.max_angle_deg)),
        )

    def non_penetration(self, name: str, s: dsl.NonPenetrationC, loc: Loc) -> Constraint | None:
        """Every unknown name and every type without a shape is reported before giving up."""
        ids, known = self.known_ids(s.types, (*loc, "types"))
        ex = self.exempt(s.exempt, loc)
        ok = known and ex is not None
        shapes: list[Any] = [None] * self.n
        origins = [(0.0, 0.0, 0.0)] * self.n
        solids: list[Any] = [None] * self.n
        hollow = [False] * self.n
        surfaces: list[Any] = [None] * self.n
        r = np.zeros(self.n)
        for t in ids:
            k, geometry = self.node(t), self.types[t].geometry
            if self.misshapen(t):
                ok = False
                continue
            try:
                shapes[k] = collision_shape(geometry, self.c.base_dir)
                solids[k] = solid_of(geometry)
                hollow[k] = isinstance(geometry, dsl.RevolveG | dsl.TrayG | dsl.MeshG)
                surfaces[k] = closed_surface(geometry, self.c.base_dir)
                origins[k] = tuple(geometry_origin(geometry).tolist())
                r[k] = bounding_radius(geometry, self.c.base_dir)
            except ShapeError as exc:
                where = self.at((*loc, "types"), s.types, t)
                self.c.error(where, f"cannot check '{self.types[t].name}': {exc}")
                ok = False
        if not ok:
            return None
        sel = Clearance(
            name,
            loc,
            types=self.mask(ids),
            radius=r,
            exempt=ex,
            exempt_ancestors=s.exempt_ancestors,
        )
        return NonPenetration(
            name,
            loc,
            pairs_of=sel,
            shapes=tuple(shapes),
            origins=tuple(origins),
            solids=tuple(solids),
            hollow=tuple(hollow),
            surfaces=tuple(surfaces),
            gap=s.margin,
            tail=_tail(s.tail, OVERLAP),
        )

    # ------------------------------------------------- what the grammar can produce ---

    def child_range(self, of: int, child: int | None) -> tuple[int, int]:
        """Fewest and most children one node of type `of` can produce (of type `child`)."""
        node = self.types[of]
        hits = [int(child is None or self.rules[r].child == child) for r in node.rules]
        if node.kind == Kind.AND:
            return sum(hits), sum(hits)
        if node.kind == Kind.OR:
            live = [h for h, p in zip(hits, node.probs, strict=True) if p > 0]
            return min(live, default=0), max(live, default=0)
        if node.kind == Kind.INDEPENDENT:
            sure = sum(h for h, p in zip(hits, node.probs, strict=True) if p >= 1)
            return sure, sum(h for h, p in zip(hits, node.probs, strict=True) if p > 0)
        if node.kind == Kind.REPEAT and node.count is not None and hits and hits[0]:
            possible = np.flatnonzero(node.count.probs > 0)
            return int(possible.min()), int(possible.max())
        return 0, 0

    def count_range(self, own: Any, per_node: Any = None) -> tuple[int, int] | None:
        """Fewest and most of a per-node quantity summed over a tree (`own(type)` counts each
        node; `per_node(type)` a range per node), respecting `max_nesting`; None when the
        grammar has errors or too many nesting states to explore."""
        if self.root is None:
            return None
        bounded = [t.id for t in self.types if t.max_nesting is not None]
        slot = {t: i for i, t in enumerate(bounded)}
        limit = [self.types[t].max_nesting for t in bounded]
        states = [0]

        @cache
        def rng(t: int, nest: tuple[int, ...]) -> tuple[int, int]:
            states[0] += 1
            if states[0] > MAX_STATES:
                raise _TooBig
            lo = hi = own(t)
            if per_node is not None:
                a, b = per_node(t)
                lo, hi = lo + a, hi + b
            node = self.types[t]
            kids = []
            for rid in node.rules:
                c = self.rules[rid].child
                depth = nest
                if c in slot:
                    i = slot[c]
                    if nest[i] >= limit[i]:
                        kids.append(None)  # blocked
                        continue
                    depth = (*nest[:i], nest[i] + 1, *nest[i + 1 :])
                kids.append(rng(c, depth))
            live = [(k, p) for k, p in zip(kids, node.probs, strict=True) if k is not None]
            if node.kind == Kind.AND:
                lo += sum(k[0] for k, _ in live)
                hi += sum(k[1] for k, _ in live)
            elif node.kind == Kind.OR and live:
                lo += min(k[0] for k, p in live if p > 0) if any(p > 0 for _, p in live) else 0
                hi += max((k[1] for k, p in live if p > 0), default=0)
            elif node.kind == Kind.INDEPENDENT:
                lo += sum(k[0] for k, p in live if p >= 1)
                hi += sum(k[1] for k, p in live if p > 0)
            elif node.kind == Kind.REPEAT and live and node.count is not None:
                possible = np.flatnonzero(node.count.probs > 0)
                k = live[0][0]
                lo += int(possible.min()) * k[0]
                hi += int(possible.max()) * k[1]
            return lo, hi

        start = tuple(1 if t == self.root else 0 for t in bounded)
        old = sys.getrecursionlimit()
        try:
            sys.setrecursionlimit(max(old, 20_000))
            return rng(self.root, start)
        except (_TooBig, RecursionError):
            return None
        finally:
            sys.setrecursionlimit(old)


class _TooBig(Exception):
    pass


# The kinds ssgc has; a new kind registers its own builder the same way, in its own module.
@register("count")
def _count(b: _Builder, name: str, spec: Any, loc: Loc) -> Constraint | None:
    return b.count(name, spec, loc)


@register("longest_chain")
def _chain(b: _Builder, name: str, spec: Any, loc: Loc) -> Constraint | None:
    return b.chain(name, spec, loc)


@register("children")
def _children(b: _Builder, name: str, spec: Any, loc: Loc) -> Constraint | None:
    return b.children(name, spec, loc)


@register("inside_box")
def _inside_box(b: _Builder, name: str, spec: Any, loc: Loc) -> Constraint | None:
    return b.inside_box(name, spec, loc)


@register("clearance")
def _clearance(b: _Builder, name: str, spec: Any, loc: Loc) -> Constraint | None:
    return b.clearance(name, spec, loc)


@register("upright")
def _upright(b: _Builder, name: str, spec: Any, loc: Loc) -> Constraint | None:
    return b.upright(name, spec, loc)


@register("non_penetration")
def _non_penetration(b: _Builder, name: str, spec: Any, loc: Loc) -> Constraint | None:
    return b.non_penetration(name, spec, loc)
