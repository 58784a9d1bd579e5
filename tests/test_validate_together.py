"""One run of `ssg validate` reports every mistake of a grammar, each once, at its token:
several mistakes inside one constraint or one law, a mistake in an aliased part, a badly named
clutter rate or type, a misspelt key, oversized geometry (docs/grammar.md section 6)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ssgc.compile import compile_text
from ssgc.errors import GrammarError


def errors(text: str) -> list[str]:
    """The located error messages of `text` ("case.yaml:LINE:COL: error: ..."), in order."""
    with pytest.raises(GrammarError) as caught:
        compile_text(text, "case.yaml")
    return [str(d) for d in caught.value.diagnostics if d.severity == "error"]


def at(text: str, line: int, token: str, nth: int = 0) -> str:
    """ "LINE:COL" of the `nth` occurrence of `token` on 1-based `line` of `text`."""
    row, col = text.splitlines()[line - 1], -1
    for _ in range(nth + 1):
        col = row.index(token, col + 1)
    return f"{line}:{col + 1}"


def found(messages: list[str], where: str, fragment: str) -> int:
    """How many messages are at `where` ("LINE:COL") and contain `fragment`."""
    return sum(m.startswith(f"case.yaml:{where}:") and fragment in m for m in messages)


# ------------------------------------------------------------- one constraint ---

TWO_TYPES = """\
grammar: g
root: T
types:
  T: {observed: true, and: [{child: A, translation: {offset: [0, 0, 1]}}]}
  A: {observed: true}
constraints:
"""


def test_every_mistake_of_one_constraint_in_one_run() -> None:
    """Each constraint gave up at its first error: `Zed` hid that A and T have no geometry,
    a radius error hid the inverted box, `Ghost` hid the unknown frame `Phantom`."""
    text = TWO_TYPES + (
        "  np: {non_penetration: {types: [A, T], exempt: [[A, Zed]]}}\n"
        "  kc: {inside_box: {types: [A], min: [0, 0, 0], max: [-1, 1, -1], keep_out: true}}\n"
        "  up: {upright: {types: [Ghost], frame: Phantom, max_angle_deg: 5}}\n"
    )
    got = errors(text)
    assert found(got, "7:54", "type 'Zed' is not a type") == 1
    assert found(got, "7:34", "cannot check 'A': it has no geometry") == 1
    assert found(got, "7:37", "cannot check 'T': it has no geometry") == 1
    assert found(got, "8:29", "no keep-out radius for 'A'") == 1
    assert found(got, "8:55", "box max is below min on the x axis") == 1
    assert found(got, "8:62", "box max is below min on the z axis") == 1
    assert found(got, "9:26", "type 'Ghost' is not a type") == 1
    assert found(got, "9:41", "frame type 'Phantom' is not a type") == 1
    assert len(got) == 8, got


def test_inside_box_names_every_type_without_geometry() -> None:
    text = TWO_TYPES + "  ib: {inside_box: {types: [A, T], min: [0, 0, 0], max: [1, 1, 1], "
    text += "geometry: true, floating: {rate: 1, mean: 1}}}\n"
    got = errors(text)
    assert found(got, "7:29", "'A' has no geometry to keep inside") == 1
    assert found(got, "7:32", "'T' has no geometry to keep inside") == 1
    assert len(got) == 2, got


# ------------------------------------------------------------------- one law ---

LAWS = """\
grammar: laws
root: T
types:
  T:
    observed: true
    and:
      - {child: A, translation: {world_normal: {mean: [0, 0, 0], variance: 1}}, rotation: {revolute: {axis: [0, 0, 0], min: 2, max: 1}}}
      - {child: A, translation: {world_box: {min: [0, 0, 0], max: [-1, -1, 0.00000001]}}, rotation: {world_bingham: {mode: {quat_wxyz: [2, 0, 0, 0]}, concentration: [20000, 100, 0]}}}
      - {child: A, translation: {world_normal: {covariance: [[1, 2, 0], [0, 1, 0], [0, 0, -1]]}}, rotation: {world_bingham: {M: [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], Z: [0, 0, 0, 20000]}}}
  A: {observed: true}
