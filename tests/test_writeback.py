"""Writing fitted numbers back into grammar YAML (ssgc.fit.writeback).

`ssg fit` rewrites the user's own file, so the tests check that nothing but the numbers changes
(byte-identity without updates, numeric-only diffs with them), that what is written compiles
and reads back as the rounded values, and that tied (anchored) parameters are handled.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from ruamel.yaml import YAML
from ruamel.yaml.comments import merge_attrib
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.fit import writeback
from ssgc.fit.writeback import (
    Loc,
    Orientation,
    SharedValueConflict,
    Update,
    apply_updates,
    format_number,
    shared_nodes,
)
from ssgc.geometry import quat_canonical, rpy_to_quat
from ssgc.io.scene import dumps_scene, scene_from_tree
from ssgc.sample.forward import sample_trees

ROOT = Path(__file__).resolve().parent.parent
GRAMMARS = sorted((ROOT / "grammars").glob("*.yaml"))
NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
FITTED = ("p", "variance", "mean", "concentration")


def load(text: str) -> Any:
    return YAML(typ="rt", pure=True).load(text)


def comments(text: str) -> list[str]:
    """Every comment of the bundled grammars (they have no `#` inside strings)."""
    return [line[line.index("#") :] for line in text.splitlines() if "#" in line]


def changed(value: Any) -> Any:
    """A new, still valid value for a fitted key (probabilities stay in (0, 1])."""
    if isinstance(value, list):
        return [changed(v) for v in value]
    return float(value) * 0.73 + 0.0123456789


def fitted_updates(tree: Any, path: Loc = ()) -> list[Update]:
    """One update per mapping that holds fitted numbers, found by walking the document."""
    out: list[Update] = []
    if isinstance(tree, dict):
        values = {k: changed(v) for k, v in tree.items() if k in FITTED}
        if values:
            out.append(Update(path, values))
        for key, value in tree.items():
            out += fitted_updates(value, (*path, key))
    elif isinstance(tree, list):
        for i, value in enumerate(tree):
            out += fitted_updates(value, (*path, i))
    return out


def orient(q: Any) -> Orientation:
    w, x, y, z = (float(v) for v in q)
    return Orientation((w, x, y, z))


def rounded(value: Any) -> Any:
    return [rounded(v) for v in value] if isinstance(value, list) else float(f"{value:.8g}")


def at(tree: Any, path: Loc) -> Any:
    for seg in path:
        tree = tree[seg]
    return tree


@pytest.mark.parametrize("path", GRAMMARS, ids=lambda p: p.name)
def test_no_updates_is_byte_identical(path: Path) -> None:
    text = path.read_text()
    assert apply_updates(text, [], path.name) == text


DOC_EXAMPLES = [  # whole documents; an indented excerpt of a grammar is not one
    m.group(1)
    for doc in sorted((ROOT / "docs").glob("*.md"))
    for m in re.finditer(r"```yaml\n(.*?)```", doc.read_text(), re.S)
    if not m.group(1)[:1].isspace()
]


@pytest.mark.parametrize("text", DOC_EXAMPLES)
def test_no_updates_keeps_the_doc_examples(text: str) -> None:
    """The examples are written by hand in several styles (`[{child: A}]`, aligned comments)."""
    assert apply_updates(text, []) == text


@pytest.mark.parametrize(
    "text",
    [
        "# header\n---\na: 1\n...\n",
        "%YAML 1.2\n---\na: [1, 2]\n",
        "a: 1",
        "a: 1\r\nb:\r\n  - 2\r\n",
        "a:\n- 1\n- 2\n",
        "a:\n    b: 1\n    c:\n    -   x: 1\n        y: 2\n",
        "# only a comment\n",
    ],
)
def test_no_updates_keeps_other_layouts(text: str) -> None:
    assert apply_updates(text, []) == text


@pytest.mark.parametrize("path", GRAMMARS, ids=lambda p: p.name)
def test_fitted_numbers_only_change_numbers(path: Path) -> None:
    text = path.read_text()
    updates = fitted_updates(load(text))
    assert updates
    out = apply_updates(text, updates, path.name)
    compile_text(out, path.name, base_dir=path.parent)
    before, after = text.splitlines(), out.splitlines()
    assert len(before) == len(after)
    diffs = [(a, b) for a, b in zip(before, after, strict=True) if a != b]
    assert diffs
    for a, b in diffs:
        assert NUMBER.sub("N", a) == NUMBER.sub("N", b), (a, b)
    assert comments(out) == comments(text)
    tree = load(out)
    for update in updates:
        for key, value in update.values.items():
            assert at(tree, (*update.path, key)) == rounded(value)


def test_insert_p_after_child_in_block_rules() -> None:
    path = next(p for p in GRAMMARS if p.name == "sink.yaml")
    text = path.read_text()
    rules = [("types", "Object", "or", i) for i in range(3)]
    out = apply_updates(
        text, [Update(r, {"p": p}) for r, p in zip(rules, (0.5, 0.3, 0.2), strict=True)]
    )
    grammar = compile_text(out, path.name, base_dir=path.parent)
    probs = grammar.types[grammar.type_id("Object")].probs
    np.testing.assert_allclose(probs, [0.5, 0.3, 0.2])
    assert "      - child: Plate\n        p: 0.5\n      - child: Bowl\n" in out
    # the blank line before the next type stays below the inserted line
    assert "      - child: TerminalCup\n        p: 0.2\n\n  Plate:" in out
    assert comments(out) == comments(text)


def test_insert_mode_into_flow_mapping() -> None:
    path = next(p for p in GRAMMARS if p.name == "sink.yaml")
    text = path.read_text()
    rule = ("types", "DishBin", "repeat", "rule")
    bingham = (*rule, "rotation", "world_bingham")
    q = rpy_to_quat(np.radians([10.0, 20.0, 30.0]))
    out = apply_updates(text, [Update(bingham, {"mode": orient(q), "concentration": 2.5})])
    line = "rotation: {world_bingham: {mode: {rpy_deg: [10.0, 20.0, 30.0]}, concentration: 2.5}}"
    assert line in out
    grammar = compile_text(out, path.name, base_dir=path.parent)
    fitted = next(r for r in grammar.rules if r.path == rule)
    assert fitted.rotation.bingham is not None
    assert abs(abs(np.dot(fitted.rotation.bingham.mode, q)) - 1) < 1e-12


def test_insert_into_block_mapping_and_new_lists() -> None:
    text = "a:\n  b: 1.0  # keep\n  # about c\n\n  c: 2\n"
    updates = [Update(("a",), {"b": 0.5, "d": [1.0, 2.0], "c": 3})]
    out = apply_updates(text, updates)
    assert out == "a:\n  b: 0.5  # keep\n  # about c\n\n  c: 3\n  d: [1.0, 2.0]\n"
    scalar_to_list = apply_updates("v: {variance: 0.1}\n", [Update(("v",), {"variance": [1, 2.5]})])
    assert scalar_to_list == "v: {variance: [1, 2.5]}\n"


@pytest.mark.parametrize("block", ["  b:\n    - 1\n    - 2  # two\n", "  b:\n    x: {y: 1}\n"])
def test_appended_key_goes_above_the_comments_that_introduce_the_next_entry(block: str) -> None:
    text = f"a:\n{block}  # about c\n\nc: 1\n"
    out = apply_updates(text, [Update(("a",), {"d": 3})])
    assert out == f"a:\n{block}  d: 3\n  # about c\n\nc: 1\n"


def test_nested_lists_edited_in_place() -> None:
    text = (
        "n:\n"
        "  covariance:\n"
        "    - [0.04, 0.01, 0.0]   # x row\n"
        "    - [0.01, 0.02, 0.0]\n"
        "    - [0.0, 0.0, 1.0]\n"
        "  M: [[0, 0, 0, 1], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]\n"
    )
    cov = [[0.05, 0.011, 0.0], [0.011, 0.03, 0.0], [0.0, 0.0, 2.0]]
    m = np.eye(4)[[1, 0, 2, 3]].tolist()
    out = apply_updates(text, [Update(("n",), {"covariance": cov, "M": m})])
    assert out == (
        "n:\n"
        "  covariance:\n"
        "    - [0.05, 0.011, 0.0]  # x row\n"  # the comment keeps its column
        "    - [0.011, 0.03, 0.0]\n"
        "    - [0.0, 0.0, 2.0]\n"
        "  M: [[0, 1.0, 0, 0.0], [1, 0, 0, 0], [0, 0.0, 1.0, 0], [0, 0, 0.0, 1.0]]\n"
    )


def test_none_keeps_the_written_value() -> None:
    text = "n: {mean: [0.5, 0.25, 0.1], variance: [0.04, 0.09, 0.0]}  # z pinned\n"
    update = Update(("n",), {"mean": [1.0, 2.0, None], "variance": [0.5, None, None]})
    out = apply_updates(text, [update])
    assert out == "n: {mean: [1.0, 2.0, 0.1], variance: [0.5, 0.09, 0.0]}    # z pinned\n"
    assert apply_updates(text, [Update(("n",), {"mean": None, "covariance": None})]) == text
    with pytest.raises(ValueError, match=r"n\.variance: None"):
        apply_updates("n: {variance: 0.1}\n", [Update(("n",), {"variance": [0.5, None, 1.0]})])


def orientation_of(mapping: Any) -> np.ndarray:
    """The quaternion an orientation mapping written in any form stands for."""
    if "quat_wxyz" in mapping:
        q = np.array(mapping["quat_wxyz"], float)
        return q / np.linalg.norm(q)
    rpy = np.array(mapping.get("rpy", mapping.get("rpy_deg")), float)
    return rpy_to_quat(np.radians(rpy) if "rpy_deg" in mapping else rpy)


QUATS = [
    np.array([1.0, 0.0, 0.0, 0.0]),
    rpy_to_quat([0.0, np.pi / 2, 0.3]),  # gimbal lock
    rpy_to_quat([0.1, -np.pi / 2, -2.0]),
    -rpy_to_quat([3.0, 0.2, -3.1]),
    *np.random.default_rng(7).normal(size=(20, 4)),
]


@pytest.mark.parametrize("form", ["rpy", "rpy_deg", "quat_wxyz"])
@pytest.mark.parametrize("q", QUATS, ids=range(len(QUATS)))
def test_orientation_round_trips_in_each_form(form: str, q: np.ndarray) -> None:
    q = q / np.linalg.norm(q)
    old = {"rpy": "[0.1, 0, 0]", "rpy_deg": "[0, 0, 90]", "quat_wxyz": "[0, 0, 0, 1]"}[form]
    text = f"rule:  # a rule\n  offset: {{{form}: {old}}}  # fitted\n  other: 1\n"
    out = apply_updates(text, [Update(("rule",), {"offset": orient(q)})])
    written = load(out)["rule"]["offset"]
    assert list(written) == [form]
    assert out.startswith("rule:  # a rule\n  offset: {") and "# fitted\n  other: 1\n" in out
    back = orientation_of(written)
    np.testing.assert_allclose(quat_canonical(back), quat_canonical(q), atol=1e-7)


def test_orientation_in_a_compiled_grammar() -> None:
    q = rpy_to_quat([0.4, -0.3, 2.0])
    for form in ("rpy", "rpy_deg", "quat_wxyz"):
        value = {"rpy": "[0, 0, 0]", "rpy_deg": "[0, 0, 0]", "quat_wxyz": "[1, 0, 0, 0]"}[form]
        text = (
            "grammar: g\nroot: {type: R}\ntypes:\n  R:\n    and:\n      - child: A\n"
            f"        rotation: {{parent_bingham: {{mode: {{{form}: {value}}}, "
            "concentration: 10}}\n  A: {}\n"
        )
        path = ("types", "R", "and", 0, "rotation", "parent_bingham")
        out = apply_updates(text, [Update(path, {"mode": orient(q)})])
        bingham = compile_text(out).rules[0].rotation.bingham
        assert bingham is not None
        assert abs(abs(float(np.dot(bingham.mode, q))) - 1) < 1e-12


@pytest.mark.parametrize("mode", ["{}", "", "null"])
def test_orientation_into_identity_or_empty_mode(mode: str) -> None:
    text = f"b:\n  mode: {mode}\n  concentration: 4.0\n".replace(" \n", "\n")
    q = rpy_to_quat(np.radians([0.0, 0.0, 90.0]))
    out = apply_updates(text, [Update(("b",), {"mode": orient(q)})])
    assert out == "b:\n  mode: {rpy_deg: [0.0, 0.0, 90.0]}\n  concentration: 4.0\n"


def test_bad_quaternion_is_refused() -> None:
    for q in ((0.0, 0.0, 0.0, 0.0), (1.0, math.nan, 0.0, 0.0), (1.0, 0.0, 0.0)):
        with pytest.raises(ValueError, match="not a quaternion"):
            apply_updates("b: {}\n", [Update(("b",), {"mode": Orientation(q)})])  # type: ignore[arg-type]


def read_back(text: str) -> Any:
    return load(f"v: {text}\n")["v"]


@given(
    st.floats(allow_nan=False, allow_infinity=False, allow_subnormal=True),
    st.integers(min_value=1, max_value=17),
)
def test_number_text_reads_back_as_the_rounded_float(x: float, digits: int) -> None:
    text = format_number(x, digits)
    expected = float(f"{x:.{digits}g}")
    while 0 < x < 1 and not 0 < expected < 1:  # a probability keeps its outcomes possible
        digits += 1
        expected = float(f"{x:.{digits}g}")
    value = read_back(text)
    assert isinstance(value, float)
    if math.isinf(expected):  # rounding 1.8e308 up overflows: it is rounded down instead
        assert math.isfinite(value) and 0 <= abs(x) - abs(value) < abs(value) * 10 ** (1 - digits)
        expected = value
    assert value == expected and math.copysign(1, value) == math.copysign(1, expected)
    assert "." in text and len(text) <= digits + 8
    safe = YAML(typ="safe", pure=True)
    safe.version = (1, 1)  # a YAML 1.1 reader (PyYAML-like) wants a dot, which we write
    assert safe.load(f"v: {text}\n")["v"] == expected


@pytest.mark.parametrize(
    ("x", "text"),
    [
        (0.00661234567, "0.0066123457"),
        (1.5e-05, "1.5e-05"),
        (12.0, "12.0"),
        (-0.0, "-0.0"),
        (1e300, "1.0e+300"),
        (5e-324, "5.0e-324"),
        (123456789012.0, "1.2345679e+11"),
        (1.7976931348623157e308, "1.7976931e+308"),
    ],
)
def test_number_examples(x: float, text: str) -> None:
    assert format_number(x) == text
    assert apply_updates("a: 1.0\n", [Update((), {"a": x})]) == f"a: {text}\n"


def test_integers_stay_integers_and_non_finite_is_refused() -> None:
    out = apply_updates("g: {p: 0.5, max: 3}\n", [Update(("g",), {"max": np.int64(5)})])
    assert out == "g: {p: 0.5, max: 5}\n"
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError, match="non-finite"):
            apply_updates("g: {p: 0.5}\n", [Update(("g",), {"p": bad})])
        with pytest.raises(ValueError, match="non-finite"):
            apply_updates("g: {m: [1, 2]}\n", [Update(("g",), {"m": [1.0, bad]})])


def test_missing_path_is_an_error() -> None:
    text = "types:\n  A:\n    or:\n      - child: B\n"
    with pytest.raises(ValueError, match=r"types\.A\.or\[3\]"):
        apply_updates(text, [Update(("types", "A", "or", 3), {"p": 0.5})])
    with pytest.raises(ValueError, match=r"types\.X"):
        apply_updates(text, [Update(("types", "X", "or", 0), {"p": 0.5})])
    with pytest.raises(ValueError, match="not a mapping"):
        apply_updates(text, [Update(("types", "A", "or"), {"p": 0.5})])


ALIASED = """\
grammar: g
root: {type: R}
types:
  R:
    and:
      - child: A
        translation: {world_normal: &n {mean: [0.0, 0.0, 0.0], variance: 1.0}}  # shared
      - child: A
        translation: {world_normal: *n}
      - child: A
        translation: {world_normal: {<<: *n, variance: 2.0}}
  A: {}
