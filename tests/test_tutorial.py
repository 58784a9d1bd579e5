"""docs/tutorial.md runs as written: its files and commands, in order, in one empty directory.

The tutorial marks what is run with these conventions (it repeats them for its editors, in an
HTML comment at the top):

- A fenced block whose info string has `file=NAME` (```` ```yaml file=table.yaml ````) is a
  file the reader writes: its text goes to NAME.  `append=NAME` adds the text to the end of NAME
  instead (the reader pastes a section into a file).
- In a ```` ```console ```` block, each line starting with `$ ` is a command; the lines after it,
  up to the next command, are what it prints (standard output and error together).  Every shown
  line must appear in what the command printed, in the same order (trailing spaces aside).
  `...` inside a shown line matches anything (timings); a line that is only `...` says lines
  were left out.  So the outputs shown are real: a change in a message fails this test.
- A command ending in `# exit code N` must exit with N; every other command must exit with 0.
- Other blocks (```` ```bash ```` for installing, a ```` ```python ```` without `file=`) are not
  run.

`ssg ...` commands run in this process (typer's CliRunner, as tests/test_cli.py does) and
`python FILE.py` by runpy, which spares a Python start and the imports per command and keeps
the default run within its budget; anything else (`cp`, `grep`) runs in bash.  The slow test runs
every command in bash, as a reader does, with the `ssg` this environment installed.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import runpy
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT
from typer.testing import CliRunner

from ssgc.cli.app import app

pytest.importorskip("matplotlib")  # `ssg render` is part of the tutorial (the viz extra)

TUTORIAL = ROOT / "docs" / "tutorial.md"
FENCE = re.compile(r"^```(\S*)(.*)$")
EXIT = re.compile(r"#\s*exit code (\d+)\s*$")


@dataclass(frozen=True)
class WriteFile:
    """A block the reader saves (or appends) as a file."""

    name: str
    text: str
    append: bool
    line: int


@dataclass(frozen=True)
class Command:
    """One `$ ` line of a console block, with the output the tutorial shows for it."""

    text: str
    shown: tuple[str, ...]
    exit_code: int
    line: int


Step = WriteFile | Command


def steps(markdown: str) -> list[Step]:
    """The tutorial's files and commands, in reading order."""
    lines = markdown.splitlines()
    found: list[Step] = []
    i = 0
    while i < len(lines):
        fence = FENCE.match(lines[i])
        if not fence:
            i += 1
            continue
        end = i + 1
        while end < len(lines) and not lines[end].startswith("```"):
            end += 1
        assert end < len(lines), f"tutorial.md:{i + 1}: unclosed code block"
        body = lines[i + 1 : end]
        info = dict(re.findall(r"(file|append)=(\S+)", fence[2]))
        if "file" in info or "append" in info:
            name = info.get("file") or info["append"]
            text = "\n".join(body) + "\n"
            found.append(WriteFile(name, text, "append" in info, i + 1))
        elif fence[1] == "console":
            found.extend(console_commands(body, i + 2))
        i = end + 1
    return found


def console_commands(body: list[str], first_line: int) -> list[Command]:
    commands: list[Command] = []
    for k, line in enumerate(body):
        if line.startswith("$ "):
            text = line[2:].strip()
            code = EXIT.search(text)
            commands.append(Command(text, (), int(code[1]) if code else 0, first_line + k))
        else:
            assert commands, f"tutorial.md:{first_line + k}: output before any `$ ` command"
            last = commands[-1]
            commands[-1] = Command(last.text, (*last.shown, line), last.exit_code, last.line)
    return commands


def shown_lines_appear(shown: tuple[str, ...], printed: str) -> str | None:
    """None when every shown line is found in the printed lines, in order; else the first
    line that is not."""
    printed_lines = [p.rstrip() for p in printed.splitlines()]
    at = 0
    for want in shown:
        if want.strip() in ("", "..."):
            continue
        pattern = re.compile(".*".join(re.escape(part) for part in want.rstrip().split("...")))
        while at < len(printed_lines) and not pattern.fullmatch(printed_lines[at]):
            at += 1
        if at == len(printed_lines):
            return want
        at += 1
    return None


