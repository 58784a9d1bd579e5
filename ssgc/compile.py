"""DSL → IR: the compiler's passes, every problem reported with its place in the document.

`load_grammar(path)` is the one entry point the rest of the program uses.  The passes:

1. read the text keeping positions, and validate its shape with pydantic (`ssgc.dsl`);
2. lower each type and rule (`Compiler`): node kinds and rule probabilities here, each rule
   part through the law its document word names (`ssgc.laws`: every law checks and lowers
   its own parameters, and beside that lowering holds its inverse, the fitted values' write-back);
3. check the whole grammar (`ssgc.checks`): references, files, recursion, reachability;
4. assemble the immutable `ssgc.ir.Grammar` and its stacked tables.

All problems found are reported together; warnings (unreachable types, bounds with no
effect) travel with the compiled grammar.
"""

from __future__ import annotations

import copy
import difflib
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

import ssgc.laws  # noqa: F401  (registers the built-in laws)
from ssgc import dsl, observation
from ssgc.checks import Finding, check_reachable, check_recursion, check_references
from ssgc.constraints.build import build_constraints
from ssgc.errors import Diagnostic, GrammarError, SsgError, one_line
from ssgc.geometry import IDENTITY_QUAT, QUAT_NORM_TOL, quat_canonical, rpy_to_quat
from ssgc.ir import Grammar, Kind, Loc, NodeType, Rule, build_tables
from ssgc.laws.base import PoseLaw, frozen, law_for
from ssgc.laws.counts import RepeatCount
from ssgc.yamlio import (
    MAX_GRAMMAR_BYTES,
    SourceMap,
    load_located,
    read_text,
    validation_diagnostics,
)

MAX_SUGGESTIONS = 50  # "did you mean" for the first unknown type names only


def load_grammar(path: str | Path, allow_outside: bool = False) -> Grammar:
    """Read, validate and compile a grammar file; raises `GrammarError` on any mistake.

    Files the grammar names (meshes, models) must lie in the grammar file's directory unless
    `allow_outside`: a grammar from elsewhere cannot point ssgc at arbitrary files.
    """
    path = Path(path)
    text = read_grammar_text(path)
    return compile_text(text, str(path), base_dir=path.parent, allow_outside=allow_outside)


def read_grammar_text(path: Path) -> str:
    """A grammar file's text; not found, not UTF-8 or NUL bytes are grammar errors."""
    try:
        return read_text(path, MAX_GRAMMAR_BYTES, "grammar file")
    except GrammarError:
        raise
    except SsgError as exc:
        raise GrammarError(exc.diagnostics) from None


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
        shape, locs, cleaned = _shape_errors(data, exc, source)
        later = _errors_beyond_shape(cleaned, locs, source, base_dir, allow_outside)
        raise GrammarError(shape + later) from None
    return Compiler(doc, source, base_dir, allow_outside).run()


MAX_SHAPE_PASSES = 4  # unknown keys nested this deep in one mapping path are all reported


def _shape_errors(
    data: dict, exc: ValidationError, source: SourceMap
) -> tuple[list[Diagnostic], list[tuple], dict]:
    """Every shape error, where each is, and the document without its unknown keys.  An
    unknown key stops the check of the mapping that holds it (its other keys go unchecked), so
    the unknown keys are taken out and the document checked again, a few times at most, adding
    what the next pass finds: one run reports a type's unknown key and its wrong values
    together.  The locations are those of the errors still in the returned document (an
    unknown key taken out is none).  What only follows from taking out a misspelt key (the
    key it meant is now missing) is not said again: the unknown key's "did you mean" names
    the fix (`_follow_on`)."""
    said: set[tuple[Any, ...]] = set()  # an aliased part's mistake, said once (yamlio)
    diagnostics = validation_diagnostics(exc, source, said)
    meant: set[tuple[tuple, str]] = set()  # (mapping, the key a dropped one was meant to be)
    seen = {str(d) for d in diagnostics}
    errors = exc.errors(include_url=False)
    locs: list[tuple] = []
    current = data
    for _ in range(MAX_SHAPE_PASSES):
        unknown = [e for e in errors if e["type"] == "unknown_key"]
        locs += [tuple(e["loc"]) for e in errors if e["type"] != "unknown_key"]
        if not unknown:
            break
        hidden = _hidden_unknown_keys(current, unknown)
        hidden_error = ValidationError.from_exception_data("doc", hidden)
        for d in validation_diagnostics(hidden_error, source, said):
            if str(d) not in seen:
                seen.add(str(d))
                diagnostics.append(d)
        unknown += hidden
        meant |= {_meant(e) for e in unknown}
        dropped = copy.deepcopy(current)
        if not all(_drop_key(dropped, e["loc"], e["ctx"]["key"]) for e in unknown):
            locs += [tuple(e["loc"]) for e in unknown]  # still there: its type is left out
            break
        current = dropped
        try:
            dsl.GrammarDoc.model_validate(current)
            break
        except ValidationError as again:
            errors = again.errors(include_url=False)
            kept = _Errors([e for e in errors if not _follow_on(e, meant)])
            for d in validation_diagnostics(cast(ValidationError, kept), source, said):
                if str(d) not in seen:
                    seen.add(str(d))
                    diagnostics.append(d)
    else:  # passes used up: the last one's errors all stay
        locs += [tuple(e["loc"]) for e in errors]
    return diagnostics, locs, current