"""
PATHS: list[Loc] = [("types", "R", "and", i, "translation", "world_normal") for i in range(3)]


def test_shared_nodes_groups_aliased_mappings() -> None:
    assert shared_nodes(ALIASED, PATHS) == [PATHS[:2]]
    assert shared_nodes(ALIASED, [PATHS[2], PATHS[0]]) == []


def test_alias_written_once_and_conflict_refused() -> None:
    same = [Update(p, {"variance": 0.5, "mean": [1.0, 2.0, 3.0]}) for p in PATHS[:2]]
    out = apply_updates(ALIASED, same)
    assert "&n {mean: [1.0, 2.0, 3.0], variance: 0.5}}  # shared\n" in out
    assert "{world_normal: *n}\n" in out
    grammar = compile_text(out)
    np.testing.assert_allclose(grammar.rules[1].translation.offset, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(grammar.rules[2].translation.offset, [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="anchor"):
        apply_updates(ALIASED, [Update(PATHS[0], {"variance": 0.7}), *same[1:]])
    with pytest.raises(ValueError, match="anchor"):
        apply_updates(ALIASED, [same[0], Update(PATHS[1], {"mean": [1.0, 2.0, 4.0]})])
    with pytest.raises(ValueError, match="anchor"):  # a key that each write would insert
        apply_updates(ALIASED, [Update(PATHS[0], {"p": 0.1}), Update(PATHS[1], {"p": 0.2})])


MERGED = """\
grammar: g
root: {type: R}
types:
  R:
    and:
      - child: A
        translation: {world_normal: &n {mean: [0.0, 0.0, 0.0], variance: 1.0, pin: [z]}}
      - child: A
        translation: {world_normal: {<<: *n, mean: [2.0, 0.0, 0.0]}}
  A: {}
