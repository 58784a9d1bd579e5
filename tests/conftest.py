"""Shared fixtures: paths of the bundled grammars and the vendored sink dataset."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import typer.testing
from hypothesis import settings

from ssgc.compile import load_grammar
from ssgc.ir import Grammar

# CI runs the property tests with a fixed derandomised seed so a landing never depends on a
# lucky draw; locally they explore new examples on every run.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int | None:
    """The suite runs in one process per core (`-n auto` in pyproject), but what a test prints
    under `-s`, and hypothesis's statistics, are not shown from worker processes: the measuring
    runs the docs quote (`-m slow -s`, `--hypothesis-show-statistics`) stay in one process."""
    if config.getoption("capture") == "no" or config.getoption("hypothesis_show_statistics", False):
        return 0
    return None  # xdist's own count


def _built_once(get_command):  # type: ignore[no-untyped-def]
    """typer's CliRunner builds the click command from the app on every `invoke` (0.1-0.2 s
    of signature and help building, in every one of the suite's thousands of command runs);
    `ssg` builds it once per process.  The tests build it once per app, as `ssg` does."""
    built: dict[int, tuple[object, object]] = {}

    def cached(app):  # type: ignore[no-untyped-def]
        if id(app) not in built:
            built[id(app)] = (app, get_command(app))  # the app is kept: its id stays its own
        return built[id(app)][1]

    return cached


typer.testing._get_command = _built_once(typer.testing._get_command)


ROOT = Path(__file__).resolve().parent.parent
GRAMMARS = ROOT / "grammars"
SINK_DATA = ROOT / "ssgc" / "data" / "sink" / "saved_scenes.yaml"


@pytest.fixture(scope="session")
def sink() -> Grammar:
    return load_grammar(GRAMMARS / "sink.yaml")


CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip


@pytest.fixture(scope="module")
def chromium():
    """One headless Chromium per test module, for the viewer's pages. Skipped, saying why,
    where playwright or the browser is missing (`.ci/run` installs both)."""
    playwright = pytest.importorskip(
        "playwright.sync_api", reason="playwright is not installed: pip install 'ssgc[test]'"
    )
    if not Path(CHROMIUM).exists():
        pytest.skip(f"no Chromium browser at {CHROMIUM}: apt-get install chromium")
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield browser
        browser.close()
