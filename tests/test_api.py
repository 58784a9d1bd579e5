"""The Python API (ssgc/api.py, docs/api.md): its examples run, and it gives what the commands
give (the same scenes as `ssg sample`, the same parse as `ssg parse`)."""

from __future__ import annotations

import doctest
import json
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAMMARS, ROOT
from typer.testing import CliRunner

import ssgc
from ssgc.api import Grammar, load_grammar
from ssgc.cli.app import app

runner = CliRunner()


@pytest.fixture(scope="module")
def gmm() -> Grammar:
    return load_grammar(GRAMMARS / "gmm.yaml")


def test_the_examples_of_docs_api_md_run(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("matplotlib")
    monkeypatch.chdir(ROOT)  # the examples name the bundled grammars from the repository root
    result = doctest.testfile(
        str(ROOT / "docs" / "api.md"),
        module_relative=False,
        optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE,
        verbose=False,
    )
    assert result.attempted > 20
    assert result.failed == 0


def test_import_ssgc_loads_nothing_else() -> None:
    code = (
        "import sys, ssgc; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('ssgc', 'numpy', 'scipy', 'matplotlib', 'pydantic', 'typer') and m != 'ssgc'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_callable_modules_stay_modules(gmm: Grammar) -> None:
    import ssgc.parse.parser as parser_module  # bound before ssgc.parse is ever called

    assert ssgc.parse.parser is parser_module
    scene = gmm.sample(1, seed=2)[0]
    assert ssgc.parse(gmm, scene).status == "optimal"
    assert callable(ssgc.fit) and callable(ssgc.explain)
    assert ssgc.explain.explain is not None  # the module's own function is still there


def test_sampled_scenes_are_the_files_ssg_sample_writes(gmm: Grammar, tmp_path: Path) -> None:
    out = tmp_path / "scenes"
    args = ["sample", str(GRAMMARS / "gmm.yaml"), "-n", "5", "--seed", "7", "-o", str(out), "-q"]
    assert runner.invoke(app, args).exit_code == 0
    for scene in gmm.sample(5, seed=7):
        # byte for byte, seed and index included: a saved scene is one --resume accepts
        written = (out / f"{scene.name}.json").read_bytes()
        assert scene.save(tmp_path / "saved.json").read_bytes() == written


def test_a_parse_is_the_entry_ssg_parse_prints(gmm: Grammar, tmp_path: Path) -> None:
    scene = gmm.sample(1, seed=3)[0]
    path = scene.save(tmp_path / "scene.json")
    result = runner.invoke(
        app, ["parse", str(path), "-g", str(GRAMMARS / "gmm.yaml"), "--top", "2"]
    )
    assert result.exit_code == 0, result.output
    printed = json.loads(result.stdout)["scenes"][0]
    mine = gmm.parse(scene, top=2).to_json()
    for doc in (printed, mine):
        del doc["timing"]
    assert printed == json.loads(json.dumps(mine))


def test_a_scene_made_from_python_data_parses_like_the_sampled_one(gmm: Grammar) -> None:
    sampled = gmm.sample(1, seed=4)[0]
    mine = gmm.scene(list(zip(sampled.types, sampled.xyz, sampled.quat, strict=True)))
    assert mine.tree is None and mine.types == sampled.types
    a, b = gmm.parse(mine).best, gmm.parse(sampled).best
    assert a is not None and b is not None
    assert a.score == pytest.approx(b.score, abs=1e-9) and a.tree.same_as(b.tree)
    assert a.tree.log_prob == pytest.approx(a.score, abs=1e-6)


def test_an_infeasible_scene_is_a_status_and_explain_names_the_culprit(gmm: Grammar) -> None:
    from ssgc.explain import UnexplainedScene

    # the grammar makes exactly one Point: no tree contains two
    scene = gmm.scene([("Root", [0, 0, 0]), ("Point", [1, 0, 0]), ("Point", [0, 1, 0])])
    result = gmm.parse(scene)
    assert result.status == "infeasible" and result.best is None
    assert "2 Point (at most 1)" in result.message
    with pytest.raises(UnexplainedScene) as caught:
        gmm.explain(scene)
    assert caught.value.status == "infeasible"


def test_fit_defaults_are_one_set_for_the_api_the_command_and_the_fitter():
    """`ssg fit`'s flags take their defaults from `ssgc.fit`'s signature, and those build the
    fitter's own default options."""
    import typer

    from ssgc.api import fit_defaults, fit_options
    from ssgc.cli.app import app
    from ssgc.fit.em import FitOptions

    defaults = fit_defaults()
    assert defaults["iterations"] == 10 and defaults["time_limit"] is None
    options = {k: v for k, v in defaults.items() if k != "time_limit"}
    assert fit_options(**options) == FitOptions()
    command = typer.main.get_command(app).commands["fit"]
    flags = {p.name: p.default for p in command.params}
    for name, value in options.items():
        # --samples has no default of its own: given, it needs --estep mcmc (the help says 100)
        assert flags[name] == (None if name == "samples" else value), name


@pytest.mark.parametrize(
    "option, value, wanted",
    [
        ("top", 0, "top must be at least 1"),
        ("iterations", 0, "iterations must be at least 1"),
        ("jobs", 0, "jobs must be at least 1"),
        ("samples", 0, "samples must be at least 1"),
        ("tol", -1.0, "tol must be ≥ 0"),
        ("tol", float("nan"), "tol must be ≥ 0"),
        ("estep", "bogus", "estep must be 'topn' or 'mcmc'"),
    ],
)
def test_fit_options_out_of_range_are_told_before_any_work(option, value, wanted):
    """What `ssg fit`'s flags bound, `ssgc.fit` refuses too (it crashed, or said that no
    scene could be parsed, or ran with the value)."""
    from ssgc.errors import SsgError

    g = load_grammar(GRAMMARS / "gmm.yaml")
    options = {"iterations": 1, "estep": "mcmc", "top": 1, option: value}
    with pytest.raises(SsgError, match=wanted):
        ssgc.fit(g, g.sample(2, seed=0), **options)


def test_the_drawing_functions_take_the_grammar_load_grammar_returns(tmp_path):
    """docs/render.md and docs/view.md: `render_file`, `render_diagram`, `view_page` and
    `write_view` take `ssgc.load_grammar`'s result (they raised AttributeError) or its `.ir`."""
    pytest.importorskip("matplotlib")
    from ssgc.render.diagram import render_diagram
    from ssgc.render.scene import render_file
    from ssgc.view.page import view_page, write_view

    g = load_grammar(GRAMMARS / "sink.yaml")
    scene = g.sample(1, seed=0)[0].save(tmp_path / "s.json")
    for grammar in (g, g.ir):
        render_diagram(grammar, tmp_path / "g.svg")
        assert render_file(scene, tmp_path / "s.png", grammar=grammar) == 1
        assert view_page(scene, grammar)[1] == 1
        assert write_view(scene, tmp_path / "v.html", grammar) == 1


def test_a_scene_of_another_grammar_is_read_by_its_types_names():
    """Type numbers are a grammar's own: a sink scene given to sink_detailed was read with
    sink's numbers, and a gmm scene given to sink raised numpy's broadcast error."""
    from ssgc.errors import SceneError

    sink, detailed = (load_grammar(GRAMMARS / f"{n}.yaml") for n in ("sink", "sink_detailed"))
    scene = sink.sample(1, seed=4)[0]
    result = ssgc.parse(detailed, scene)
    assert result.status == "optimal"
    assert sorted(result.best.tree.scene().types) == sorted(scene.types)
    gmm = load_grammar(GRAMMARS / "gmm.yaml")
    for call in (ssgc.parse, ssgc.explain, lambda g, s: ssgc.fit(g, [s], iterations=1)):
        with pytest.raises(SceneError, match="which is not a type in grammar 'sink'"):
            call(sink, gmm.sample(1)[0])
    with pytest.raises(TypeError, match="expected a Scene"):
        ssgc.parse(sink, scene.to_json())
    with pytest.raises(TypeError, match="expected a Grammar"):
        ssgc.parse("grammars/sink.yaml", scene)


@pytest.mark.parametrize(
    "call, wanted",
    [
        (lambda g, s: ssgc.parse(g, s, top=0), "top must be a whole number >= 1"),
        (lambda g, s: ssgc.parse(g, s, top=1.5), "top must be a whole number >= 1"),
        (lambda g, s: g.sample(1, seed=-1), r"seed must be a whole number in \[0, 2\*\*63\)"),
        (lambda g, s: g.sample(1, seed=2**64), r"seed must be a whole number"),
        (lambda g, s: g.sample(1, seed=1.7), r"seed must be a whole number"),
        (lambda g, s: s.tree.scene("two\nlines"), "one line of printable text"),
        (lambda g, s: g.sample(2.5), "n must be a whole number >= 0"),
        (lambda g, s: g.sample(True), "n must be a whole number >= 0"),
        (lambda g, s: ssgc.parse(g, s, time_limit=float("nan")), "time_limit must be a finite"),
        (lambda g, s: ssgc.parse(g, s, time_limit=0), "time_limit must be a finite"),
        (lambda g, s: ssgc.explain(g, s, time_limit=-1), "time_limit must be a finite"),
        (lambda g, s: ssgc.fit(g, [s], iterations=2.5), "iterations must be a whole number"),
        (lambda g, s: ssgc.fit(g, [s], top=2.5), "top must be a whole number"),
        (lambda g, s: ssgc.fit(g, [s], seed=-1), r"seed must be a whole number"),
    ],
)
def test_out_of_range_arguments_are_value_errors(call, wanted):
    g = load_grammar(GRAMMARS / "sink.yaml")
    with pytest.raises(ValueError, match=wanted):
        call(g, g.sample(1)[0])


@pytest.mark.parametrize(
    "objects",
    [
        [("DishBin",)],
        "abc",
        [{"type": "DishBin", "xyz": [0, 0, 0]}],
        [("DishBin", [0, 0, 0], [1, 0, 0, 0], 5)],
    ],
)
def test_objects_of_the_wrong_shape_are_scene_errors(objects):
    from ssgc.errors import SceneError

    g = load_grammar(GRAMMARS / "sink.yaml")
    with pytest.raises(SceneError, match="must be \\(type, xyz\\) or \\(type, xyz, quat_wxyz\\)"):
        g.scene(objects)
    with pytest.raises(SceneError, match="xyz"):  # a 1x3 array is not a position
        g.scene([("DishBin", np.zeros((1, 3)))])


@pytest.mark.parametrize(
    "xyz, said",
    [
        (0.5, "expected a list, got 0.5"),
        (None, "expected a list"),
        ([Decimal("0.5"), 0, 0], "expected a number"),
        ([1j, 0, 0], "expected a number"),
        ([10**5000, 0, 0], "too many digits"),
    ],
)
def test_a_position_that_is_not_three_numbers_is_a_scene_error(xyz, said):
    """A number or None where the list belongs, or numbers JSON cannot hold, raised Python's
    own TypeError."""
    from ssgc.errors import SceneError

    g = load_grammar(GRAMMARS / "sink.yaml")
    with pytest.raises(SceneError, match=said):
        g.scene([("DishBin", xyz)])
    assert len(g.scene([("DishBin", (v for v in (0.5, 0, 0)))])) == 1


def test_a_scene_without_a_parse_is_an_ssg_error_with_its_status():
    from ssgc.errors import SsgError
    from ssgc.explain import UnexplainedScene

    g = load_grammar(GRAMMARS / "sink.yaml")
    with pytest.raises(SsgError) as caught:
        ssgc.explain(g, g.scene([("DishBin", [0, 0, 0]), ("DishBin", [1, 0, 0])]))
    assert isinstance(caught.value, UnexplainedScene)
    assert caught.value.status == "infeasible" and caught.value.exit_code == 2


def test_saving_a_loaded_scene_keeps_its_metadata(tmp_path):
    """docs/scenes.md: `metadata`, the scene's and each object's, is kept as it is."""
    g = load_grammar(GRAMMARS / "sink.yaml")
    doc = g.sample(1, seed=0)[0].to_json()
    doc["metadata"] = {"source": "typed by hand"}
    doc["objects"][0]["metadata"] = {"note": "the bin"}
    path = tmp_path / "a.json"
    path.write_text(json.dumps(doc))
    (scene,) = ssgc.load_scenes(path, g)
    again = scene.save(tmp_path / "b.json")
    saved = json.loads(again.read_text())
    assert saved["metadata"] == {"source": "typed by hand"}
    assert saved["objects"][0]["metadata"] == {"note": "the bin"}
    assert "metadata" not in saved["objects"][1]


def test_ssgc_api_and_ssgc_errors_are_there_in_a_fresh_interpreter():
    code = "import ssgc; print(ssgc.api.fit_defaults()['top'], ssgc.errors.SceneError.__name__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["10", "SceneError"]


def test_numpy_numbers_are_arguments_like_any_other(gmm: Grammar) -> None:
    """A numpy integer reached the fit journal's JSON: TypeError, not serializable."""
    scenes = gmm.sample(np.int64(4), seed=np.int64(1))
    result = ssgc.fit(gmm, scenes, iterations=np.int64(1), top=np.int64(2), seed=np.uint8(3))
    assert len(result.iterations) == 1


def test_a_scenes_arrays_cannot_be_changed_in_place(gmm: Grammar) -> None:
    """Centring `s.xyz` in place moved the scene past every check (a NaN reached the file)."""
    scene = gmm.sample(1, seed=0)[0]
    for array in (scene.xyz, scene.quat, scene.tree.parent):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 0
    moved = scene.xyz.copy()
    moved -= 1.0
    assert not np.allclose(moved, scene.xyz)


def test_an_explanation_is_the_entry_ssg_explain_prints_and_short_to_show(gmm, tmp_path):
    scene = gmm.sample(1, seed=0)[0]
    path = scene.save(tmp_path / "s.json")
    result = CliRunner().invoke(
        app, ["explain", str(path), "-g", str(GRAMMARS / "gmm.yaml"), "--json"]
    )
    entry = json.loads(result.stdout)["scenes"][0]
    explained = ssgc.explain(gmm, ssgc.load_scenes(path, gmm)[0])
    assert set(explained.to_json()) == set(entry) and entry["status"] == explained.status
    assert len(repr(explained)) < 200 and len(repr(explained.objects[0])) < 200


def test_scenes_and_parses_of_a_grammar_with_collision_shapes_pickle():
    """python-fcl's shapes cannot be pickled: nothing of sink.yaml could go to another process
    (ProcessPoolExecutor, joblib) or be deep-copied."""
    import copy
    import pickle

    g = load_grammar(GRAMMARS / "sink.yaml")
    scene = g.sample(1, seed=0)[0]
    again = pickle.loads(pickle.dumps(scene))
    assert again.to_json() == scene.to_json() and again.grammar.path == g.path
    result = ssgc.parse(g, scene)
    assert pickle.loads(pickle.dumps(result)).best.score == result.best.score
    assert copy.deepcopy(g).text == g.text


def test_the_callable_modules_show_their_functions_signatures():
    """`help(ssgc.parse)` and a notebook's `ssgc.parse?` showed `(*args, **kwargs)`."""
    import inspect

    assert list(inspect.signature(ssgc.parse).parameters)[:3] == ["grammar", "scene", "top"]
    assert "iterations" in inspect.signature(ssgc.fit).parameters
    assert "time_limit" in inspect.signature(ssgc.explain).parameters
    assert "ssgc.parse(grammar, scene" in ssgc.parse.__doc__


def test_fit_refuses_samples_without_the_posterior_e_step():
    """`ssg fit --samples 5` without `--estep mcmc` is refused; `ssgc.fit(..., samples=5)` ran
    and ignored it, its default of 100 looking given."""
    from ssgc.errors import SsgError

    g = load_grammar(GRAMMARS / "gmm.yaml")
    with pytest.raises(SsgError, match="needs the posterior E-step"):
        ssgc.fit(g, g.sample(2, seed=0), iterations=1, top=1, samples=5)
