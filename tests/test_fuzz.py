"""Fuzzing every way input reaches `ssg`: bad input is a located message, never a traceback.

Generated inputs go through the real command line, in process (typer's `CliRunner` on
`ssgc.cli.app:app`):

- grammar files for `ssg validate`, `ssg inspect` and `ssg sample -n 2`;
- JSON scenes and sink-format YAML datasets for `ssg parse SCENES -g GRAMMAR`, with the
  `sink` and `singles_pairs_dependency` grammars;
- JSON scenes and `ssg parse` outputs for `ssg render`, `view`, `export` and `settle`;
- and, through the Python API, objects given as Python data (`ssgc.api.Grammar.scene`);
- valid grammars of the whole language (tests/grammar_gen.py) through every command.

Inputs are mutations of the real files (the bundled grammars, sampled scenes, the sink
dataset), documents built from the file formats with hostile values put in (wrong types,
missing and unknown keys, NaN, infinities, huge numbers, zero or negative variances, zero and
non-unit quaternions, unicode and control characters in names, duplicate keys, deep or
cyclic structures), YAML and JSON oddities (anchors, alias bombs, tags, several documents) and
plain bytes (empty files, random bytes, invalid UTF-8).

Every run must end with exit code 0 (the input happened to be valid) or a user-error code
(1, or 2 for `parse`), never 70 (an internal error) nor an exception; it must not print a
traceback, an error must say something, and every line of stderr must be one diagnostic
(``FILE:LINE:COL: error: ...``), so a message never spills over several lines.

Profiles (docs/robustness.md): the quick one runs with the test suite; the long one runs
10,000 cases per entry point::

    SSG_FUZZ=long python -m pytest tests/test_fuzz.py -q --hypothesis-show-statistics
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from textwrap import dedent
from typing import Any

import grammar_gen
import numpy as np
import pytest
from conftest import GRAMMARS, SINK_DATA
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner, Result

from ssgc.cli.app import app
from ssgc.compile import compile_text, load_grammar, read_grammar_text
from ssgc.errors import GrammarError
from ssgc.io.scene import dumps_scene, scene_from_tree
from ssgc.sample.forward import sample_trees

PROFILE = os.environ.get("SSG_FUZZ", "quick")
if PROFILE not in ("quick", "long") and not PROFILE.isdigit():
    raise ValueError(f"SSG_FUZZ must be 'quick', 'long' or a number of cases, got {PROFILE!r}")
LONG_CASES = 10_000
# A warning of the YAML reader reaches the user's terminal as ruamel's own text (its source
# file, '<unicode string>' for the file): ssg turns what it warns about into located
# diagnostics, so here any such warning is an uncaught exception.
pytestmark = [
    pytest.mark.filterwarnings("error::ruamel.yaml.error.YAMLWarning"),
    # and matplotlib's, once per character its font lacks (`ssg render` says it once, located)
    pytest.mark.filterwarnings("error:Glyph"),
]
PARSE_GRAMMARS = ("sink.yaml", "singles_pairs_dependency.yaml")


def fuzz(quick: int) -> settings:
    """`quick` cases by default, `LONG_CASES` in the long profile (or SSG_FUZZ=N cases); no
    per-case deadline (tests check behaviour, not wall-clock time; pytest's
    `faulthandler_timeout` prints the stack of a test that hangs), and the CI profile's
    derandomisation is inherited."""
    cases = {"quick": quick, "long": LONG_CASES}.get(PROFILE) or int(PROFILE)
    return settings(
        max_examples=cases,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )


# ---------------------------------------------------------------------- rendering ---


@dataclass(frozen=True)
class Raw:
    """Text put into a document as it is (an unquoted YAML word, a 5000-digit number)."""

    text: str


@dataclass(frozen=True, eq=False)
class DupKey:
    """A mapping key written like another key of the same mapping: a duplicate key.

    Compared by identity, so a dict can hold it next to the key it duplicates."""

    name: str


def yaml_scalar(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, Raw):
        return value.text
    if isinstance(value, DupKey):
        return json.dumps(value.name)
    if isinstance(value, float):
        if math.isnan(value):
            return ".nan"
        if math.isinf(value):
            return ".inf" if value > 0 else "-.inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", value):
        return value  # plain, so `Null`, `true` and `yes` get YAML's reading of them
    return json.dumps(value)


def to_yaml(value: Any, block: bool, indent: int = 0) -> str:
    """A YAML document for `value`: block style (indented) or flow style (`{a: [1]}`)."""
    pad = " " * indent
    if isinstance(value, dict) and value and block:
        lines = []
        for key, item in value.items():
            nested = isinstance(item, (dict, list)) and bool(item)
            body = to_yaml(item, block, indent + 2)
            lines.append(f"{pad}{yaml_scalar(key)}:" + (f"\n{body}" if nested else f" {body}"))
        return "\n".join(lines)
    if isinstance(value, list) and value and block:
        lines = []
        for item in value:
            body = to_yaml(item, block, indent + 2).lstrip(" ")
            lines.append(f"{pad}- {body}")
        return "\n".join(lines)
    if isinstance(value, dict):
        inner = ", ".join(f"{yaml_scalar(k)}: {to_yaml(v, False)}" for k, v in value.items())
        return "{" + inner + "}"
    if isinstance(value, list):
        return "[" + ", ".join(to_yaml(v, False) for v in value) + "]"
    return yaml_scalar(value)


def to_json(value: Any) -> str:
    """JSON text for `value`, with Python's NaN/Infinity words and raw text kept as it is."""
    if isinstance(value, Raw):
        return value.text
    if isinstance(value, DupKey):
        return json.dumps(value.name)
    if isinstance(value, dict):
        items = (
            f"{to_json(k) if isinstance(k, DupKey) else json.dumps(str(k))}: {to_json(v)}"
            for k, v in value.items()
        )
        return "{" + ", ".join(items) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(to_json(v) for v in value) + "]"
    return json.dumps(value)


def encode(text: str) -> bytes:
    """UTF-8, keeping lone surrogates (they become invalid UTF-8, which is worth a case)."""
    return text.encode("utf-8", "surrogatepass")


# ------------------------------------------------------------------ hostile values ---

HOSTILE_NUMBERS: list[Any] = [
    math.nan,
    math.inf,
    -math.inf,
    0.0,
    -0.0,
    -1,
    1e308,
    -1e308,
    5e-324,
    1e-320,
    2**63,
    -(2**63) - 1,
    10**30,
    1e16 + 1,
]
HOSTILE_WORDS = [
    "1" * 5000,
    "-" + "9" * 4400,
    "1e99999",
    "1e400",
    "-.inf",
    ".NaN",
    "NaN",
    "Infinity",
    "-Infinity",
    "0x1F",
    "0o17",
    "1_000",
    "+.5",
    "0.0.0",
    "2024-13-45",
    "2024-01-01",
    "12:30:00",
    "!!int x",
    "!!float []",
    "!!binary aGVsbG8=",
    "!!set {a, b}",
    "!!omap [a: 1]",
    "!!python/object/apply:os.system [echo hi]",
    "!custom x",
    "&a x",
    "*a",
    "*undefined",
    "? [a]",
    "|",
    ">",
    "'",
    '"',
    "[",
    "{",
    "@",
    "`",
    "%",
    '"0.5"',
    "[]",
    "{}",
    "[1, 2",
    "\t",
    "yes",
    "No",
    "Null",
    "~",
    "True",
    "",
]
NAMES = [
    "Root",
    "A",
    "B",
    "Leaf",
    "Null",
    "true",
    "1abc",
    "",
    "a" * 201,
    "é",
    "名前",
    "A\nB",
    "A B",
    "\u202eevil",
    "\x1b[31mred",
    "A\u2028B",
    "\ud800",
]

small_numbers = st.one_of(
    st.sampled_from([0, 0.0, 0.1, 0.5, 1, 1.0, 2]),
    st.floats(-3, 3, allow_nan=False),
    st.integers(-3, 12),
)
numbers = st.one_of(
    small_numbers,
    small_numbers,
    small_numbers,
    st.sampled_from(HOSTILE_NUMBERS),
    st.floats(),
    st.integers(-(2**70), 2**70),
    st.sampled_from(HOSTILE_WORDS).map(Raw),
)
names = st.one_of(
    st.sampled_from(NAMES),
    st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,10}", fullmatch=True),
    st.text(max_size=12),
)
junk = st.recursive(
    st.one_of(st.none(), st.booleans(), numbers, names),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(names, inner, max_size=4)),
    max_leaves=8,
)


def vec(n: int) -> st.SearchStrategy[Any]:
    """Mostly `n` numbers; sometimes a wrong length or not a list at all."""
    return st.one_of(
        st.lists(numbers, min_size=n, max_size=n),
        st.lists(numbers, min_size=n, max_size=n),
        st.lists(numbers, max_size=n + 2),
        junk,
    )


