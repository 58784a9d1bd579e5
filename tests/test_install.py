"""`pip install .` alone must be enough for the README's quick start and the core commands.

A fresh machine has none of the packages that only an extra brings (matplotlib, drake,
mujoco, ...), but this test environment has them all, so a core command that came to import
one would pass every other test.  These tests run the commands in a subprocess with every
module of an extra-only distribution blocked from import, as on that fresh machine.  The list
comes from pyproject.toml, so a package moved between the core and an extra is followed.
(python-fcl was extra-only while the bundled sink grammars declared `non_penetration`, and the
quick start failed on a fresh machine: docs/dependencies.md.)"""

from __future__ import annotations

import importlib.metadata
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUN = """
import sys
for name in {blocked!r}:
    sys.modules[name] = None  # `import name` now raises ImportError
from ssgc.cli.app import main
sys.argv = ["ssg", *sys.argv[1:]]
main()
"""


def _dist(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement(line: str) -> str:
    return _dist(re.split(r"[\s<>=!~\[;]", line.strip(), maxsplit=1)[0])


def extra_only_modules() -> list[str]:
    """Top-level modules of installed distributions that an extra names and the core does not."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {_requirement(r) for r in project["dependencies"]}
    extras = {_requirement(r) for reqs in project["optional-dependencies"].values() for r in reqs}
    only = extras - core
    owners = importlib.metadata.packages_distributions()
    return sorted(m for m, dists in owners.items() if any(_dist(d) in only for d in dists))


def ssg_core_only(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    script = RUN.format(blocked=extra_only_modules())
    return subprocess.run(
        [sys.executable, "-c", script, *args], cwd=cwd, capture_output=True, text=True, timeout=600
    )


def quick_start() -> list[str]:
    """The README's first command, after its `pip install . && `."""
    block = re.search(r"```bash\n(.*?)\n```", (ROOT / "README.md").read_text(), re.S)
    assert block is not None, "README has no bash block"
    install, _, command = block.group(1).partition(" && ")
    assert install == "pip install .", install
    words = shlex.split(command)
    assert words[0] == "ssg", words
    return words[1:]


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory with the bundled grammars, where the quick start has run."""
    d = tmp_path_factory.mktemp("fresh")
    (d / "grammars").symlink_to(ROOT / "grammars")
    done = ssg_core_only(quick_start(), d)
    assert done.returncode == 0, done.stderr
    return d


def test_the_blocked_modules_cannot_be_imported(workdir: Path) -> None:
    """The check itself: pictures need the `viz` extra, and under the block they say so."""
    blocked = extra_only_modules()
    if "matplotlib" not in blocked:
        pytest.skip("matplotlib is not installed, so there is nothing to block")
    assert "fcl" not in blocked  # a runtime dependency now
    scene = next((workdir / "scenes").glob("*.json"))
    done = ssg_core_only(["render", str(scene), "-o", str(workdir / "x.png")], workdir)
    assert done.returncode == 1, done.stderr
    assert "matplotlib" in done.stderr and "Traceback" not in done.stderr
    assert not (workdir / "x.png").exists()


def test_the_readme_quick_start_runs_without_extras(workdir: Path) -> None:
    scenes = sorted((workdir / "scenes").glob("*.json"))
    assert len(scenes) == 5, scenes


def test_every_bundled_grammar_validates_without_extras(workdir: Path) -> None:
    grammars = sorted(str(p) for p in (ROOT / "grammars").glob("*.yaml"))
    done = ssg_core_only(["validate", *grammars], workdir)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count(": ok (") == len(grammars)


def test_core_commands_on_the_sink_grammar_run_without_extras(workdir: Path) -> None:
    """parse, explain (its overlap reasons use FCL) and fit (it measures the overlap tail)."""
    scene = sorted((workdir / "scenes").glob("*.json"))[0]
    for args in (
        ["parse", str(scene), "-g", "grammars/sink.yaml", "-o", "parse.json"],
        ["explain", str(scene), "-g", "grammars/sink.yaml"],
        ["fit", "scenes", "-g", "grammars/sink.yaml", "-o", "fit.yaml", "--iterations", "1"],
    ):
        done = ssg_core_only(args, workdir)
        assert done.returncode == 0, (args, done.stderr)
        assert "Traceback" not in done.stderr
