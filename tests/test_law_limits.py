"""Limits of the placement laws that `ssg validate` enforces, and what the sampler refuses.

- Positions and offsets written in a rule lie within the 1,000 km every scene reader accepts
  (`dsl.MAX_COORDINATE`), and `ssg sample` writes no scene whose nodes its spreads or chained
  offsets carried beyond it.
- A box or revolute range counts points within 1e-6 m (rad) outside it as inside, so a
  narrow one would carry more than its mass: free box axes and arcs narrower than 1e-4 are
  refused, pins (`min == max`) still work.
- Observation noise does not widen a box or a partial revolute: `ssg validate` warns.
- A pinned axis's variance may be 0 but not negative, written as `variance` or `covariance`.
"""

from __future__ import annotations

from pathlib import Path
from textwrap import dedent

import numpy as np
import pytest
from typer.testing import CliRunner

import ssgc.api
from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.errors import Diagnostic, GrammarError, SsgError
from ssgc.laws.position_box import BoxTranslation
from ssgc.laws.rotation_revolute import RevoluteRotation

FILE = "case.yaml"


def grammar(translation: str = "same", rotation: str = "same", extra: str = "") -> str:
    """One observed child `C` of an observed root `Base`, placed by the given rule parts."""
    return (
        dedent(f"""\
        grammar: g
        root: {{type: Base, pose: {{xyz: [0, 0, 0.5]}}}}
        types:
          Base:
            observed: true
            and:
              - child: C
                translation: {translation}
                rotation: {rotation}
          C: {{observed: true}}
        """)
        + extra
    )


def place(text: str, needle: str) -> tuple[int, int]:
    """1-based line and column of the one occurrence of `needle` in `text`."""
    assert text.count(needle) == 1, needle
    before = text[: text.index(needle)]
    return before.count("\n") + 1, len(before) - (before.rfind("\n") + 1) + 1


def the_error(text: str) -> Diagnostic:
    """The one diagnostic of a grammar with one mistake."""
    with pytest.raises(GrammarError) as info:
        compile_text(text, FILE)
    errors = [d for d in info.value.diagnostics if d.severity == "error"]
    assert len(errors) == 1, "\n".join(map(str, info.value.diagnostics))
    return errors[0]


# --------------------------------------------------- 1a: constants within 1,000 km ---


@pytest.mark.parametrize(
    ("translation", "at", "got"),
    [
        ("{offset: [0, 2000000, 0]}", "2000000", "2e+06"),
        ("{world_normal: {mean: [1e300, 0, 0], variance: 1}}", "1e300", "1e+300"),
        ("{world_normal_offset: {mean: [0, 0, -1.5e6], variance: 1}}", "-1.5e6", "1.5e+06"),
        ("{parent_normal_offset: {mean: [0, 3e6, 0], variance: 1}}", "3e6", "3e+06"),
        ("{world_box: {min: [0, 0, 0], max: [1e200, 1e200, 1e200]}}", "[1e200", "1e+200"),
        ("{world_box_offset: {min: [-2e6, 0, 0], max: [0, 1, 1]}}", "-2e6", "2e+06"),
    ],
)
def test_a_position_or_offset_beyond_1000_km_is_one_located_error(translation, at, got):
    text = grammar(translation)
    d = the_error(text)
    assert "within 1,000 km" in d.message and f"got {got} m" in d.message, d
    assert d.line == place(text, at)[0], d


def test_a_clutter_region_beyond_1000_km_is_refused():
    section = dedent("""\
        observation:
          clutter: {region: {min: [0, 0, 0], max: [1, 1, 5e6]}, rates: {Sponge: 0.1}}
        """)
    text = grammar(extra=section)
    d = the_error(text)
    assert "within 1,000 km" in d.message and d.line == place(text, "5e6")[0], d


def test_constants_at_the_limit_compile():
    compile_text(grammar("{offset: [0, 1e6, 0]}"), FILE)
    compile_text(grammar("{world_box: {min: [-1e6, -1e6, 0], max: [1e6, 1e6, 0]}}"), FILE)
    compile_text(grammar("{world_normal: {mean: [-1e6, 0, 0], variance: 1}}"), FILE)


def test_validate_refuses_a_far_offset(tmp_path: Path):
    path = tmp_path / "far.yaml"
    path.write_text(grammar("{offset: [0, 2000000, 0]}"))
    result = CliRunner().invoke(app, ["validate", str(path)])
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{path}:8:"), result.stderr
    assert "1,000 km" in lines[0]


# ------------------------------------------------ 1b: no scene beyond 1,000 km written ---


