"""The `ssg` command line: a thin typer layer over the `ssgc` API.

Every command runs inside `_user_errors`, which turns an `SsgError` (a user's mistake) into its
located messages on stderr and a non-zero exit code.  Anything else is a bug in ssgc: it is
reported in one paragraph (set SSG_DEBUG=1 for the traceback), still never a raw traceback.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from ssgc import __version__
from ssgc.cli import render as render_cli
from ssgc.errors import SsgError, SsgWarning, one_line
from ssgc.io.outputs import ENVIRONMENT_ERRNOS, Output, command_line, unused_removed

app = typer.Typer(
    name="ssg",
    help="Spatial scene grammars: validate, inspect, sample, parse and fit them.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # click's plain help: flags whole, no <bool> tags (tests/test_help.py)
)
bench_app = typer.Typer(
    help="Measure speed; prints JSON with --json.", no_args_is_help=True, rich_markup_mode=None
)
app.add_typer(bench_app, name="bench")

# Text is printed as it is: no emoji codes (rich would print `g.yaml:100:3` as `g.yaml💯3`)
# and no markup (a grammar named "[/]" in an `inspect` table title would be an error).


class _Console(Console):
    def on_broken_pipe(self) -> None:
        """rich ends the program itself with exit 1 when the reader of a pipe is gone; ours
        is the `BrokenPipeError` that `_user_errors` ends quietly with EXIT_PIPE, as Unix
        tools do (`ssg inspect g.yaml | head -c 10` exited 1)."""
        self.quiet = True
        raise BrokenPipeError


out = _Console(soft_wrap=True, emoji=False, markup=False)
err = _Console(stderr=True, soft_wrap=True, emoji=False, markup=False)
MAX_SHOWN_DIAGNOSTICS = 30


@contextmanager
def _user_errors() -> Iterator[None]:
    try:
        yield
    except SsgError as exc:
        _print_diagnostics(exc)
        raise typer.Exit(exc.exit_code) from None
    except KeyboardInterrupt:
        err.print("ssg: interrupted")
        raise typer.Exit(130) from None
    except (typer.Exit, typer.Abort):
        raise
    except BrokenPipeError:  # `ssg ... | head`: the reader is gone; end quietly, as Unix tools do
        _silence_stdout()
        raise typer.Exit(EXIT_PIPE) from None
    except OSError as exc:
        if exc.errno not in ENVIRONMENT_ERRNOS:
            raise _internal_error(exc) from None
        _print_diagnostics(_environment_error(exc))
        raise typer.Exit(1) from None
    except Exception as exc:  # a bug in ssgc, not the user's mistake
        if _CtrlC.pressed or _caused_by_interrupt(exc):
            # a library turned the Ctrl-C into its own error: numpy, interrupted while it
            # compared rows in `np.unique(axis=0)`, raises "Cannot compare structured arrays"
            # (a resumed `ssg fit` stopped with exit 70 instead of 130 in a CI run)
            err.print("ssg: interrupted")
            raise typer.Exit(130) from None
        raise _internal_error(exc) from None


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is among the exceptions that led to `exc`."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


EXIT_PIPE = 141  # what a shell reports for a command ended by SIGPIPE (128 + 13)


def _internal_error(exc: Exception) -> typer.Exit:
    if os.environ.get("SSG_DEBUG"):
        raise exc
    err.print(
        f"ssg: internal error: {type(exc).__name__}: {exc}. This is a bug in ssgc; "
        "please report it with the command you ran (SSG_DEBUG=1 shows the traceback).",
        markup=False,
        highlight=False,
    )
    return typer.Exit(70)


def _environment_error(exc: OSError) -> SsgError:
    """A full disk, an I/O error, a denied permission: the machine's fault, exit 1.  An error
    without a file name comes from writing standard output (every file ssgc writes is named by
    `ssgc.io.outputs`)."""
    if exc.filename is None:
        _silence_stdout()  # what is still buffered cannot be written either
        return SsgError.single(f"cannot write standard output: {exc.strerror}", "<stdout>")
    return SsgError.single(exc.strerror or str(exc), str(exc.filename))


def _silence_stdout() -> None:
    """Point standard output at /dev/null, so the flush at exit neither fails nor complains
    (Python prints "Exception ignored ... BrokenPipeError" otherwise)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, ValueError, OSError):
        return  # not a real file (in tests: typer's CliRunner)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