def _meant(unknown: dict[str, Any]) -> tuple[tuple, str]:
    """The mapping of an unknown-key error and the allowed key it is closest to ('' if none),
    as `dsl.unknown_key_error` suggests it."""
    allowed = unknown["ctx"]["allowed"].split(", ")
    close = difflib.get_close_matches(unknown["ctx"]["key"], allowed, n=1)
    return tuple(unknown["loc"]), close[0] if close else ""


def _follow_on(e: Any, meant: set[tuple[tuple, str]]) -> bool:
    """Whether error `e` only follows from a misspelt key taken out: the key it meant is
    missing (`lenght` → `length: missing required key`), or a one-of that wants it is unmet
    (`varience` → "give exactly one of `variance` or `covariance`") — and only if the key it
    meant was not given as well: a mapping with `variance`, `covariance` and `varience` has
    both mistakes."""
    loc = tuple(e["loc"])
    if e["type"] == "missing":
        return (loc[:-1], str(loc[-1])) in meant
    if e["type"].startswith("value_error"):
        given = e.get("input")
        given = given if isinstance(given, dict) else {}
        return any(
            at == loc and f"`{key}`" in e["msg"] and key not in given for at, key in meant if key
        )
    return False


class _Errors:
    """Some of a `ValidationError`'s errors, read as one by `validation_diagnostics` (which
    asks only for `errors()`): the follow-ons of a misspelt key left out."""

    def __init__(self, errors: list[Any]) -> None:
        self.kept = errors

    def errors(self, include_url: bool = False) -> list[Any]:
        return self.kept


def _hidden_unknown_keys(data: Any, unknown: list[Any]) -> list[Any]:
    """The unknown keys that the reported ones hide: a mapping's check stops at its first
    unknown key, so a mapping of forty misspelt keys would take forty passes.  Each is an
    error of the same form, for the same pass."""
    hidden = []
    for e in unknown:
        node = _node_at(data, e["loc"])
        allowed, reported = e["ctx"]["allowed"].split(", "), e["ctx"]["key"]
        for key in node if isinstance(node, dict) else ():
            if str(key) not in allowed and str(key) != reported:
                error = dsl.unknown_key_error(str(key), allowed)
                hidden.append({"type": error, "loc": e["loc"], "input": node, "ctx": error.context})
    return hidden


def _node_at(data: Any, loc: Any) -> Any:
    """The value at `loc` (steps that name no key or index, such as a union's tag, skipped)."""
    node = data
    for step in loc:
        if isinstance(node, dict) and step in node:
            node = node[step]
        elif isinstance(node, list) and isinstance(step, int) and 0 <= step < len(node):
            node = node[step]
    return node


def _drop_key(data: Any, loc: Any, key: str) -> bool:
    """Remove `key` from the mapping at `loc`; false if it is not found."""
    node = _node_at(data, loc)
    if isinstance(node, dict) and key in node:
        del node[key]
        return True
    return False


