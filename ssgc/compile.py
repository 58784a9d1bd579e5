"""DSL → IR: every semantic check of a grammar, each with a located message.

`load_grammar(path)` is the one entry point the rest of the program uses: read, validate the
shape with pydantic, then `Compiler` checks what needs the whole document and lowers it to the
immutable `ssgc.ir.Grammar`.  All problems found are reported together; warnings (unreachable
types, bounds with no effect) travel with the compiled grammar.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from ssgc import dsl
from ssgc.distributions.bingham import Bingham
from ssgc.distributions.discrete import CountLaw
from ssgc.distributions.normal import Normal
from ssgc.distributions.uniform import UniformBox, UniformRevolute
from ssgc.errors import Diagnostic, GrammarError, SsgError, one_line
from ssgc.geometry import IDENTITY_QUAT, quat_canonical, rpy_to_quat
from ssgc.ir import (
    Grammar,
    Kind,
    Loc,
    NodeType,
    RKind,
    RotationPart,
    Rule,
    TKind,
    TranslationPart,
    build_tables,
)
from ssgc.yamlio import (
    MAX_GRAMMAR_BYTES,
    SourceMap,
    load_located,
    read_text,
    validation_diagnostics,
)

MAX_CONCENTRATION = 1e4
QUAT_NORM_TOL = 1e-3
ORTHOGONALITY_TOL = 1e-6
MAX_CYCLES_REPORTED = 20  # a grammar with more unbounded cycles gets the first ones
MAX_SUGGESTIONS = 50  # "did you mean" for the first unknown type names only
AXES = {"x": 0, "y": 1, "z": 2}


def load_grammar(path: str | Path, allow_outside: bool = False) -> Grammar:
    """Read, validate and compile a grammar file; raises `GrammarError` on any mistake.

    Files the grammar names (meshes, models) must lie in the grammar file's directory unless
    `allow_outside`: a grammar from elsewhere cannot point ssgc at arbitrary files.
    """
    path = Path(path)
    try:
        text = read_text(path, MAX_GRAMMAR_BYTES, "grammar file")
    except GrammarError:
        raise
    except SsgError as exc:  # not found, not UTF-8, NUL bytes: still a grammar error
        raise GrammarError(exc.diagnostics) from None
    return compile_text(text, str(path), base_dir=path.parent, allow_outside=allow_outside)


def compile_text(
    text: str,
    file: str = "<grammar>",
    base_dir: Path | None = None,
    allow_outside: bool = False,
) -> Grammar:
    """Compile grammar text; file names in it are relative to `base_dir` (see `load_grammar`).

    Without `base_dir` only the spelling of a file name is checked (absolute, or `..` out).
    """
    try:
        data, source = load_located(text, file)
    except GrammarError:
        raise
    except Exception as exc:  # SsgError from the loader: re-type it as a grammar error
        diagnostics = getattr(exc, "diagnostics", None)
        if diagnostics is None:
            raise
        raise GrammarError(diagnostics) from None
    if not isinstance(data, dict):
        names = {
            "list": "a list",
            "str": "a string",
            "int": "a number",
            "float": "a number",
            "bool": "true or false",
        }
        got = "an empty file" if data is None else names.get(type(data).__name__, "a scalar")
        raise GrammarError([source.diagnostic((), f"expected a grammar mapping, got {got}")])
    try:
        doc = dsl.GrammarDoc.model_validate(data)
    except ValidationError as exc:
        raise GrammarError(validation_diagnostics(exc, source)) from None
    return Compiler(doc, source, base_dir, allow_outside).run()


class Compiler:
    """Checks one validated document and lowers it; collects every diagnostic it finds."""

    def __init__(
        self,
        doc: dsl.GrammarDoc,
        source: SourceMap,
        base_dir: Path | None = None,
        allow_outside: bool = False,
    ) -> None:
        self.doc = doc
        self.source = source
        self.base_dir = base_dir
        self.allow_outside = allow_outside
        self.errors: list[Diagnostic] = []
        self.warnings: list[Diagnostic] = []
        self.names = list(doc.types)
        self.ids = {name: i for i, name in enumerate(self.names)}
        self.suggestions = 0

    # ---------------------------------------------------------------- diagnostics ---

    def error(self, loc: Loc, message: str) -> None:
        self.errors.append(self.source.diagnostic(loc, message))

    def warn(self, loc: Loc, message: str) -> None:
        self.warnings.append(self.source.diagnostic(loc, message, "warning"))

    def unknown_type(self, loc: Loc, name: str, what: str) -> None:
        # Suggestions cost a comparison with every type: a few are enough (no quadratic time
        # for a generated file with thousands of misspelt names).
        self.suggestions += 1
        close = (
            difflib.get_close_matches(name, self.names, n=1)
            if self.suggestions <= MAX_SUGGESTIONS
            else []
        )
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        self.error(loc, f"{what} '{name}' is not a type of this grammar{hint}")

    # ----------------------------------------------------------------------- run ---

    def run(self) -> Grammar:
        if one_line(self.doc.grammar) != self.doc.grammar:  # it is printed, and names files
            self.error(("grammar",), "the grammar name must be one line of printable text")
        root_spec = self.doc.root_spec
        root_loc: Loc = ("root", "type") if isinstance(self.doc.root, dsl.Root) else ("root",)
        if root_spec.type not in self.ids:
            self.unknown_type(root_loc, root_spec.type, "root type")
        root_quat = self.orientation(root_spec.pose, ("root", "pose"))
        rules: list[Rule] = []
        types = [self.node_type(name, spec, rules) for name, spec in self.doc.types.items()]
        self.check_root_not_produced(rules, root_spec.type)
        self.check_labels(types)
        self.check_files(types)
        if not self.errors and root_spec.type in self.ids:
            self.check_recursion(types, rules)
            self.check_reachable(types, rules, self.ids[root_spec.type])
        if self.errors:
            raise GrammarError(self.errors + self.warnings)
        types_t, rules_t = tuple(types), tuple(rules)
        return Grammar(
            name=self.doc.grammar,
            file=self.source.file,
            types=types_t,
            rules=rules_t,
            root=self.ids[root_spec.type],
            root_xyz=_frozen(root_spec.pose.xyz),
            root_quat=_frozen(root_quat),
            tables=build_tables(types_t, rules_t),
            warnings=tuple(self.warnings),
            type_ids=dict(self.ids),
        )

    # ----------------------------------------------------------------- node types ---

    def node_type(self, name: str, spec: dsl.NodeType, rules: list[Rule]) -> NodeType:
        tid = self.ids[name]
        loc: Loc = ("types", name)
        kind, key, rule_specs = _kind_of(spec)
        if kind in (Kind.AND, Kind.OR, Kind.INDEPENDENT) and not rule_specs:
            self.error((*loc, key), f"an `{key}` needs at least one rule")
        for field, word in (
            ("and_", "and"),
            ("or_", "or"),
            ("independent", "independent"),
            ("repeat", "repeat"),
        ):
            # `and:` with nothing after it is null, which would silently make a terminal type
            if field in spec.model_fields_set and getattr(spec, field) is None:
                self.error(
                    (*loc, word),
                    f"`{word}` is empty: give its rules, or remove the key for a terminal type",
                )
        rule_locs: list[Loc] = (
            [(*loc, "repeat", "rule")]
            if kind == Kind.REPEAT
            else [(*loc, key, i) for i in range(len(rule_specs))]
        )
        first = len(rules)
        for index, (rspec, rloc) in enumerate(zip(rule_specs, rule_locs, strict=True)):
            rule = self.rule(len(rules), tid, index, rspec, rloc)
            if rule is not None:
                rules.append(rule)
        probs = self.rule_probs(kind, key, rule_specs, rule_locs, loc)
        count = self.count_law(spec.repeat, (*loc, "repeat", "count")) if spec.repeat else None
        count_family, count_start = "", 0
        if spec.repeat is not None:
            geometric = isinstance(spec.repeat.count, dsl.GeometricCountSpec)
            count_family = "geometric" if geometric else "probs"
            count_start = spec.repeat.count.geometric.start if geometric else 0
        if spec.labels and not spec.observed:
            self.error(
                (*loc, "labels"), "labels name dataset objects, so the type must be observed"
            )
        return NodeType(
            id=tid,
            name=name,
            kind=kind,
            observed=spec.observed,
            rules=tuple(range(first, len(rules))),
            probs=_frozen(probs),
            count=count,
            max_nesting=spec.max_nesting,
            geometry=spec.geometry,
            model=spec.model,
            body=spec.body,
            labels=tuple(spec.labels),
            fixed=spec.fixed,
            path=loc,
            count_family=count_family,
            count_start=count_start,
        )

    def rule_probs(
        self, kind: Kind, key: str, specs: list[dsl.Rule], locs: list[Loc], loc: Loc
    ) -> NDArray[np.float64]:
        given = [r.p is not None for r in specs]
        if kind in (Kind.AND, Kind.REPEAT):
            for spec, rloc in zip(specs, locs, strict=True):
                if spec.p is not None:
                    self.error((*rloc, "p"), f"`p` has no meaning in `{key}` (every rule fires)")
            return np.ones(len(specs))
        if kind == Kind.INDEPENDENT:
            for spec, rloc in zip(specs, locs, strict=True):
                if spec.p is None:
                    self.error(rloc, "every rule of `independent` needs its probability `p`")
                elif spec.p > 1:
                    self.error(
                        (*rloc, "p"),
                        f"`p` of an `independent` rule is a probability in [0, 1], got {spec.p:g}",
                    )
            return np.array([r.p if r.p is not None else 0.0 for r in specs])
        if kind == Kind.OR and specs:
            if any(given) and not all(given):
                missing = locs[given.index(False)]
                self.error(
                    missing, "give `p` for every rule of an `or`, or for none (equal weights)"
                )
                return np.full(len(specs), 1.0 / len(specs))
            weights = np.array([r.p for r in specs]) if all(given) else np.ones(len(specs))
            if weights.sum() <= 0:
                self.error((*loc, key), "the weights `p` of an `or` sum to zero")
                return np.full(len(specs), 1.0 / len(specs))
            return weights / weights.sum()
        return np.zeros(0)

    def count_law(self, spec: dsl.Repeat, loc: Loc) -> CountLaw | None:
        count = spec.count
        try:
            if isinstance(count, dsl.GeometricCountSpec):
                g = count.geometric
                if g.start > g.max:
                    self.error((*loc, "geometric", "start"), f"start {g.start} exceeds max {g.max}")
                    return None
                return CountLaw.geometric(g.p, g.max, g.start)
            if sum(count.probs) <= 0:
                self.error((*loc, "probs"), "count probabilities sum to zero")
                return None
            return CountLaw(np.asarray(count.probs, float))
        except ValueError as exc:
            self.error(loc, str(exc))
            return None

    # ---------------------------------------------------------------------- rules ---

    def rule(self, rid: int, parent: int, index: int, spec: dsl.Rule, loc: Loc) -> Rule | None:
        if spec.child not in self.ids:
            self.unknown_type((*loc, "child"), spec.child, "child type")
            return None
        translation = self.translation(spec.translation, (*loc, "translation"))
        rotation = self.rotation(spec.rotation, (*loc, "rotation"))
        if translation is None or rotation is None:
            return None
        return Rule(rid, parent, index, self.ids[spec.child], translation, rotation, loc)

    def translation(self, spec: object, loc: Loc) -> TranslationPart | None:
        zero, all_free = np.zeros(3), np.ones(3, bool)
        if spec == "same":
            return TranslationPart(TKind.FIXED, _frozen(zero), _frozen(~all_free), path=loc)
        if isinstance(spec, dsl.OffsetT):
            return TranslationPart(TKind.FIXED, _frozen(spec.offset), _frozen(~all_free), path=loc)
        for cls, kind, key in (
            (dsl.WorldNormalT, TKind.WORLD_NORMAL, "world_normal"),
            (dsl.WorldNormalOffsetT, TKind.WORLD_NORMAL_OFFSET, "world_normal_offset"),
            (dsl.ParentNormalOffsetT, TKind.PARENT_NORMAL_OFFSET, "parent_normal_offset"),
        ):
            if isinstance(spec, cls):
                return self.normal_part(kind, getattr(spec, key), (*loc, key))
        for cls, kind, key in (
            (dsl.WorldBoxT, TKind.WORLD_BOX, "world_box"),
            (dsl.WorldBoxOffsetT, TKind.WORLD_BOX_OFFSET, "world_box_offset"),
        ):
            if isinstance(spec, cls):
                return self.box_part(kind, getattr(spec, key), (*loc, key))
        raise AssertionError(f"unhandled translation {spec!r}")  # pydantic guarantees the variants

    def normal_part(self, kind: TKind, p: dsl.NormalParams, loc: Loc) -> TranslationPart | None:
        free = np.ones(3, bool)
        for axis in p.pin:
            free[AXES[axis]] = False
        if not free.any():
            self.error((*loc, "pin"), "all three axes are pinned; use `offset` for a fixed offset")
            return None
        if p.covariance is not None:
            cov = np.asarray(p.covariance, float)
            if not np.allclose(cov, cov.T, rtol=0, atol=1e-12 * max(1.0, np.abs(cov).max())):
                self.error((*loc, "covariance"), "covariance must be symmetric")
                return None
            sub = cov[np.ix_(free, free)]
            try:
                with np.errstate(all="ignore"):  # huge entries overflow: NaN fails below
                    eig = np.linalg.eigvalsh(sub)
            except np.linalg.LinAlgError:
                eig = np.array([np.nan])
            if not np.all(eig > 0):
                self.error((*loc, "covariance"), "covariance must be positive definite")
                return None
        else:
            var = np.broadcast_to(np.asarray(p.variance, float), (3,))
            bad = (var < 0) | (free & (var == 0))  # zero is fine only on a pinned axis
            for i in np.flatnonzero(bad):
                where = (
                    (*loc, "variance", int(i))
                    if isinstance(p.variance, list)
                    else (*loc, "variance")
                )
                self.error(where, f"variance must be positive, got {var[i]:g} ({'xyz'[i]} axis)")
            if np.any(bad):
                return None
            sub = np.diag(var[free])
        try:
            normal = Normal(np.asarray(p.mean, float)[free], sub)
        except ValueError as exc:  # numerically singular despite the checks above
            spread = "covariance" if p.covariance is not None else "variance"
            self.error((*loc, spread), f"invalid {spread} (too large or nearly singular): {exc}")
            return None
        family = (
            "full"
            if p.covariance is not None
            else ("diagonal" if isinstance(p.variance, list) else "isotropic")
        )
        return TranslationPart(
            kind,
            _frozen(p.mean),
            _frozen(free),
            normal=normal,
            fixed=p.fixed,
            path=loc,
            family=family,
        )

    def box_part(self, kind: TKind, p: dsl.BoxParams, loc: Loc) -> TranslationPart | None:
        lo, hi = np.asarray(p.min, float), np.asarray(p.max, float)
        if np.any(hi < lo):
            i = int(np.flatnonzero(hi < lo)[0])
            self.error((*loc, "max", i), f"box max must be >= min, got {hi[i]:g} < {lo[i]:g}")
            return None
        with np.errstate(over="ignore"):
            too_wide = not np.all(np.isfinite(hi - lo))
        if too_wide:  # the density 1/volume would be 0
            self.error((*loc, "max"), "box is too large (its width overflows)")
            return None
        box = UniformBox(lo, hi)
        return TranslationPart(
            kind, _frozen(lo), _frozen(box.free_axes), box=box, fixed=p.fixed, path=loc
        )

    def rotation(self, spec: object, loc: Loc) -> RotationPart | None:
        if spec == "same":
            return RotationPart(RKind.FIXED, _frozen(IDENTITY_QUAT), path=loc)
        if spec == "uniform":
            return RotationPart(RKind.UNIFORM, _frozen(IDENTITY_QUAT), path=loc)
        if isinstance(spec, dsl.OffsetR):
            q = self.orientation(spec.offset, (*loc, "offset"))
            return RotationPart(RKind.FIXED, _frozen(q), path=loc)
        if isinstance(spec, (dsl.WorldBinghamR, dsl.ParentBinghamR)):
            world = isinstance(spec, dsl.WorldBinghamR)
            key = "world_bingham" if world else "parent_bingham"
            bingham = self.bingham(getattr(spec, key), (*loc, key))
            if bingham is None:
                return None
            kind = RKind.WORLD_BINGHAM if world else RKind.PARENT_BINGHAM
            params = getattr(spec, key)
            family = (
                "raw"
                if params.M is not None
                else ("axes" if isinstance(params.concentration, list) else "isotropic")
            )
            return RotationPart(
                kind,
                _frozen(IDENTITY_QUAT),
                bingham=bingham,
                fixed=params.fixed,
                path=(*loc, key),  # the parameter block, as for translations and revolutes
                family=family,
            )
        if isinstance(spec, dsl.RevoluteR):
            return self.revolute(spec.revolute, (*loc, "revolute"))
        raise AssertionError(f"unhandled rotation {spec!r}")

    def bingham(self, p: dsl.BinghamParams, loc: Loc) -> Bingham | None:
        if p.M is not None and p.Z is not None:
            m = np.asarray(p.M, float)
            with np.errstate(all="ignore"):
                err = np.abs(m.T @ m - np.eye(4)).max()
            if not err <= ORTHOGONALITY_TOL:  # NaN (overflow) is not orthogonal either
                self.error((*loc, "M"), f"Bingham M must be orthogonal (max |MᵀM - I| = {err:.2g})")
                return None
            z = np.asarray(p.Z, float)
            spread = z.max() - z.min()
            if spread > MAX_CONCENTRATION:
                self.error(
                    (*loc, "Z"),
                    f"Bingham Z spans {spread:g}, over the supported {MAX_CONCENTRATION:g}",
                )
                return None
            return self.checked_bingham(lambda: Bingham(m, z), (*loc, "M"))
        conc = np.broadcast_to(np.asarray(p.concentration, float), (3,))
        if np.any(conc > MAX_CONCENTRATION):
            self.error(
                (*loc, "concentration"),
                f"concentration must be at most {MAX_CONCENTRATION:g}, got {conc.max():.10g}",
            )
            return None
        mode = self.orientation(p.mode, (*loc, "mode")) if p.mode else IDENTITY_QUAT
        return self.checked_bingham(lambda: Bingham.from_mode(mode, conc), loc)

    def checked_bingham(self, make: Callable[[], Bingham], loc: Loc) -> Bingham | None:
        """`make()`, with the distribution's own checks reported as located errors."""
        try:
            return make()
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.error(loc, f"invalid Bingham parameters: {exc}")
            return None

    def revolute(self, p: dsl.RevoluteParams, loc: Loc) -> RotationPart | None:
        axis = np.asarray(p.axis, float)
        scale = np.abs(axis).max()
        if scale == 0:
            self.error((*loc, "axis"), "revolute axis must be nonzero")
            return None
        axis = axis / scale  # so that the norm neither overflows nor underflows
        norm = np.linalg.norm(axis)
        if not p.max > p.min:
            self.error((*loc, "max"), f"revolute max must be > min, got [{p.min:g}, {p.max:g}]")
            return None
        if p.max - p.min > 2 * np.pi + 1e-9:
            self.error((*loc, "max"), f"revolute range exceeds 2π ({p.max - p.min:g} rad)")
            return None
        revolute = UniformRevolute(p.min, min(p.max, p.min + 2 * np.pi))
        return RotationPart(
            RKind.REVOLUTE,
            _frozen(IDENTITY_QUAT),
            axis=_frozen(axis / norm),
            revolute=revolute,
            fixed=p.fixed,
            path=loc,
        )

    def orientation(self, o: dsl.Orientation, loc: Loc) -> NDArray[np.float64]:
        if o.rpy is not None:
            return quat_canonical(rpy_to_quat(np.asarray(o.rpy, float)))
        if o.rpy_deg is not None:
            return quat_canonical(rpy_to_quat(np.radians(np.asarray(o.rpy_deg, float))))
        if o.quat_wxyz is not None:
            q = np.asarray(o.quat_wxyz, float)
            norm = float(np.hypot.reduce(q))  # no overflow for huge entries
            if abs(norm - 1) > QUAT_NORM_TOL:
                self.error(
                    (*loc, "quat_wxyz"),
                    f"quaternion must have unit norm (±{QUAT_NORM_TOL:g}), got {norm:.6g}",
                )
                return IDENTITY_QUAT.copy()
            return quat_canonical(q / norm)
        return IDENTITY_QUAT.copy()

    # ------------------------------------------------------------- global checks ---

    def check_root_not_produced(self, rules: list[Rule], root_name: str) -> None:
        root = self.ids.get(root_name)
        for r in rules:
            if r.child == root:
                self.error(
                    (*r.path, "child"), f"the root type '{root_name}' cannot be produced by a rule"
                )

    def check_labels(self, types: list[NodeType]) -> None:
        """Dataset objects are matched to types by model file and label: both must be unique."""
        owners: dict[tuple[str, str], str] = {}
        for t in types:
            if t.model and not t.observed:
                self.warn(
                    (*t.path, "model"),
                    f"type '{t.name}' is not observed, so its `model` is never exported or matched",
                )
            keys = [("model", t.model)] if t.model and t.observed else []
            keys += [("label", label) for label in dict.fromkeys(t.labels)]
            if len(set(t.labels)) < len(t.labels):
                self.warn((*t.path, "labels"), f"type '{t.name}' lists a label twice")
            for key in keys:
                if key in owners:
                    loc = (*t.path, "model" if key[0] == "model" else "labels")
                    self.error(loc, f"{key[0]} '{key[1]}' already names type '{owners[key]}'")
                owners[key] = t.name

    def check_files(self, types: list[NodeType]) -> None:
        """Mesh and model files are named relative to the grammar file and must stay in its
        directory (see `load_grammar`).  A missing mesh is worth a warning; models are names
        for matching dataset objects too, and are not expected to exist here."""
        for t in types:
            if isinstance(t.geometry, dsl.MeshG):
                loc = (*t.path, "geometry", "mesh", "file")
                mesh = self.file_reference(t.geometry.mesh.file, "mesh file", loc)
                if mesh is not None and self.base_dir is not None and not _is_file(mesh):
                    inside = mesh.is_relative_to(self.base_dir.resolve())
                    where = " next to the grammar" if inside else ""
                    name = t.geometry.mesh.file
                    self.warn(loc, f"mesh file '{name}' not found{where} (looked for {mesh})")
            if t.model:
                self.file_reference(t.model, "model file", (*t.path, "model"))

    def file_reference(self, name: str, what: str, loc: Loc) -> Path | None:
        """The file `name` means, or None after reporting why it cannot be used.

        The file is outside the grammar's directory when the path, resolved, is: an absolute
        path elsewhere, a `..` that climbs out, or a symbolic link on the way that points out.
        Without a directory (text compiled on its own) absolute paths and a leading `..` are.
        """
        if "\x00" in name:
            self.error(loc, f"{what} name contains a NUL character")
            return None
        target, place, link = None, "", ""
        if self.base_dir is None:
            outside = os.path.isabs(name) or os.path.normpath(name).split(os.sep)[0] == ".."
        else:
            try:
                base = self.base_dir.resolve()
                target = (self.base_dir / name).resolve()
            except (OSError, RuntimeError) as exc:  # a loop of symbolic links
                self.error(loc, f"cannot resolve {what} '{name}': {exc}")
                return None
            place = f" ({base})"
            outside = not target.is_relative_to(base)
            if outside and Path(os.path.normpath(base / name)).is_relative_to(base):
                link = f" (through a symbolic link, to {target})"
        if outside and not self.allow_outside:
            self.error(
                loc,
                f"{what} '{name}'{link} is outside the grammar's directory{place}; move it "
                "there, or allow it with --allow-outside-files",
            )
            return None
        return target

    def check_recursion(self, types: list[NodeType], rules: list[Rule]) -> None:
        """Every cycle of the type graph must pass through a type with `max_nesting`.

        Strongly connected components find the types on a cycle in linear time (a grammar may
        have thousands of types); a path is searched for only to name a cycle in a message.
        """
        children: dict[int, list[Rule]] = {t.id: [] for t in types}
        for r in rules:
            children[r.parent].append(r)
        bounded = {t.id for t in types if t.max_nesting is not None}
        free = [t.id for t in types if t.id not in bounded]
        loops = _on_cycles(free, children)  # cycles of types without a bound
        on_cycle: set[int] = set()
        reported = 0
        for t in types:
            if t.id not in loops or t.id in on_cycle or reported >= MAX_CYCLES_REPORTED:
                continue
            cycle = _find_cycle(t.id, children, loops[t.id])
            if cycle is None:  # cannot happen: t is on a cycle of its component
                continue
            on_cycle.update(r.parent for r in cycle)
            reported += 1
            names = " -> ".join([self.names[r.parent] for r in cycle] + [self.names[t.id]])
            self.error(
                (*cycle[-1].path, "child"),
                f"unbounded recursion {names}; set `max_nesting` on one of these types",
            )
        recursive = _on_cycles([t.id for t in types], children)
        for t in types:
            if t.id in bounded and t.id not in recursive:
                self.warn(
                    (*t.path, "max_nesting"),
                    f"type '{t.name}' is not recursive, so `max_nesting` has no effect",
                )

    def check_reachable(self, types: list[NodeType], rules: list[Rule], root: int) -> None:
        seen, stack = {root}, [root]
        kids: dict[int, list[int]] = {}
        for r in rules:
            kids.setdefault(r.parent, []).append(r.child)
        while stack:
            for c in kids.get(stack.pop(), []):
                if c not in seen:
                    seen.add(c)
                    stack.append(c)
        for t in types:
            if t.id not in seen:
                self.warn(t.path, f"type '{t.name}' is unreachable from the root")


