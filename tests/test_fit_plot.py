"""`ssg fit --plot DIR`: three pictures of the fit, checked before the fit and written whole."""

from __future__ import annotations

import json
import shutil

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


@pytest.mark.parametrize("kept", ["all", "none"])
def test_titles_and_legends_fit_in_the_picture(points, kept):
    """gmm has one type: its single panel was 3.2 in wide and the title was cut to "ositions
    seen from above: ..."; a grammar observing only its root drew an empty 0..1 axes."""
    from ssgc.render.fit import counts_figure, positions_figure

    g = load_grammar(GMM)
    pops = [data_population(load_scenes(points, g)), sample_population(g, 50, 0, "samples")]
    types = [t.id for t in g.types if t.observed and t.id != g.root] if kept == "all" else []
    names = [g.types[t].name for t in types]
    for fig in (counts_figure(pops, types, names), positions_figure(pops, types, names)):
        fig.canvas.draw()
        box = fig.bbox
        texts = [fig._suptitle, *fig.legends] if fig._suptitle else list(fig.legends)
        assert texts
        for text in texts:
            extent = text.get_window_extent()
            assert extent.x0 >= box.x0 - 1 and extent.x1 <= box.x1 + 1, text
    if kept == "none":
        shown = [t.get_text() for ax in fig.axes for t in ax.texts]
        assert shown == ["no observed type besides the root"]


def test_a_fit_stopped_while_drawing_keeps_the_grammar_for_resume(points, tmp_path, monkeypatch):
    """In-place `-o GRAMMAR`: the grammar is written last, after the pictures, so a Ctrl-C
    while they are drawn leaves it and its journal as they were, and --resume finishes the
    fit (once the fitted grammar was written first, and --resume refused the journal)."""
    import ssgc.render.fit as render_fit

    grammar = tmp_path / "gmm.yaml"
    shutil.copy(GMM, grammar)
    before = grammar.read_bytes()
    plots = tmp_path / "plots"
    plots.mkdir()
    fit = ("fit", points, "-g", grammar, "--iterations", 1, "--top", 1, "--plot", plots, "-q")
    real = render_fit.plot_fit

    def stopped(*args: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(render_fit, "plot_fit", stopped)
    assert run(*fit, "-o", grammar).exit_code == 130
    assert grammar.read_bytes() == before
    assert (tmp_path / "gmm.yaml.partial.jsonl").is_file()
    monkeypatch.setattr(render_fit, "plot_fit", real)
    result = run(*fit, "-o", grammar, "--resume")
    assert result.exit_code == 0, result.output
    assert run(*fit, "-o", tmp_path / "once.yaml").exit_code == 0
    assert grammar.read_bytes() == (tmp_path / "once.yaml").read_bytes() != before
    assert not (tmp_path / "gmm.yaml.partial.jsonl").exists()