def matrix(n: int) -> st.SearchStrategy[Any]:
    return st.one_of(st.lists(vec(n), min_size=n, max_size=n), junk)


def sometimes_junk(strategy: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    return st.one_of(strategy, strategy, strategy, junk)


@st.composite
def mapping(
    draw: st.DrawFn,
    required: dict[str, st.SearchStrategy[Any]],
    optional: dict[str, st.SearchStrategy[Any]] | None = None,
) -> dict[Any, Any]:
    """A mapping of the format: required keys mostly there, optional ones sometimes, now and
    then an unknown or a duplicated key."""
    out: dict[Any, Any] = {}
    for key, value in required.items():
        if draw(st.integers(0, 9)):
            out[key] = draw(value)
    for key, value in (optional or {}).items():
        if draw(st.booleans()):
            out[key] = draw(value)
    if not draw(st.integers(0, 9)):
        out[draw(names)] = draw(junk)
    if out and not draw(st.integers(0, 14)):
        key = draw(st.sampled_from(sorted(str(k) for k in out)))
        out[DupKey(key)] = draw(junk)
    return out


def one_of_keys(options: dict[str, st.SearchStrategy[Any]]) -> st.SearchStrategy[Any]:
    """`{variant: params}` for one of `options` (a one-key mapping, as the formats write)."""
    return st.one_of(*(value.map(lambda v, k=key: {k: v}) for key, value in options.items()))


# ------------------------------------------------------------------------ grammars ---

GRAMMAR_TEXTS = {p.name: p.read_text(encoding="utf-8") for p in sorted(GRAMMARS.glob("*.yaml"))}
TYPE_POOL = ["Root", "A", "B", "C", "Leaf"]
type_names = st.one_of(st.sampled_from(TYPE_POOL), st.sampled_from(TYPE_POOL), names)
orientation = mapping({}, {"rpy": vec(3), "rpy_deg": vec(3), "quat_wxyz": vec(4)})
normal_params = mapping(
    {"variance": st.one_of(numbers, vec(3))},
    {
        "mean": vec(3),
        "covariance": matrix(3),
        "pin": st.lists(st.sampled_from(["x", "y", "z", "w", ""]), max_size=4),
        "fixed": st.booleans(),
    },
)
box_params = mapping({"min": vec(3), "max": vec(3)}, {"fixed": st.booleans()})
translation = st.one_of(
    st.sampled_from(["same", "uniform", "offset", ""]),
    one_of_keys(
        {
            "offset": vec(3),
            "world_normal": normal_params,
            "world_normal_offset": normal_params,
            "parent_normal_offset": normal_params,
            "world_box": box_params,
            "world_box_offset": box_params,
        }
    ),
    junk,
)
bingham = mapping(
    {"concentration": st.one_of(numbers, vec(3))},
    {"mode": orientation, "M": matrix(4), "Z": vec(4), "fixed": st.booleans()},
)
rotation = st.one_of(
    st.sampled_from(["same", "uniform", "offset"]),
    one_of_keys(
        {
            "offset": orientation,
            "world_bingham": bingham,
            "parent_bingham": bingham,
            "revolute": mapping({}, {"axis": vec(3), "min": numbers, "max": numbers}),
        }
    ),
    junk,
)
rule = mapping(
    {"child": type_names},
    {"p": numbers, "translation": translation, "rotation": rotation},
)
rules = st.one_of(st.lists(rule, max_size=4), junk)
count = one_of_keys(
    {
        "probs": st.one_of(st.lists(numbers, max_size=8), junk),
        "geometric": mapping(
            {"p": numbers, "max": st.one_of(st.integers(-2, 1002), numbers)},
            {"start": st.one_of(st.integers(-2, 20), numbers)},
        ),
    }
)
MESH_FILES = [
    "m.obj",
    "meshes/m.obj",
    "../m.obj",
    "a/../../m.obj",
    "/etc/passwd",
    "~/m.obj",
    "C:\\m.obj",
    "a\x00b",
    "x" * 300,
    "/".join(["d"] * 200),
    "",
    ".",
    "..",
]
shape = one_of_keys(
    {
        "box": mapping({"size": vec(3)}),
        "cylinder": mapping({"radius": numbers, "length": numbers}),
        "sphere": mapping({"radius": numbers}),
        "mesh": mapping(
            {"file": st.one_of(st.sampled_from(MESH_FILES), names)},
            {"scale": st.one_of(numbers, vec(3))},
        ),
        # a profile: [r, z] points, often from the axis back to it, sometimes crossing itself,
        # off the axis, with negative r or points of the wrong length
        "revolve": mapping(
            {
                "profile": sometimes_junk(
                    st.one_of(
                        st.builds(
                            lambda mid, z0, z1: [[0, z0], *mid, [0, z1]],
                            st.lists(vec(2), max_size=6),
                            numbers,
                            numbers,
                        ),
                        st.lists(st.one_of(vec(2), vec(3), junk), max_size=6),
                    )
                )
            }
        ),
        # an open box: walls that may leave no room inside, or be missing
        "tray": mapping({"size": vec(3)}, {"wall": numbers}),
    }
)
# a shape, sometimes with its `origin` in the object's frame beside it (or only the origin)
geometry = sometimes_junk(
    st.one_of(
        shape,
        st.builds(lambda g, o: {**g, "origin": o}, shape, st.one_of(vec(3), vec(2), junk)),
        st.builds(lambda o: {"origin": o}, vec(3)),
    )
)
node_type = mapping(
    {},
    {
        "observed": sometimes_junk(st.booleans()),
        "geometry": geometry,
        "model": st.one_of(st.sampled_from(MESH_FILES), names),
        "body": sometimes_junk(
            mapping(
                {},
                {
                    "static": sometimes_junk(st.booleans()),
                    "mass": numbers,
                    "density": numbers,
                    "collision": st.one_of(st.sampled_from(["hull", "decomposition"]), names),
                },
            )
        ),
        "labels": st.one_of(st.lists(names, max_size=3), junk),
        "max_nesting": st.one_of(st.integers(-1, 101), numbers),
        "fixed": st.booleans(),
        "and": rules,
        "or": rules,
        "independent": rules,
        "repeat": mapping({"count": sometimes_junk(count), "rule": sometimes_junk(rule)}),
    },
)
bound = st.one_of(st.integers(-2, 12), numbers, st.none())
type_list = st.one_of(st.lists(type_names, max_size=3), junk)
axis = st.sampled_from(["x", "y", "z", "w"])
exempt = st.one_of(st.lists(st.lists(type_names, max_size=3), max_size=2), junk)
radius = st.one_of(st.dictionaries(type_names, numbers, max_size=2), junk)
tail = sometimes_junk(
    mapping({"rate": st.one_of(st.floats(0, 1.5), numbers), "mean": numbers})
)  # a physical tail of ssg explain (ssgc/tails.py)
box_corner = st.one_of(st.lists(st.one_of(numbers, st.none()), min_size=3, max_size=3), junk)
constraint = one_of_keys(
    {
        "count": mapping({"type": type_names}, {"min": bound, "max": bound}),
        "longest_chain": mapping({"type": type_names}, {"min": bound, "max": bound}),
        "children": mapping({"of": type_names}, {"child": type_names, "min": bound, "max": bound}),
        "inside_box": mapping(
            {"types": type_list, "min": box_corner, "max": box_corner},
            {
                "frame": type_names,
                "keep_out": st.booleans(),
                "radius": radius,
                "geometry": sometimes_junk(st.booleans()),
                "floating": tail,
                "outside": tail,
            },
        ),
        "clearance": mapping(
            {"types": type_list},
            {"radius": radius, "exempt": exempt, "exempt_ancestors": st.booleans()},
        ),
        "upright": mapping(
            {"types": type_list, "max_angle_deg": numbers},
            {"axis": axis, "frame": type_names, "frame_axis": axis},
        ),
        "non_penetration": mapping(
            {"types": type_list}, {"margin": numbers, "exempt": exempt, "tail": tail}
        ),
    }
)
noise_spec = mapping({}, {"position": numbers, "rotation_deg": numbers})
observation = mapping(
    {},
    {
        "noise": st.one_of(
            st.dictionaries(
                st.one_of(type_names, st.just("default")), sometimes_junk(noise_spec), max_size=3
            ),
            junk,
        ),
        "clutter": mapping(
            {
                "region": mapping({"min": box_corner, "max": box_corner}, {}),
                "rates": st.one_of(st.dictionaries(type_names, numbers, max_size=3), junk),
            },
            {"max": bound},
        ),
    },
)
grammar_doc = mapping(
    {
        "grammar": sometimes_junk(names),
        "root": st.one_of(
            type_names,
            mapping({"type": type_names}, {"pose": orientation, "required": st.booleans()}),
            junk,
        ),
        "types": st.one_of(
            st.dictionaries(type_names, sometimes_junk(node_type), min_size=1, max_size=5), junk
        ),
    },
    {
        "description": sometimes_junk(st.text(max_size=20)),
        "constraints": st.one_of(
            st.dictionaries(names, sometimes_junk(constraint), max_size=3), junk
        ),
        "observation": sometimes_junk(observation),
    },
)


@st.composite
def built_grammars(draw: st.DrawFn) -> str:
    """A grammar document built key by key from the language, with hostile values in it."""
    doc = draw(sometimes_junk(grammar_doc))
    if draw(st.integers(0, 4)) == 0:
        return to_json(doc)  # JSON is YAML too
    return to_yaml(doc, block=draw(st.booleans())) + "\n"


@st.composite
def deep_grammars(
    draw: st.DrawFn, longest: int = 1500, deepest: int = 100, most: int = 1000
) -> str:
    """Long chains and cycles of types: recursion bounded, unbounded, and exploding (up to
    `longest` types, `max_nesting` up to `deepest`, counts up to `most`)."""
    n = draw(st.integers(1, longest))
    shape = draw(st.sampled_from(["chain", "cycle", "bounded-cycle", "explosive", "wide"]))
    lines = ["grammar: deep", "root: T0", "types:"]
    if shape == "wide":  # one type with n rules, each a child type
        lines.append("  T0:\n    and:")
        lines += [f"      - child: T{i + 1}" for i in range(n)]
        lines += [f"  T{i + 1}: {{observed: true}}" for i in range(n)]
        return "\n".join(lines) + "\n"
    if shape == "explosive":  # nested repeats with large counts under a recursion bound
        nesting = draw(st.integers(1, deepest))
        counts = draw(st.integers(1, most))
        probs = ", ".join(["0"] * counts + ["1"])
        lines += [
            "  T0: {and: [{child: T1}]}",
            f"  T1: {{max_nesting: {nesting}, observed: true, repeat: "
            f"{{count: {{probs: [{probs}]}}, rule: {{child: T1}}}}}}",
        ]
        return "\n".join(lines) + "\n"
    bounded = draw(st.integers(0, n - 1)) if shape == "bounded-cycle" else -1
    for i in range(n):
        child = f"T{i + 1}" if i + 1 < n or shape == "chain" else "T1"
        bound = f"max_nesting: {draw(st.integers(1, deepest))}, " if i == bounded else ""
        lines.append(f"  T{i}: {{{bound}observed: true, and: [{{child: {child}}}]}}")
    if shape == "chain":
        lines.append(f"  T{n}: {{observed: true}}")
    return "\n".join(lines) + "\n"


G15 = """grammar: deep
root: T0
types:
  T0: {and: [{child: T1}]}
  T1: {max_nesting: 2, observed: true, repeat: {count: {probs: [0, 1]}, rule: {child: T1}}}
"""


@fuzz(quick=8)
@given(text=deep_grammars(longest=6, deepest=3, most=3))
@example(text=G15)
def test_fuzz_parse_small_deep_grammars(work: Path, text: str) -> None:
    """Scenes sampled from small deep grammars parse (exit 0), their best tree at least as
    probable as the sampled one.  Was exit 2, `infeasible`, for the bug hunt's g15 (G15):
    the parser charged the second T1's repeat, blocked by `max_nesting`, log P(0) = -inf,
    where the sampler and the scorer give a blocked repeat no children with probability 1."""
    data = encode(text)
    grammar, out = write(work / "deep.yaml", data), work / "deep_scenes"
    args = ["sample", str(grammar), "-n", "2", "-o", str(out), "-q", "--overwrite"]
    result = invoke(args)
    check(result, {0, 1}, [grammar, out], data)
    if result.exit_code != 0:
        return  # an unbounded cycle: refused
    result = invoke(["parse", str(out), "-g", str(grammar), "-q"])
    check(result, {0}, [grammar, out], data)
    for scene in json.loads(result.stdout)["scenes"]:
        truth = json.loads((out / f"{scene['name']}.json").read_text())["log_prob"]
        assert scene["parses"][0]["score"] >= truth - 1e-9, (scene, text)


NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
NOISE = st.text(
    alphabet=st.sampled_from(list(":-[]{},#&*!|>'\"%@`?\t\n a0.\x07\x00\ufeffé\u2028\\")),
    min_size=1,
    max_size=6,
)


@st.composite
def mutated(draw: st.DrawFn, texts: list[str]) -> str:
    """A real file with a few edits: lines deleted, duplicated (duplicate keys) or moved,
    numbers and words replaced by hostile ones, noise inserted, the end cut off."""
    text = draw(st.sampled_from(texts))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(
            st.sampled_from(
                ["delete", "duplicate", "move", "number", "word", "insert", "indent", "truncate"]
            )
        )
        lines = text.splitlines(keepends=True)
        if op in ("delete", "duplicate", "move", "indent") and lines:
            i = draw(st.integers(0, len(lines) - 1))
            line = lines[i]
            if op == "delete":
                del lines[i]
            elif op == "duplicate":
                lines.insert(i, line)
            elif op == "move":
                del lines[i]
                lines.insert(draw(st.integers(0, len(lines))), line)
            else:
                lines[i] = " " * draw(st.integers(0, 5)) + line.lstrip(" ")
            text = "".join(lines)
        elif op in ("number", "word"):
            matches = list((NUMBER if op == "number" else WORD).finditer(text))
            if matches:
                m = draw(st.sampled_from(matches))
                new = draw(
                    st.one_of(
                        st.sampled_from(HOSTILE_WORDS),
                        numbers.map(yaml_scalar),
                        names.map(yaml_scalar),
                        st.text(max_size=6),
                    )
                )
                text = text[: m.start()] + new + text[m.end() :]
        elif op == "insert":
            at = draw(st.integers(0, len(text)))
            text = text[:at] + draw(NOISE) + text[at:]
        else:
            text = text[: draw(st.integers(0, len(text)))]
    return text


def alias_bomb(width: int, depth: int) -> str:
    lines = [f"a0: &a0 [{', '.join(['lol'] * width)}]"]
    for i in range(1, depth + 1):
        lines.append(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]")
    return "\n".join(lines) + "\n"


@st.composite
def yaml_oddities(draw: st.DrawFn) -> str:
    """Documents that stress the reader: bombs, nesting, tags, anchors, directives."""
    n = draw(st.integers(1, 30_000))
    grammar = draw(st.sampled_from(sorted(GRAMMAR_TEXTS.values())))
    return draw(
        st.sampled_from(
            [
                alias_bomb(draw(st.integers(2, 12)), draw(st.integers(1, 9))),
                "[" * n + "]" * draw(st.integers(0, n)),
                "{a: " * n + "1" + "}" * draw(st.integers(0, n)),
                "".join(f"{' ' * (2 * i)}k{i}:\n" for i in range(min(n, 3000))) + "  v\n",
                "- " * min(n, 5000) + "x\n",
                "a: &a [*a]\n",
                "a: &a {b: *a}\n",
                "&a a: 1\n*a : 2\n",
                "base: &b {grammar: g, root: R}\n<<: *b\ntypes: {R: {}}\n",
                "grammar: g\nroot: R\ntypes: {R: {}}\n<<: [*x]\n",
                "%YAML 1.1\n---\ngrammar: g\nroot: R\ntypes: {R: {observed: yes}}\n",
                "%TAG ! tag:evil.example,2024:\n---\ngrammar: !x g\n",
                "--- !!python/object/apply:os.system ['echo hi']\n",
                "grammar: !!binary aGVsbG8=\nroot: R\ntypes: {R: {}}\n",
                "grammar: g\nroot: R\ntypes: !!omap [R: {}]\n",
                "grammar: g\nroot: R\ntypes: {? [R] : {}}\n",
                "grammar: g\nroot: R\ntypes: {? {a: [1]} : {}}\n",
                grammar + "\n---\n" + grammar,
                grammar.replace("\n", "\r\n"),
                grammar.replace("\n", "\r"),
                grammar.replace("  ", "\t", 1),
                "\ufeff\ufeff" + grammar,
                "grammar: g\nroot: R\ntypes: {R: {}}\n" + "# " + "x" * n + "\n",
                "grammar: " + "x" * n + "\nroot: R\ntypes: {R: {}}\n",
                "grammar: g\nroot: R\ntypes: {R: {labels: [" + ", ".join(["a"] * n) + "]}}\n",
                "grammar: g\nroot: R\ntypes:\n  R: {}\n  R: {}\n",
                '{"grammar": "g", "grammar": "h", "root": "R", "types": {"R": {}}}',
            ]
        )
    )


@st.composite
def raw_bytes(draw: st.DrawFn, texts: list[str]) -> bytes:
    """Bytes that are not (all) UTF-8 text: random, a valid file with bad bytes in it, other
    encodings, empty and blank files."""
    text = encode(draw(st.sampled_from(texts)))
    at = draw(st.integers(0, len(text)))
    return draw(
        st.one_of(
            st.binary(max_size=300),
            st.sampled_from([b"", b" ", b"\n\n", b"\xef\xbb\xbf", b"\x00", b"\xff\xfe"]),
            st.binary(min_size=1, max_size=4).map(lambda b: text[:at] + b + text[at:]),
            st.just(text.decode("utf-8", "replace").encode("utf-16")),
            st.just(text.decode("utf-8", "replace").encode("latin-1", "replace")),
        )
    )


def grammar_inputs() -> st.SearchStrategy[bytes]:
    texts = list(GRAMMAR_TEXTS.values())
    return st.one_of(
        mutated(texts).map(encode),
        mutated(texts).map(encode),
        built_grammars().map(encode),
        built_grammars().map(encode),
        deep_grammars().map(encode),
        yaml_oddities().map(encode),
        raw_bytes(texts),
    )


# -------------------------------------------------------------------------- scenes ---


def small_scenes(grammar_file: str, seed: int, most: int = 6) -> list[str]:
    """JSON scenes sampled from a grammar, with at most `most` objects (the parser is fast on
    them), as written by `ssg sample` (with the tree) and as a user would (objects only)."""
    g = load_grammar(GRAMMARS / grammar_file)
    trees, logp = sample_trees(g, 40, seed)
    out = []
    for i in range(40):
        scene = scene_from_tree(g, trees.tree(i), f"s{i}", float(logp[i]))
        if len(scene) <= most:
            text = dumps_scene(g, scene, seed=seed, index=i)
            out.append(text)
            doc = json.loads(text)
            out.append(json.dumps({"objects": doc["objects"]}, indent=1))
        if len(out) >= 12:
            break
    return out


def small_sink_scenes(most: int = 4) -> list[str]:
    """Scenes of the sink dataset with at most `most` dishes, one or two to a file."""
    text = SINK_DATA.read_text(encoding="utf-8")
    starts = [m.start() for m in re.finditer(r"^\S", text, re.MULTILINE)] + [len(text)]
    blocks = [text[a:b] for a, b in itertools.pairwise(starts)]
    small = [b for b in blocks if b.count("model_file:") - 1 <= most][:8]
    return small + [a + b for a, b in zip(small[::2], small[1::2], strict=False)]


SINK_GRAMMAR = load_grammar(GRAMMARS / "sink.yaml")
SCENE_TEXTS = small_scenes("sink.yaml", 0) + small_scenes("singles_pairs_dependency.yaml", 1)
SINK_TEXTS = small_sink_scenes()


def parse_outputs(texts: list[str]) -> list[str]:
    """`ssg parse` outputs whose best parse of each scene is its sampled tree (a valid
    output of the grammar), one or two scenes to a file: `export` and `settle` read them."""
    docs = [json.loads(t) for t in texts]
    scenes = [
        {
            "name": d["name"],
            "status": "optimal",
            "parses": [{"score": d["log_prob"], "tree": d["tree"]}],
        }
        for d in docs
        if "tree" in d
    ]
    out = [{"grammar": "g", "scenes": [s]} for s in scenes]
    out += [{"grammar": "g", "scenes": [a, b]} for a, b in itertools.pairwise(scenes[:4])]
    return [json.dumps(d, indent=1) for d in out]


PARSE_TEXTS = parse_outputs(SCENE_TEXTS)
OBJECT_TYPES = sorted(
    {t.name for name in PARSE_GRAMMARS for t in load_grammar(GRAMMARS / name).types}
)
MODELS = sorted(t.model for t in SINK_GRAMMAR.types if t.model)
LABELS = sorted({label for t in SINK_GRAMMAR.types for label in t.labels} | {"plate", "cup"})

pose = mapping({"xyz": vec(3)}, {"quat_wxyz": vec(4), "rpy": vec(3)})
scene_object = mapping(
    {"type": st.one_of(st.sampled_from(OBJECT_TYPES), names), "pose": sometimes_junk(pose)},
    {"metadata": junk},
)
tree_node = mapping(
    {
        "id": st.one_of(st.integers(-1, 8), numbers),
        "type": st.one_of(st.sampled_from(OBJECT_TYPES), names),
        "pose": pose,
    },
    {
        "parent": st.one_of(st.none(), st.integers(-1, 8), numbers),
        "rule": st.one_of(st.none(), st.integers(-1, 4), numbers),
        "observed": junk,
    },
)
scene_doc = mapping(
    {"objects": st.one_of(st.lists(sometimes_junk(scene_object), max_size=5), junk)},
    {
        "format": st.one_of(st.just("ssgc.scene/1"), names),
        "name": names,
        "grammar": names,
        "seed": numbers,
        "index": numbers,
        "log_prob": numbers,
        "metadata": junk,
        "tree": mapping({"nodes": st.one_of(st.lists(tree_node, max_size=6), junk)}),
    },
)


@st.composite
def edited_json(draw: st.DrawFn, texts: list[str]) -> str:
    """A valid scene with one value somewhere in it replaced, removed or duplicated."""
    doc = json.loads(draw(st.sampled_from(texts)))
    for _ in range(draw(st.integers(1, 3))):
        parent, key = doc, None
        while True:  # walk down to a random place
            keys = list(parent) if isinstance(parent, dict) else list(range(len(parent)))
            if not keys:
                break
            key = draw(st.sampled_from(keys))
            child = parent[key]
            if not isinstance(child, (dict, list)) or not child or draw(st.integers(0, 2)) == 0:
                break
            parent = child
        if key is None:
            continue
        op = draw(st.sampled_from(["replace", "replace", "delete", "duplicate"]))
        if op == "replace":
            parent[key] = draw(st.one_of(numbers, junk, vec(3), vec(4)))
        elif op == "delete" and isinstance(parent, dict):
            del parent[key]
        elif op == "delete":
            parent.pop(key)
        elif isinstance(parent, dict):
            parent[DupKey(str(key))] = draw(junk)
        else:
            parent.append(parent[key])
    return to_json(doc)


@st.composite
def json_oddities(draw: st.DrawFn) -> str:
    n = draw(st.integers(1, 30_000))
    scene = draw(st.sampled_from(SCENE_TEXTS))
    return draw(
        st.sampled_from(
            [
                "[" * n + "]" * draw(st.integers(0, n)),
                '{"objects": ' * n + "[]" + "}" * draw(st.integers(0, n)),
                '{"objects": [], "objects": []}',
                '{"objects": [{"type": "DishBin", "type": "DishBin", "pose": {"xyz": [0, 0, 0]}}]}',
                '{"objects": [{"type": "DishBin", "pose": {"xyz": [' + "1" * n + ", 0, 0]}}]}",
                '{"objects": [], "seed": ' + "9" * n + "}",
                '{"objects": [], "log_prob": -' + "9" * n + ".5}",
                '{"objects": [], "log_prob": 1e999}',
                '{"objects": [], "name": "' + "x" * n + '"}',
                '{"objects": [], "name": "a\\u0000b\\nc"}',
                '{"objects": [], "name": "\\ud800"}',
                scene + scene,
                scene.replace("\n", "\r\n"),
                "\ufeff" + scene,
                scene[: len(scene) // 2],
                scene.replace('"quat_wxyz"', '"rpy"', 1),
                scene.replace("[1.0, 0.0, 0.0, 0.0]", "[0, 0, 0, 0]"),
                scene.replace("[1.0, 0.0, 0.0, 0.0]", "[1e308, 1e308, 0, 0]"),
                scene.replace('"xyz": [', '"xyz": [1e308, ', 1).replace(", 0.0]", "]", 1),
            ]
        )
    )


def scene_json_inputs() -> st.SearchStrategy[bytes]:
    return st.one_of(
        mutated(SCENE_TEXTS).map(encode),
        edited_json(SCENE_TEXTS).map(encode),
        edited_json(SCENE_TEXTS).map(encode),
        sometimes_junk(scene_doc).map(to_json).map(encode),
        sometimes_junk(scene_doc).map(to_json).map(encode),
        json_oddities().map(encode),
        yaml_oddities().map(encode),
        raw_bytes(SCENE_TEXTS),
    )


parse_result_doc = mapping(
    {
        "scenes": st.one_of(
            st.lists(
                mapping(
                    {"name": names, "status": names},
                    {
                        "parses": st.lists(
                            mapping(
                                {"tree": mapping({"nodes": st.lists(tree_node, max_size=5)})},
                                {
                                    "score": numbers,
                                    "rules": st.lists(
                                        mapping({"node": numbers}, {"log_prob": numbers}),
                                        max_size=5,
                                    ),
                                },
                            ),
                            max_size=2,
                        )
                    },
                ),
                max_size=2,
            ),
            junk,
        )
    }
)


def render_inputs() -> st.SearchStrategy[bytes]:
    """Scenes and `ssg parse` outputs: what `render`, `view`, `export` and `settle` read."""
    return st.one_of(
        scene_json_inputs(),
        sometimes_junk(parse_result_doc).map(to_json).map(encode),
        edited_json(PARSE_TEXTS).map(encode),
        edited_json(PARSE_TEXTS).map(encode),
    )


sink_pose = mapping({"xyz": vec(3), "rpy": vec(3)})
sink_object = mapping(
    {"model_file": st.one_of(st.sampled_from(MODELS), names), "pose": sometimes_junk(sink_pose)},
    {
        "metadata": st.one_of(mapping({"class": st.one_of(st.sampled_from(LABELS), junk)}), junk),
        "root_body_name": names,
    },
)
sink_scene = mapping(
    {"objects": st.one_of(st.lists(sometimes_junk(sink_object), max_size=4), junk)},
    {
        "world_description": st.one_of(
            mapping({"models": st.one_of(st.lists(sink_object, max_size=2), junk)}), junk
        )
    },
)
sink_doc = st.one_of(st.dictionaries(names, sometimes_junk(sink_scene), max_size=3), junk)


@st.composite
def built_sink(draw: st.DrawFn) -> str:
    return to_yaml(draw(sink_doc), block=draw(st.booleans())) + "\n"


def sink_yaml_inputs() -> st.SearchStrategy[bytes]:
    return st.one_of(
        mutated(SINK_TEXTS).map(encode),
        mutated(SINK_TEXTS).map(encode),
        built_sink().map(encode),
        built_sink().map(encode),
        yaml_oddities().map(encode),
        raw_bytes(SINK_TEXTS),
    )


# ----------------------------------------------------------------------- the runs ---

RUNNER = CliRunner()
MORE = re.compile(r"^\.\.\. and \d+ more$")
# `ssg parse`: a scene it could not parse; `ssg settle`: a scene that did not come to rest
STATUS = re.compile(r"^.*: (infeasible|no_parse|error|not settled): ")
PARSE_CODES = {0, 1, 2, 3, 4}  # 3: no parse found (unproven), 4: time limit (docs/robustness.md)


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def invoke(args: list[str]) -> Result:
    """Run `ssg ARGS` in process, with numpy's floating-point warnings off as `main()` does."""
    with np.errstate(all="ignore"):
        return RUNNER.invoke(app, args)


def check(result: Result, codes: set[int], files: list[Path], data: bytes) -> None:
    """The contract of every command with any input (see the module docstring)."""
    shown = f"input {data[:300]!r}{'...' if len(data) > 300 else ''}\nstderr:\n{result.stderr}"
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        import traceback

        trace = "".join(traceback.format_exception(result.exception))
        pytest.fail(f"uncaught exception\n{trace}\n{shown}")
    assert result.exit_code != 70, f"internal error\n{shown}"
    assert result.exit_code in codes, f"exit code {result.exit_code}\n{shown}"
    assert "Traceback" not in result.output, shown
    if result.exit_code != 0:
        assert result.stderr.strip(), f"an error without a message\n{shown}"
    diagnostic = re.compile(
        "^(" + "|".join(re.escape(str(f)) for f in files) + r")(:\d+(:\d+)?)?: (error|warning): \S"
    )
    for line in result.stderr.splitlines():
        ok = diagnostic.match(line) or MORE.match(line) or (2 in codes and STATUS.match(line))
        assert ok, f"not one diagnostic per line: {line!r}\n{shown}"


def write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


@fuzz(quick=120)
@given(data=grammar_inputs())
def test_fuzz_validate(work: Path, data: bytes) -> None:
    path = write(work / "grammar.yaml", data)
    check(invoke(["validate", str(path)]), {0, 1}, [path], data)


@fuzz(quick=40)
@given(data=grammar_inputs(), as_json=st.booleans())
def test_fuzz_inspect(work: Path, data: bytes, as_json: bool) -> None:
    path = write(work / "grammar.yaml", data)
    result = invoke(["inspect", str(path), *(["--json"] if as_json else [])])
    check(result, {0, 1}, [path], data)
    if result.exit_code == 0 and as_json:
        json.loads(result.stdout)


@fuzz(quick=40)
@given(data=grammar_inputs())
def test_fuzz_sample(work: Path, data: bytes) -> None:
    path = write(work / "grammar.yaml", data)
    out = work / "out"  # each case is another run: --overwrite clears the last one's scenes
    result = invoke(["sample", str(path), "-n", "2", "-o", str(out), "-q", "--overwrite"])
    check(result, {0, 1}, [path, out], data)


@fuzz(quick=40)
@given(
    data=grammar_inputs(),
    names=st.sampled_from(["all", "all", "a,b", "", ","]),
    more=st.sampled_from([[], ["-j", "2"], ["--resume"], ["-j", "2", "--resume"]]),
)
def test_fuzz_sample_constrained(work: Path, data: bytes, names: str, more: list[str]) -> None:
    path = write(work / "grammar.yaml", data)
    out = work / "out_constrained"
    args = ["sample", str(path), "-n", "2", "-o", str(out), "-q", "--constraints", names, *more]
    result = invoke([*args, "--max-tries", "3000", "--time-limit", "20"])
    check(result, {0, 1, 2}, [path, out], data)


@fuzz(quick=30)
@given(
    data=render_inputs(),
    grammar=st.sampled_from(PARSE_GRAMMARS),
    fmt=st.sampled_from(["dmd", "sdf", "mjcf", "glb", "usd"]),
)
@example(data=b'{"objects": [], "name": "' + b"x" * 250 + b'"}', grammar="sink.yaml", fmt="dmd")
def test_fuzz_export_json(work: Path, data: bytes, grammar: str, fmt: str) -> None:
    path = write(work / "scene.json", data)
    grammar_path = GRAMMARS / grammar
    args = ["export", str(path), "-g", str(grammar_path), "-f", fmt, "-o", str(work / "exported")]
    result = invoke([*args, "-q"])
    check(result, {0, 1}, [path, grammar_path], data)


@fuzz(quick=20)
@given(data=render_inputs(), grammar=st.sampled_from(PARSE_GRAMMARS))
def test_fuzz_settle_json(work: Path, data: bytes, grammar: str) -> None:
    path = write(work / "scene.json", data)
    grammar_path = GRAMMARS / grammar
    args = ["settle", str(path), "-g", str(grammar_path), "-o", str(work / "settled"), "-q"]
    result = invoke([*args, "--max-time", "0.2"])
    check(result, {0, 1, 2}, [path, grammar_path], data)
    if result.exit_code in (0, 2):
        for settled in (work / "settled").glob("*.json"):
            json.loads(settled.read_text(), parse_constant=pytest.fail)  # no NaN or Infinity


@fuzz(quick=30)
@given(data=st.binary(max_size=3000), suffix=st.sampled_from([".obj", ".stl", ".ply", ".glb"]))
def test_fuzz_mesh_file(work: Path, data: bytes, suffix: str) -> None:
    """Any bytes as a mesh: `ssg validate` accepts the file or says why, at the mesh's line."""
    write(work / f"m{suffix}", data)
    path = work / "g.yaml"
    path.write_text(
        f"grammar: g\nroot: A\ntypes:\n  A:\n    observed: true\n"
        f"    geometry: {{mesh: {{file: m{suffix}}}}}\n"
    )
    result = invoke(["validate", str(path)])
    check(result, {0, 1}, [path], data)
    if result.exit_code == 1:
        assert f"{path}:6:" in result.stderr, result.stderr


def check_parse(work: Path, data: bytes, suffix: str, grammar: str) -> None:
    path = write(work / f"scene{suffix}", data)
    grammar_path = GRAMMARS / grammar
    result = invoke(["parse", str(path), "-g", str(grammar_path), "-q"])
    check(result, PARSE_CODES, [path, grammar_path], data)
    if result.exit_code in (0, 2, 3, 4):
        assert json.loads(result.stdout)["scenes"], result.stdout


@fuzz(quick=40)
@given(data=scene_json_inputs(), grammar=st.sampled_from(PARSE_GRAMMARS))
def test_fuzz_parse_json(work: Path, data: bytes, grammar: str) -> None:
    check_parse(work, data, ".json", grammar)


@fuzz(quick=30)
@given(data=sink_yaml_inputs(), grammar=st.sampled_from(PARSE_GRAMMARS))
def test_fuzz_parse_sink_yaml(work: Path, data: bytes, grammar: str) -> None:
    check_parse(work, data, ".yaml", grammar)


@fuzz(quick=25)
@given(data=scene_json_inputs(), grammar=st.sampled_from(PARSE_GRAMMARS))
def test_fuzz_explain_json(work: Path, data: bytes, grammar: str) -> None:
    path = write(work / "scene.json", data)
    grammar_path = GRAMMARS / grammar
    result = invoke(["explain", str(path), "-g", str(grammar_path), "--json"])
    check(result, PARSE_CODES, [path, grammar_path], data)
    if result.exit_code in (0, 2, 3, 4):
        assert json.loads(result.stdout)["scenes"], result.stdout


@fuzz(quick=25)
@given(data=render_inputs(), with_grammar=st.booleans())
def test_fuzz_render(work: Path, data: bytes, with_grammar: bool) -> None:
    """`ssg render` on any scene or parse result: a picture or one message, never a half file."""
    path = write(work / "scene.json", data)
    out = work / "picture.png"
    out.unlink(missing_ok=True)
    grammar = ["-g", str(GRAMMARS / "sink.yaml")] if with_grammar else []
    result = invoke(["render", str(path), "-o", str(out), "-q", *grammar])
    check(result, {0, 1}, [path, GRAMMARS / "sink.yaml"], data)
    assert out.exists() == (result.exit_code == 0)
    assert not list(work.glob(".picture.png.*"))


@fuzz(quick=15)
@given(data=render_inputs(), with_grammar=st.booleans())
def test_fuzz_view(work: Path, data: bytes, with_grammar: bool) -> None:
    """`ssg view` reads what `ssg render` reads: a page or one message, never a half file."""
    path = write(work / "scene.json", data)
    out = work / "page.html"
    out.unlink(missing_ok=True)
    grammar = ["-g", str(GRAMMARS / "sink.yaml")] if with_grammar else []
    result = invoke(["view", str(path), "-o", str(out), "-q", *grammar])
    check(result, {0, 1}, [path, GRAMMARS / "sink.yaml"], data)
    assert out.exists() == (result.exit_code == 0)
    if result.exit_code == 0:
        html = out.read_text()
        assert html.count("</script>") == 2  # nothing in the data ends its block
    assert not list(work.glob(".page.html.*"))


def check_fit(work: Path, dataset: Path, grammar: Path, data: bytes, estep: str = "topn") -> None:
    """`ssg fit` on anything: the contract, and a fitted grammar that compiles or no file."""
    out = work / "fitted.yaml"
    out.unlink(missing_ok=True)
    args = ["fit", str(dataset), "-g", str(grammar), "-o", str(out), "-q", "--estep", estep]
    if estep == "mcmc":
        args += ["--samples", "4"]
    result = invoke([*args, "--iterations", "2", "--top", "2", "--time-limit", "5"])
    check(result, {0, 1, 2}, [dataset, grammar, out], data)
    if result.exit_code == 0:  # read as ssgc reads a grammar (a leading BOM is not text)
        compile_text(read_grammar_text(out), str(out))
    else:
        assert not out.exists()


FIT_BOUNDS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["1e-300", "10000", "10000.0001", "0", "-0", "1e4x", "", "0x10"]),
)