def _print_diagnostics(exc: SsgError) -> None:
    shown = exc.diagnostics[:MAX_SHOWN_DIAGNOSTICS]
    for d in shown:
        err.print(str(d), markup=False, highlight=False)
    hidden = len(exc.diagnostics) - len(shown)
    if hidden > 0:
        err.print(f"... and {hidden} more", markup=False, highlight=False)


def _command(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap a command body in the user-error handler (keeps typer's signature intact)."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with unused_removed(), command_line(sys.argv[1:]), _user_errors():
            return fn(*args, **kwargs)

    return wrapper


def _version(value: bool) -> None:
    if value:
        out.print(f"ssg {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version, is_eager=True, help="Print the version and exit."
        ),
    ] = False,
) -> None:
    """Spatial scene grammar compiler."""


def finite(value: float | None) -> float | None:
    """The check of a number option: `inf` passes the `min` bounds typer checks (`nan` does
    not), and a time limit of inf wrote `Infinity` into JSON, which is not JSON."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter("must be a finite number")
    return value


def finite_from(low: float, high: float = math.inf) -> Callable[[float | None], float | None]:
    """The check of a number option with bounds, in place of typer's `min`/`max`: typer checks
    those before the callback, and NaN fails them, so `--time-limit nan` said "Input should be
    greater than or equal to 0.001" (and `--max-time -inf` passed to the command) instead of
    "must be a finite number" (docs/robustness.md).  Finiteness first, then the bounds, in
    typer's words; both are usage errors (exit 2)."""

    def check(value: float | None) -> float | None:
        finite(value)
        if value is not None and value < low:
            raise typer.BadParameter(f"Input should be greater than or equal to {low:g}")
        if value is not None and value > high:
            raise typer.BadParameter(f"Input should be less than or equal to {high:g}")
        return value

    return check


GrammarArg = Annotated[Path, typer.Argument(help="Grammar YAML file.", show_default=False)]
# Mesh and model files a grammar names must be in its directory unless the user allows others
# (docs/robustness.md): a grammar from elsewhere cannot point ssg at arbitrary files.
AllowOutside = Annotated[
    bool,
    typer.Option(
        "--allow-outside-files",
        help="Allow mesh and model files outside the grammar's directory.",
    ),
]


def _summary(dest_: Output, text: str) -> None:
    """The closing line: on stdout, unless the output itself went there."""
    (err if dest_.stdout else out).print(text, markup=False, highlight=False)


def _note_discarded(journal: Any, quiet: bool) -> None:
    if journal.discarded and not quiet:
        err.print(
            f"note: starting again; the journal {journal.path} of an interrupted run is "
            "replaced (--resume continues it)",
            markup=False,
            highlight=False,
        )


def _in_range(value: float, flag: str, low: float, high: float) -> float:
    """A positive bound of the M-step, checked here so that the message reads as numbers are
    written (typer prints a range's 1e-300 with all its zeros); a number that is not finite is
    said to be so first, as every number option says it (docs/robustness.md)."""
    finite(value)
    if not (low < value <= high and math.isfinite(value)):
        upper = " and finite" if math.isinf(high) else f" and at most {high:g}"
        raise typer.BadParameter(f"must be above {low:g}{upper}, got {value:g}", param_hint=flag)
    return value


def _check_method(method: str, solver: str) -> None:
    from ssgc.parse.parser import METHODS

    if method not in METHODS:
        raise SsgError.single(f"--method must be {_one_of(METHODS)}, got '{method}'")
    if solver == "scip":
        raise SsgError.single(
            "--solver scip is not available in this build; HiGHS (the default) solves every "
            "parse model, including the latent-pose bound"
        )
    if solver != "highs":
        raise SsgError.single(f"--solver must be highs or scip, got '{solver}'")


