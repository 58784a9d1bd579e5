"""`fn` over items in order, in this process or in forked worker processes.

The E-step's parses and constrained sampling's blocks are independent pieces of work whose
results must come back in order (a journal, numbered scenes), so that the output is the same
for any number of processes.  Workers are forked with the work already built: nothing is
pickled but the items and the results.  They ignore Ctrl-C (the main process handles it and
stops them) and, on Linux, die with the main process if it is killed, so a SIGKILLed run
leaves no orphans behind.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_fn: Callable[[Any], Any] | None = None  # what forked workers call


def ordered_map(fn: Callable[[T], R], items: Sequence[T], jobs: int = 1) -> Iterator[R]:
    """`fn(item)` for each item, in order; by `jobs` forked workers when there is more than one
    job and more than one item.  The caller may stop iterating at any point (the workers are
    then stopped)."""
    global _fn
    if jobs <= 1 or len(items) <= 1:
        for item in items:
            yield fn(item)
        return
    _fn = fn
    context = multiprocessing.get_context("fork")
    try:
        with context.Pool(min(jobs, len(items)), initializer=_worker_setup) as pool:
            yield from pool.imap(_call, items, chunksize=1)
    finally:
        _fn = None


def _call(item: Any) -> Any:
    assert _fn is not None, "workers are forked after the function is set"
    return _fn(item)


def _worker_setup() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except OSError:
            pass  # no such libc: a killed run's workers then linger until their pipe closes
