"""The observation model (`observation:` in a grammar; docs/grammar.md section 9): sensor noise
on observed poses and clutter objects (issue 16, item 4)."""

from __future__ import annotations

import json
import re
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_explain import DINNER, dinner_scene, moved
from typer.testing import CliRunner

import ssgc.api
from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.errors import GrammarError
from ssgc.explain import UnexplainedScene, explain, unexplained_objects
from ssgc.fit.em import parameter_ties
from ssgc.io.scene import Scene, scene_from_tree
from ssgc.laws.position_normal import NormalTranslation
from ssgc.laws.rotation_bingham import BinghamRotation
from ssgc.parse.parser import Parser
from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees

NOISE = (
    "observation:\n  noise:\n    Plate: {position: 0.004, rotation_deg: 2}\n"
    "    Mug: {position: 0.005}\n"
)
CLUTTER = (
    "observation:\n  clutter:\n    region: {min: [-1, -1, 0], max: [1, 1, 1.5]}\n"
    "    rates: {Sponge: 0.2, Mug: 0.1}\n"
)


def with_section(section: str, text: str = DINNER) -> object:
    return compile_text(text + section, "dinner.yaml")


def errors_of(section: str) -> list[str]:
    with pytest.raises(GrammarError) as info:
        with_section(section)
    return [str(d) for d in info.value.diagnostics]


def test_without_observation_the_grammar_is_unchanged():
    g, again = compile_text(DINNER), with_section("observation: {}\n")
    assert [t.name for t in g.types] == [t.name for t in again.types]
    for a, b in zip(g.rules, again.rules, strict=True):
        assert (
            a.translation is b.translation or a.translation.describe() == b.translation.describe()
        )
        assert a.rotation.describe() == b.rotation.describe()
    assert all(not t.synthetic for t in again.types)


def test_noise_widens_the_laws_between_observed_poses():
    g = with_section(NOISE)
    table_plate, plate_mug = g.rules
    # Table (latent, exact) -> Plate: the pinned z gets the plate's noise; x, y add it
    t = table_plate.translation
    assert isinstance(t, NormalTranslation) and t.free.all()
    assert np.allclose(np.diag(t.normal.cov), [0.25 + 0.004**2, 0.25 + 0.004**2, 0.004**2])
    assert t.fixed  # `ssg fit` keeps the laws the observation model made
    # Plate -> Mug, parent frame: both ends' noise, plus the plate's turn on the 2 cm lever
    lever = (0.02 * np.deg2rad(2.0)) ** 2
    expect = 0.004**2 + 0.005**2 + lever
    m = plate_mug.translation
    assert np.allclose(np.diag(m.normal.cov), [0.0004 + expect, 0.0004 + expect, expect])
    # world-frame Bingham of a plate: its concentration combined with the noise's, c k / (c + k)
    k = 2.0 / np.deg2rad(2.0) ** 2
    r = table_plate.rotation
    assert isinstance(r, BinghamRotation)
    assert np.allclose(np.sort(r.bingham.concentration)[::-1][:2], 50 * k / (50 + k))


@settings(max_examples=10, deadline=None)
@given(sigma=st.floats(0.001, 0.05), deg=st.floats(1.0, 20.0))
def test_a_fixed_offset_with_noise_is_a_normal_about_it(sigma, deg):
    """A fixed rule between two observed poses becomes the law of the noise itself: a Normal
    of the two ends' variance about the offset, a Bingham of their angle variance."""
    text = (
        "grammar: lamp\nroot: Table\ntypes:\n  Table:\n    observed: true\n    and:\n"
        "      - child: Lamp\n        translation: {offset: [0, 0, 0.5]}\n"
        "        rotation: {offset: {rpy_deg: [0, 0, 90]}}\n  Lamp: {observed: true}\n"
        f"observation:\n  noise:\n    Lamp: {{position: {sigma}, rotation_deg: {deg}}}\n"
    )
    g = compile_text(text)
    rule = next(r for r in g.rules if g.types[r.child].name == "Lamp")
    cov = rule.translation.normal.cov
    assert np.allclose(cov, sigma**2 * np.eye(3))
    assert np.allclose(rule.translation.offset, [0, 0, 0.5])
    conc = rule.rotation.bingham.concentration
    assert np.allclose(np.sort(conc)[1:], min(2.0 / np.deg2rad(deg) ** 2, 1e4))


