"""`ssg sample --resume`: find which scenes an interrupted run has already written.

Scene files are written atomically (`ssgc.io.atomic`), so a file under a scene's name is whole
unless something other than ssgc wrote it.  A file counts as done when it is valid JSON with
the header this run would write (format, name, grammar, seed, index) and a body (objects, tree,
log_prob).  A file with another grammar, seed or index is an error: resuming must never mix two
runs in one directory.  A file that is not valid JSON is not a finished scene, so it is redone.

Only the grammar's name is recorded in a scene file.  To catch a grammar that was edited under
the same name, the sampler compares the `log_prob` of every done scene of each chunk it draws
again (the chunks holding missing scenes) with the freshly drawn value: `check_same_draw`.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import Diagnostic, SsgError
from ssgc.io.atomic import remove_stale_temps
from ssgc.io.scene import FORMAT

_NEVER_MIX = "--resume never mixes two runs: use the same grammar and --seed, or another -o"


@dataclass
class SampledScenes:
    """What an output directory already holds of one run of `ssg sample`."""

    directory: Path
    done: NDArray[np.bool_]  # per scene index: its file is complete and belongs to this run
    log_prob: NDArray[np.float64]  # per scene index: the log_prob its file records (if done)
    redone: int  # files present under a scene's name but not valid JSON
    removed_temps: int  # temporary files of a killed run, deleted

    def check_same_draws(
        self, start: int, log_probs: NDArray[np.float64], name_of: Callable[[int], str]
    ) -> None:
        """The done scenes `start`, `start + 1`, … must be the scenes this run draws (with
        `log_probs`), not just carry the same header: a grammar edited under the same name
        draws other scenes.  Called before any file of the chunk is written."""
        for k in np.flatnonzero(self.done[start : start + len(log_probs)]):
            index = start + int(k)
            if self.log_prob[index] != log_probs[k]:
                raise SsgError.single(
                    f"this file records log_prob {float(self.log_prob[index])!r} for scene "
                    f"{index}, but drawing it again gives {float(log_probs[k])!r}: the grammar "
                    f"(or the ssgc or numpy version) changed since it was written; {_NEVER_MIX}",
                    str(self.directory / f"{name_of(index)}.json"),
                )


def scan_sampled(
    directory: Path, stem: str, name_of: Callable[[int], str], n: int, grammar: str, seed: int
) -> SampledScenes:
    """Check the files `stem_INDEX.json` (INDEX < n, named by `name_of`) of `directory` and
    delete the temporary files a killed run left for such names.

    Raises an `SsgError` listing every file that belongs to another run.
    """
    ours = re.compile(re.escape(stem) + r"_[0-9]+\.json")
    removed = remove_stale_temps(directory, lambda target: ours.fullmatch(target) is not None)
    done = np.zeros(n, np.bool_)
    log_prob = np.zeros(n, np.float64)
    redone = 0
    errors: list[Diagnostic] = []
    for entry in os.scandir(directory):
        if not ours.fullmatch(entry.name) or not entry.is_file():
            continue
        index = int(entry.name[len(stem) + 1 : -len(".json")])
        if index >= n or f"{name_of(index)}.json" != entry.name:
            continue  # another -n (more scenes, or wider indices): not part of this run
        expected = {
            "format": FORMAT,
            "name": name_of(index),
            "grammar": grammar,
            "seed": seed,
            "index": index,
        }
        try:
            doc = json.loads(Path(entry.path).read_bytes())
        except (ValueError, RecursionError):  # invalid JSON or UTF-8: not a finished scene
            redone += 1
            continue
        problem = _foreign(doc, expected)
        if problem is not None:
            errors.append(Diagnostic(f"{problem}; {_NEVER_MIX}", entry.path))
        elif _complete(doc):
            done[index] = True
            log_prob[index] = doc["log_prob"]
        else:
            redone += 1
    if errors:
        errors.sort(key=lambda d: d.file or "")
        raise SsgError(errors)
    return SampledScenes(directory, done, log_prob, redone, removed)


def _same(a: Any, b: Any) -> bool:
    return type(a) is type(b) and a == b  # so that JSON `true` is not the seed 1


def _foreign(doc: Any, expected: dict[str, Any]) -> str | None:
    """Why a valid JSON file under a scene's name is not that scene of this run, if it is not."""
    if not isinstance(doc, dict):
        return "not a scene file of `ssg sample` (not a JSON object)"
    wrong = [k for k, v in expected.items() if not _same(doc.get(k), v)]
    if not wrong:
        return None
    has = ", ".join(f"{k} {json.dumps(doc.get(k))}" for k in wrong)
    want = ", ".join(f"{k} {json.dumps(expected[k])}" for k in wrong)
    return f"this scene file has {has}, but this run writes {want}"


def _complete(doc: dict[str, Any]) -> bool:
    lp = doc.get("log_prob")
    return (
        isinstance(doc.get("objects"), list)
        and isinstance(doc.get("tree"), dict)
        and isinstance(lp, float | int)
        and not isinstance(lp, bool)
        and math.isfinite(lp)
    )