def test_sample_refuses_a_scene_its_spread_carries_beyond_the_limit(tmp_path: Path):
    path = tmp_path / "wide.yaml"
    path.write_text(grammar("{world_normal: {mean: [0, 0, 0], variance: 1e14}}"))
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["sample", str(path), "-n", "3", "-o", str(out)])
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "object C" in lines[0] and "1,000 km" in lines[0] and "g_000000" in lines[0]
    assert not out.exists() or not any(out.iterdir()), sorted(out.iterdir())


def test_sample_refuses_chained_offsets_that_add_up_beyond_the_limit(tmp_path: Path):
    """Each offset is within the limit; their sum is not.  The API refuses too."""
    text = dedent("""\
        grammar: chained
        root: A
        types:
          A: {and: [{child: B, translation: {offset: [900000, 0, 0]}}]}
          B: {and: [{child: C, translation: {offset: [900000, 0, 0]}}]}
          C: {observed: true}
        """)
    path = tmp_path / "chained.yaml"
    path.write_text(text)
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["sample", str(path), "-n", "2", "-o", str(out)])
    assert result.exit_code == 1, result.output
    assert "object C" in result.stderr and "1.8e+06 m" in result.stderr, result.stderr
    assert not out.exists() or not any(out.iterdir())
    with pytest.raises(SsgError, match="1,000 km"):
        ssgc.api.load_grammar(path).sample(2)