ROOMS = """grammar: room
root: {type: Room, pose: {xyz: [0, 0, 0], rpy_deg: [0, 0, 90]}}
types:
  Room:
    and:
      - {child: Table, translation: {offset: [1, 0, 0.4]}}
      - child: Chair
        translation:
          parent_normal_offset: {mean: [0, 1, 0], variance: [0.01, 0.02, 0], pin: [z]}
  Table: {observed: true}
  Chair: {observed: true}
observation:
  noise:
    default: {position: 0.01, rotation_deg: 2}
"""


def test_an_object_fixed_to_a_latent_root_gets_its_noise_and_only_it():
    """The latent root's pose is exact.  Counted as not tied to an observed pose, the root
    joined the table's block: the table's noise went nowhere (sampled sd 0 per axis; a table
    5 mm off was infeasible) and onto the chair's rule as the parent's (z variance doubled,
    plus the 2° lever on 1 m, and the Bingham's concentration halved)."""
    g = compile_text(ROOMS)
    table, chair = g.rules
    assert np.allclose(table.translation.normal.cov, 0.01**2 * np.eye(3))
    assert np.allclose(np.diag(chair.translation.normal.cov), [0.0101, 0.0201, 0.0001])
    k = 2.0 / np.deg2rad(2.0) ** 2
    assert np.allclose(np.sort(chair.rotation.bingham.concentration)[1:], k)
    trees, _ = sample_trees(g, 4000, 0)
    tables = trees.xyz[trees.type == g.type_ids["Table"]]
    assert np.allclose(tables.std(axis=0), 0.01, rtol=0.1)
    types = np.array([g.type_ids["Table"], g.type_ids["Chair"]])
    off = np.array([[0.0, 1.0, 0.405], [-1.0, 0.0, 0.0]])  # the table 5 mm above its place
    scene = Scene("off", types, off, np.tile([1.0, 0, 0, 0], (2, 1)))
    assert Parser(g).parse(scene).status == "optimal"


def test_a_lifted_mug_parses_with_noise_and_keeps_its_tree():
    exact, noisy = compile_text(DINNER), with_section(NOISE)
    scene = dinner_scene(exact)
    lifted = moved(scene, 4, [0.0, 0.0, 0.01])
    with pytest.raises(UnexplainedScene):
        explain(exact, lifted)
    truth = Parser(exact).parse(scene).parses[0].tree
    result = Parser(noisy).parse(lifted)
    assert result.status == "optimal"
    tree = result.parses[0].tree
    # each mug under the same plate as in the exact parse of the unlifted scene
    assert _mug_plates(exact, scene, truth) == _mug_plates(noisy, lifted, tree)


def _mug_plates(g, scene: Scene, tree) -> list[int]:
    from ssgc.explain import match_objects

    obj_of = match_objects(g, scene, tree)
    mugs = np.flatnonzero(g.tables.type_observed[tree.type] & (tree.parent >= 0))
    return sorted(
        (int(obj_of[n]), int(obj_of[tree.parent[n]]))
        for n in mugs
        if g.types[int(tree.type[n])].name == "Mug"
    )


def test_an_observed_root_with_noise_gets_its_own_node():
    text = DINNER.replace("  Table:\n", "  Table:\n    observed: true\n", 1)
    text += "observation:\n  noise:\n    default: {position: 0.003}\n"
    g = compile_text(text, "dinner.yaml")
    names = [t.name for t in g.types]
    # its node holds the root's rules and count law where the document wrote them (ssg fit)
    node = g.types[g.type_ids["~node:Table"]]
    assert node.path == ("types", "Table") and node.count is not None
    parameter_ties(g, text, "dinner.yaml")  # every fitted parameter has its place
    assert g.types[g.root].name == "~scene" and "~node:Table" in names
    assert g.types[g.type_ids["Table"]].observed and not g.types[g.type_ids["Table"]].rules
    # a sampled scene: the observed table is off the root pose by the noise, and it parses
    trees, logp = sample_trees(g, 3, 0)
    table = trees.type == g.type_ids["Table"]
    assert np.all(np.linalg.norm(trees.xyz[table], axis=1) > 0)
    assert np.allclose(score_trees(g, trees), logp)
    parser = Parser(g)
    for i in range(3):
        scene = scene_from_tree(g, trees.tree(i), f"s{i}")
        best = parser.parse(scene).parses[0]
        assert best.score >= logp[i] - 1e-6