"""


TWO = "{mean: [0.0, 0.0, 0.0], variance: 1.0}"
THREE = "{mean: [0.0, 0.0, 0.0], variance: 1.0, pin: [z]}"


@pytest.mark.parametrize(
    ("anchored", "merging", "update", "after"),
    [  # a number and a list, inherited from a block of 2 and of 3 keys
        (TWO, "mean: [2.0, 0.0, 0.0]", {"variance": 3.0}, TWO.replace("1.0}", "3.0}")),
        (THREE, "mean: [2.0, 0.0, 0.0]", {"variance": 3.0}, THREE.replace("1.0,", "3.0,")),
        (
            TWO,
            "variance: 2.0",
            {"mean": [0.5, 0.5, 0.5]},
            TWO.replace("0.0, 0.0, 0.0", "0.5, 0.5, 0.5"),
        ),
        (
            THREE,
            "variance: 2.0",
            {"mean": [0.5, 0.5, 0.0]},
            THREE.replace("0.0, 0.0, 0.0", "0.5, 0.5, 0.0"),
        ),
    ],
    ids=["number of 2 keys", "number of 3 keys", "list of 2 keys", "list of 3 keys"],
)
def test_merged_key_is_written_at_its_anchor(
    anchored: str, merging: str, update: dict[str, Any], after: str
) -> None:
    """The merging block is fitted, the anchored one is not: the value it inherits is written
    where it is written, at the anchor, and the merging block keeps its own keys only."""
    text = MERGED.replace(THREE, anchored).replace("mean: [2.0, 0.0, 0.0]}", f"{merging}}}")
    out = apply_updates(text, [Update(PATHS[1], update)])
    assert out == text.replace(anchored, after)
    tree = load(out)
    for key, value in update.items():
        assert at(tree, (*PATHS[0], key)) == at(tree, (*PATHS[1], key)) == value
    compile_text(out)


def test_merged_key_is_found_in_both_ruamel_layouts() -> None:
    """ruamel.yaml 0.19 keeps a mapping's `<<` sources as a list of mappings, older versions
    as (position, mapping) pairs; a merged key is found at its source in either."""
    tree = load("a: &a {x: 1.0, y: 2.0, z: 3.0}\nb: &b {w: 1.0}\nc: {<<: [*b, *a], x: 0.0}\n")
    a, b, c = tree["a"], tree["b"], tree["c"]
    for layout in ([b, a], [(0, b), (1, a)]):
        setattr(c, merge_attrib, layout)
        owners = [writeback._owner(c, key) for key in ("x", "y", "z", "w")]
        assert all(o is m for o, m in zip(owners, (c, a, a, b), strict=True))
    assert writeback._owner(a, "x") is a and not hasattr(a, merge_attrib)


def test_merged_number_fitted_in_both_blocks_is_refused() -> None:
    """The anchored block and the merging block both fitted: the inherited number (in a
    block of 2 keys: it once crashed on the key names) would need two values."""
    text = MERGED.replace(", pin: [z]", "")
    same = [Update(PATHS[0], {"variance": 0.5}), Update(PATHS[1], {"variance": 0.5})]
    assert "&n {mean: [0.0, 0.0, 0.0], variance: 0.5}" in apply_updates(text, same)
    with pytest.raises(SharedValueConflict, match=r"and\[1\]\.translation\.world_normal\.variance"):
        apply_updates(
            text, [Update(PATHS[0], {"variance": 0.5}), Update(PATHS[1], {"variance": 0.7})]
        )


def test_aliased_number_is_written_once_at_its_anchor() -> None:
    """A number shared as `&v 1.0` / `*v` is tied like a shared list: one value is written at
    the anchor and the alias stays an alias; two values are refused, as for a list."""
    text = "a: {v: &v 1.0}  # anchor\nb: {v: *v}\nc: [&w 1.0, *w]\n"
    both = [Update(("b",), {"v": 0.5}), Update(("a",), {"v": 0.5})]
    assert apply_updates(text, both) == "a: {v: &v 0.5}  # anchor\nb: {v: *v}\nc: [&w 1.0, *w]\n"
    one = apply_updates(text, [Update(("b",), {"v": 0.2}), Update((), {"c": [2.0, 2.0]})])
    assert one == "a: {v: &v 0.2}  # anchor\nb: {v: *v}\nc: [&w 2.0, *w]\n"
    with pytest.raises(SharedValueConflict, match=r"a\.v is the YAML node of b\.v"):
        apply_updates(text, [Update(("b",), {"v": 0.5}), Update(("a",), {"v": 0.7})])
    with pytest.raises(SharedValueConflict, match=r"c\[1\] is the YAML node of c\[0\]"):
        apply_updates(text, [Update((), {"c": [2.0, 3.0]})])


CRLF = "# top\r\n---\r\n# about a\r\na: 1.0  # one\r\nb:\r\n  - 2.0\r\n\r\n# end\r\n"


def test_crlf_is_kept_exactly_and_a_second_write_changes_nothing_else() -> None:
    """ruamel keeps a `\\r` it reads in the comments: the line ends are taken off first."""
    first = apply_updates(CRLF, [Update((), {"a": 0.5})])
    assert first == CRLF.replace("a: 1.0", "a: 0.5")
    assert apply_updates(first, [Update((), {"a": 0.5})]) == first
    assert apply_updates(CRLF.replace("---\r\n", ""), [Update((), {"b": [3.0]})]) == (
        CRLF.replace("---\r\n", "").replace("- 2.0", "- 3.0")
    )


@pytest.mark.parametrize(
    "text",
    [
        "\ufeffa: 1.0  # a byte-order mark\n",
        "\ufeff# c\r\n---\r\na: 1.0\r\n",
        '--- {"a": 1.0, "b": [1, 2]}\n',
        "# c\n--- {a: 1.0}  # flow\n",
        "--- [{a: 1.0}]\n",
    ],
)
def test_byte_order_mark_and_content_on_the_document_start_line_are_kept(text: str) -> None:
    assert apply_updates(text, []) == text
    path: Loc = (0,) if text.startswith("--- [") else ()
    out = apply_updates(text, [Update(path, {"a": 0.5})])
    assert out == text.replace("1.0", "0.5", 1)


@pytest.mark.parametrize("x", [1 - 1e-9, 0.999999999999, 1 - 2**-53, 0.99999999949])
def test_a_number_inside_0_1_is_not_written_as_1(x: float) -> None:
    """A fitted probability just below 1 written as `1.0` would make the other outcomes
    impossible (docs/fitting.md 4.2): it gets the digits it needs."""
    value = read_back(format_number(x))
    assert 0 < value < 1 and abs(value - x) <= 1e-8
    out = apply_updates("g: {p: 0.5}\n", [Update(("g",), {"p": x})])
    assert 0 < load(out)["g"]["p"] < 1
    assert format_number(0.5) == "0.5" and format_number(1 - 1e-8) == "0.99999999"


# ---------------------------------------------------------------- through `ssg fit` ---

TINY = """\
grammar: tiny
root: Root
types:
  Root:
    observed: true
    or:
      - child: A
        p: 0.5
        translation: {world_normal: {mean: [0, 0, 0], variance: 1.0}}
      - child: A
        p: 0.5
        translation: {world_normal: {mean: [2, 0, 0], variance: 1.0}}
  A: {observed: true}