def test_sample_writes_scenes_within_the_limit(tmp_path: Path):
    path = tmp_path / "near.yaml"
    path.write_text(grammar("{world_normal: {mean: [0, 0, 0], variance: 1e6}}"))
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["sample", str(path), "-n", "3", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert len(list(out.glob("*.json"))) == 3


# ------------------------------------------- 2: narrow boxes and arcs are refused ---


def box_mass(width: float) -> float | None:
    """The mass a `world_box` `width` wide on z carries along z (its density integrated over
    z on a grid fine enough for the 1e-6 m tolerance); None if the compiler refuses it."""
    text = grammar(f"{{world_box: {{min: [0, 0, 0], max: [1, 1, {width!r}]}}}}")
    try:
        g = compile_text(text, FILE)
    except GrammarError:
        return None
    law = next(r.translation for r in g.rules if isinstance(r.translation, BoxTranslation))
    z = np.linspace(-1e-5, width + 1e-5, 200_001)
    u = np.column_stack([np.full_like(z, 0.5), np.full_like(z, 0.5), z])
    cols = {k: np.broadcast_to(v, (len(z), *np.shape(v))) for k, v in law.row().items()}
    return float(np.exp(BoxTranslation.density(cols, u)).sum() * (z[1] - z[0]))


def arc_mass(width: float) -> float | None:
    """The same for a revolute range `width` wide (density integrated over the angle)."""
    text = grammar(rotation=f"{{revolute: {{axis: [0, 0, 1], min: 0, max: {width!r}}}}}")
    try:
        g = compile_text(text, FILE)
    except GrammarError:
        return None
    law = next(r.rotation for r in g.rules if isinstance(r.rotation, RevoluteRotation))
    theta = np.linspace(-1e-5, width + 1e-5, 200_001)
    q = np.column_stack([np.cos(theta / 2), 0 * theta, 0 * theta, np.sin(theta / 2)])
    cols = {k: np.broadcast_to(v, (len(q), *np.shape(v))) for k, v in law.row().items()}
    return float(np.exp(RevoluteRotation.density(cols, q)).sum() * (theta[1] - theta[0]))


@pytest.mark.parametrize("width", [1e-7, 1e-6, 5e-5, 1e-4, 2e-4, 1e-3])
def test_every_box_and_arc_the_compiler_accepts_carries_its_mass_within_2_percent(width):
    """A box 0.1 µm wide integrated to ~21: the 1e-6 tolerance of its faces adds 2e-6 to its
    width.  Those narrower than 1e-4 are refused now, so what compiles is within 2%."""
    for mass in (box_mass(width), arc_mass(width)):
        if width < 1e-4:
            assert mass is None, f"width {width:g} compiled, mass {mass}"
        else:
            assert mass is not None and abs(mass - 1) <= 0.021, (width, mass)


def test_a_narrow_box_axis_is_refused_at_its_place_and_a_pin_is_not():
    text = grammar("{world_box_offset: {min: [0, 0, 0.1], max: [1, 1, 0.10005]}}")
    d = the_error(text)
    assert d.line == place(text, "0.10005")[0] and d.column == place(text, "0.10005")[1], d
    assert "narrower than 0.0001 m" in d.message and "z" in d.message, d
    compile_text(grammar("{world_box_offset: {min: [0, 0, 0.1], max: [1, 1, 0.1]}}"), FILE)


def test_a_narrow_revolute_range_is_refused():
    text = grammar(rotation="{revolute: {axis: [0, 0, 1], min: 0.5, max: 0.50001}}")
    d = the_error(text)
    assert d.line == place(text, "0.50001")[0] and "narrower than 0.0001 rad" in d.message, d


def test_a_narrow_clutter_region_is_refused():
    section = dedent("""\
        observation:
          clutter: {region: {min: [0, 0, 0], max: [1, 1, 0.00001]}, rates: {Sponge: 0.1}}
        """)
    d = the_error(grammar(extra=section))
    assert "narrower than 0.0001 m" in d.message, d


# ----------------------------------------- 3: noise does not widen boxes and arcs ---

NOISE = "observation:\n  noise:\n    default: {position: 0.005, rotation_deg: 2}\n"
BOX = "{world_box_offset: {min: [-0.5, -0.5, 0.4], max: [0.5, 0.5, 0.4]}}"
ARC = "{revolute: {axis: [0, 0, 1], min: 0, max: 3}}"


def warnings_of(text: str) -> list[Diagnostic]:
    return [d for d in compile_text(text, FILE).warnings if d.severity == "warning"]


def test_noise_on_a_box_or_partial_revolute_rule_is_one_warning_per_rule():
    text = grammar(BOX, ARC, NOISE)
    (w,) = warnings_of(text)
    assert w.line == place(text, "world_box_offset")[0], w
    assert "noise does not widen" in w.message and "box" in w.message, w
    assert "revolute" in w.message and "C" in w.message, w
    (w,) = warnings_of(grammar(rotation=ARC, extra=NOISE))
    assert "revolute" in w.message and "box" not in w.message, w
    (w,) = warnings_of(grammar(BOX, extra=NOISE))
    assert "box" in w.message and "revolute" not in w.message, w


def test_noise_that_widens_every_part_or_none_is_not_warned_about():
    full = "{revolute: {axis: [0, 0, 1]}}"
    normal = "{world_normal_offset: {mean: [0, 0, 0.4], variance: 0.01, pin: [z]}}"
    assert warnings_of(grammar(normal, full, NOISE)) == []
    assert warnings_of(grammar(BOX, ARC)) == []  # no observation: nothing to widen
    rotation_only = NOISE.replace("position: 0.005, ", "")
    assert warnings_of(grammar(BOX, extra=rotation_only)) == []  # a box meets no position noise


def test_validate_prints_the_warning_and_succeeds(tmp_path: Path):
    path = tmp_path / "noisebox.yaml"
    path.write_text(grammar(BOX, ARC, NOISE))
    result = CliRunner().invoke(app, ["validate", str(path)])
    assert result.exit_code == 0, result.output
    assert f"{path}:8:" in result.output and "warning: noise does not widen" in result.output


# -------------------------------------- 4: a pinned axis's variance is not negative ---


def test_a_negative_pinned_variance_in_a_covariance_is_refused_at_its_entry():
    text = grammar("{world_normal: {covariance: [[1, 0, 0], [0, 1, 0], [0, 0, -1]], pin: [z]}}")
    d = the_error(text)
    assert d.line == 8 and d.column == place(text, "-1]]")[1], d
    assert "got -1 (z axis)" in d.message and "negative" in d.message, d


def test_a_zero_pinned_variance_in_either_form_compiles():
    compile_text(
        grammar("{world_normal: {covariance: [[1, 0, 0], [0, 1, 0], [0, 0, 0]], pin: [z]}}"), FILE
    )
    compile_text(grammar("{world_normal: {variance: [1, 1, 0], pin: [z]}}"), FILE)


# ------------------------------------- a pinned axis's covariance coupling has no effect ---


def test_a_covariance_coupling_a_pinned_axis_is_warned_about_at_its_entry():
    """The rows and columns of pinned axes are dropped, not conditioned on (grammar.md 4.2):
    a coupling written there silently did nothing."""
    law = "{world_normal: {covariance: [[1, 0, 0.3], [0, 1, 0], [0.3, 0, 0]], pin: [z]}}"
    text = grammar(translation=law)
    g = compile_text(text, FILE)
    warned = [w for w in g.warnings if "couples the pinned z axis with x" in w.message]
    assert len(warned) == 1, g.warnings
    line, col = place(text, "0.3, 0, 0]]")  # its row: the pinned axis z, column x
    assert (warned[0].line, warned[0].column) == (line, col)
    free = "{world_normal: {covariance: [[1, 0.2, 0], [0.2, 1, 0], [0, 0, 0]], pin: [z]}}"
    assert not [w for w in compile_text(grammar(translation=free), FILE).warnings]