def test_a_grammar_with_clutter_is_fitted_with_its_rates_as_written(tmp_path: Path) -> None:
    """The clutter's count law belongs to a type the compiler adds (`~clutter`), fixed and
    with no YAML node: the fit's check of shared nodes looked it up and stopped with an
    internal error (found by the all-commands fuzz test)."""
    text = DINNER + CLUTTER
    g = compile_text(text, "dinner.yaml")
    parameter_ties(g, text, "dinner.yaml")
    grammar = ssgc.api.Grammar(g, text, None)
    result = ssgc.api.fit(grammar, grammar.sample(4, seed=2), iterations=1, top=1)
    assert "rates: {Sponge: 0.2, Mug: 0.1}" in result.grammar.text


def with_sponge(g, scene: Scene, xyz: list[float]) -> Scene:  # type: ignore[no-untyped-def]
    """The scene and one more object, a `Sponge` (a type only clutter makes) at `xyz`."""
    return Scene(
        "sponge",
        np.r_[scene.types, g.type_ids["Sponge"]],
        np.r_[scene.xyz, [xyz]],
        np.r_[scene.quat, [[1.0, 0, 0, 0]]],
    )


def test_clutter_flags_the_object_the_grammar_does_not_make():
    g = with_section(CLUTTER)
    scene = dinner_scene(g)
    sponge = with_sponge(g, scene, [0.2, 0.2, 0.8])
    e = explain(g, sponge)
    assert e.objects[0].index == 6 and e.objects[0].unexplained
    assert [o.index for o in e.objects if o.unexplained] == [6]
    assert "UNEXPLAINED" in e.text().splitlines()[1]
    # a mug far from every plate: the clutter explains it better than a 1 m placement
    far = moved(scene, 5, [0.0, 0.6, 0.0])
    tree = Parser(g).parse(far).parses[0].tree
    assert unexplained_objects(g, far, tree) == [5]


def test_without_clutter_the_extra_object_is_named():
    g = with_section("observation:\n  noise: {}\n", DINNER + "  Sponge: {observed: true}\n")
    scene = dinner_scene(g)
    sponge = replace(scene, types=np.r_[scene.types[:5], g.type_ids["Sponge"]])
    with pytest.raises(UnexplainedScene) as info:
        explain(g, sponge)
    assert info.value.diagnosis.objects == [5]


@pytest.mark.parametrize(
    "section, words",
    [
        ("observation:\n  noise:\n    Fork: {position: 0.01}\n", "not a type of this grammar"),
        ("observation:\n  noise:\n    Table: {position: 0.01}\n", "not an observed type"),
        ("observation:\n  noise:\n    Mug: {rotation_deg: 0.1}\n", "at least 0.8103°"),
        ("observation:\n  noise:\n    Mug: {position: -1}\n", "greater than or equal to 0"),
        ("observation:\n  noise:\n    Mug: {sigma: 1}\n", "unknown key 'sigma'"),
        (
            "observation:\n  clutter:\n    region: {min: [0, 0, 0], max: [1, 1, 1]}\n"
            "    rates: {Plate: 0.1}\n",
            "has rules of its own",
        ),
        (
            "observation:\n  clutter:\n    region: {min: [0, 0, 0], max: [1, 1, 0]}\n"
            "    rates: {Sponge: 0.1}\n",
            "max > min",
        ),
    ],
)
def test_observation_mistakes_are_located(section, words):
    errors = errors_of(section)
    assert any(words in e for e in errors), errors
    assert all(e.startswith("dinner.yaml:") and e.split(":")[1].isdigit() for e in errors)


def test_observation_mistakes_are_reported_with_the_rules_and_with_each_other():
    """One run reports them all (docs/grammar.md, section 6): the section was not checked at
    all while a rule had an error, and an empty clutter region hid the clutter types' errors."""
    text = DINNER.replace("child: Mug", "child: Mugg")
    section = (
        "observation:\n  noise:\n    Table: {position: 0.01}\n    Fork: {position: 0.01}\n"
        "  clutter:\n    region: {min: [0, 0, 0], max: [1, 0, 1]}\n    rates: {Table: 0.1}\n"
    )
    with pytest.raises(GrammarError) as info:
        with_section(section, text)
    errors = " | ".join(str(d) for d in info.value.diagnostics)
    for words in (
        "child type 'Mugg' is not a type",
        "noise of 'Table': not an observed type",
        "noise of 'Fork': not a type of this grammar",
        "the clutter region needs max > min",
        "clutter of type 'Table': the type is not observed",
    ):
        assert words in errors