def _one_of(names: tuple[str, ...]) -> str:
    """`a, b or c`, for messages."""
    return ", ".join(names[:-1]) + " or " + names[-1] if len(names) > 1 else names[0]


class _CtrlC:
    """A Ctrl-C is never lost.  Python raises KeyboardInterrupt wherever the main thread is;
    where it cannot propagate (a destructor run by the garbage collector, a callback), it is
    printed as "Exception ignored" and the command would go on.  So the press is remembered,
    and the next step of a long command (each scene of a progress bar) raises it again."""

    pressed = False

    @classmethod
    def handler(cls, signum: int, frame: Any) -> None:
        cls.pressed = True
        raise KeyboardInterrupt

    @classmethod
    def install(cls) -> None:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not ignored
            signal.signal(signal.SIGINT, cls.handler)


class _Steps(Progress):
    """rich's progress bar, whose every step is a point where a remembered Ctrl-C is raised."""

    def advance(self, task_id: Any, advance: float = 1) -> None:
        if _CtrlC.pressed:
            raise KeyboardInterrupt
        super().advance(task_id, advance)


@contextmanager
def _warnings_about(file: Path | str) -> Iterator[None]:
    """Print each `SsgWarning` raised inside as ``FILE: warning: message``, about the input it
    concerns; other warnings pass on as they were."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        if isinstance(w.message, SsgWarning):
            err.print(f"{file}: warning: {one_line(str(w.message))}", highlight=False)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


@contextmanager
def _progress(quiet: bool) -> Iterator[Progress]:
    progress = _Steps(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=err,
        disable=quiet or not sys.stderr.isatty(),
        transient=True,
    )
    with progress:
        yield progress


# Each command lives in a module of its own and registers itself on `app` when imported; the
# order of the imports is the order of `ssg --help`.
app.command("render", short_help="Draw scenes, trees and parses (PNG, SVG).")(
    _command(render_cli.render)
)  # docs/render.md
# isort: off
from ssgc.cli import validate as _validate  # noqa: E402, F401
from ssgc.cli import sample as _sample  # noqa: E402, F401
from ssgc.cli import inspect as _inspect  # noqa: E402, F401
from ssgc.cli import parse as _parse  # noqa: E402, F401
from ssgc.cli import fit as _fit  # noqa: E402, F401
from ssgc.cli import schema as _schema  # noqa: E402, F401
from ssgc.cli import explain as _explain  # noqa: E402, F401
from ssgc.cli import export as _export  # noqa: E402, F401
from ssgc.cli import settle as _settle  # noqa: E402, F401
from ssgc.cli import bench as _bench  # noqa: E402, F401  (`ssg bench sample|parse`)
from ssgc.cli import view as _view  # noqa: E402, F401  (`ssg view`)
# isort: on


def main() -> None:
    np.seterr(all="ignore")  # -inf log-probabilities are expected values, not warnings
    _CtrlC.install()
    try:
        app()
        code: Any = 0
    except SystemExit as exc:
        code = exc.code
    sys.exit(_flush_stdout(code))


def _flush_stdout(code: Any) -> Any:
    """Write out what standard output still buffers before Python does it at exit, where a
    closed pipe or a full disk would only print "Exception ignored" and exit 120."""
    try:
        if sys.stdout is not None:
            sys.stdout.flush()
    except BrokenPipeError:
        _silence_stdout()
        return code or EXIT_PIPE
    except OSError as exc:
        _silence_stdout()
        _print_diagnostics(
            SsgError.single(f"cannot write standard output: {exc.strerror}", "<stdout>")
        )
        return code or 1
    return code


if __name__ == "__main__":
    # `python -m ssgc.cli.app`: run the importable module, on whose `app` the commands of
    # the command modules registered (not this __main__ copy's).
    from ssgc.cli.app import main as _real_main

    _real_main()