def _errors_beyond_shape(
    data: dict,
    locs: list[tuple],
    source: SourceMap,
    base_dir: Path | None,
    allow_outside: bool,
) -> list[Diagnostic]:
    """The semantic errors of the rest of a grammar whose shape is wrong in some node types
    or in its `observation` section, so that one run reports them all (not one stage per run).

    A rule's translation or rotation with a shape error is checked as `same`, and a repeat's
    misshapen count law as `COUNT_STAND_IN`, so the rule's child, probability and other part
    still are.  A rule of an `and`, `or` or `independent`
    list with a shape error elsewhere is left out, and the type's other rules are still
    checked (their messages keep their places: `_Renumbered`).  A type with a shape error
    elsewhere is checked as a terminal stub: its name stays known, so the rest gets no
    follow-on "unknown type" errors.  A type whose name itself is misshapen is left out: what
    names it (a rule's `child`, a noise entry, a clutter rate) has the same shape error and is
    left out too, so no follow-on error comes of it.  The `observation` section gets stand-ins
    too (`_observation_stand_in`).  Warnings (which a stub or a missing rule could cause) are
    dropped.  A shape error elsewhere (root, grammar name) leaves nothing sound to check.
    """
    in_observation = [loc for loc in locs if loc[:1] == ("observation",)]
    locs = [loc for loc in locs if loc[:1] != ("observation",)]
    bad: set[str] = set()
    misnamed: set[str] = set()  # types whose name breaks the pattern: left out
    bad_rules: dict[tuple, set[int]] = {}
    # type -> (path, stand-in) of the rule parts (placements, a count law) to check in place
    # of misshapen ones
    stand_ins: dict[str, list[tuple[tuple, Any]]] = {}
    for loc in locs:
        if len(loc) < 2 or loc[0] != "types" or not isinstance(loc[1], str):
            return []
        if len(loc) >= 3 and loc[2] == "[key]":  # a type's name itself
            misnamed.add(loc[1])
            continue
        part = _rule_part(loc)
        if part is not None:
            stand_ins.setdefault(loc[1], []).append(part)
        elif len(loc) >= 5 and loc[2] in RULE_LISTS and isinstance(loc[3], int):
            bad_rules.setdefault(loc[:3], set()).add(loc[3])
        else:
            bad.add(loc[1])
    types = data.get("types")
    if not isinstance(types, dict):
        return []
    kept: dict[tuple, list[int]] = {}
    fixed = {}
    for name, original in types.items():
        if name in misnamed:
            continue
        if name in bad:
            fixed[name] = _stub(original, [loc for loc in locs if loc[1] == name])
            continue
        body = dict(original) if isinstance(original, dict) else original
        for path, value in stand_ins.get(name, []):
            body = _with_value(body, path, value)
        for word in RULE_LISTS:
            drop = bad_rules.get(("types", name, word))
            if drop and isinstance(body, dict) and isinstance(body.get(word), list):
                kept[("types", name, word)] = [i for i in range(len(body[word])) if i not in drop]
                body[word] = [r for i, r in enumerate(body[word]) if i not in drop]
        if name in stand_ins and not _valid_type(body):  # a stand-in had no place to go
            body = _stub(original, [loc for loc in locs if loc[1] == name])
        fixed[name] = body
    stubbed = {**data, "types": fixed}
    if in_observation:
        stubbed["observation"] = _observation_stand_in(data.get("observation"), in_observation)
    try:
        doc = dsl.GrammarDoc.model_validate(stubbed)
    except ValidationError:
        return []
    try:
        renumbered = _Renumbered(source, kept)
        compiler = Compiler(doc, renumbered, base_dir, allow_outside, True, frozenset(kept))  # type: ignore[arg-type]
        compiler.misshapen = frozenset(
            loc[1] for loc in locs if len(loc) >= 3 and loc[2] == "geometry"
        )
        compiler.run()
    except GrammarError as later:
        return [d for d in later.diagnostics if d.severity != "warning"]
    return []


# What an `observation` section's misshapen part is checked as: no noise, a rate of 1, a unit
# box, the default `max`.  Each keeps the name it is under checked, and adds no error.
OBSERVATION_STAND_INS = {
    "noise": {},
    "rates": 1.0,
    "region": {"min": [0, 0, 0], "max": [1, 1, 1]},
    "max": 3,
}


