"""The Python API's answers to a user's mistakes, and what its results let a user change
(docs/api.md): one clear error that names the argument, never an AttributeError from deep in;
documents that are the caller's own; files that every command reads again."""

from __future__ import annotations

import copy
import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAMMARS, ROOT
from typer.testing import CliRunner

import ssgc
from ssgc.api import Grammar, Tree, fit_defaults, fit_options, load_grammar, open_fit
from ssgc.cli.app import app
from ssgc.errors import SceneError, SsgError
from ssgc.explain import UnexplainedScene


@pytest.fixture(scope="module")
def gmm() -> Grammar:
    return load_grammar(GRAMMARS / "gmm.yaml")


@pytest.fixture(scope="module")
def sink() -> Grammar:
    return load_grammar(GRAMMARS / "sink.yaml")


def _options(**changed: object):  # type: ignore[no-untyped-def]
    keywords = {k: v for k, v in fit_defaults().items() if k != "time_limit"}
    return fit_options(**keywords | changed)


def test_an_unexplained_scene_pickles_and_copies(sink: Grammar) -> None:
    """Explaining in a process pool broke the pool: the exception could not be rebuilt from
    its one-string `args` (UnexplainedScene.__init__() missing 'status')."""
    with pytest.raises(UnexplainedScene) as caught:
        ssgc.explain(sink, sink.scene([], name="empty"))
    error = caught.value
    for again in (pickle.loads(pickle.dumps(error)), copy.copy(error), copy.deepcopy(error)):
        assert type(again) is UnexplainedScene
        assert str(again) == str(error) and again.exit_code == error.exit_code == 2
        assert again.status == "infeasible"
        assert again.diagnosis is not None and again.diagnosis.message == error.diagnosis.message


def test_save_refuses_the_grammars_own_file_and_replaces_another(tmp_path: Path) -> None:
    """`g.sample(1)[0].save(g.path)` replaced the grammar with a scene."""
    shutil.copy(GRAMMARS / "gmm.yaml", tmp_path / "gmm.yaml")
    g = load_grammar(tmp_path / "gmm.yaml")
    text = g.path.read_text()
    scene = g.sample(1)[0]
    for path in (g.path, str(g.path)):
        with pytest.raises(SsgError, match="input file"):
            scene.save(path)
    assert g.path.read_text() == text
    other = tmp_path / "old.json"
    other.write_text("{}")
    scene.save(other)  # docs/api.md: an existing file is replaced
    assert json.loads(other.read_text())["name"] == scene.name


@pytest.mark.parametrize("tries", [-3, 0, 2.5, True, "5"])
def test_max_tries_is_a_whole_number_of_at_least_one(sink: Grammar, tries: object) -> None:
    """It was never checked: -3 gave Unmet "before the first candidate", 2.5 and True were
    taken, "5" raised a TypeError from the sampler."""
    with pytest.raises(ValueError, match="max_tries must be a whole number >= 1"):
        sink.sample(1, constraints="all", max_tries=tries)
    assert len(sink.sample(1, constraints="all", max_tries=np.int64(50))) == 1


def test_a_scenes_document_is_the_callers_own(sink: Grammar, tmp_path: Path) -> None:
    """Editing `to_json()`'s metadata changed the scene (and what `save` wrote)."""
    kept = sink.sample(1, seed=0, constraints="all")[0]
    doc = kept.to_json()
    doc["metadata"]["sampler"]["method"] = "HACKED"
    assert kept.metadata is not None and kept.metadata["sampler"]["method"] == "rejection"
    assert kept.to_json()["metadata"]["sampler"]["method"] == "rejection"
    saved = sink.sample(1, seed=0)[0].to_json()
    saved["metadata"] = {"source": {"by": "hand"}}
    saved["objects"][0]["metadata"] = {"note": ["the bin"]}
    (tmp_path / "a.json").write_text(json.dumps(saved))
    (loaded,) = ssgc.load_scenes(tmp_path / "a.json", sink)
    doc = loaded.to_json()
    doc["metadata"]["source"]["by"] = "HACKED"
    doc["objects"][0]["metadata"]["note"].append("HACKED")
    again = loaded.to_json()
    assert again["metadata"] == {"source": {"by": "hand"}}
    assert again["objects"][0]["metadata"] == {"note": ["the bin"]}


