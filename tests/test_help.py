"""`--help` of every command: every flag shown whole, no `<bool>` tags on flags (issue 16)."""

from __future__ import annotations

from typing import Any

import pytest
import typer
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app

runner = CliRunner()


def commands() -> list[tuple[list[str], Any]]:
    """Every command and subcommand, with the words that reach it."""
    found = []

    def walk(words: list[str], cmd: Any) -> None:
        found.append((words, cmd))
        if hasattr(cmd, "commands"):  # a group (typer's own click types)
            for name, sub in cmd.commands.items():
                if not sub.hidden:
                    walk([*words, name], sub)

    walk([], typer.main.get_command(app))
    return found


@pytest.mark.parametrize("width", [60, 100])
@pytest.mark.parametrize(
    "words,cmd", [pytest.param(w, c, id=" ".join(w) or "ssg") for w, c in commands()]
)
def test_help_shows_every_flag_whole(words, cmd, width):
    result = runner.invoke(app, [*words, "--help"], terminal_width=width)
    assert result.exit_code == 0, result.output
    text = result.output
    assert "<bool>" not in text
    assert "…" not in text  # nothing cut short
    listed = text.split("Commands:")[1].splitlines() if "Commands:" in text else []
    assert not [line for line in listed if line.endswith("...")]  # click cuts long summaries
    assert all(len(line) <= width for line in text.splitlines())
    tokens = set(text.replace(",", " ").split())
    for param in cmd.params:
        if param.param_type_name == "option" and not param.hidden:
            assert param.help, f"{param.opts[0]} of `{' '.join(words)}` has no help"
            for flag in param.opts + param.secondary_opts:
                assert flag in tokens, f"{flag} missing from `{' '.join(words)} --help`"


def test_every_command_that_reads_a_grammar_takes_allow_outside_files():
    """A grammar naming a mesh outside its directory is refused with "allow it with
    --allow-outside-files": every command that can meet that message takes the flag
    (`ssg render -g` did not)."""
    missing = []
    for words, cmd in commands():
        names = {p.name for p in getattr(cmd, "params", [])}
        if names & {"grammar", "grammars", "grammar_path"}:
            flags = {f for p in cmd.params for f in getattr(p, "opts", [])}
            if "--allow-outside-files" not in flags:
                missing.append(" ".join(words))
    assert not missing, missing


def test_bench_sample_takes_the_n_it_is_given(monkeypatch):
    """`-n 20000 --constraints ...` ran 1,000 scenes: 20,000 was taken for "no -n given"."""
    import ssgc.bench

    asked = []
    monkeypatch.setattr(ssgc.bench, "bench_constrained", lambda g, c, n, *a: asked.append(n) or {})
    command = ["bench", "sample", str(GRAMMARS / "bin_packing.yaml"), "--constraints", "all"]
    for extra in (["-n", "20000"], []):
        result = runner.invoke(app, [*command, *extra])
        assert result.exit_code == 0, result.output
    assert asked == [20000, 1000]


@pytest.mark.parametrize(
    "words, said",
    [
        (["bench", "sample", "{gmm}", "-n", "3", "--method", "hmc"], "--method and -j time"),
        (["bench", "sample", "{gmm}", "-n", "3", "-j", "2"], "--method and -j time"),
        (["inspect", "{gmm}", "--json", "--diagram", "{tmp}/g.svg"], "give one"),
        (["view", "{gmm}", "-o", "{tmp}/p.html", "--port", "9999"], "--port is the port of"),
        (["sample", "{gmm}", "-o", "{tmp}/s", "--method", "hmc"], "--method, --penalty-eps"),
        (["sample", "{gmm}", "-o", "{tmp}/s", "--penalty-eps", "0.01"], "--method, --penalty"),
        (["sample", "{gmm}", "-o", "{tmp}/s", "-j", "2"], "and --jobs need --constraints"),
        (["fit", "{tmp}", "-g", "{gmm}", "-o", "{tmp}/f.yaml", "--samples", "9"], "--estep mcmc"),
    ],
)
def test_an_option_that_would_do_nothing_is_refused(tmp_path, words, said):
    """They were accepted and ignored: no timing of methods without --constraints, no JSON
    with a diagram, no port without --serve."""
    args = [w.format(gmm=GRAMMARS / "gmm.yaml", tmp=tmp_path) for w in words]
    result = runner.invoke(app, args)
    assert result.exit_code == 1 and said in result.output, result.output
    assert not list(tmp_path.iterdir())


def test_every_number_option_refuses_infinity():
    """`inf` passed every `min` bound: `--time-limit inf` wrote `Infinity` into JSON, which no
    JSON reader takes, and `settle --max-time inf` was an internal error."""
    tried = []
    for words, cmd in commands():
        for param in getattr(cmd, "params", []):
            if param.param_type_name == "option" and _takes_a_float(param):
                flag = param.opts[0]
                result = runner.invoke(app, [*words, flag, "inf"])
                assert result.exit_code == 2, (words, flag, result.output)
                assert "Invalid value" in result.output, result.output
                tried.append(f"{' '.join(words)} {flag}")
    assert len(tried) >= 8, tried  # the time limits, settle's --max-time, fit's numbers


def _takes_a_float(param: Any) -> bool:
    """Whether an option reads a float: by its annotation (typer 0.29 keeps its own copy of
    click) or by click's parameter type (older typer)."""
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is not None:
        return descriptor.annotation is float
    return type(param.type).__name__ in ("FloatParamType", "FloatRange")