"""
COUNTS = """\
grammar: counts
root: Root
types:
  Root:
    observed: true
    and: [{child: A}, {child: B}]
  A:
    fixed: true
    repeat:
      count: {probs: &pr [0.25, 0.25, 0.25, 0.25]}
      rule: {child: X, translation: {world_normal: {mean: [0, 0, 0], variance: 1.0}}}
  B:
    repeat:
      count: {probs: *pr}
      rule: {child: Y, translation: {world_normal: {mean: [2, 0, 0], variance: 1.0}}}
  X: {observed: true}
  Y: {observed: true}
"""
FIRST = "types.Root.or[0].translation.world_normal"
SECOND = "types.Root.or[1].translation.world_normal"


def fit_cli(tmp_path: Path, text: str, *flags: str, scenes: int = 5) -> tuple[Any, Path]:
    """`ssg fit` of `text` on scenes sampled from it; the result and the output's path."""
    grammar = compile_text(text)
    trees, logp = sample_trees(grammar, scenes, 1)
    data = tmp_path / "data"
    data.mkdir()
    for i in range(scenes):
        scene = scene_from_tree(grammar, trees.tree(i), f"s{i}", float(logp[i]))
        (data / f"s{i}.json").write_text(dumps_scene(grammar, scene))
    (tmp_path / "g.yaml").write_text(text)
    out = tmp_path / "out.yaml"
    args = ["fit", str(data), "-g", str(tmp_path / "g.yaml"), "-o", str(out), "-q", *flags]
    return CliRunner().invoke(app, args), out


