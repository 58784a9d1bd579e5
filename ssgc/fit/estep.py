"""The E-step's parsing: every scene's top-N trees, in one process or in several.

Scenes are independent, so `jobs` worker processes parse them side by side.  Results come
back in scene order (`imap`), so the journal, and therefore the fit, is the same for any
number of jobs.  Workers are forked with the iteration's parser already built (nothing is
pickled but scene indices and results), ignore Ctrl-C (the main process handles it and
stops them), and die with the main process if it is killed, so a SIGKILLed fit leaves no
orphans behind.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import signal
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from ssgc.io.scene import Scene
from ssgc.parse.parser import Parser, SceneParses

_PR_SET_PDEATHSIG = 1  # linux/prctl.h


@dataclass(frozen=True)
class Parsed:
    index: int
    result: SceneParses | None  # None: the deadline had passed before the parse could start
    limit: float | None  # the time limit the parse was given (seconds), if any


@dataclass(frozen=True)
class _Work:
    parser: Parser
    scenes: Sequence[Scene]
    top: int
    deadline: float | None  # time.monotonic() value, the same clock in every process


_work: _Work | None = None  # what forked workers parse with


def parse_scenes(
    parser: Parser,
    scenes: Sequence[Scene],
    start: int,
    top: int,
    deadline: float | None,
    jobs: int = 1,
) -> Iterator[Parsed]:
    """Parse scenes `start`, `start + 1`, ... in order; each gets the time left until
    `deadline`.  The caller may stop iterating at any point (the workers are then stopped)."""
    global _work
    work = _Work(parser, scenes, top, deadline)
    indices = range(start, len(scenes))
    if jobs <= 1 or len(indices) <= 1:
        for index in indices:
            yield _parse(work, index)
        return
    _work = work
    context = multiprocessing.get_context("fork")
    try:
        with context.Pool(min(jobs, len(indices)), initializer=_worker_setup) as pool:
            yield from pool.imap(_parse_in_worker, indices, chunksize=1)
    finally:
        _work = None


def _parse(work: _Work, index: int) -> Parsed:
    if work.deadline is None:
        return Parsed(index, work.parser.parse(work.scenes[index], top=work.top), None)
    limit = work.deadline - time.monotonic()
    if limit <= 0:
        return Parsed(index, None, limit)
    result = work.parser.parse(work.scenes[index], top=work.top, time_limit=limit)
    return Parsed(index, result, limit)


def _parse_in_worker(index: int) -> Parsed:
    assert _work is not None, "workers are forked after the work is set"
    return _parse(_work, index)


def _worker_setup() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except OSError:
            pass  # no such libc: a killed fit's workers then linger until their pipe closes