def test_the_least_rotation_noise_the_message_names_is_accepted():
    """The message said "at least 0.81°" and refused 0.81 (the limit is 0.81028°)."""
    errors = errors_of("observation:\n  noise:\n    Mug: {rotation_deg: 0.81}\n")
    least = re.search(r"at least ([0-9.]+)°", " ".join(errors)).group(1)
    assert least == "0.8103"
    with_section(f"observation:\n  noise:\n    Mug: {{rotation_deg: {least}}}\n")


def test_validate_cli_names_the_place(tmp_path: Path):
    path = tmp_path / "g.yaml"
    path.write_text(DINNER + "observation:\n  noise:\n    Fork: {position: 0.01}\n")
    out = CliRunner().invoke(app, ["validate", str(path)])
    assert (out.exit_code not in (0, None) and out.exception is None) or isinstance(
        out.exception, SystemExit
    )
    assert f"{path}:" in out.output and "Fork" in out.output


@pytest.mark.slow
def test_real_sink_scenes_with_noise_and_clutter():
    """Issue 16, "Done means": the 80 sink scenes jittered by 5 mm and 2° parse with noise and
    keep their trees (but for near-ties of the exact grammar); one sponge per scene is the one
    object flagged unexplained."""
    sys.path.insert(0, str(Path(__file__).parent))
    from observation_check import clutter_check, noise_check

    noise = noise_check()
    assert noise["parsed"] == noise["scenes"] == 80
    assert noise["parsed_without_noise_model"] == 0
    assert noise["same_tree"] >= 78, noise["differ"]
    clutter = clutter_check()
    assert clutter["sponge_flagged_alone"] == 80, clutter["wrong"]


def test_the_diagnosis_hints_at_noise_and_clutter():
    g = compile_text(DINNER + "  Sponge: {observed: true}\n")
    scene = dinner_scene(g)
    with pytest.raises(UnexplainedScene) as info:
        explain(g, moved(scene, 4, [0.0, 0.0, 0.01]))
    assert "`observation: noise`" in info.value.diagnosis.message
    sponge = replace(scene, types=np.r_[scene.types[:5], g.type_ids["Sponge"]])
    with pytest.raises(UnexplainedScene) as info:
        explain(g, sponge)
    assert "`observation: clutter`" in info.value.diagnosis.message
    assert "`observation: noise`" not in info.value.diagnosis.message


def test_render_marks_clutter_objects():
    from ssgc.render.scene import View, unexplained

    view = View(
        "s",
        "s",
        ("~scene", "Table", "~clutter", "~clutter:object", "Sponge", "Plate"),
        np.zeros((6, 3)),
        np.tile([1.0, 0, 0, 0], (6, 1)),
        np.array([False, True, False, False, True, True]),
        np.array([-1, 0, 0, 2, 3, 1]),
    )
    assert unexplained(view).tolist() == [False, False, False, False, True, False]


def test_parse_cli_lists_the_unexplained_objects(tmp_path: Path):
    g = with_section(CLUTTER)
    scene = dinner_scene(g)
    grammar, path, out = tmp_path / "g.yaml", tmp_path / "scene.json", tmp_path / "out.json"
    grammar.write_text(DINNER + CLUTTER)
    objects = [
        {"type": g.types[int(t)].name, "pose": {"xyz": list(x), "quat_wxyz": list(q)}}
        for t, x, q in zip(scene.types, scene.xyz, scene.quat, strict=True)
    ]
    objects.append({"type": "Sponge", "pose": {"xyz": [0.2, 0.2, 0.8]}})
    path.write_text(json.dumps({"grammar": "dinner", "objects": objects}))
    result = CliRunner().invoke(app, ["parse", str(path), "-g", str(grammar), "-o", str(out), "-q"])
    assert result.exit_code == 0, result.output
    assert json.loads(out.read_text())["scenes"][0]["parses"][0]["unexplained"] == [6]