@fuzz(quick=12)
@given(variance=FIT_BOUNDS, ceiling=FIT_BOUNDS)
@example(variance="inf", ceiling="400")
@example(variance="1e-4", ceiling="nan")
@example(variance="5.992310449541053e+307", ceiling="1e-300")  # the fit overflowed to inf
def test_fuzz_fit_bounds(work: Path, variance: str, ceiling: str) -> None:
    """`--min-variance` and `--max-concentration` given any text: a fit, or a usage message
    naming the flag (exit 2) and no file, never an internal error (`inf` was one)."""
    data = work / "bounds_data"
    if not data.exists():
        assert (
            invoke(
                ["sample", str(GRAMMARS / "gmm.yaml"), "-n", "4", "-o", str(data), "-q"]
            ).exit_code
            == 0
        )
    out = work / "bounds.yaml"
    out.unlink(missing_ok=True)
    args = ["fit", str(data), "-g", str(GRAMMARS / "gmm.yaml"), "-o", str(out), "-q"]
    bounds = [f"--min-variance={variance}", f"--max-concentration={ceiling}"]
    result = invoke([*args, "--iterations", "1", "--top", "1", *bounds])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    assert result.exit_code in (0, 2), result.output
    assert "Traceback" not in result.output
    assert out.exists() == (result.exit_code == 0)
    if result.exit_code == 2:
        assert "--min-variance" in result.output or "--max-concentration" in result.output


