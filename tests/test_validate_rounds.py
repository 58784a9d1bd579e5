"""`ssg validate` reports a grammar's errors of every kind in one run (issue 16, item 7): fix
everything it reports once and the grammar validates; nothing was held back for a next round."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from ssgc.cli.app import app

runner = CliRunner()

BAD = """\
grammar: bad
root:
  type: Table
  pose: {xyz: [0, 0, 0]}
types:
  Table:
    observed: true
    geometry: {mesh: {file: nothere.obj}}
    independent:
      - child: Mug
        translation: {world_normal: {mean: [0, 0, 0], variance: 0.01}}
        rotation: same
      - child: Plate
        p: 0.5
        translation: {world_normal: {mean: [0, 0], variance: -1}}
        rotation: same
      - child: Spoon
        p: 1.5
        translation: {world_normal: {mean: [0, 0, 0], variance: 0.01}}
        rotation: same
  Mug:
    observed: true
    geometry: {cylinder: {radius: 0.04, length: "tall"}}
    colour: red
  Plate:
    observed: yes_please
    or:
      - {child: Bowl, p: 0.7, translation: same, rotation: same}
      - {child: Mug, p: 0.3, translation: same, rotation: same}
  Bowl: {observed: true}
"""

# Every mistake above, where it is and what the message says (YAML shape, unknown key, meaning,
# and the mesh file).
EXPECTED = {
    (8, 29): "mesh file 'nothere.obj': not found",
    (10, 9): "needs its probability `p`",
    (15, 38): "must have at least 3 items",
    (15, 62): "must be greater than 0",
    (17, 16): "child type 'Spoon' is not a type",
    (18, 12): "probability in [0, 1], got 1.5",
    (23, 49): "expected a number, got 'tall'",
    (24, 5): "unknown key 'colour'",
    (26, 15): "expected true or false",
}

FIXES = [
    ("file: nothere.obj", "file: tetra.obj"),
    ("      - child: Mug\n", "      - child: Mug\n        p: 0.5\n"),
    ("mean: [0, 0], variance: -1", "mean: [0, 0, 0], variance: 0.01"),
    ("child: Spoon", "child: Bowl"),
    ("p: 1.5", "p: 0.5"),
    ('length: "tall"', "length: 0.1"),
    ("    colour: red\n", ""),
    ("yes_please", "true"),
]
TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def test_every_kind_of_error_in_one_run(tmp_path: Path):
    grammar = tmp_path / "bad.yaml"
    grammar.write_text(BAD)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 1
    lines = [ln for ln in result.output.splitlines() if ": error: " in ln]
    found = {}
    for line in lines:
        where, message = line.split(": error: ", 1)
        _, row, col = where.rsplit(":", 2)
        found[(int(row), int(col))] = message
    assert set(found) == set(EXPECTED), result.output
    for place, words in EXPECTED.items():
        assert words in found[place]


def test_fixing_what_one_run_reports_is_enough(tmp_path: Path):
    text = BAD
    for old, new in FIXES:
        assert old in text
        text = text.replace(old, new, 1)
    (tmp_path / "tetra.obj").write_text(TETRA)
    grammar = tmp_path / "fixed.yaml"
    grammar.write_text(text)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 0, result.output


# A type with an unknown key and a misshapen translation in its `repeat` rule, whose child is
# misspelt and whose rotation is wrong too: the rule's other parts are still checked.
NESTED = """\
grammar: nested
root: {type: Table, pose: {xyz: [0, 0, 0.375]}}
types:
  Table:
    observed: true
    colour: red
    repeat:
      count: {probs: [0.1, 0.3, 0.4, 0.2]}
      rule:
        child: Plat
        translation: {parent_normal_offset: {mean: [0, 0], variance: [0.04, 0.01, 0], pin: [w]}}
        rotation: {revolute: {axis: [0, 0, 0]}}
  Plate:
    observed: true
    or:
      - {child: Cupp, translation: {world_normal: {mean: [0, 0, 1], variance: -1}}, rotation: same}
      - {child: Cup, rotation: {revolute: {axis: [0, 0, 0]}}}
  Cup: {observed: true}
