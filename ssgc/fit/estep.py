"""The E-step's parsing: every scene's top-N trees, in one process or in several.

Scenes are independent, so `jobs` worker processes parse them side by side
(`ssgc.forked.ordered_map`: forked with the iteration's parser already built).  Results come
back in scene order, so the journal, and therefore the fit, is the same for any number of
jobs.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from ssgc.forked import ordered_map
from ssgc.io.scene import Scene
from ssgc.parse.parser import Parser, SceneParses


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
    work = _Work(parser, scenes, top, deadline)
    yield from ordered_map(functools.partial(_parse, work), range(start, len(scenes)), jobs)


def _parse(work: _Work, index: int) -> Parsed:
    if work.deadline is None:
        return Parsed(index, work.parser.parse(work.scenes[index], top=work.top), None)
    limit = work.deadline - time.monotonic()
    if limit <= 0:
        return Parsed(index, None, limit)
    result = work.parser.parse(work.scenes[index], top=work.top, time_limit=limit)
    return Parsed(index, result, limit)