@fuzz(quick=8)
@given(data=grammar_inputs(), estep=st.sampled_from(["topn", "mcmc"]))
@example(data=b"\xef\xbb\xbf" * 2 + GRAMMAR_TEXTS["gmm.yaml"].encode(), estep="topn")
@example(data=b"grammar: g\nroot: R\ntypes: {R: {}}\n", estep="topn")  # no rule: exit 70
def test_fuzz_fit_grammar(work: Path, data: bytes, estep: str) -> None:
    """Fuzzed grammars fitted to scenes they sampled themselves (when they can sample)."""
    path = write(work / "grammar.yaml", data)
    scenes = work / "fit_scenes"
    shutil.rmtree(scenes, ignore_errors=True)
    result = invoke(["sample", str(path), "-n", "3", "-o", str(scenes), "-q"])
    if result.exit_code != 0:
        scenes.mkdir(exist_ok=True)  # an empty dataset: refused, with a message
    check_fit(work, scenes, path, data, estep)


@fuzz(quick=30)
@given(
    data=scene_json_inputs(),
    grammar=st.sampled_from(PARSE_GRAMMARS),
    estep=st.sampled_from(["topn", "mcmc"]),
)
def test_fuzz_fit_dataset(work: Path, data: bytes, grammar: str, estep: str) -> None:
    check_fit(work, write(work / "dataset.json", data), GRAMMARS / grammar, data, estep)


