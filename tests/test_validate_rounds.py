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