def _observation_stand_in(section: Any, locs: list[tuple]) -> Any:
    """The `observation` section with stand-ins (`OBSERVATION_STAND_INS`) for its misshapen
    parts, so that the types its noise entries and clutter rates name are still checked;
    without the clutter, or the whole section, when a stand-in does not make it valid.  A rate
    under a misshapen type name is left out (as a noise entry is), after the other stand-ins
    (one of which could put it back), so the other rates and the region are still checked."""
    bad_rates: set[Any] = set()
    for loc in locs:
        path = loc[1:]
        if path[:1] == ("noise",):
            section = _noise_stand_in(section, path)
        elif path[:2] == ("clutter", "rates") and len(path) >= 4 and path[3] == "[key]":
            bad_rates.add(path[2])
        elif path[:2] == ("clutter", "rates") and len(path) >= 3:
            section = _with_value(section, path[:3], OBSERVATION_STAND_INS["rates"])
        elif path[:1] == ("clutter",) and path[1:2] in (("region",), ("max",)):
            section = _with_value(section, path[:2], OBSERVATION_STAND_INS[path[1]])
        elif isinstance(section, dict):
            section = {**section, "clutter": None}
    section = _without_rates(section, bad_rates)
    for candidate in (section, {**section, "clutter": None} if isinstance(section, dict) else None):
        try:
            dsl.ObservationSpec.model_validate(candidate)
            return candidate
        except ValidationError:
            continue
    return None


def _without_rates(section: Any, names: set[Any]) -> Any:
    """`section` without the clutter rates of the types `names` (misshapen names)."""
    clutter = section.get("clutter") if isinstance(section, dict) else None
    rates = clutter.get("rates") if isinstance(clutter, dict) else None
    if not names or not isinstance(rates, dict):
        return section
    kept = {k: v for k, v in rates.items() if k not in names}
    return {**section, "clutter": {**clutter, "rates": kept}}


def _noise_stand_in(section: Any, path: tuple) -> Any:
    """`section` with no noise in place of a misshapen noise entry (its name still checked),
    without an entry whose name is misshapen, with no noise at all for a misshapen `noise`."""
    noise = section.get("noise") if isinstance(section, dict) else None
    if len(path) >= 3 and path[2] == "[key]" and isinstance(noise, dict):
        return {**section, "noise": {k: v for k, v in noise.items() if k != path[1]}}
    return _with_value(section, path[:2], OBSERVATION_STAND_INS["noise"])


STUB_KEEPS = ("observed", "geometry")  # what other checks (noise, keep-out radii) read of a type


def _stub(body: Any, locs: list[tuple]) -> dict:
    """An empty terminal type in place of one with a shape error, keeping its `observed` and
    `geometry` when the error is elsewhere (so checks that read them raise nothing false)."""
    if not isinstance(body, dict):
        return {}
    broken = {loc[2] for loc in locs if len(loc) >= 3}
    stub = {k: body[k] for k in STUB_KEEPS if k in body and k not in broken}
    return stub if _valid_type(stub) else {}


def _valid_type(body: Any) -> bool:
    try:
        dsl.NodeType.model_validate(body)
    except ValidationError:
        return False
    return True


RULE_LISTS = ("and", "or", "independent")  # the document's keys of a type's rule lists
RULE_PARTS = ("translation", "rotation")


# A `repeat` whose count law is misshapen is checked with this one: it adds no rule and
# forces none (count 0 is possible), and constraints are not checked against a stand-in.
COUNT_STAND_IN = {"probs": [0.5, 0.5]}


def _rule_part(loc: tuple) -> tuple[tuple, Any] | None:
    """The path in its type of the rule part a shape error lies in, and what to check in its
    place: `same` for a translation or rotation (`("or", 2, "translation")`, `("repeat", "rule",
    "rotation")`), `COUNT_STAND_IN` for a repeat's count; None if the error is elsewhere."""
    if len(loc) >= 4 and loc[2] == "repeat" and loc[3] == "count":
        return ("repeat", "count"), COUNT_STAND_IN
    if len(loc) < 5 or loc[4] not in RULE_PARTS:
        return None
    if loc[2] in RULE_LISTS and isinstance(loc[3], int):
        return tuple(loc[2:5]), "same"
    if loc[2] == "repeat" and loc[3] == "rule":
        return tuple(loc[2:5]), "same"
    return None