@fuzz(quick=12)
@given(data=sink_yaml_inputs(), grammar=st.sampled_from(PARSE_GRAMMARS))
def test_fuzz_fit_sink_yaml(work: Path, data: bytes, grammar: str) -> None:
    """Sink-format datasets, as `parse` gets them: the third form of `ssg fit`'s dataset."""
    check_fit(work, write(work / "dataset.yaml", data), GRAMMARS / grammar, data)


@pytest.fixture(scope="module")
def journals(work: Path) -> dict[str, tuple[list[str], Path, str]]:
    """A complete journal of `ssg parse -o` and one of `ssg fit` (kept by disabling their
    deletion), with the command line that resumes each."""
    from ssgc.io.journal import Journal

    data = work / "journal_scenes"
    assert (
        invoke(["sample", str(GRAMMARS / "gmm.yaml"), "-n", "4", "-o", str(data), "-q"]).exit_code
        == 0
    )
    runs = {
        "parse": [
            "parse",
            str(data),
            "-g",
            str(GRAMMARS / "gmm.yaml"),
            "-o",
            str(work / "jp.json"),
        ],
        "fit": ["fit", str(data), "-g", str(GRAMMARS / "gmm.yaml"), "-o", str(work / "jf.yaml")],
    }
    runs["fit"] += ["--iterations", "2", "--top", "2"]
    found = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Journal, "delete", lambda self: None)
        for name, args in runs.items():
            result = invoke([*args, "-q"])
            assert result.exit_code == 0, result.output
            journal = Path(args[args.index("-o") + 1] + ".partial.jsonl")
            found[name] = ([*args, "-q", "--resume"], journal, journal.read_text())
    return found