@pytest.mark.parametrize(
    ("text", "where", "fitted", "kept"),
    [
        (  # the root's pose
            TINY.replace("root: Root", "root: {type: Root, pose: {xyz: &o [0, 0, 0]}}").replace(
                "mean: [0, 0, 0]", "mean: *o"
            ),
            "9:38",
            f"{FIRST}.mean",
            "root.pose.xyz",
        ),
        (  # a `fixed` law's list
            TINY.replace(
                "{mean: [0, 0, 0], variance: 1.0}",
                "{fixed: true, mean: [0, 0, 0], variance: &v [1, 1, 1]}",
            ).replace("variance: 1.0", "variance: *v"),
            "12:55",
            f"{SECOND}.variance",
            f"{FIRST}.variance",
        ),
        (  # a `fixed` law's number
            TINY.replace(
                "{mean: [0, 0, 0], variance: 1.0}",
                "{fixed: true, mean: [0, 0, 0], variance: &v 1.0}",
            ).replace("variance: 1.0", "variance: *v"),
            "12:55",
            f"{SECOND}.variance",
            f"{FIRST}.variance",
        ),
        (  # a number merged from a `fixed` law
            TINY.replace(
                "{mean: [0, 0, 0], variance: 1.0}",
                "&n {fixed: true, mean: [0, 0, 0], variance: 1.0}",
            ).replace(
                "{mean: [2, 0, 0], variance: 1.0}", "{<<: *n, fixed: false, mean: [2, 0, 0]}"
            ),
            "12:37",
            f"{SECOND}.variance",
            f"{FIRST}.variance",
        ),
        (COUNTS, "14:15", "types.B.repeat.count.probs", "types.A.repeat.count.probs"),
    ],
    ids=["root pose", "fixed list", "fixed number", "merged from fixed", "fixed type's count"],
)
def test_a_value_shared_with_one_the_fit_keeps_is_refused_before_fitting(
    tmp_path: Path, text: str, where: str, fitted: str, kept: str
) -> None:
    """Writing the fitted value would change the root's pose or a fixed law through the alias
    (the fitted grammar could then not parse its own data): refused, located, nothing written."""
    result, _ = fit_cli(tmp_path, text)
    assert result.exit_code == 1, result.output
    grammar = tmp_path / "g.yaml"
    assert result.output.startswith(
        f"{grammar}:{where}: error: {fitted} is one YAML node with {kept} (an anchor"
    )
    assert "ssg fit must keep as written" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "g.yaml"]