"""

NESTED_EXPECTED = {
    (6, 5): "unknown key 'colour'",
    (10, 16): "child type 'Plat' is not a type",
    (11, 46): "must have at least 3 items",
    (11, 93): "must be 'x', 'y' or 'z'",
    (12, 31): "revolute axis must be nonzero",
    (16, 17): "child type 'Cupp' is not a type",
    (16, 79): "must be greater than 0",
    (17, 44): "revolute axis must be nonzero",
}

NESTED_FIXES = [
    ("    colour: red\n", ""),
    ("child: Plat\n", "child: Plate\n"),
    (
        "mean: [0, 0], variance: [0.04, 0.01, 0], pin: [w]",
        "mean: [0, 0, 0.4], variance: [0.04, 0.01, 0], pin: [z]",
    ),
    ("axis: [0, 0, 0]}}\n  Plate", "axis: [0, 0, 1]}}\n  Plate"),
    ("child: Cupp", "child: Cup"),
    ("variance: -1", "variance: 0.01"),
    ("axis: [0, 0, 0]}}}", "axis: [0, 0, 1]}}}"),
]


def test_a_misshapen_rule_part_leaves_the_rest_of_its_rule_checked(tmp_path: Path):
    grammar = tmp_path / "nested.yaml"
    grammar.write_text(NESTED)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 1
    found = {}
    for line in result.output.splitlines():
        if ": error: " in line:
            where, message = line.split(": error: ", 1)
            _, row, col = where.rsplit(":", 2)
            found[(int(row), int(col))] = message
    assert set(found) == set(NESTED_EXPECTED), result.output
    for place, words in NESTED_EXPECTED.items():
        assert words in found[place]
    text = NESTED
    for old, new in NESTED_FIXES:
        assert old in text
        text = text.replace(old, new, 1)
    grammar.write_text(text)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 0, result.output


# A rule's error, and an `observation` section wrong in every way it can be: a misshapen noise
# entry, noise on a latent type and on no type, too little rotation noise, an empty clutter
# region, clutter of a latent type.  The section's errors were held back until the rules had
# none, and the region's hid the clutter types'.
OBSERVATION = """\
grammar: observed_badly
root: Base
types:
  Base:
    and:
      - {child: A}
      - {child: B, rotation: {offset: {quat_wxyz: [1, 0, 0, 0.1]}}}
  A: {observed: true}
  B: {observed: true}
observation:
  noise:
    Base: {position: 0.01}
    Zed: {position: 0.01}
    A: {rotation_deg: 0.5}
    B: {position: -1}
  clutter:
    region: {min: [0, 0, 0], max: [1, 0, 1]}
    rates: {Base: 0.1, Napkin: 0.2}
"""

OBSERVATION_EXPECTED = {
    (7, 40): "quaternion must have unit norm",
    (12, 5): "noise of 'Base': not an observed type",
    (13, 5): "noise of 'Zed': not a type of this grammar",
    (14, 23): "rotation noise must be 0 or at least",
    (15, 19): "must be greater than or equal to 0",
    (17, 30): "the clutter region needs max > min",
    (18, 19): "clutter of type 'Base': the type is not observed",
}

OBSERVATION_FIXES = [
    ("0, 0.1]", "0, 0]"),
    ("    Base: {position: 0.01}\n", ""),
    ("    Zed: {position: 0.01}\n", ""),
    ("rotation_deg: 0.5", "rotation_deg: 1"),
    ("position: -1", "position: 0.01"),
    ("max: [1, 0, 1]", "max: [1, 1, 1]"),
    ("Base: 0.1, ", ""),
]


def test_the_observation_section_is_checked_with_the_rules(tmp_path: Path):
    grammar = tmp_path / "observed.yaml"
    grammar.write_text(OBSERVATION)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 1
    found = {}
    for line in result.output.splitlines():
        if ": error: " in line:
            where, message = line.split(": error: ", 1)
            _, row, col = where.rsplit(":", 2)
            found[(int(row), int(col))] = message
    assert set(found) == set(OBSERVATION_EXPECTED), result.output
    for place, words in OBSERVATION_EXPECTED.items():
        assert words in found[place]
    text = OBSERVATION
    for old, new in OBSERVATION_FIXES:
        assert old in text
        text = text.replace(old, new, 1)
    grammar.write_text(text)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 0, result.output


# Shape errors whose stand-ins must not raise anything false: a table whose geometry is wrong
# keeps its place in the constraints' trees (no "can never hold"), and a missing count law
# leaves the repeat's rule checked.
STAND_INS = """\
grammar: stand_ins
root: {type: Table, pose: {xyz: [0, 0, 0.375]}}
types:
  Table:
    observed: true
    geometry: {box: {size: [1.2, 0.8]}}
    independent:
      - {child: Shelf, p: 0.5}
  Shelf:
    repeat:
      rule: {child: Plat}
  Plate: {observed: true, geometry: {cylinder: {radius: 0.1, length: 0.02}}}