def journal_inputs(text: str) -> st.SearchStrategy[bytes]:
    """A journal with lines deleted, duplicated or moved (each line still intact: the order
    checks), values or bytes changed (the checksums), cut off anywhere, or not text at all."""
    lines = text.splitlines(keepends=True)
    return st.one_of(
        mutated([text]).map(encode),
        mutated([text]).map(encode),
        st.integers(0, len(text)).map(lambda n: encode(text[:n])),
        st.permutations(lines).map(lambda ls: encode("".join(ls))),
        st.lists(st.sampled_from(lines), max_size=len(lines) + 2).map(
            lambda ls: encode("".join(ls))
        ),
        raw_bytes([text]),
    )


@fuzz(quick=25)
@given(data=st.data(), command=st.sampled_from(["parse", "fit"]))
def test_fuzz_resume_journal(
    journals: dict[str, tuple[list[str], Path, str]], data: st.DataObject, command: str
) -> None:
    """`--resume` from a damaged journal: a located message or a finished run, never a bug."""
    args, journal, text = journals[command]
    content = data.draw(journal_inputs(text))
    journal.write_bytes(content)
    out = Path(args[args.index("-o") + 1])
    out.unlink(missing_ok=True)
    result = invoke(args)
    files = [journal, out, Path(args[1]), GRAMMARS / "gmm.yaml"]
    check(result, {0, 1, 2}, files, content)
    if result.exit_code == 0 and command == "fit":
        compile_text(read_grammar_text(out), str(out))
    elif result.exit_code == 0:
        assert json.loads(out.read_text())["scenes"]
    else:
        assert not out.exists()