def test_noise_on_some_types_keeps_every_block_observed():
    """Noise on the mugs only: the fixed rule into a mug stays fixed (its `or` parent's pose is
    the mug's own), even though the plates' side of the same `or` is observed exactly."""
    text = (
        "grammar: g\nroot: Bin\ntypes:\n  Bin:\n    observed: true\n    repeat:\n"
        "      count: {probs: [0, 0.5, 0.5]}\n      rule:\n        child: Thing\n"
        "        translation: {world_normal: {mean: [0, 0, 0], variance: 0.01}}\n"
        "        rotation: {world_bingham: {concentration: 10}}\n"
        "  Thing:\n    or:\n      - child: Plate\n      - child: Mug\n"
        "  Plate: {observed: true}\n  Mug: {observed: true}\n"
        "observation:\n  noise:\n    Mug: {position: 0.005}\n"
    )
    g = compile_text(text)
    into = {g.types[r.child].name: r for r in g.rules}
    assert into["Mug"].translation.point is not None  # still one block with Thing
    assert into["Thing"].translation.normal.cov[0, 0] == pytest.approx(0.01 + 0.005**2)
    trees, logp = sample_trees(g, 4, 1)
    parser = Parser(g)
    for i in range(4):
        best = parser.parse(scene_from_tree(g, trees.tree(i), f"s{i}")).parses[0]
        assert best.score >= logp[i] - 1e-6


CONSTRAINED = DINNER.replace(
    "  Plate:\n    observed: true\n",
    "  Plate:\n    observed: true\n    geometry: {cylinder: {radius: 0.1, length: 0.02}}\n",
).replace(
    "  Mug:\n    observed: true\n",
    "  Mug:\n    observed: true\n    geometry: {cylinder: {radius: 0.04, length: 0.08}}\n",
) + (
    "constraints:\n"
    "  apart: {non_penetration: {types: [Plate, Mug]}}\n"
    "  spaced: {clearance: {types: [Plate]}}\n"
    "  mugs_up: {upright: {types: [Mug], max_angle_deg: 30}}\n"
    "  on_table: {inside_box: {types: [Plate, Mug], min: [-2, -2, 0.5], max: [2, 2, 1.5], "
    "geometry: true}}\n"
    "observation:\n  noise:\n    default: {position: 0.004, rotation_deg: 2}\n"
    "  clutter:\n    region: {min: [-1, -1, 0.7], max: [1, 1, 1.0]}\n"
    "    rates: {Sponge: 0.2, Mug: 0.1}\n"
)


def test_constraints_of_every_pose_kind_with_an_observation_that_adds_types():
    """The observation adds types after the user's (clutter, `~clutter`): every constraint's
    per-type table must cover them.  `ssg explain` of a scene with a clutter object indexed
    `non_penetration`'s type mask with the clutter node's type and failed with an IndexError
    (found by trying a sink scene with a sponge and a lifted bowl)."""
    g = compile_text(CONSTRAINED, "dinner.yaml")
    n = len(g.types)
    assert n > len(compile_text(CONSTRAINED.split("observation:")[0]).types)
    for c in g.constraints:
        assert len(c.reads(n)) == n and (getattr(c, "types", None) is None or len(c.types) == n)
    scene = dinner_scene(g)
    sponge = with_sponge(g, scene, [0.6, 0.6, 0.8])
    e = explain(g, sponge)
    assert [o.index for o in e.objects if o.unexplained] == [6]
    kept = ssgc.api.Grammar(g, CONSTRAINED).sample(4, seed=2, constraints="all")
    assert len(kept) == 4
    for s in kept:
        assert np.isfinite(s.log_prob)


TEA = """
grammar: tea_table
root: {type: Table, pose: {xyz: [0, 0, 0.375]}}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0.2, 0.4, 0.4]}
      rule:
        child: Teacup
        translation: {parent_normal_offset: {mean: [0, 0, 0.405], variance: 0.04, pin: [z]}}
        rotation: {revolute: {axis: [0, 0, 1]}}
  Teacup: {observed: true}
"""
TEA_OBSERVED = {
    "noise on the root": "observation: {noise: {default: {position: 0.005}}}",
    "clutter": "observation: {clutter: {region: {min: [-1, -1, 0], max: [1, 1, 2]}, "
    "rates: {Sponge: 0.1}}}",
}


@pytest.mark.parametrize("section", sorted(TEA_OBSERVED))
def test_an_observation_section_that_moves_the_root_names_a_missing_root(section):
    """Noise on an observed root, or clutter, hangs the root under a new `~scene` root, where
    it cannot be implied: a scene without the table was `infeasible` with "no tree of the
    grammar contains this scene's objects, and removing up to 2 object(s) does not help"
    (for a one-object scene).  It is now refused at once, naming the root and why."""
    grammar = compile_text(TEA + TEA_OBSERVED[section])
    cup = Scene(
        name="cup",
        types=np.array([grammar.type_id("Teacup")]),
        xyz=np.array([[0.1, 0.0, 0.78]]),
        quat=np.array([[1.0, 0, 0, 0]]),
    )
    result = Parser(grammar).parse(cup)
    assert result.status == "infeasible"
    assert "scene 'cup' has no Table" in result.message
    assert "`observation` section" in result.message
    with pytest.raises(UnexplainedScene, match="has no Table"):
        explain(grammar, cup)


