"""Verdicts of constrained sampling that the session-33 hunt found wrong: a scene is written
only when every chosen constraint holds on it (the root's own terms too), a constraint that
fails on the fixed root is refused before sampling, a frame an object can lack (its own type,
the root) is a validate error, and the out-of-time message says what happened."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.errors import GrammarError, SsgError
from ssgc.sample import constrained
from ssgc.sample.constrained import Tally, _unmet, sample_blocks, select
from ssgc.sample.forward import sample_trees
from ssgc.sample.staged import Outcome, OutOfTime, rejection_batch

RUNNER = CliRunner()
# The hunt's rootmix.yaml: the root Table stands at z 0.375, turned 30 degrees about z.
ROOTMIX = """\
grammar: rootmix
root: {type: Table, pose: {xyz: [0, 0, 0.375], rpy_deg: [0, 0, 30]}}
types:
  Table:
    observed: true
    geometry: {box: {size: [1.2, 1.2, 0.75]}}
    repeat:
      count: {probs: [1, 1, 1]}
      rule:
        child: Cup
        translation: {world_box_offset: {min: [-0.5, -0.5, 0.8], max: [0.5, 0.5, 0.8]}}
  Cup:
    observed: true
    geometry: {cylinder: {radius: 0.05, length: 0.1}}
constraints:
  all_upright: {upright: {types: [Table, Cup], max_angle_deg: 10, axis: x}}
  all_high: {inside_box: {types: [Table, Cup], min: [-1, -1, 0.5], max: [1, 1, 2]}}
  table_high: {inside_box: {types: [Table], min: [-1, -1, 0.5], max: [1, 1, 2]}}
  all_above: {inside_box: {types: [Table, Cup], min: [-1, -1, 0.3], max: [1, 1, 2]}}
  cups_high: {inside_box: {types: [Cup], min: [-0.4, -1, 0.5], max: [1, 1, 2]}}
"""


@pytest.fixture(scope="module")
def rootmix():  # type: ignore[no-untyped-def]
    return compile_text(ROOTMIX, "rootmix.yaml")


def _sample(tmp_path: Path, names: str, *more: str):  # type: ignore[no-untyped-def]
    path = tmp_path / "rootmix.yaml"
    path.write_text(ROOTMIX)
    out = tmp_path / "out"
    args = ["sample", str(path), "-n", "5", "--constraints", names, "-o", str(out), "-q", *more]
    return RUNNER.invoke(app, args), out


# ------------------------------------------------------------------ the fixed root ---


@pytest.mark.parametrize(
    ("names", "method"),
    [
        ("all_high", "auto"),
        ("all_upright", "auto"),
        ("table_high", "auto"),
        ("all_high", "rjmcmc"),
        ("all_upright", "hmc"),
        ("table_high", "project"),
    ],
)
def test_a_constraint_the_fixed_root_fails_is_refused_before_sampling(
    tmp_path: Path, names: str, method: str
) -> None:
    """Rejection wrote 5 scenes with "all_high": -0.125 (the table's origin is below the
    box) and exit 0; the other methods tried until --max-tries ran out."""
    result, out = _sample(tmp_path, names, "--method", method, "--max-tries", "3000")
    assert result.exit_code == 2, result.output
    assert f"constraint '{names}' can never hold" in result.stderr
    assert "the root 'Table'" in result.stderr
    assert not list(out.glob("*.json"))


def test_the_api_refuses_it_too(rootmix) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(SsgError, match="'all_high' can never hold") as caught:
        list(sample_blocks(rootmix, select(rootmix, "all_high"), 5, 0))
    assert caught.value.exit_code == 2


def test_staged_rejection_judges_the_roots_own_terms(rootmix) -> None:  # type: ignore[no-untyped-def]
    """The pose stage judged only terms with a freshly posed node, and the root is posed
    when the tree is made: every candidate was kept with a negative margin."""
    for name in ("all_high", "all_upright", "table_high"):
        o = rejection_batch(rootmix, select(rootmix, name), 64, np.random.default_rng(1))
        assert o.trees.n_scenes == 0, name
        assert o.rejected[name] == o.evaluated[name] == 64, name


def test_a_root_that_passes_still_samples(tmp_path: Path) -> None:
    """The root's terms are judged with the rest: a box the table stands in keeps scenes."""
    result, out = _sample(tmp_path, "all_above,cups_high")
    assert result.exit_code == 0, result.output
    files = sorted(out.glob("*.json"))
    assert len(files) == 5
    for f in files:
        margins = json.loads(f.read_text())["metadata"]["constraints"]
        assert margins["all_above"] is None or margins["all_above"] >= 0
        assert margins["cups_high"] is None or margins["cups_high"] >= 0