def _with_value(body: Any, path: tuple, value: Any) -> Any:
    """A copy of a type's body with `value` at `path` (the parts on the way copied, the
    document itself untouched); unchanged if the path up to its last key is not there."""
    if not path:
        return value
    step, rest = path[0], path[1:]
    if isinstance(body, dict) and (step in body or not rest):  # a missing last key is added
        return {**body, step: _with_value(body.get(step), rest, value)}
    if isinstance(body, list) and isinstance(step, int) and 0 <= step < len(body):
        return [_with_value(x, rest, value) if i == step else x for i, x in enumerate(body)]
    return body


class _Renumbered:
    """The source map of a document some of whose rules were left out: a location in the
    shortened copy is turned back into the rule's place in the document."""

    def __init__(self, source: SourceMap, kept: dict[tuple, list[int]]) -> None:
        self.source, self.kept, self.file = source, kept, source.file
        self.notes: tuple[Diagnostic, ...] = ()  # the loader's warnings: the first pass has them

    def diagnostic(self, loc: Any, message: str, severity: str = "error") -> Diagnostic:
        loc = tuple(loc)
        rules = self.kept.get(loc[:3]) if len(loc) >= 4 else None
        if rules is not None and isinstance(loc[3], int) and 0 <= loc[3] < len(rules):
            loc = (*loc[:3], rules[loc[3]], *loc[4:])
        return self.source.diagnostic(loc, message, severity)


class Report:
    """The diagnostics of one compile, located in the document by `source`."""

    def __init__(self, source: SourceMap, names: list[str]) -> None:
        self.source = source
        self.names = names
        self.errors: list[Diagnostic] = []
        self.warnings: list[Diagnostic] = list(source.notes)
        self.said = set(self.warnings)  # every diagnostic so far: each is reported once
        self.suggestions = 0

    def error(self, loc: Loc, message: str) -> None:
        self.say(self.errors, self.source.diagnostic(loc, message))

    def warn(self, loc: Loc, message: str) -> None:
        self.say(self.warnings, self.source.diagnostic(loc, message, "warning"))

    def say(self, into: list[Diagnostic], d: Diagnostic) -> None:
        """Add `d` unless it was said already: a part of the document shared through a YAML
        alias (`*t`) is checked at each use, but its mistakes are in one place, said once."""
        if d not in self.said:
            self.said.add(d)
            into.append(d)

    def add(self, findings: list[Finding]) -> None:
        for severity, loc, message in findings:
            (self.error if severity == "error" else self.warn)(loc, message)

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


# entries of the scorer's (types x widest rules) tables: 400 MB per table of 8-byte numbers
MAX_TABLE_CELLS = 50_000_000