def test_a_list_shared_by_fitted_places_is_still_fitted(tmp_path: Path) -> None:
    """Shared only between fitted places, and tied (one law through an alias): allowed."""
    text = TINY.replace(
        "{mean: [0, 0, 0], variance: 1.0}}", "&law {mean: [0, 0, 0], variance: 1.0}}"
    )
    text = text.replace("{world_normal: {mean: [2, 0, 0], variance: 1.0}}", "{world_normal: *law}")
    result, out = fit_cli(tmp_path, text, "--iterations", "1")
    assert result.exit_code == 0, result.output
    assert "{world_normal: &law {mean: [" in out.read_text()
    assert "{world_normal: *law}" in out.read_text()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (  # a number aliased between two rules, fitted apart: it was silently untied
            TINY.replace(
                "variance: 1.0}}\n      - child", "variance: &v 1.0}}\n      - child"
            ).replace("variance: 1.0}}\n  A:", "variance: *v}}\n  A:"),
            f"{SECOND}.variance is the YAML node of {FIRST}.variance too",
        ),
        (  # a rule merged into the other: its `p` (this crashed, exit 70)
            TINY.replace(
                "      - child: A\n        p: 0.5\n        translation: {world_normal: {mean: [0",
                "      - &r {child: A, p: 0.5, translation: {world_normal: {mean: [0",
                1,
            )
            .replace(
                "1.0}}\n      - child: A\n        p: 0.5\n        translation:",
                "1.0}}}\n      - {<<: *r, translation:",
            )
            .replace("variance: 1.0}}\n  A:", "variance: 1.0}}}\n  A:"),
            "types.Root.or[1].p is the YAML node of types.Root.or[0].p too",
        ),
    ],
    ids=["aliased number", "merged rule"],
)
def test_one_node_fitted_to_two_values_is_a_user_error(
    tmp_path: Path, text: str, message: str
) -> None:
    compile_text(text)
    result, out = fit_cli(tmp_path, text, "--iterations", "1", scenes=8)
    assert result.exit_code == 1, result.output
    assert message in result.output
    assert "cannot give one YAML node two values" in result.output
    assert not out.exists()


