"""`ssg fit --plot DIR`: three pictures of the fit, checked before the fit and written whole."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.io.scene import load_scenes
from ssgc.render.fit import FILES, data_population, sample_population

pytest.importorskip("matplotlib")
runner = CliRunner()
GMM = GRAMMARS / "gmm.yaml"


def run(*args: object):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def points(tmp_path_factory):
    out = tmp_path_factory.mktemp("points")
    assert run("sample", GMM, "-n", 12, "--seed", 4, "-o", out, "-q").exit_code == 0
    return out


def test_fit_draws_three_pictures(points, tmp_path):
    plots = tmp_path / "plots"
    plots.mkdir()
    result = run(
        "fit", points, "-g", GMM, "-o", tmp_path / "fitted.yaml", "--iterations", 2,
        "--top", 1, "--plot", plots, "--report", tmp_path / "report.json", "-q",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    from matplotlib.image import imread

    for name in FILES:
        pixels = imread(plots / name)[..., :3]
        assert np.any(np.abs(pixels - 1.0) > 0.05, axis=-1).mean() > 0.02, name
    report = json.loads((tmp_path / "report.json").read_text())
    assert len(report["iterations"]) == 2


def test_a_bad_plot_directory_stops_the_fit_before_it_starts(points, tmp_path):
    fitted = tmp_path / "fitted.yaml"
    result = run("fit", points, "-g", GMM, "-o", fitted, "--plot", tmp_path / "missing")
    assert result.exit_code == 1
    assert "missing" in result.output and "Traceback" not in result.output
    assert not fitted.exists()


def test_populations_hold_the_observed_objects(points):
    g = load_grammar(GMM)
    scenes = load_scenes(points, g)
    data = data_population(scenes)
    assert data.n_scenes == len(scenes)
    assert np.array_equal(np.bincount(data.scene), [len(s.types) for s in scenes])
    sampled = sample_population(g, 50, 0, "samples")
    observed = {t.id for t in g.types if t.observed}
    assert set(sampled.type.tolist()) <= observed
    assert sampled.n_scenes == 50 and sampled.xyz.shape == (len(sampled.type), 3)