# The compiler itself, without the command line around it: every diagnostic of a grammar is
# located (line and column), whatever the text.  (Merged from test_grammar_errors.py.)
# no position when the nesting that exhausts the reader's recursion is on one line (`- - - -`)
UNLOCATED = ("invalid YAML: nested too deeply",)
LOCATED = re.compile(r"^case\.yaml:\d+:\d+: (error|warning): \S")


def grammar_texts() -> st.SearchStrategy[str]:
    texts = list(GRAMMAR_TEXTS.values())
    return st.one_of(mutated(texts), mutated(texts), built_grammars(), deep_grammars())


@fuzz(quick=150)
@given(text=st.one_of(grammar_texts(), yaml_oddities()))
def test_fuzz_compile_is_accepted_or_located(text: str) -> None:
    try:
        compile_text(text, "case.yaml")
    except GrammarError as exc:
        assert exc.diagnostics
        for d in exc.diagnostics:
            if d.message in UNLOCATED:
                continue
            assert d.file == "case.yaml" and d.line is not None and d.column is not None, str(d)
            assert d.line >= 1 and d.column >= 1, str(d)
            assert LOCATED.match(str(d)), str(d)
            assert "\n" not in str(d), str(d)


# ------------------------------------------------------- bugs the fuzzer has found ---


def run_ok(args: list[str], data: bytes, files: list[Path], codes: set[int]) -> Result:
    result = invoke(args)
    check(result, codes, files, data)
    return result


def chain(n: int, bound: str = "") -> str:
    """A grammar whose types form a chain T0 -> T1 -> ... -> Tn."""
    lines = ["grammar: chain", "root: T0", "types:"]
    lines += [f"  T{i}: {{{bound}observed: true, and: [{{child: T{i + 1}}}]}}" for i in range(n)]
    return "\n".join([*lines, f"  T{n}: {{observed: true}}"]) + "\n"


def test_inspect_of_a_long_chain_of_types(work: Path) -> None:
    """Was a RecursionError (exit 70): the supertree was counted recursively."""
    data = encode(chain(3000))
    path = write(work / "chain.yaml", data)
    result = run_ok(["inspect", str(path), "--json"], data, [path], {0})
    assert json.loads(result.stdout)["supertree_nodes"] == 3001


@pytest.mark.timing
def test_validate_of_many_types_is_not_slow(work: Path) -> None:
    """The recursion check copied paths (cubic time): 4000 types took 30 s, now ~1 s."""
    data = encode(chain(4000))
    path = write(work / "chain.yaml", data)
    started = time.monotonic()
    run_ok(["validate", str(path)], data, [path], {0})
    assert time.monotonic() - started < 20


def test_unbounded_recursion_in_a_long_cycle_is_reported(work: Path) -> None:
    text = chain(3000).replace("  T3000: {observed: true}", "  T3000: {and: [{child: T1}]}")
    path = write(work / "cycle.yaml", encode(text))
    result = run_ok(["validate", str(path)], encode(text), [path], {1})
    assert "unbounded recursion T1 -> T2 -> " in result.stderr
    assert "T2999 -> T3000 -> T1; set `max_nesting`" in result.stderr


@pytest.mark.parametrize(
    ("text", "at"),
    [
        ("[" * 3000, (1, 201)),
        ("{a: " * 3000, (1, 801)),
        ("grammar: g\nroot: [" + "[" * 250, (2, 207)),
        ("# '\"\nü: [" + "[" * 250, (2, 204)),  # columns count characters, not bytes
    ],
    ids=["brackets", "braces", "in-a-grammar", "after-non-ascii"],
)
def test_deep_flow_collections_are_refused_where_they_pass_the_limit(
    text: str, at: tuple[int, int]
) -> None:
    """Was "invalid YAML: nested too deeply" with no position, after 5-10 s in ruamel's
    scanner (its work per token grows with the open depth): 10 s of a CI fuzz run each."""
    with pytest.raises(GrammarError) as info:
        compile_text(text, "case.yaml")
    (d,) = info.value.diagnostics
    assert (d.line, d.column) == at
    assert d.message == "document is nested more than 200 levels deep"


def test_deep_block_nesting_is_located_at_its_deepest_line() -> None:
    """Block mappings nested past what the reader's recursion allows had no position."""
    text = "grammar: g\nroot: A\ntypes:\n" + "".join(
        " " * (2 * k + 2) + f"k{k}:\n" for k in range(400)
    )
    with pytest.raises(GrammarError) as info:
        compile_text(text, "case.yaml")
    (d,) = info.value.diagnostics
    assert d.message == "invalid YAML: nested too deeply"
    assert (d.line, d.column) == (3 + 400, 2 * 399 + 3)


def test_brackets_in_comments_and_quotes_are_not_nesting() -> None:
    """The depth count before ruamel skips quoted scalars and comments."""
    text = GRAMMAR_TEXTS["gmm.yaml"].replace("grammar: gmm", 'grammar: "gmm' + "[" * 150 + '"')
    grammar = compile_text(text + "# " + "{" * 300 + "\n", "case.yaml")
    assert grammar.name == "gmm" + "[" * 150


def test_supertree_too_large_to_count(work: Path) -> None:
    """Two bounded types nested 100 deep each, 1000 copies a level: more than 10**18 nodes."""
    probs = ", ".join(["0"] * 1000 + ["1"])
    text = dedent(f"""\
        grammar: huge
        root: R
        types:
          R: {{and: [{{child: A}}]}}
          A:
            max_nesting: 100
            repeat: {{count: {{probs: [{probs}]}}, rule: {{child: A}}}}
        """)
    path = write(work / "huge.yaml", encode(text))
    assert (
        json.loads(run_ok(["inspect", str(path), "--json"], b"", [path], {0}).stdout)[
            "supertree_nodes"
        ]
        is None
    )
    assert (
        "supertree: too large to count" in run_ok(["inspect", str(path)], b"", [path], {0}).stdout
    )


def test_sampling_an_exploding_grammar_is_a_message(work: Path) -> None:
    """Nested repeats of 10 under `max_nesting: 7`: 10**7 nodes a scene.  Was a hang and a
    machine out of memory; now refused as soon as a chunk of scenes passes the node limit."""
    text = dedent("""\
        grammar: boom
        root: R
        types:
          R: {and: [{child: A}]}
          A:
            max_nesting: 7
            repeat: {count: {probs: [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1]}, rule: {child: A}}
        """)
    path = write(work / "boom.yaml", encode(text))
    result = run_ok(
        ["sample", str(path), "-n", "2", "-o", str(work / "out"), "-q", "--overwrite"],
        b"",
        [path],
        {1},
    )
    assert "makes scenes too large to sample" in result.stderr


def test_sampling_beyond_the_limit_is_a_message(work: Path) -> None:
    """A variance of 1e14 m² drew objects thousands of km away, written to scene files no
    command reads; now refused before any is written."""
    text = dedent("""\
        grammar: far
        root: R
        types:
          R: {and: [{child: A, translation: {world_normal: {variance: 1e14}}}]}
          A: {observed: true}
        """)
    path = write(work / "far.yaml", encode(text))
    out = work / "far_out"  # `out` may hold another case's run, which is left as it was
    result = run_ok(
        ["sample", str(path), "-n", "2", "-o", str(out), "-q", "--overwrite"], b"", [path], {1}
    )
    assert "scene far_000000: object A was drawn at" in result.stderr
    assert "1,000 km" in result.stderr and not list(out.glob("*.json"))


