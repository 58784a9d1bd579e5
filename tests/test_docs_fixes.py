"""Behaviour the docs promise and the code did not give (a docs-against-behaviour hunt):
`ssg validate -q` printing errors only, `Scene.metadata` showing a scene file's metadata, the
fit report's `tails` key always there, the pinned-axis variance message in the list form,
and the source paths docs/interruptions.md cites."""

from __future__ import annotations

import json
import pickle
import re
from pathlib import Path

import pytest
from conftest import GRAMMARS, ROOT
from typer.testing import CliRunner

import ssgc
from ssgc.api import Grammar, load_grammar
from ssgc.cli.app import app
from ssgc.errors import GrammarError
from ssgc.fit.em import FitResult, report_json

UNREACHABLE = "grammar: g\nroot: A\ntypes:\n  A: {observed: true}\n  B: {observed: true}\n"
# an error the reachability check still runs past (docs/grammar.md section 6)
ERROR_AND_WARNING = (
    UNREACHABLE + "constraints:\n  apart:\n    non_penetration:\n      types: [Nope]\n"
)


@pytest.fixture(scope="module")
def sink() -> Grammar:
    return load_grammar(GRAMMARS / "sink.yaml")


# ---------------------------------------------------------- ssg validate -q ---


def test_validate_quiet_hides_the_warnings_of_a_good_grammar(tmp_path: Path) -> None:
    """`-q` is "Print errors only.", but every warning was printed all the same."""
    path = tmp_path / "g.yaml"
    path.write_text(UNREACHABLE)
    loud = CliRunner().invoke(app, ["validate", str(path)])
    assert loud.exit_code == 0 and "unreachable" in loud.stderr
    quiet = CliRunner().invoke(app, ["validate", "-q", str(path)])
    assert quiet.exit_code == 0
    assert quiet.stdout == "" and quiet.stderr == ""


def test_validate_quiet_prints_the_errors_alone(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    path.write_text(ERROR_AND_WARNING)
    loud = CliRunner().invoke(app, ["validate", str(path)])
    assert loud.exit_code == 1 and "warning: type 'B' is unreachable" in loud.stderr
    quiet = CliRunner().invoke(app, ["validate", "-q", str(path)])
    assert quiet.exit_code == 1
    assert quiet.stderr.splitlines() == [
        f"{path}:9:15: error: type 'Nope' is not a type of this grammar"
    ]


# ---------------------------------------------------------- Scene.metadata ---


def test_a_loaded_scene_shows_its_files_metadata(sink: Grammar, tmp_path: Path) -> None:
    """docs/api.md: each constrained scene records how it was sampled in `.metadata`; a loaded
    one gave None while its `to_json()` held the sampler's record."""
    out = tmp_path / "kept"
    args = ["sample", str(GRAMMARS / "sink.yaml"), "-n", "2", "--seed", "5"]
    result = CliRunner().invoke(app, [*args, "--constraints", "all", "-o", str(out), "-q"])
    assert result.exit_code == 0, result.output
    loaded = ssgc.load_scenes(out, sink)
    for scene in loaded:
        assert scene.metadata["sampler"]["method"] == "rejection"
        assert scene.metadata == scene.to_json()["metadata"]
        path = tmp_path / "again.json"
        scene.save(path)  # byte for byte the file `ssg sample` wrote
        assert path.read_bytes() == (out / f"{scene.name}.json").read_bytes()


def test_a_hand_written_scenes_metadata_is_kept_as_it_is(sink: Grammar, tmp_path: Path) -> None:
    doc = sink.sample(1, seed=0)[0].to_json()
    doc["metadata"] = {"source": "typed by hand"}
    path = tmp_path / "hand.json"
    path.write_text(json.dumps(doc))
    (scene,) = ssgc.load_scenes(path, sink)
    assert scene.metadata == {"source": "typed by hand"}
    del scene.metadata["source"]  # what `.metadata` holds is what is written
    scene.metadata["note"] = "edited"
    assert scene.to_json()["metadata"] == {"note": "edited"}
    assert pickle.loads(pickle.dumps(scene)).metadata == {"note": "edited"}


def test_a_scene_without_metadata_has_an_empty_dict(sink: Grammar, tmp_path: Path) -> None:
    """It was None, so `scene.metadata["note"] = ...` was a TypeError; an empty dict must not
    add `"metadata": {}` to the files written."""
    out = tmp_path / "plain"
    args = ["sample", str(GRAMMARS / "sink.yaml"), "-n", "1", "--seed", "3", "-o", str(out), "-q"]
    assert CliRunner().invoke(app, args).exit_code == 0
    (written,) = out.glob("*.json")
    (loaded,) = ssgc.load_scenes(written, sink)
    (sampled,) = sink.sample(1, seed=3)
    made = sink.scene([("DishBin", [0, 0, 0])])
    for scene in (loaded, sampled, made):
        assert scene.metadata == {}
        assert "metadata" not in scene.to_json()
    path = tmp_path / "again.json"
    sampled.save(path)
    assert path.read_bytes() == written.read_bytes()
    sampled.metadata["note"] = "mine"
    assert sampled.to_json()["metadata"] == {"note": "mine"}
    assert sink.sample(1, seed=3)[0].metadata == {}  # each scene has its own dict


# ---------------------------------------------------- the fit report's tails ---


def test_the_fit_report_always_has_tails() -> None:
    """docs/fitting.md section 11 lists `tails` for every report; it was left out when no
    tails were written (a grammar without such constraints)."""
    doc = json.loads(report_json(FitResult("", [], "iterations", "stopped")))
    assert doc["tails"] == []
    assert "mmd" not in doc  # "only with --mmd"


# ------------------------------------------- a pinned axis's negative variance ---


@pytest.mark.parametrize(
    "law",
    [
        "{variance: [1, 1, -1], pin: [z]}",
        "{covariance: [[1, 0, 0], [0, 1, 0], [0, 0, -1]], pin: [z]}",
    ],
    ids=["list", "covariance"],
)
def test_a_pinned_axis_negative_variance_says_so(tmp_path: Path, law: str) -> None:
    """The list form said "variance must be positive", as if a pinned axis's variance could
    not be 0 (docs/grammar.md 4.2: it may, in either form, but not be negative)."""
    path = tmp_path / "pv.yaml"
    path.write_text(
        "grammar: g\nroot: A\ntypes:\n"
        f"  A: {{and: [{{child: B, translation: {{world_normal: {law}}}}}]}}\n"
        "  B: {observed: true}\n"
    )
    with pytest.raises(GrammarError) as caught:
        load_grammar(path)
    assert [d.message for d in caught.value.diagnostics] == [
        "the variance of a pinned axis may be 0 but not negative, got -1 (z axis)"
    ]


# ------------------------------------------------- docs/interruptions.md paths ---


def test_the_source_files_interruptions_md_cites_exist() -> None:
    """It cited `ssgc/cli/launch.py`; the file is `cli/launch.py`."""
    text = (ROOT / "docs" / "interruptions.md").read_text()
    cited = set(re.findall(r"`([\w/]+\.py)`", text))
    assert "cli/launch.py" in cited
    assert [p for p in sorted(cited) if not (ROOT / p).is_file()] == []