def test_an_explanations_document_is_the_callers_own(gmm: Grammar) -> None:
    """Editing `to_json()["rules"]` changed `why.text()`."""
    why = ssgc.explain(gmm, gmm.sample(1, seed=1)[0])
    text = why.text()
    doc = why.to_json()
    doc["rules"][0]["rule"] = "HACKED"
    assert why.text() == text and why.to_json()["rules"][0]["rule"] != "HACKED"


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), {1, 2}])
def test_save_refuses_metadata_no_command_could_read(sink, tmp_path, bad) -> None:
    """A NaN in the metadata was written as a bare `NaN`, which `ssg render` and
    `ssgc.load_scenes` then refused ("metadata must hold finite numbers")."""
    scene = sink.sample(1, seed=0, constraints="all")[0]
    scene.metadata["bad"] = bad  # type: ignore[index]
    path = tmp_path / "bad.json"
    with pytest.raises(SceneError, match="metadata must hold only what JSON holds"):
        scene.save(path)
    assert not path.exists()


def test_a_loaded_sampled_scene_saves_as_ssg_sample_resume_accepts(gmm, tmp_path) -> None:
    """Loading dropped the file's seed and index, so saving it again made `--resume` refuse
    the directory ("this scene file has seed null, index null")."""
    out = tmp_path / "res"
    args = ["sample", str(GRAMMARS / "gmm.yaml"), "-n", "3", "--seed", "4", "-o", str(out), "-q"]
    assert CliRunner().invoke(app, args).exit_code == 0
    (scene,) = ssgc.load_scenes(out / "gmm_000001.json", gmm)
    assert scene.run == (4, 1)
    scene.save(out / "gmm_000001.json")
    (out / "gmm_000002.json").unlink()
    result = CliRunner().invoke(app, [*args, "--resume"])
    assert result.exit_code == 0, result.output
    assert (out / "gmm_000002.json").exists()


@pytest.mark.parametrize(
    "call, wanted",
    [
        (lambda g: ssgc.load_scenes(GRAMMARS, str(GRAMMARS / "gmm.yaml")), "expected a Grammar"),
        (lambda g: ssgc.load_scenes(GRAMMARS, None), "expected a Grammar"),
        (lambda g: ssgc.load_scenes(g, GRAMMARS), "path must be a str or Path"),
        (lambda g: ssgc.load_scenes(GRAMMARS, g.ir), "compiled grammar"),
    ],
)
def test_load_scenes_with_a_wrong_argument_is_a_type_error(gmm, call, wanted) -> None:
    """They raised AttributeError: 'str' object has no attribute 'ir'."""
    with pytest.raises(TypeError, match=wanted):
        call(gmm)


def test_open_fit_takes_the_apis_scenes_and_a_str_dataset(gmm: Grammar) -> None:
    """docs/api.md's `open_fit(grammar, scenes, dataset, options)` raised AttributeError for
    the API's scenes ('list' has no 'tobytes') and for a str dataset (no 'resolve')."""
    scenes = gmm.sample(10, seed=1)
    options = _options(iterations=2, top=2)
    with open_fit(gmm, scenes, "my scenes", options) as run:
        report = run.fit()
    fitted = ssgc.fit(gmm, scenes, iterations=2, top=2)
    assert run.fitted(report).text == fitted.grammar.text
    with open_fit(gmm, [s.data for s in scenes], Path("x"), options) as run:  # as ssg fit does
        assert run.fit().text == fitted.grammar.text


@pytest.mark.parametrize(
    "arguments, wanted",
    [
        (lambda g, s, o: (g, "scenes/", "d", o), "scenes must be a list of scenes"),
        (lambda g, s, o: (g, 5, "d", o), "scenes must be a list of scenes"),
        (lambda g, s, o: (g, [s[0], "x.json"], "d", o), r"scenes\[1\] must be a Scene"),
        (lambda g, s, o: (g, s, 7, o), "dataset must be a str or Path"),
        (lambda g, s, o: (g, s, "d", {"top": 2}), "options must come from ssgc.api.fit_options"),
        (lambda g, s, o: (g.ir, s, "d", o), "compiled grammar"),
    ],
)
def test_open_fit_with_a_wrong_argument_is_a_type_error(gmm, arguments, wanted) -> None:
    with pytest.raises(TypeError, match=wanted):
        with open_fit(*arguments(gmm, gmm.sample(2), _options())):
            pass