def test_noise_off_the_root_still_implies_a_missing_root():
    """Noise on the cups only leaves the table the tree's root: a scene of one cup parses,
    the table implied at its pose."""
    grammar = compile_text(TEA + "observation: {noise: {Teacup: {position: 0.005}}}")
    cup = Scene(
        name="cup",
        types=np.array([grammar.type_id("Teacup")]),
        xyz=np.array([[0.1, 0.0, 0.78]]),
        quat=np.array([[1.0, 0, 0, 0]]),
    )
    assert grammar.required_root is None
    assert Parser(grammar).parse(cup).status == "optimal"


LEVER = """grammar: lever
root: {type: R, pose: {xyz: [0, 0, 0]}}
types:
  R:
    observed: true
    and:
      - child: L
        translation: {parent_normal_offset: {mean: [0, 0, 0], variance: 0.0001}}
        rotation: {revolute: {axis: [0, 0, 1]}}
  L:
    and:
      - {child: O, translation: {offset: [0.5, 0, 0]}, rotation: same}
  O: {observed: true}
observation:
  noise:
    O: {rotation_deg: 10}
"""
TWO_AT_ONCE = """grammar: pair
root: {type: R, pose: {xyz: [0, 0, 0]}}
types:
  R:
    observed: true
    and:
      - child: L
        translation: {parent_normal_offset: {mean: [0, 0, 0], variance: 0.01}}
  L:
    and:
      - {child: O1, translation: {offset: [0.3, 0, 0]}}
      - {child: O2, translation: {offset: [-0.3, 0, 0]}}
  O1: {observed: true}
  O2: {observed: true}
observation:
  noise:
    default: {position: 0.01}
"""
LOOP = """grammar: loop
root: {type: A, pose: {xyz: [0, 0, 0]}}
types:
  A:
    observed: true
    and:
      - {child: L, translation: {offset: [0.2, 0, 0]}}
  L:
    max_nesting: 2
    or:
      - {child: L, p: 0.5}
      - {child: O, p: 0.5, translation: {offset: [0.1, 0, 0]}}
  O: {observed: true}
observation:
  noise:
    default: {position: 0.01}
"""


def _scene(g, objects):
    types = np.array([g.type_ids[t] for t, _ in objects])
    xyz = np.array([p for _, p in objects], float)
    return Scene("s", types, xyz, np.tile([1.0, 0, 0, 0], (len(objects), 1)))


def test_rotation_noise_does_not_swing_an_object_on_its_offset():
    """O hangs 0.5 m off a latent L by a fixed offset.  Its 10° of rotation noise went to the
    rule placing L and swung O on that lever: its z spread 0.087 m instead of L's 0.01, and
    O turned by one sd about y scored as an 8.7σ outlier.  The noise is now on L -> O."""
    g = compile_text(LEVER)
    trees, _ = sample_trees(g, 4000, 0)
    o = trees.xyz[trees.type == g.type_ids["O"]]
    assert o[:, 2].std() == pytest.approx(0.01, rel=0.1)
    scene = _scene(g, [("R", [0, 0, 0]), ("O", [0.5, 0, 0])])
    turned = replace(scene, quat=np.array([[1.0, 0, 0, 0], [np.cos(0.0873), 0, np.sin(0.0873), 0]]))
    flat, tilted = (Parser(g).parse(s).parses[0].score for s in (scene, turned))
    assert flat - tilted < 2.0  # one sd of rotation noise costs about half a nat, not 38


@pytest.mark.parametrize(
    ("text", "objects"),
    [
        (TWO_AT_ONCE, [("R", [0, 0, 0]), ("O1", [0.305, 0, 0]), ("O2", [-0.3, 0.004, 0])]),
        (LOOP, [("A", [0, 0, 0]), ("O", [0.305, 0.003, 0])]),
    ],
    ids=["two-at-once", "loop"],
)
def test_independent_noise_of_objects_fixed_together_parses(text, objects):
    """Two observed objects fixed to one latent node kept their relative pose exact, and a
    fixed `L -> L` loop made L untied so O lost its noise: 5 mm off, both were infeasible."""
    g = compile_text(text)
    assert Parser(g).parse(_scene(g, objects)).status == "optimal"
