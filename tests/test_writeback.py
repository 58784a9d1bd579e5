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

from ssgc.compile import compile_text
from ssgc.fit.writeback import (
    Loc,
    Orientation,
    Update,
    apply_updates,
    format_number,
    shared_nodes,
)
from ssgc.geometry import quat_canonical, rpy_to_quat

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
        "  M: [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], "
        "[0.0, 0.0, 0.0, 1.0]]\n"
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
    assert out.startswith("rule:  # a rule\n  offset: {") and "} # fitted\n  other: 1\n" in out
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


def test_merged_key_is_written_at_its_anchor() -> None:
    out = apply_updates(ALIASED, [Update(PATHS[2], {"mean": [0.5, 0.5, 0.5], "variance": 3.0})])
    assert "&n {mean: [0.5, 0.5, 0.5], variance: 1.0}" in out
    assert "{world_normal: {<<: *n, variance: 3.0}}" in out
    compile_text(out)
