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

import hashlib
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
from ssgc.io.atomic import remove_stale_temps, write_text_atomic
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
            doc = _as_sampled(json.loads(Path(entry.path).read_bytes()))
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


def _as_sampled(doc: Any) -> Any:
    """A scene file of `ssg sample --settle` keeps its run's seed, index and log-probability in
    `metadata.settle` (its tree and log_prob, which describe the poses before settling, are
    dropped): read them from there, so that a settled run resumes as a plain one does."""
    meta = doc.get("metadata") if isinstance(doc, dict) else None
    settle = meta.get("settle") if isinstance(meta, dict) else None
    if not isinstance(settle, dict) or "seed" in doc or "log_prob" in doc:
        return doc
    fields = {"seed": "seed", "index": "index", "log_prob": "source_log_prob"}
    read = {k: settle.get(v) for k, v in fields.items()}
    return {**doc, **read, "tree": {}}  # no tree to check: settling dropped it


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


# ----------------------------------------------------------------- the run manifest ---

MANIFEST = "ssg-sample.manifest"  # not *.json: a dataset directory's *.json files are scenes
MANIFEST_FORMAT = "ssgc.sample-run/1"
SAME_RUN = (
    "grammar",
    "grammar_sha256",
    "seed",
    "count",
    "width",
    "constraints",
    "method",
    "settle",
    "export",
)  # what --resume compares
# What a manifest written before a key existed meant by its absence.
_ABSENT = {"settle": False, "export": []}
_SCENE_NAME = re.compile(r"[A-Za-z0-9_.-]*_[0-9]+\.json")  # the names `ssg sample` gives


def _recorded(manifest: dict, key: str) -> Any:
    return manifest.get(key, _ABSENT.get(key))


def run_manifest(grammar: str, grammar_file: Path, seed: int, count: int, width: int) -> dict:
    """What identifies one run of `ssg sample -o DIR`; kept in DIR as `MANIFEST`."""
    return {
        "format": MANIFEST_FORMAT,
        "grammar": grammar,
        "grammar_file": str(grammar_file.resolve()),
        "grammar_sha256": hashlib.sha256(grammar_file.read_bytes()).hexdigest(),
        "seed": seed,
        "count": count,
        "width": width,
        "complete": False,
    }


def prepare_sample_dir(
    directory: Path, manifest: dict, resume: bool, overwrite: bool
) -> list[str] | None:
    """Before a run of `ssg sample` writes into `directory` (under its lock): refuse a
    directory holding another run's scenes; with `resume`, refuse a run that is not the same
    one (grammar, its file's digest, seed, count).

    With `overwrite`, returns the other run's scene files, which `clear_old_run` deletes only
    once this run has a scene to write: a run that finds none must leave them (else None)."""
    found = _read_manifest(directory, overwrite)
    jsons = sorted(e.name for e in os.scandir(directory) if e.name.endswith(".json"))
    if resume:
        if found is None and jsons:
            raise SsgError.single(
                f"--resume continues only a run of `ssg sample` recorded in a manifest "
                f"({MANIFEST}); this directory holds {len(jsons)} .json file(s) but no manifest: "
                "write to another -o, or start again with --overwrite",
                str(directory),
            )
        if found is not None:
            _check_same_sample_run(found, manifest, directory)
        return None
    same = found is not None and all(_recorded(found, k) == manifest[k] for k in SAME_RUN)
    if same or (found is None and not jsons):
        return None  # a new directory, or this very run again: every file is rewritten alike
    others = [n for n in jsons if not _SCENE_NAME.fullmatch(n)]
    if others:  # not ours: --overwrite would not delete them either, so do not suggest it
        shown = ", ".join(others[:5]) + (", ..." if len(others) > 5 else "")
        raise SsgError.single(
            f"this directory holds .json files that `ssg sample` did not name ({shown}), "
            "which a dataset reader would take as scenes; --overwrite deletes only scene "
            "files: move them, or write to another -o",
            str(directory),
        )
    if not overwrite:
        raise SsgError.single(
            f"this directory holds {_describe(found, jsons)}; --overwrite deletes them first, "
            "--resume continues the same run, or write to another -o",
            str(directory),
        )
    return jsons


def _read_manifest(directory: Path, overwrite: bool) -> dict | None:
    path = directory / MANIFEST
    try:
        doc = json.loads(path.read_bytes())
    except FileNotFoundError:
        return None
    except (OSError, ValueError, RecursionError):
        doc = None
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        if overwrite:
            return {}  # cleared with the scenes
        raise SsgError.single(
            "not a manifest of `ssg sample`; delete it, or start again with --overwrite",
            str(path),
        )
    return doc


def _describe(found: dict | None, jsons: list[str]) -> str:
    if found:
        return (
            f"the scenes of another run ({found.get('count')} scene(s) of grammar "
            f"{json.dumps(found.get('grammar'))}, seed {found.get('seed')})"
        )
    return f"{len(jsons)} .json file(s) of another run"


def _check_same_sample_run(found: dict, manifest: dict, directory: Path) -> None:
    differ = [k for k in SAME_RUN if _recorded(found, k) != manifest[k]]
    if differ:
        raise SsgError(
            [
                Diagnostic(
                    f"these scenes are of another run ({k}: {json.dumps(_recorded(found, k))}, now "
                    f"{json.dumps(manifest[k])}); {_NEVER_MIX}",
                    str(directory / MANIFEST),
                )
                for k in differ
            ]
        )


def clear_old_run(directory: Path, jsons: list[str]) -> None:
    """`--overwrite`: delete the scenes (and temporary files) of `ssg sample` runs and the
    manifest (`prepare_sample_dir` has refused a directory with other .json files)."""
    remove_stale_temps(directory, lambda target: _SCENE_NAME.fullmatch(target) is not None)
    for name in jsons:
        (directory / name).unlink(missing_ok=True)
    (directory / MANIFEST).unlink(missing_ok=True)


def write_manifest(directory: Path, manifest: dict) -> None:
    write_text_atomic(directory / MANIFEST, json.dumps(manifest, indent=1) + "\n")