"""  # noqa: E501


def test_every_mistake_of_one_law_in_one_run() -> None:
    """Each law stopped at its first error, so this file took three runs."""
    got = errors(LAWS)
    expected = [
        (at(LAWS, 7, "axis"), "revolute axis must be nonzero"),
        (at(LAWS, 7, "1}}}"), "revolute max must be > min"),
        (at(LAWS, 8, "-1"), "box max must be >= min, got -1 < 0"),
        (at(LAWS, 8, "-1", 1), "box max must be >= min, got -1 < 0"),
        (at(LAWS, 8, "0.00000001"), "narrower than 0.0001 m"),
        (at(LAWS, 8, "20000"), "concentration must be at most 10000, got 20000"),
        (at(LAWS, 8, "quat_wxyz"), "quaternion must have unit norm"),
        (at(LAWS, 9, "covariance"), "covariance must be symmetric"),
        (at(LAWS, 9, "covariance"), "covariance must be positive definite"),
        (at(LAWS, 9, "M:"), "Bingham M must be orthogonal"),
        (at(LAWS, 9, "Z:"), "Bingham Z spans 20000"),
    ]
    for where, fragment in expected:
        assert found(got, where, fragment) == 1, (where, fragment, got)
    assert len(got) == len(expected), got


BOX_RULE = (
    "grammar: g\nroot: T\ntypes:\n"
    "  T: {{observed: true, and: [{{child: A, translation: "
    "{{world_box: {{min: [0, 0, 0], max: {hi}}}}}}}]}}\n"
    "  A: {{observed: true}}\n"
)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.sampled_from(["ok", "inverted", "narrow"]), min_size=3, max_size=3))
def test_a_box_reports_each_bad_axis(axes: list[str]) -> None:
    """k bad axes of one box are k located errors in one run, one at each axis's number."""
    value = {"ok": "1", "inverted": "-1", "narrow": "0.00000001"}
    hi = "[" + ", ".join(value[a] for a in axes) + "]"
    text = BOX_RULE.format(hi=hi)
    bad = [i for i, a in enumerate(axes) if a != "ok"]
    if not bad:
        compile_text(text, "case.yaml")
        return
    got = errors(text)
    assert len(got) == len(bad), got
    line = text.splitlines()[3]
    start = line.index(hi) + 1
    cols = [start + len(", ".join(value[a] for a in axes[:i])) + (2 if i else 0) for i in bad]
    for i, col in zip(bad, cols, strict=True):
        fragment = "box max must be >= min" if axes[i] == "inverted" else f"wide on {'xyz'[i]}"
        assert found(got, f"4:{col + 1}", fragment) == 1, (col, got)


# ------------------------------------------------------------------- aliases ---


def test_a_shape_error_in_an_aliased_part_is_said_once() -> None:
    """Each use of `*r` repeated the error (its path differs), filling the 30-message cap and
    hiding the `observed: tru` below."""
    uses = "".join("      - *r\n" for _ in range(34))
    text = (
        "grammar: anchors\nroot: T\ntypes:\n  T:\n    observed: true\n    and:\n"
        "      - &r {child: A, translation: {world_normal: {mean: [0,0,0], variance: -1}}}\n"
        + uses
        + "  A: {observed: tru}\n"
    )
    got = errors(text)
    assert found(got, at(text, 7, "-1"), "must be greater than 0, got -1") == 1, got
    assert found(got, "42:17", "expected true or false, got 'tru'") == 1, got
    assert len(got) == 2, got


def test_two_missing_keys_of_one_mapping_are_both_said() -> None:
    """They share a place and a message: only their paths tell them apart."""
    got = errors("grammar: g\nroot: T\ntypes:\n  T: {observed: true, geometry: {cylinder: {}}}\n")
    assert any("cylinder.radius: missing required key" in m for m in got), got
    assert any("cylinder.length: missing required key" in m for m in got), got


# --------------------------------------------------------------- bad names ---


def test_a_badly_named_clutter_rate_keeps_the_clutter_checked() -> None:
    text = """\
grammar: obs
root: R
types:
  R: {observed: true, and: [{child: L}]}
  L: {and: [{child: A}]}
  A: {observed: true}
observation:
  clutter:
    region: {min: [0, 0, 0], max: [1, 0, 1]}
    rates: {R: 1, L: 2, "Bad Name": 1}
"""
    got = errors(text)
    assert found(got, "10:25", "must match pattern") == 1, got
    assert found(got, "9:30", "the clutter region needs max > min") == 1, got
    assert found(got, at(text, 10, "1,"), "'R': the type has rules of its own") == 1, got
    assert found(got, at(text, 10, "2,"), "'L': the type is not observed") == 1, got


def test_a_badly_named_type_keeps_the_meaning_checked() -> None:
    text = """\
grammar: badkey
root: R
types:
  R: {observed: true, and: [{child: Cupp}, {child: Bad-Name}]}
  Bad-Name: {observed: true}
  Cup: {observed: tru}
"""
    got = errors(text)
    assert found(got, "5:3", "must match pattern") == 1, got
    assert found(got, "6:19", "expected true or false, got 'tru'") == 1, got
    assert found(got, "4:37", "child type 'Cupp' is not a type of this grammar") == 1, got
    assert not any("'Bad-Name' is not a type" in m for m in got), got


# ------------------------------------------------------------ misspelt keys ---

BASE = """\
grammar: g
root: T
types:
  T:
    observed: true
    geometry: {cylinder: {radius: 0.1, length: 0.2}}
    and:
      - {child: A, translation: {world_normal: {mean: [0, 0, 1], variance: 0.1}}}
  A: {observed: true}
constraints:
  n: {count: {type: A, max: 5}}
"""


