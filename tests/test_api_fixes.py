"""What a notebook user of the Python API ran into (docs/api.md): a grammar file overwritten
after a change of directory, fit options used as they came, another grammar's scenes read by
number, a time-limit exit code, errors that could not travel between processes, and arguments
of the wrong kind answered by Python's own errors."""

from __future__ import annotations

import io
import json
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAMMARS

import ssgc
from ssgc.api import Grammar, fit_defaults, fit_options, load_grammar, open_fit
from ssgc.errors import GrammarError, SceneError, SsgError
from ssgc.explain import UnexplainedScene


@pytest.fixture(scope="module")
def gmm() -> Grammar:
    return load_grammar(GRAMMARS / "gmm.yaml")


@pytest.fixture(scope="module")
def sink() -> Grammar:
    return load_grammar(GRAMMARS / "sink.yaml")


def _keywords(**changed: object) -> dict[str, object]:
    return {k: v for k, v in fit_defaults().items() if k != "time_limit"} | changed


def test_save_still_refuses_the_grammar_file_after_a_change_of_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A grammar loaded by a relative path kept it relative: after `%cd`, `Scene.save` on the
    grammar's file no longer saw it was the grammar's, and replaced the grammar with a scene."""
    (tmp_path / "g").mkdir()
    shutil.copy(GRAMMARS / "gmm.yaml", tmp_path / "g" / "gmm.yaml")
    monkeypatch.chdir(tmp_path)
    g = load_grammar("g/gmm.yaml")
    text = (tmp_path / "g" / "gmm.yaml").read_text()
    scene = g.sample(1)[0]
    monkeypatch.chdir(tmp_path / "g")
    with pytest.raises(SsgError, match="input file"):
        scene.save(tmp_path / "g" / "gmm.yaml")
    assert (tmp_path / "g" / "gmm.yaml").read_text() == text
    again = pickle.loads(pickle.dumps(g))  # compiled again where its file is, not in the cwd
    assert again.path == tmp_path / "g" / "gmm.yaml"


@pytest.mark.parametrize(
    ("changed", "named"),
    [
        ({"iterations": 2.5}, "iterations"),
        ({"top": "3"}, "top"),
        ({"seed": -1}, "seed"),
        ({"seed": None}, "seed"),
        ({"estep": "mcmc", "samples": 2.5}, "samples"),
        ({"tol": "small"}, "tol"),
        ({"jobs": 1.0}, "jobs"),
    ],
)
def test_fit_options_checks_each_argument_as_fit_does(changed: dict, named: str) -> None:
    """`fit_options` (docs/api.md's progress-display path) took 2.5 iterations and ran 3, and
    let a string reach a comparison deep in the fitter."""
    with pytest.raises(ValueError, match=f"^{named} must be"):
        fit_options(**_keywords(**changed))


def test_fit_options_take_numpy_integers(gmm: Grammar) -> None:
    """A numpy top reached the journal's JSON ("int64 is not JSON serializable")."""
    options = fit_options(**_keywords(top=np.int64(2), iterations=np.int32(1)))
    assert type(options.top) is int and type(options.iterations) is int
    with open_fit(gmm, gmm.sample(4), "numpy", options) as run:
        assert run.fit().iterations


@pytest.mark.parametrize("limit", [0, -1, float("nan"), "5"])
def test_a_run_s_time_limit_is_checked(gmm: Grammar, limit: object) -> None:
    """0 and -1 returned at once with status time_limit, nan ran without a limit."""
    with open_fit(gmm, gmm.sample(3), "x", fit_options(**_keywords(iterations=1))) as run:
        with pytest.raises(ValueError, match="time_limit must be"):
            run.fit(time_limit=limit)  # type: ignore[arg-type]


def test_a_fit_run_prints_as_one_line(gmm: Grammar) -> None:
    with open_fit(gmm, gmm.sample(30), "x", fit_options(**_keywords(iterations=1))) as run:
        assert repr(run) == "<FitRun of 'gmm': 30 scenes>"


def test_another_grammars_library_scenes_are_refused(gmm: Grammar, sink: Grammar) -> None:
    """`ssgc.fit(gmm, [s.data for s in sink scenes])` broke in numpy ("operands could not be
    broadcast"); the other way round read gmm's type numbers as sink's."""
    with pytest.raises(TypeError, match=r"library's scene .* pass the Scene"):
        ssgc.fit(gmm, [s.data for s in sink.sample(2)], iterations=1, top=1)
    with pytest.raises(TypeError, match=r"library's scene .* pass the Scene"):
        ssgc.parse(gmm, gmm.sample(1)[0].data)  # type: ignore[arg-type]
    options = fit_options(**_keywords(iterations=1, top=1))
    for mine, theirs in ((gmm, sink), (sink, gmm)):
        with pytest.raises(SceneError, match=f"not observed types of grammar '{mine.name}'"):
            with open_fit(mine, [s.data for s in theirs.sample(3)], "x", options):
                pass


def test_an_explanation_cut_by_the_time_limit_has_exit_code_4(sink: Grammar) -> None:
    """`ssg explain --time-limit` exits 4 on such a scene; the API's error said 3."""
    scene = sink.sample(3, seed=1)[1]
    with pytest.raises(UnexplainedScene) as caught:
        ssgc.explain(sink, scene, time_limit=0.01)
    error = caught.value
    assert (error.status, error.phase, error.exit_code) == ("no_parse", "time", 4)
    again = pickle.loads(pickle.dumps(error))
    assert (again.phase, again.exit_code) == ("time", 4)


def test_an_error_travels_between_processes_whole() -> None:
    """An unpickled SsgError was rebuilt from its message, read as a list of diagnostics: its
    `args` held the message's characters, one per line."""
    with pytest.raises(GrammarError) as caught:
        load_grammar("/no/such/grammar.yaml")
    error = caught.value
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is GrammarError
    assert again.args == error.args == (str(error),)
    assert again.diagnostics == error.diagnostics and again.exit_code == error.exit_code
    made = SsgError.single("two\nlines", "f.yaml", 3, 4, exit_code=5)
    assert pickle.loads(pickle.dumps(made)).args == made.args


def test_star_import_gives_the_api() -> None:
    names: dict[str, object] = {}
    exec("from ssgc import *", names)
    assert names["load_grammar"] is ssgc.api.load_grammar
    assert names["Scene"] is ssgc.api.Scene and callable(names["parse"])


@pytest.mark.parametrize(
    "call",
    [
        lambda g, s: load_grammar(g),
        lambda g, s: load_grammar(None),
        lambda g, s: load_grammar(GRAMMARS / "gmm.yaml", allow_outside="yes"),
        lambda g, s: s.save(5),
        lambda g, s: s.render(None),
    ],
    ids=["grammar-as-path", "none-path", "allow-outside", "save-int", "render-none"],
)
def test_arguments_of_the_wrong_kind_are_named(gmm: Grammar, call) -> None:  # type: ignore[no-untyped-def]
    """They raised Python's own errors ("expected str, bytes or os.PathLike object, not
    Grammar", "'NoneType' object is not iterable"), which say neither argument nor remedy."""
    with pytest.raises(TypeError) as caught:
        call(gmm, gmm.sample(1)[0])
    message = str(caught.value)
    assert "must be" in message and "os.PathLike" not in message


def test_no_objects_is_a_scene_error(gmm: Grammar) -> None:
    """`g.scene(None)` said "'NoneType' object is not iterable"."""
    with pytest.raises(SceneError, match=r"objects must be a list of \(type, xyz\)"):
        gmm.scene(None)  # type: ignore[arg-type]


def test_a_scene_name_is_text(gmm: Grammar) -> None:
    """name=None made a scene named None, written as null and printed "scene 'None'"."""
    with pytest.raises(ValueError, match="a name is text"):
        gmm.scene([("Object", [0, 0, 0])], name=None)  # type: ignore[arg-type]


def test_metadata_keys_must_be_text(gmm: Grammar, tmp_path: Path) -> None:
    """{1: 2} was saved as {"1": 2}: a different dict came back."""
    scene = gmm.sample(1)[0]
    scene.metadata[1] = 2
    with pytest.raises(SceneError, match="the key 1 is not text"):
        scene.save(tmp_path / "s.json")
    assert not (tmp_path / "s.json").exists()
    del scene.metadata[1]
    scene.metadata["nested"] = [{"ok": 1}]
    saved = json.loads(scene.save(tmp_path / "s.json").read_text())
    assert saved["metadata"]["nested"] == [{"ok": 1}]


@pytest.mark.parametrize("limit", [-1, "a", 1.5])
def test_explanation_text_checks_its_limit(gmm: Grammar, limit: object) -> None:
    """text(-1) dropped the last object and rule without a word."""
    why = ssgc.explain(gmm, gmm.sample(1)[0])
    with pytest.raises(ValueError, match="limit must be"):
        why.text(limit)  # type: ignore[arg-type]
    assert why.text(0).count("\n") < why.text().count("\n")


def test_a_picture_to_captured_standard_output_says_why(
    gmm: Grammar, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A notebook's standard output has no file descriptor: "cannot write the picture: None"."""
    pytest.importorskip("matplotlib")
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    with pytest.raises(SsgError, match=r"not a file .* give a file path"):
        gmm.sample(1)[0].render("-")


def test_grammar_fit_takes_options_in_order(gmm: Grammar) -> None:
    """`g.fit(data, 1)` was a TypeError, though `ssgc.fit(g, data, 1)` worked."""
    data = gmm.sample(10)
    by_method, by_function = gmm.fit(data, 1, 2), ssgc.fit(gmm, data, 1, 2)
    assert by_method.grammar.text == by_function.grammar.text
    assert len(by_method.iterations) == 1