constraints:
  some_plates: {count: {type: Plate, min: 1}}
  apart: {clearance: {types: [Plate]}}
"""


def test_stand_ins_for_misshapen_parts_raise_nothing_false(tmp_path: Path):
    grammar = tmp_path / "stand_ins.yaml"
    grammar.write_text(STAND_INS)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 1
    errors = [ln.split(": error: ", 1)[1] for ln in result.output.splitlines() if ": error: " in ln]
    assert len(errors) == 3, result.output
    assert "types.Table.geometry.box.size: must have at least 3 items" in errors[0]
    assert "types.Shelf.repeat.count: missing required key" in errors[1]
    assert "child type 'Plat' is not a type" in errors[2]
    fixed = STAND_INS.replace("[1.2, 0.8]", "[1.2, 0.8, 0.75]")
    fixed = fixed.replace(
        "rule: {child: Plat}", "count: {probs: [0, 1]}\n      rule: {child: Plate}"
    )
    grammar.write_text(fixed)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 0, result.output


# A missing mesh (an error to `ssg validate`) and an unreachable type (a warning).
MESH_AND_ORPHAN = """\
grammar: orphan
root: Table
types:
  Table:
    observed: true
    geometry: {mesh: {file: nothere.obj}}
  Orphan: {}
"""


def test_the_warnings_are_printed_with_the_mesh_errors(tmp_path: Path):
    """The mesh errors were raised before the warnings were printed, so they were lost; the
    compiler's own warning about the same missing mesh is not repeated beside its error."""
    grammar = tmp_path / "orphan.yaml"
    grammar.write_text(MESH_AND_ORPHAN)
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [
        f"{grammar}:6:29: error: mesh file 'nothere.obj': not found",
        f"{grammar}:7:3: warning: type 'Orphan' is unreachable from the root",
    ]
    broken = MESH_AND_ORPHAN + "constraints: {c: {count: {type: Nope}}}\n"
    grammar.write_text(broken)  # the compiler fails too: the same two, after its error
    result = runner.invoke(app, ["validate", str(grammar)])
    assert result.exit_code == 1
    assert result.stderr.splitlines()[1:] == [
        f"{grammar}:6:29: error: mesh file 'nothere.obj': not found",
        f"{grammar}:7:3: warning: type 'Orphan' is unreachable from the root",
    ]
    assert "type 'Nope' is not a type" in result.stderr.splitlines()[0]


def test_a_grammar_over_the_size_limit_is_not_read_for_its_meshes(tmp_path, monkeypatch):
    """`ssg validate` looks for the meshes of a grammar that does not compile by reading the
    document itself; it did so without the size limit, so a 5 MB file the compiler refused at
    once then took minutes in the YAML reader."""
    import ssgc.yamlio
    from ssgc.assets import check_document_meshes
    from ssgc.yamlio import MAX_GRAMMAR_BYTES

    big = tmp_path / "big.yaml"
    big.write_text("grammar: g\n#" + "x" * MAX_GRAMMAR_BYTES + "\n")

    read = []
    monkeypatch.setattr(ssgc.yamlio, "load_located", lambda *args: read.append(args))
    assert check_document_meshes(big) == []
    assert not read  # the YAML reader never saw it