@pytest.mark.parametrize(
    ("old", "new", "where"),
    [
        ("length:", "lenght:", "6:40"),
        ("variance:", "varience:", "8:66"),
        ("type: A", "tipe: A", "11:15"),
        ("grammar:", "grammer:", "1:1"),
    ],
)
def test_a_misspelt_key_is_one_message(old: str, new: str, where: str) -> None:
    """The unknown key's "did you mean" names the fix: no second message that the key it
    meant is missing, or that a one-of wants it."""
    got = errors(BASE.replace(old, new, 1))
    assert found(got, where, f"unknown key '{new[:-1].split(':')[0]}'") == 1, got
    assert len(got) == 1, got


# ------------------------------------------------------------------ sizes ---


@pytest.mark.parametrize(
    ("geometry", "where", "fragment"),
    [
        ("{revolve: {profile: [[0, 0], [1.0e200, 0], [1, 1], [0, 1]]}}", "4:63", "profile coord"),
        ("{box: {size: [1.0e200, 1, 1]}}", "4:47", "a geometry's size"),
        ("{cylinder: {radius: 1.0e200, length: 1}}", "4:53", "a radius"),
        ("{sphere: {radius: 1.0e200}}", "4:51", "a radius"),
        ("{tray: {size: [1, 1, 1.0e200], wall: 0.1}}", "4:54", "a geometry's size"),
    ],
)
def test_geometry_sizes_are_bounded(geometry: str, where: str, fragment: str) -> None:
    """A 1e200 profile passed `ssg validate` after FCL printed Eigen's complaints hundreds of
    times; now it is a located shape error, and no follow-on "has no geometry"."""
    text = (
        f"grammar: g\nroot: T\ntypes:\n  T: {{observed: true, geometry: {geometry}}}\n"
        "constraints:\n  np: {non_penetration: {types: [T]}}\n"
    )
    got = errors(text)
    assert found(got, where, fragment) == 1, got
    assert len(got) == 1, got


def test_geometry_at_the_limit_is_accepted() -> None:
    compile_text(
        "grammar: g\nroot: T\ntypes:\n"
        "  T: {observed: true, geometry: {box: {size: [2000000, 1, 1]}}}\n",
        "case.yaml",
    )


# ------------------------------------------------------ small places and hints ---

LABELS = """\
grammar: lab
root: R
types:
  R: {observed: true, labels: [a, b, a], and: [{child: C}]}
  C: {observed: true, labels: [c, b]}
"""


def test_a_label_s_mistakes_point_at_the_label() -> None:
    """Both pointed at the `labels` key, not at the label named twice or taken."""
    messages = errors(LABELS)
    assert found(messages, at(LABELS, 5, "b]"), "label 'b' already names type 'R'") == 1
    with pytest.raises(GrammarError) as caught:
        compile_text(LABELS, "case.yaml")
    warnings = [str(d) for d in caught.value.diagnostics if d.severity == "warning"]
    assert warnings == [f"case.yaml:{at(LABELS, 4, 'a]')}: warning: type 'R' lists a label twice"]


def test_a_misspelt_noise_type_gets_a_suggestion() -> None:
    text = """\
grammar: typo
root: Table
types:
  Table: {observed: true, and: [{child: Cup, translation: {offset: [0, 0, 1]}}]}
  Cup: {observed: true}
observation:
  noise: {Cupp: {position: 0.01}}
"""
    (message,) = errors(text)
    assert "noise of 'Cupp': not a type of this grammar (did you mean 'Cup'?)" in message


def test_a_position_just_beyond_the_limit_says_its_digits() -> None:
    """`got 1e+06 m` for 1000000.0000001 m read as the limit itself."""
    from ssgc.dsl import _within_limit

    with pytest.raises(ValueError, match=r"got 1000000\.0000001 m"):
        _within_limit([1000000.0000001, 0.0, 0.0], "a position")


def test_a_misspelt_key_hides_no_other_mistake_of_its_mapping() -> None:
    """With `variance`, `covariance` and `varience` all given, "give exactly one" was dropped
    as a follow-on of the misspelling, though it holds without it."""
    text = """\
grammar: f
root: R
types:
  R:
    observed: true
    and:
      - child: A
        translation:
          world_normal:
            {mean: [0, 0, 0], variance: 0.1, covariance: [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
             varience: 1}
  A: {observed: true}
"""
    messages = errors(text)
    assert sum("unknown key 'varience'" in m for m in messages) == 1
    assert sum("give exactly one of `variance` or `covariance`" in m for m in messages) == 1


def test_a_radius_for_the_type_a_misspelt_name_meant_is_no_second_mistake() -> None:
    text = """\
grammar: v
root: R
types:
  R:
    observed: true
    geometry: {box: {size: [1, 1, 0.1]}}
    and: [{child: M, translation: {offset: [0, 0, 0.2]}}]
  M: {observed: true, geometry: {sphere: {radius: 0.1}}}
constraints:
  a: {inside_box: {types: [Mx], min: [0, 0, 0], max: [1, 1, 1], keep_out: true, radius: {M: 1}}}
"""
    messages = errors(text)
    assert messages and all("'Mx' is not a type" in m for m in messages), messages