def test_a_probability_near_1_stays_below_1(tmp_path: Path) -> None:
    """(hits + α) / (seen + 2α) = 1 - 3e-9 with α = 1e-7 on 30 scenes: `p: 1.0` would make
    every scene without an A impossible."""
    text = TINY.replace("or:", "independent:").replace("p: 0.5", "p: 0.999", 1)
    text = text.replace("child: A\n        p: 0.5", "child: B\n        p: 0.5") + "  B: {}\n"
    result, out = fit_cli(tmp_path, text, "--iterations", "1", "--pseudocount", "1e-7", scenes=30)
    assert result.exit_code == 0, result.output
    p = load(out.read_text())["types"]["Root"]["independent"][0]["p"]
    assert 0.9999 < p < 1


def test_a_covariance_keeps_the_digits_it_needs_to_stay_positive_definite():
    """Spreads of 1.8 km along a line and 1 mm across it: rounded to 8 digits, the smallest
    eigenvalue became negative and the fitted grammar was refused as not positive definite."""
    turn = np.array([[1, -1, 0], [1, 1, 0], [0, 0, np.sqrt(2)]]) / np.sqrt(2)
    cov = turn @ np.diag([3.16e6, 1e-6, 0.414]) @ turn.T
    eight = np.array([[float(f"{x:.8g}") for x in row] for row in cov])
    assert np.linalg.eigvalsh(eight).min() <= 0  # what 8 digits did
    text = (
        "grammar: g\nroot: {type: R}\ntypes:\n  R:\n    observed: true\n    and:\n"
        "      - child: A\n"
        "        translation: {world_normal: {mean: [0, 0, 0], covariance: "
        "[[1, 0, 0], [0, 1, 0], [0, 0, 1]]}}\n"
        "  A: {observed: true}\n"
    )
    path = ("types", "R", "and", 0, "translation", "world_normal")
    fitted = apply_updates(text, [Update(path, {"covariance": cov.tolist()})])
    compile_text(fitted, "fitted.yaml")  # refused if not positive definite as written