def test_sampling_too_deep_trees_is_a_message(work: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Deeper than MAX_LEVELS was a RuntimeError (exit 70)."""
    import ssgc.sample.forward

    monkeypatch.setattr(ssgc.sample.forward, "MAX_LEVELS", 5)
    path = write(work / "chain.yaml", encode(chain(10)))
    result = run_ok(
        ["sample", str(path), "-n", "1", "-o", str(work / "out"), "--overwrite"], b"", [path], {1}
    )
    assert "makes trees deeper than 5 levels" in result.stderr


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        pytest.param(
            '{"objects": [{"type": "DishBin", "pose": {"xyz": [' + "1" * 5000 + ", 0, 0]}}]}",
            "1:51: error: invalid JSON: an integer of more than 4300 digits",
            id="5000-digit-integer",
        ),
        pytest.param(
            '{"objects": [],\n "bad\\ud800": 1}',
            "2:2: error: a string holds a lone UTF-16 surrogate",
            id="lone-surrogate",
        ),
        pytest.param('{"objects": [], "name": "a\\nb"}', "one line of printable", id="name"),
    ],
)
def test_bad_json_scenes(work: Path, text: str, fragment: str) -> None:
    data = encode(text)
    path = write(work / "scene.json", data)
    grammar = GRAMMARS / "sink.yaml"
    result = run_ok(["parse", str(path), "-g", str(grammar)], data, [path, grammar], {1})
    assert fragment in result.stderr


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        pytest.param(
            "s1:\n  objects: []\n  world_description: {models: 5}\n",
            "3:3: error: expected a mapping with a list `models`",
            id="models-not-a-list",
        ),
        pytest.param("{}\n", "1:1: error: the dataset has no scenes", id="no-scenes"),
        pytest.param('"a\\x1bb": {objects: []}\n', "printable text, got 'a\\x1bb'", id="name"),
    ],
)
def test_bad_sink_datasets(work: Path, text: str, fragment: str) -> None:
    data = encode(text)
    path = write(work / "scenes.yaml", data)
    grammar = GRAMMARS / "sink.yaml"
    result = run_ok(["parse", str(path), "-g", str(grammar)], data, [path, grammar], {1})
    assert fragment in result.stderr


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        pytest.param(
            'grammar: g\nroot: R\ntypes:\n  R: {"a\\nb": 1}\n',
            "unknown key 'a\\nb'",
            id="newline",
        ),
        pytest.param(
            '{"\\ud800\\udc00": null}', "unknown key '\U00010000'", id="surrogate-pair-joined"
        ),
        pytest.param('{"\\ud800": 1}', "1:2: error: a string holds a lone", id="lone-surrogate"),
        pytest.param(
            "grammar: " + "1" * 5000 + "\n",
            "as !!int (an integer of more than 4300 digits)",
            id="5000-digit-integer",
        ),
        # a rule's constants beyond the 1,000 km scene files hold made unreadable scenes
        pytest.param(
            "grammar: g\nroot: R\ntypes:\n  R: {and: [{child: A, translation: {offset: "
            "[0, 2e6, 0]}}]}\n  A: {observed: true}\n",
            "4:38: error: types.R.and[0].translation.offset: a position or offset must lie "
            "within 1,000 km",
            id="far-offset",
        ),
        pytest.param(
            "grammar: g\nroot: R\ntypes:\n  R: {and: [{child: A, translation: {world_normal: "
            "{mean: [1e300, 0, 0], variance: 1}}}]}\n  A: {observed: true}\n",
            "within 1,000 km of the origin on each axis, got 1e+300 m",
            id="far-mean",
        ),
        # a box or arc this narrow had a mass of up to 21 (its faces' 1e-6 tolerance)
        pytest.param(
            "grammar: g\nroot: R\ntypes:\n  R: {and: [{child: A, translation: {world_box: "
            "{min: [0, 0, 0], max: [1, 1, 1e-7]}}}]}\n  A: {observed: true}\n",
            "box is 1e-07 m wide on z, narrower than 0.0001 m",
            id="narrow-box",
        ),
        pytest.param(
            "grammar: g\nroot: R\ntypes:\n  R: {and: [{child: A, rotation: {revolute: "
            "{min: 0, max: 1e-7}}}]}\n  A: {observed: true}\n",
            "revolute range is 1e-07 rad wide, narrower than 0.0001 rad",
            id="narrow-revolute",
        ),
        pytest.param(
            "grammar: g\nroot: R\ntypes:\n  R: {and: [{child: A, translation: {world_normal: "
            "{covariance: [[1, 0, 0], [0, 1, 0], [0, 0, -1]], pin: [z]}}}]}\n"
            "  A: {observed: true}\n",
            "the variance of a pinned axis may be 0 but not negative, got -1 (z axis)",
            id="negative-pinned-covariance",
        ),
    ],
)
def test_bad_grammar_text(work: Path, text: str, fragment: str) -> None:
    data = encode(text)
    path = write(work / "grammar.yaml", data)
    result = run_ok(["validate", str(path)], data, [path], {1})
    assert fragment in result.stderr


def test_messages_and_tables_are_printed_as_they_are(work: Path) -> None:
    """rich printed `FILE:100:21` as `FILE💯21`, and read a grammar name "[/]" as markup in the
    `inspect` table title (an internal error); a name with a terminal escape is refused."""
    types = "".join(f"  T{i}: {{}}\n" for i in range(96))
    text = f"grammar: g\nroot: R\ntypes:\n{types}  R: {{and: [{{child: X}}]}}\n"
    path = write(work / "g.yaml", encode(text))
    assert f"{path}:100:21: error: " in run_ok(["validate", str(path)], b"", [path], {1}).stderr
    path = write(work / "g.yaml", b'grammar: "[/]:smile:"\nroot: R\ntypes: {R: {}}\n')
    assert "grammar '[/]:smile:'" in run_ok(["inspect", str(path)], b"", [path], {0}).stdout
    path = write(work / "g.yaml", b'grammar: "a\\e[31m"\nroot: R\ntypes: {R: {}}\n')
    result = run_ok(["validate", str(path)], b"", [path], {1})
    assert "1:10: error: the grammar name must be one line of printable text" in result.stderr


# ------------------------------------------------------------- the Python API ---


@fuzz(quick=40)
@given(
    objects=st.lists(
        st.tuples(
            st.sampled_from(["Root", "Point", "Nope", "", "P\u00f6int\n", "Root "]),
            st.lists(st.floats(width=64) | st.integers(-(10**400), 10**400), max_size=4),
            st.lists(st.floats(-2, 2) | st.just(0.0), min_size=3, max_size=5),
        ),
        max_size=4,
    )
)
def test_fuzz_api_scene_from_python_data(objects: list[tuple[str, list, list]]) -> None:
    """`Grammar.scene` checks Python data as a scene file is checked: a scene, or a
    `SceneError` whose every diagnostic is located in `<python>`."""
    from ssgc.errors import SceneError

    g = _api_gmm()
    try:
        scene = g.scene(objects)
    except SceneError as exc:
        assert exc.diagnostics and all(d.file == "<python>" and d.message for d in exc.diagnostics)
        return
    assert len(scene) == len(objects) and scene.types == [o[0] for o in objects]
    assert np.all(np.isfinite(scene.xyz)) and np.allclose(np.linalg.norm(scene.quat, axis=1), 1)


@functools.cache
def _api_gmm() -> Any:
    from ssgc.api import load_grammar

    return load_grammar(GRAMMARS / "gmm.yaml")


# ------------------------------------------------- every command, generated grammars ---


@fuzz(quick=6)
@given(spec=grammar_gen.grammars(extras=True))
def test_every_command_on_generated_grammars(work: Path, spec: dict[str, Any]) -> None:
    """Valid grammars of the whole language (tests/grammar_gen.py, with geometry, pose
    constraints and an observation section) through every command, on scenes sampled from
    them: the same contract.  (Found this way: a scene with no object stopped `parse` and
    `export`, a scene without geometry stopped `export --format glb`, a clutter object in a
    tree stopped `explain` and constrained sampling.)"""
    import tempfile

    text = grammar_gen.to_yaml(spec).encode()
    d = Path(tempfile.mkdtemp(dir=work))
    g, scenes = write(d / "g.yaml", text), d / "scenes"
    result = invoke(["sample", str(g), "-n", "3", "--seed", "1", "-o", str(scenes), "-q"])
    check(result, {0}, [g, scenes], text)
    runs: list[tuple[list[str], set[int]]] = [
        (["export", str(scenes), "-g", str(g), "-f", f, "-o", str(d / f), "-q"], {0})
        for f in ("dmd", "sdf", "mjcf", "glb", "usd")
    ]
    runs += [
        (["parse", str(scenes), "-g", str(g), "-q", "--time-limit", "3"], PARSE_CODES),
        (["explain", str(scenes), "-g", str(g), "--time-limit", "3"], PARSE_CODES),
        (
            [
                "fit",
                str(scenes),
                "-g",
                str(g),
                "-o",
                str(d / "fit.yaml"),
                "-q",
                "--iterations",
                "1",
                "--time-limit",
                "20",
            ],
            {0, 1, 2},
        ),
        (["render", str(scenes), "-g", str(g), "-o", str(d / "r.png"), "-n", "2", "-q"], {0}),
        (["view", str(scenes), "-g", str(g), "-o", str(d / "v.html"), "-q"], {0}),
        (["inspect", str(g), "--diagram", str(d / "d.svg")], {0}),
        (["settle", str(scenes), "-g", str(g), "-o", str(d / "settled"), "-q"], {0, 2}),
        (
            [
                "sample",
                str(g),
                "-n",
                "2",
                "--constraints",
                "all",
                "-o",
                str(d / "c"),
                "-q",
                "--max-tries",
                "500",
                "--time-limit",
                "10",
            ],
            {0, 2},
        ),
    ]
    for args, codes in runs:
        check(invoke(args), codes, [g, scenes], text)