@pytest.mark.parametrize(
    "dataset, wanted",
    [
        (5, "dataset must be a list of scenes"),
        ([None], r"dataset\[0\] must be a Scene, got NoneType"),
    ],
)
def test_fit_with_a_dataset_of_no_scenes_is_a_type_error(gmm, dataset, wanted) -> None:
    """5 raised list()'s own TypeError, [None] an AttributeError from the fitter."""
    with pytest.raises(TypeError, match=wanted):
        ssgc.fit(gmm, dataset)


def test_trees_compare_within_one_grammars_types_and_rules(gmm, sink) -> None:
    """A tree of another grammar raised IndexError, and None an AttributeError."""
    tree = gmm.sample(1, seed=3)[0].tree
    assert tree is not None
    with pytest.raises(TypeError, match="other must be a Tree"):
        tree.same_as(None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="tree of grammar 'sink'"):
        tree.same_as(sink.sample(3, seed=5)[0].tree)  # type: ignore[arg-type]
    again = load_grammar(GRAMMARS / "gmm.yaml").sample(1, seed=3)[0].tree
    assert again is not None and tree.same_as(again)
    fitted = ssgc.fit(gmm, gmm.sample(10, seed=1), iterations=1, top=2).grammar
    assert fitted.text != gmm.text and tree.same_as(Tree(fitted, tree.trees))


def test_load_grammar_is_documented_as_what_it_checks(tmp_path: Path) -> None:
    """docs/api.md said load_grammar checks the file as `ssg validate` does, which opens the
    mesh files; it compiles the file as the other commands do, a missing mesh a warning."""
    shutil.copy(GRAMMARS / "dimsum_table.yaml", tmp_path / "g.yaml")
    g = load_grammar(tmp_path / "g.yaml")
    assert any("mesh file" in d.message and "not found" in d.message for d in g.ir.warnings)
    docs = " ".join((ROOT / "docs" / "api.md").read_text().split())
    assert "checks the file as `ssg validate` does" not in docs
    assert "unlike `ssg validate`, it does not open mesh files" in docs


def test_help_on_ssgc_explain_names_the_api_function() -> None:
    """`help(ssgc.explain)` showed only the library's explain(grammar, scene, tree, **parse)."""
    import pydoc

    assert "ssgc.explain(grammar, scene, time_limit=None)` is `ssgc.api.explain`" in " ".join(
        pydoc.render_doc(ssgc.explain, renderer=pydoc.plaintext).split()
    )


@pytest.mark.parametrize(
    "call, wanted",
    [
        (lambda g, s: ssgc.parse(g, s, time_limit=10**400), "time_limit must be a finite"),
        (lambda g, s: ssgc.explain(g, s, time_limit=10**400), "time_limit must be a finite"),
        (lambda g, s: g.sample(1, constraints="all", time_limit=10**400), "time_limit must"),
        (lambda g, s: ssgc.parse(g, s, time_limit=True), "time_limit must be a finite"),
        (lambda g, s: ssgc.parse(g, s, time_limit="5"), "time_limit must be a finite"),
        (lambda g, s: ssgc.fit(g, [s], tol="abc"), "tol must be a number, got 'abc'"),
        (lambda g, s: ssgc.fit(g, [s], tol=None), "tol must be a number, got None"),
        (lambda g, s: ssgc.fit(g, [s], pseudocount="x"), "pseudocount must be a number"),
        (lambda g, s: ssgc.fit(g, [s], min_variance=[1]), "min_variance must be a number"),
    ],
)
def test_a_number_argument_that_is_no_number_is_a_value_error(sink, call, wanted) -> None:
    """10**400 raised OverflowError, True a TypeError (docs/api.md: a bool is a ValueError),
    tol="abc" float()'s own ValueError that named no argument."""
    with pytest.raises(ValueError, match=wanted):
        call(sink, sink.sample(1)[0])