def test_no_method_yields_a_scene_whose_margins_fail(rootmix, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The last word is the final margins: a method that kept every candidate (here, plain
    forward sampling) still yields only the scenes on which every constraint holds."""
    chosen = select(rootmix, "cups_high")

    def keep_all(grammar, constraints, size, rng, deadline=None):  # type: ignore[no-untyped-def]
        trees, logp = sample_trees(grammar, size, int(rng.integers(2**31)))
        margins = {c.name: c.margin(trees) for c in constraints}
        zero = dict.fromkeys(margins, 0)
        best = dict.fromkeys(margins, -np.inf)
        return Outcome(trees, logp, margins, dict(zero), dict(zero), best, size)

    monkeypatch.setitem(constrained.METHODS, "rejection", keep_all)
    tally = Tally()
    (block,) = sample_blocks(rootmix, chosen, 40, 3, tally=tally)
    assert block.trees.n_scenes == 40
    assert np.all(block.margins["cups_high"] >= 0)
    assert np.all(chosen[0].margin(block.trees) >= 0)
    assert tally.rejected["cups_high"] > 0  # some forward draws put a cup outside the box


# ---------------------------------------------------------------- frames one can lack ---

FRAMES = """\
grammar: frames
root: {type: Table, pose: {xyz: [0, 0, 0.375]}}
types:
  Table:
    observed: true
    geometry: {box: {size: [1.2, 1.2, 0.75]}}
    repeat:
      count: {probs: [0, 1, 1]}
      rule: {child: Tray, translation: {offset: [0, 0, 0.4]}}
  Tray:
    observed: true
    geometry: {cylinder: {radius: 0.1, length: 0.06}}
    max_nesting: 3
    or:
      - {child: Tray, p: 0.5, translation: {offset: [0, 0, 0.06]}}
      - {child: Cup, p: 0.5, translation: {offset: [0, 0, 0.06]}}
  Cup: {observed: true, geometry: {cylinder: {radius: 0.05, length: 0.1}}}
constraints:
"""


@pytest.mark.parametrize(
    ("entry", "what"),
    [
        ("{inside_box: {types: [Tray], frame: Tray, min: [-1, -1, 0], max: [1, 1, 1]}}", "Tray"),
        ("{upright: {types: [Tray], frame: Tray, max_angle_deg: 5}}", "Tray"),
        (
            "{inside_box: {types: [Table], frame: Table, min: [-1, -1, -1], max: [1, 1, 1]}}",
            "Table",
        ),
        ("{upright: {types: [Cup, Table], frame: Table, max_angle_deg: 5}}", "Table"),
    ],
)
def test_a_listed_type_is_not_its_own_frame(entry: str, what: str) -> None:
    """A frame is the nearest proper ancestor: a bottom tray has no tray above it, the root
    nothing at all.  Validate said ok, and sampling rejected every candidate (margin -inf)."""
    with pytest.raises(GrammarError) as caught:
        compile_text(FRAMES + f"  c: {entry}\n", "frames.yaml")
    (message,) = [str(d) for d in caught.value.diagnostics]
    assert message.startswith("frames.yaml:19:")
    assert f"a '{what}' can occur without a '{what}' above it" in message


def test_frames_every_object_has_still_compile() -> None:
    text = FRAMES + (
        "  a: {inside_box: {types: [Cup], frame: Tray, min: [-1, -1, 0], max: [1, 1, 1]}}\n"
        "  b: {upright: {types: [Tray, Cup], frame: Table, max_angle_deg: 5}}\n"
    )
    assert [c.name for c in compile_text(text, "frames.yaml").constraints] == ["a", "b"]


# ------------------------------------------------------------------------- messages ---


def test_out_of_time_before_any_attempt_finished_says_so(rootmix) -> None:
    """A chain method's first attempt outran --time-limit after many seconds of work, and
    the message said "before the first candidate"."""
    message = str(_unmet(rootmix, Tally(abandoned=1), 2, "--time-limit 15 s", {}))
    assert "before the first candidate" not in message
    assert "no attempt finished within the limit (--time-limit 15 s)" in message
    message = str(_unmet(rootmix, Tally(), 2, "--time-limit 1e-12 s", {}))
    assert "before the first candidate (--time-limit 1e-12 s)" in message  # none began


def test_a_chain_attempt_cut_short_is_told_from_none_begun(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The same through `sample_blocks`: an attempt that outruns the deadline."""
    g = compile_text(ROOTMIX, "rootmix.yaml")

    def slow(grammar, constraints, size, rng, deadline=None):  # type: ignore[no-untyped-def]
        raise OutOfTime

    monkeypatch.setitem(constrained.METHODS, "hmc", slow)
    with pytest.raises(SsgError) as caught:
        list(sample_blocks(g, select(g, "cups_high"), 2, 0, "hmc", time_limit=60))
    (head,) = [d.message for d in caught.value.diagnostics]
    assert head.endswith("no attempt finished within the limit (--time-limit 60 s)")