class Compiler(Report):
    """Lowers one validated document, runs the whole-grammar checks on the result and
    assembles the IR; collects every diagnostic it finds."""

    def __init__(
        self,
        doc: dsl.GrammarDoc,
        source: SourceMap,
        base_dir: Path | None = None,
        allow_outside: bool = False,
        partial: bool = False,
        shortened: frozenset[Loc] = frozenset(),
    ) -> None:
        super().__init__(source, list(doc.types))
        self.doc = doc
        self.base_dir = base_dir
        self.allow_outside = allow_outside
        # A document some of whose parts were stubbed (`_errors_beyond_shape`): what a tree of
        # it can hold says nothing of the grammar, so constraints are not checked against it.
        self.partial = partial
        # The rule lists (`("types", name, "or")`) that lost misshapen rules in such a document.
        self.shortened = shortened
        # The types whose `geometry` has a shape error (said already): a constraint that needs
        # their shape gives up on it without a follow-on "it has no geometry".
        self.misshapen: frozenset[str] = frozenset()
        self.ids = {name: i for i, name in enumerate(self.names)}

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
        root = self.ids.get(root_spec.type)
        if root is not None and root_spec.required and not types[root].observed:
            self.error(
                ("root", "required"),
                f"the root type '{root_spec.type}' is not observed, so no scene shows it: "
                "only an observed root can be required",
            )
        self.add(check_references(types, rules, root, self.base_dir, self.allow_outside))
        if root is not None:
            self.add(check_recursion(types, rules))
            if not self.errors:
                self.add(self.reachable(types, rules, root))
        sound = not self.errors and not self.partial
        # The observation adds types (clutter, an observed root's node) after the user's: the
        # constraints are checked on the grammar as written but sized for every type.
        seen = None
        if self.errors:  # no grammar of observed scenes to build, but its section is checked
            observation.check(self.doc.observation, types, rules, self.ids, self)
        else:
            root_id = self.ids[root_spec.type]
            seen = observation.apply(self.doc.observation, types, rules, root_id, self.ids, self)
        n_types = len(types) if seen is None else len(seen.types)
        true = {} if seen is None else observation.true_nodes(seen, types, root)
        constraints = build_constraints(self, types, rules, root, sound, n_types, true)
        if self.errors:
            raise GrammarError(self.errors + self.warnings)
        assert seen is not None
        types_t, rules_t = tuple(seen.types), tuple(seen.rules)
        self.check_table_size(types_t)
        if self.errors:
            raise GrammarError(self.errors + self.warnings)
        return Grammar(
            name=self.doc.grammar,
            file=self.source.file,
            types=types_t,
            rules=rules_t,
            root=seen.root,
            root_xyz=frozen(root_spec.pose.xyz),
            root_quat=frozen(root_quat),
            tables=build_tables(types_t, rules_t),
            warnings=tuple(self.warnings),
            type_ids=seen.ids,
            constraints=constraints,
            observation=self.doc.observation,
            required_root=self.required_root(root_spec, seen),
        )

    def check_table_size(self, types: tuple[NodeType, ...]) -> None:
        """The scorer's tables hold a row per type as wide as the widest type's rules (and
        its longest count law): 20,000 types under one `or` of 20,000 rules asked for 3 GB per
        table and stopped `ssg validate` with exit 70.  Past MAX_TABLE_CELLS the grammar is
        refused at the type that makes the tables wide."""
        widest = max(types, key=lambda t: len(t.rules))
        longest = max(types, key=lambda t: 0 if t.count is None else t.count.max_count)
        for t, what, k in (
            (widest, "rules", len(widest.rules)),
            (longest, "counts", 0 if longest.count is None else longest.count.max_count + 1),
        ):
            if len(types) * k > MAX_TABLE_CELLS:
                self.error(
                    t.path,
                    f"type '{t.name}' has {k:,} {what} and the grammar {len(types):,} types: "
                    f"its tables would hold {len(types) * k:,} entries, more than "
                    f"{MAX_TABLE_CELLS:,}; split its {what} over intermediate types",
                )

    def reachable(self, types: list[NodeType], rules: list[Rule], root: int) -> list[Finding]:
        """Warnings for the types that neither the root nor the `observation` section's
        clutter (which makes the types its rates name) can reach."""
        spec = self.doc.observation
        clutter = set() if spec is None or spec.clutter is None else set(spec.clutter.rates)
        starts = [root, *(t.id for t in types if t.name in clutter)]
        return check_reachable(types, rules, starts)

    def required_root(self, root_spec: dsl.Root, seen: observation.Observed) -> int | None:
        """The root type every scene must show: one declared `required`, or an observed
        root that the `observation` section moved under a new root (noise on the root, or
        clutter).  A missing root is implied only as the tree's root, at its exact pose; under
        the new root it would be an observed node without an object, and every such scene was
        `infeasible` with no word of the root."""
        root = seen.ids[root_spec.type]
        moved = seen.root != root and seen.types[root].observed
        return root if root_spec.required or moved else None

    # ----------------------------------------------------------------- node types ---

    def node_type(self, name: str, spec: dsl.NodeType, rules: list[Rule]) -> NodeType:
        tid = self.ids[name]
        loc: Loc = ("types", name)
        kind, key, rule_specs = _kind_of(spec)
        whole = (*loc, key) not in self.shortened  # the list as written, not cut by `partial`
        if kind in (Kind.AND, Kind.OR, Kind.INDEPENDENT) and not rule_specs and whole:
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
        probs = rule_probs(kind, key, rule_specs, rule_locs, loc, self, whole)
        count = (
            RepeatCount.lower(spec.repeat, (*loc, "repeat", "count"), self) if spec.repeat else None
        )
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
            probs=frozen(probs),
            count=count,
            max_nesting=spec.max_nesting,
            geometry=spec.geometry,
            model=spec.model,
            body=spec.body,
            labels=tuple(spec.labels),
            fixed=spec.fixed,
            path=loc,
        )

    # ---------------------------------------------------------------------- rules ---

    def rule(self, rid: int, parent: int, index: int, spec: dsl.Rule, loc: Loc) -> Rule | None:
        known = spec.child in self.ids
        if not known:
            self.unknown_type((*loc, "child"), spec.child, "child type")
        # The placement is checked even under a misspelt child: one run, every mistake.
        translation = self.part("translation", spec.translation, (*loc, "translation"))
        rotation = self.part("rotation", spec.rotation, (*loc, "rotation"))
        if not known or translation is None or rotation is None:
            return None
        return Rule(rid, parent, index, self.ids[spec.child], translation, rotation, loc)

    def part(self, part: str, spec: object, loc: Loc) -> PoseLaw | None:
        """Lower one part of a rule through the law its document word names."""
        word = spec if isinstance(spec, str) else dsl.one_key(spec)
        if word is None:  # pydantic guarantees the variants
            raise AssertionError(f"unhandled {part} {spec!r}")
        law = law_for(part, word)
        if isinstance(spec, str):
            return law.lower(None, word, loc, self)
        return law.lower(getattr(spec, word), word, (*loc, word), self)

    def orientation(self, o: dsl.Orientation, loc: Loc) -> NDArray[np.float64]:
        return orientation(o, loc, self)


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