def test_a_real_option_too_large_for_a_float_is_out_of_range(gmm: Grammar) -> None:
    """`ssgc.fit(..., max_concentration=10**400)` raised float()'s OverflowError; it is out of
    range, said as `ssg fit` says it."""
    with pytest.raises(SsgError, match="max_concentration must be above 0"):
        ssgc.fit(gmm, gmm.sample(2), max_concentration=10**400)


def test_the_compiled_grammar_is_told_apart_from_the_apis(sink: Grammar) -> None:
    """`ssgc.explain(g.ir, s)` said "expected a Grammar ..., got Grammar"."""
    scene = sink.sample(1)[0]
    for call in (ssgc.explain, ssgc.parse, lambda g, s: ssgc.fit(g, [s])):
        with pytest.raises(TypeError, match=r"compiled grammar \(ssgc.ir.Grammar.*Grammar itself"):
            call(sink.ir, scene)


def test_an_explain_output_given_as_a_scene_is_called_one(gmm, tmp_path) -> None:
    """It was called "an `ssg parse` output"."""
    why = ssgc.explain(gmm, gmm.sample(1)[0])
    path = tmp_path / "why.json"
    path.write_text(json.dumps({"grammar": "gmm", "scenes": [why.to_json()]}))
    with pytest.raises(SceneError, match="this is an `ssg explain --json` output, not a scene"):
        ssgc.load_scenes(path, gmm)


@pytest.mark.parametrize(
    ("keywords", "wanted"),
    [
        ({"max_tries": 10}, r"max_tries= and time_limit= bound constrained sampling"),
        ({"time_limit": 1.0}, r"max_tries= and time_limit= bound constrained sampling"),
        ({"method": "rjmcmc"}, r"method= chooses how constrained sampling draws"),
        ({"constraints": "all", "method": "bogus"}, r"method must be 'auto' or one of: "),
        ({"constraints": "all", "method": None}, r"method must be .*, got None"),
    ],
)
def test_sample_mistakes_name_the_apis_arguments(sink: Grammar, keywords, wanted) -> None:
    """They said "ssg: error: --max-tries and --time-limit need --constraints" and
    "--method, --penalty-eps and --jobs need --constraints", options `g.sample` has not."""
    with pytest.raises(ValueError, match=wanted) as caught:
        sink.sample(2, **keywords)
    assert "--" not in str(caught.value) and "ssg:" not in str(caught.value)


UNREACHABLE = """\
grammar: unreachable
root: {type: Bin, pose: {xyz: [0, 0, 0]}}
types:
  Bin:
    observed: true
    geometry: {box: {size: [0.3, 0.3, 0.1]}}
    repeat:
      count: {probs: [0, 0, 1]}
      rule:
        child: Disc
        translation: {world_box_offset: {min: [-0.14, -0.14, 0], max: [0.14, 0.14, 0]}}
  Disc: {observed: true, geometry: {cylinder: {radius: 0.05, length: 0.02}}}
constraints:
  far_apart: {clearance: {types: [Disc], radius: {Disc: 0.3}}}
"""


@pytest.mark.parametrize(
    ("keywords", "wanted"),
    [({"max_tries": 3000}, "(max_tries=3000)"), ({"time_limit": 0.2}, "(time_limit=0.2)")],
)
def test_unmet_names_the_apis_limit(tmp_path: Path, keywords, wanted) -> None:
    """It quoted "(--max-tries 3,000)" and "(--time-limit 0.2 s)"."""
    (tmp_path / "g.yaml").write_text(UNREACHABLE)
    g = load_grammar(tmp_path / "g.yaml")
    with pytest.raises(SsgError) as caught:
        g.sample(2, constraints="far_apart", **keywords)
    assert caught.value.exit_code == 2
    assert wanted in str(caught.value) and "--" not in str(caught.value)


def test_constraints_as_a_list_is_a_type_error_that_says_what_to_pass(sink: Grammar) -> None:
    """docs/api.md did not say what else is refused: a list of names is an argument of the
    wrong kind (a TypeError), and the message says how to pass those names."""
    with pytest.raises(TypeError, match=r"got \['dishes_in_bin'\]; join the names with commas"):
        sink.sample(1, constraints=["dishes_in_bin"])