def test_a_json_grammar_stays_json() -> None:
    """A key the fit adds (`p`) was written unquoted among quoted ones: `"child": "A", p: 0.25`
    is YAML, but no longer JSON."""
    import json

    text = '{\n  "grammar": "g",\n  "types": {"R": {"or": [{"child": "A"}, {"child": "B"}]}}\n}\n'
    rules = ("types", "R", "or")
    out = apply_updates(text, [Update((*rules, 0), {"p": 0.25}), Update((*rules, 1), {"p": 0.75})])
    assert json.loads(out)["types"]["R"]["or"] == [
        {"child": "A", "p": 0.25},
        {"child": "B", "p": 0.75},
    ]


def test_the_fitted_file_keeps_the_grammars_byte_order_mark(tmp_path: Path) -> None:
    result, out = fit_cli(tmp_path, "\ufeff" + TINY, "--iterations", "1")
    assert result.exit_code == 0, result.output
    data = out.read_bytes()
    assert data.startswith(b"\xef\xbb\xbf") and not data.startswith(b"\xef\xbb\xbf" * 2)
    plain = tmp_path / "plain"
    plain.mkdir()
    result, out = fit_cli(plain, TINY, "--iterations", "1")
    assert result.exit_code == 0 and not out.read_bytes().startswith(b"\xef\xbb\xbf")


UNUSED_ANCHORS = """\
grammar: g5
root: {type: Root}
types:
  Root:
    observed: true
    geometry: &shape {sphere: {radius: 0.05}}
    and:
      - child: A
        translation: {world_normal: &law {mean: [0.0, 0.0, 0.0], variance: 1.0}}
      - child: B
        translation: {world_normal: &unused {mean: [1.0, 0.0, 0.0], variance: 1.0}}
  A: {observed: true, geometry: &lonely {box: {size: [0.1, 0.1, 0.1]}}}
  B: {observed: true, geometry: *shape}
"""


def test_anchors_without_aliases_are_kept() -> None:
    """ruamel.yaml leaves out an anchor on a mapping or list that no alias uses: `&law`,
    `&unused` and `&lonely` (on a geometry the fit never touches) were deleted on write-back."""
    rules = ("types", "Root", "and")
    updates = [
        Update((*rules, i, "translation", "world_normal"), {"mean": [0.5, 0.0, 0.0]})
        for i in (0, 1)
    ]
    out = apply_updates(UNUSED_ANCHORS, updates)
    assert out == UNUSED_ANCHORS.replace("mean: [0.0,", "mean: [0.5,").replace(
        "mean: [1.0,", "mean: [0.5,"
    )
    assert apply_updates(UNUSED_ANCHORS, []) == UNUSED_ANCHORS
    seq = "a: &l [1, 2]\nb: &m {c: &n [3]}\n"
    assert apply_updates(seq, []) == seq