Runner = Callable[[str, Path], tuple[int, str]]


def run_in_process(command: str, cwd: Path) -> tuple[int, str]:
    """`ssg` and `python FILE` here (see the module's docstring); the rest in bash."""
    words = shlex.split(command, comments=True)
    if words[0] == "ssg":
        with np.errstate(all="ignore"):  # as `ssg`'s main does
            result = CliRunner().invoke(app, words[1:])
        if result.exception is not None and not isinstance(result.exception, SystemExit):
            raise result.exception
        return result.exit_code, result.output
    if words[0] == "python" and len(words) == 2 and words[1].endswith(".py"):
        buffer = io.StringIO()
        with contextlib.redirect_stdout(buffer), np.errstate(all="ignore"):
            runpy.run_path(str(cwd / words[1]), run_name="__main__")
        return 0, buffer.getvalue()
    return run_in_bash(command, cwd)


def run_in_bash(command: str, cwd: Path) -> tuple[int, str]:
    """The command as a reader's shell runs it, `ssg` and `python` those of this environment."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    done = subprocess.run(
        ["bash", "-c", command],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=600,
    )
    return done.returncode, done.stdout


def follow(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, run: Runner) -> None:
    """Do what the tutorial says, step by step, checking exit codes and shown outputs."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("COLUMNS", "100")
    all_steps = steps(TUTORIAL.read_text(encoding="utf-8"))
    assert sum(isinstance(s, Command) for s in all_steps) >= 10
    for step in all_steps:
        where = f"docs/tutorial.md:{step.line}"
        if isinstance(step, WriteFile):
            target = tmp_path / step.name
            assert step.append == target.exists(), f"{where}: {step.name} exists: {target.exists()}"
            with target.open("a" if step.append else "w", encoding="utf-8") as f:
                f.write(step.text)
            continue
        code, printed = run(step.text, tmp_path)
        assert code == step.exit_code, f"{where}: `{step.text}` exited {code}:\n{printed}"
        missing = shown_lines_appear(step.shown, printed)
        assert missing is None, f"{where}: `{step.text}` did not print {missing!r}:\n{printed}"


def test_tutorial_runs_as_written(tmp_path, monkeypatch):
    follow(tmp_path, monkeypatch, run_in_process)


@pytest.mark.slow
def test_tutorial_runs_as_written_in_a_shell(tmp_path, monkeypatch):
    if shutil.which("ssg", path=str(Path(sys.executable).parent)) is None:
        pytest.skip("no `ssg` script beside this Python: install the package (pip install -e .)")
    follow(tmp_path, monkeypatch, run_in_bash)


def test_shown_output_is_checked_in_order_with_wildcards():
    printed = "iteration 1: log-evidence 3.5, 0.57 s\nwrote fitted.yaml\n"
    assert shown_lines_appear(("iteration 1: log-evidence 3.5, ... s",), printed) is None
    assert shown_lines_appear(("...", "wrote fitted.yaml"), printed) is None
    assert shown_lines_appear(("wrote fitted.yaml", "iteration 1: ..."), printed) is not None
    assert shown_lines_appear(("iteration 2: ...",), printed) == "iteration 2: ..."


def test_the_tutorial_conventions_are_read_as_documented():
    text = (
        "```yaml file=a.yaml\nx: 1\n```\n"
        "```yaml append=a.yaml\ny: 2\n```\n"
        "```console\n$ ssg validate a.yaml   # exit code 1\nsome output\n$ ls\n```\n"
        "```bash\npip install ssgc\n```\n"
    )
    got = steps(text)
    assert got[0] == WriteFile("a.yaml", "x: 1\n", False, 1)
    assert got[1] == WriteFile("a.yaml", "y: 2\n", True, 4)
    assert got[2] == Command("ssg validate a.yaml   # exit code 1", ("some output",), 1, 8)
    assert got[3] == Command("ls", (), 0, 10)
    assert len(got) == 4