# Why a rule of these kinds has no probability of its own.
WHY_NO_P = {"and": "every rule fires", "repeat": "its rule fires as many times as `count` draws"}


def rule_probs(
    kind: Kind,
    key: str,
    specs: list[dsl.Rule],
    locs: list[Loc],
    loc: Loc,
    report: Report,
    whole: bool = True,
) -> NDArray[np.float64]:
    """The normalised weights of an `or`, the probabilities of an `independent`.  Unless
    `whole`, some rules were left out (`_errors_beyond_shape`) and the weights that remain may
    sum to zero where the file's do not, so that is not reported."""
    given = [r.p is not None for r in specs]
    if kind in (Kind.AND, Kind.REPEAT):
        for spec, rloc in zip(specs, locs, strict=True):
            if spec.p is not None:
                report.error((*rloc, "p"), f"`p` has no meaning in `{key}` ({WHY_NO_P[key]})")
        return np.ones(len(specs))
    if kind == Kind.INDEPENDENT:
        for spec, rloc in zip(specs, locs, strict=True):
            if spec.p is None:
                report.error(rloc, "every rule of `independent` needs its probability `p`")
            elif spec.p > 1:
                report.error(
                    (*rloc, "p"),
                    f"`p` of an `independent` rule is a probability in [0, 1], got {spec.p:g}",
                )
        return np.array([r.p if r.p is not None else 0.0 for r in specs])
    if kind == Kind.OR and specs:
        if any(given) and not all(given):
            missing = locs[given.index(False)]
            report.error(missing, "give `p` for every rule of an `or`, or for none (equal weights)")
            return np.full(len(specs), 1.0 / len(specs))
        weights = np.array([r.p for r in specs]) if all(given) else np.ones(len(specs))
        if not np.any(weights > 0):  # (their sum may overflow: 2 × 1e308)
            if whole:
                report.error((*loc, key), "the weights `p` of an `or` sum to zero")
            return np.full(len(specs), 1.0 / len(specs))
        weights = weights / weights.max()  # two weights of 1e308 sum to inf
        return weights / weights.sum()
    return np.zeros(0)


def orientation(o: dsl.Orientation, loc: Loc, report: Report) -> NDArray[np.float64]:
    """A written orientation as a canonical unit quaternion (wxyz)."""
    if o.rpy is not None:
        return quat_canonical(rpy_to_quat(np.asarray(o.rpy, float)))
    if o.rpy_deg is not None:
        return quat_canonical(rpy_to_quat(np.radians(np.asarray(o.rpy_deg, float))))
    if o.quat_wxyz is not None:
        q = np.asarray(o.quat_wxyz, float)
        norm = float(np.hypot.reduce(q))  # no overflow for huge entries
        if abs(norm - 1) > QUAT_NORM_TOL:
            report.error(
                (*loc, "quat_wxyz"),
                f"quaternion must have unit norm (±{QUAT_NORM_TOL:g}), got {norm:.6g}",
            )
            return IDENTITY_QUAT.copy()
        return quat_canonical(q / norm)
    return IDENTITY_QUAT.copy()