def _kind_of(spec: dsl.NodeType) -> tuple[Kind, str, list[dsl.Rule]]:
    if spec.and_ is not None:
        return Kind.AND, "and", spec.and_
    if spec.or_ is not None:
        return Kind.OR, "or", spec.or_
    if spec.independent is not None:
        return Kind.INDEPENDENT, "independent", spec.independent
    if spec.repeat is not None:
        return Kind.REPEAT, "repeat", [spec.repeat.rule]
    return Kind.TERMINAL, "", []


def _on_cycles(nodes: list[int], children: dict[int, list[Rule]]) -> dict[int, set[int]]:
    """The types among `nodes` that lie on a cycle through `nodes` only, each mapped to its
    strongly connected component (Tarjan's algorithm, without recursion)."""
    allowed = set(nodes)
    index: dict[int, int] = {}
    low: dict[int, int] = {}
    stack: list[int] = []
    on_stack: set[int] = set()
    out: dict[int, set[int]] = {}
    for root in nodes:
        if root in index:
            continue
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        work = [(root, iter(children[root]))]
        while work:
            node, kids = work[-1]
            for r in kids:
                child = r.child
                if child not in allowed:
                    continue
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(children[child])))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:  # every child done
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    looped = any(r.child == node for r in children[node])
                    if len(component) > 1 or looped:
                        out.update(dict.fromkeys(component, component))
    return out


def _find_cycle(
    start: int, children: dict[int, list[Rule]], allowed: set[int]
) -> list[Rule] | None:
    """Rules of a path start -> ... -> start through `allowed` types, if any (depth first)."""
    via: dict[int, Rule] = {}  # the rule each type was first reached by
    stack = [start]
    seen = {start}
    while stack:
        node = stack.pop()
        for r in children[node]:
            if r.child == start:
                path = [r]
                while node != start:
                    path.append(via[node])
                    node = via[node].parent
                return path[::-1]
            if r.child not in seen and r.child in allowed:
                seen.add(r.child)
                via[r.child] = r
                stack.append(r.child)
    return None


def _is_file(path: Path) -> bool:
    """`path.is_file()`, False for a name the system refuses (too long, a loop of links)."""
    try:
        return path.is_file()
    except (OSError, RuntimeError):
        return False


def _frozen(a: object) -> NDArray[np.float64]:
    """A read-only array, keeping booleans boolean (axis masks) and making the rest float."""
    arr = np.asarray(a)
    out = np.array(arr, dtype=bool if arr.dtype == bool else float)
    out.flags.writeable = False
    return out
