"""`ssg parse -o OUT.json`: a journal of finished scenes, so an interrupted run can resume.

Parsing a large dataset takes hours; a crash, a Ctrl-C or a killed job must not lose the
scenes already parsed.  While it runs, `ssg parse` appends each finished scene's result to
``OUT.json.partial.jsonl`` (JSON Lines), one line per scene, flushed and fsynced before the
next scene starts.  The first line is a header naming the run; ``--resume`` refuses a journal
whose header differs from the new run's, since mixing would give an OUT.json no single run
produces.  At the end OUT.json is written atomically from the journal (streamed, so the results
are never all in memory) and the journal is deleted.

The journal's lines::

    {"journal": "ssgc.parse-journal/1", "grammar": ..., "grammar_sha256": ...,
     "scenes": ..., "scene_count": ..., "scenes_sha256": ..., "top": ..., "method": ...,
     "time_limit": ...}
    {"index": 0, "result": {...one scene of OUT.json...}}
    {"index": 1, "result": {...}}

A line is written with a single ``write`` of the whole line, so a kill leaves at most the last
line cut short; resuming ignores (and truncates) such a line.  Every entry line ends with the
SHA-256 of the rest of it (``"sha256": ...``, `_sealed`): a line changed on disk — a bad sector,
an edit, a line of another journal pasted in — is reported as damage, never taken as work done.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, TextIO

from ssgc.errors import Diagnostic, SsgError
from ssgc.io import atomic
from ssgc.io.atomic import fitted_name, remove_stale_temps, temp_part, write_text_atomic
from ssgc.io.scene import Scene, dumps_json

# /3: statuses are optimal (certified) / feasible / infeasible (proven) / no_parse / error;
# a /2 journal's "optimal" and "infeasible" were not always proven, so it is not resumed.
JOURNAL_FORMAT = "ssgc.parse-journal/3"
FAILED = ("infeasible", "no_parse", "error")  # scenes without a parse


JOURNAL_SUFFIX = ".partial.jsonl"


def journal_path(output: Path) -> Path:
    """Where the journal of a run writing `output` lives: next to it, so it is on the same
    filesystem and found again by a resumed run.  An output name too long to take the suffix
    is shortened first (`fitted_name`: the same name on every run)."""
    return output.with_name(fitted_name(output.name, len(JOURNAL_SUFFIX)) + JOURNAL_SUFFIX)


def run_header(
    grammar_name: str,
    grammar_file: Path,
    scenes_path: Path,
    scenes: Sequence[Scene],
    top: int,
    method: str,
    time_limit: float | None,
    explain: bool = False,
) -> dict[str, Any]:
    """What makes two runs the same run: their grammar, their scenes and their options
    (`--explain` too: a resumed run would mix scenes with and without explanations).

    The digests catch a grammar or dataset edited in place between the two runs.
    """
    return {
        "journal": JOURNAL_FORMAT,
        "grammar": grammar_name,
        "grammar_sha256": hashlib.sha256(grammar_file.read_bytes()).hexdigest(),
        "scenes": str(scenes_path.resolve()),
        "scene_count": len(scenes),
        "scenes_sha256": scenes_digest(scenes),
        "top": top,
        "method": method,
        "time_limit": time_limit,
        "explain": explain,
    }


def scenes_digest(scenes: Sequence[Scene]) -> str:
    """SHA-256 of the scenes' names, types and poses: catches a dataset edited in place."""
    digest = hashlib.sha256()
    for scene in scenes:
        for part in (scene.name.encode(), scene.types, scene.xyz, scene.quat):
            digest.update(part if isinstance(part, bytes) else part.tobytes())
        digest.update(b"\0")
    return digest.hexdigest()


class JournalWriteError(SsgError):
    """The journal could not be written: what it already holds is kept for `--resume`."""


class Journal:
    """A JSON Lines file whose first line names the run and whose other lines are entries.

    Entries are appended with one `write` each and fsynced, so a killed run leaves complete
    entries and at most one cut-off last line, which recovery ignores and truncates.
    Subclasses say which entries may follow which (`accept`).
    """

    FORMAT = JOURNAL_FORMAT
    WHAT = "parse journal"

    def __init__(self, path: Path, header: dict[str, Any], resume: bool) -> None:
        self.path = path
        self.discarded = False  # a journal was there but this run does not resume it
        self.entries = 0
        # the temporary files of the journal and of the output: for a long output name,
        # `journal_path` and `temp_part` shorten it alike (their suffixes are as long)
        ours = {temp_part(path.name), temp_part(path.name.removesuffix(JOURNAL_SUFFIX))}
        try:
            remove_stale_temps(path.parent, ours.__contains__)
            if resume and path.exists():
                self._recover(header)
            else:
                self.discarded = path.exists()
                write_text_atomic(path, json.dumps(header) + "\n")
            self._fd = os.open(path, os.O_WRONLY | os.O_APPEND)
        except OSError as exc:
            raise SsgError.single(
                f"cannot write the {self.WHAT}: {exc.strerror}", str(path)
            ) from None

    def accept(self, entry: Any, lineno: int) -> None:
        """Take in one recovered entry; raise SsgError if it cannot come next."""
        raise NotImplementedError

    def damaged(self, lineno: int, why: str) -> SsgError:
        return SsgError.single(
            f"damaged {self.WHAT} (line {lineno} {why}); delete it or run without --resume",
            str(self.path),
        )

    def _recover(self, header: dict[str, Any]) -> None:
        """Check the journal's header; take its complete lines; cut off a partial last one."""
        with open(self.path, "rb") as f:
            first = f.readline()
            found = _json_line(first)
            if isinstance(found, dict) and _older(found.get("journal"), self.FORMAT):
                raise SsgError.single(
                    f"this {self.WHAT} was written by an older ssgc "
                    f"({found['journal']}, now {self.FORMAT}) whose parse statuses meant "
                    "less (an uncertified tree was 'optimal', an unproven one 'infeasible'); "
                    "run without --resume to start again",
                    str(self.path),
                )
            if not isinstance(found, dict) or found.get("journal") != self.FORMAT:
                raise SsgError.single(
                    f"not a {self.WHAT} of ssgc; delete it or run without --resume",
                    str(self.path),
                )
            _check_same_run(found, header, str(self.path))
            good_bytes = len(first)
            for lineno, line in enumerate(f, start=2):
                if not line.endswith(b"\n"):
                    break  # the line a killed run was writing: ignored, then cut off
                self.accept(self._unsealed(line, lineno), lineno)
                self.entries += 1
                good_bytes += len(line)
        os.truncate(self.path, good_bytes)

    def write_entry(self, entry: dict[str, Any]) -> None:
        """Append one entry durably before the work goes on."""
        try:
            atomic.write_all(self._fd, _sealed(entry))
            os.fsync(self._fd)
        except OSError as exc:
            kept = "; its finished work is kept, --resume continues it" if self.entries else ""
            raise JournalWriteError.single(
                f"cannot write the {self.WHAT}: {exc.strerror}{kept}", str(self.path)
            ) from None
        self.entries += 1

    def _unsealed(self, line: bytes, lineno: int) -> Any:
        """The entry of a line, if its checksum holds (else the journal is damaged)."""
        entry = _json_line(line)
        if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
            raise self.damaged(lineno, "is not an entry")
        digest = entry.pop("sha256")
        if _digest(json.dumps(entry)) != digest:
            raise self.damaged(lineno, "does not match its checksum")
        return entry

    def close(self) -> None:
        os.close(self._fd)

    def delete(self) -> None:
        self.path.unlink(missing_ok=True)

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
        if exc is not None and self.entries == 0:
            self.delete()  # failed before any work was recorded (e.g. a grammar refused)


class ParseJournal(Journal):
    """The journal of one run of `ssg parse -o`: `done` scenes are finished, in input order."""

    def __init__(self, path: Path, header: dict[str, Any], resume: bool) -> None:
        self.done = 0
        super().__init__(path, header, resume)
        if self.done > header["scene_count"]:
            raise SsgError.single("the journal has more scenes than the input", str(self.path))

    def accept(self, entry: Any, lineno: int) -> None:
        if not isinstance(entry, dict) or entry.get("index") != self.done:
            raise self.damaged(lineno, f"is not the result of scene {self.done}")
        self.done += 1

    def append(self, index: int, result: dict[str, Any]) -> None:
        """Record scene `index`'s result durably before the next scene is parsed."""
        if index != self.done:
            raise ValueError(f"scenes must be journalled in order: expected {self.done}")
        self.write_entry({"index": index, "result": result})
        self.done += 1

    def results(self) -> Iterator[dict[str, Any]]:
        """The recorded results in input order, read back one line at a time."""
        with open(self.path, "rb") as f:
            f.readline()  # the header
            for lineno, line in enumerate(f, start=2):
                yield self._unsealed(line, lineno)["result"]

    def __enter__(self) -> ParseJournal:
        return self


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()


def _sealed(entry: dict[str, Any]) -> bytes:
    """One journal line: the entry's JSON with the SHA-256 of that JSON as its last key.

    Reading the line back and dumping it without that key gives the same text (Python's JSON
    round-trips every value), so the checksum can be verified."""
    text = json.dumps(entry)
    sep = ", " if entry else ""
    return (text[:-1] + f'{sep}"sha256": "{_digest(text)}"}}\n').encode("utf-8", "surrogatepass")


def _json_line(line: bytes) -> Any:
    try:
        return json.loads(line)
    except ValueError:
        return None


def _check_same_run(found: dict[str, Any], header: dict[str, Any], file: str) -> None:
    differ = [k for k in header if k != "journal" and found.get(k) != header[k]]
    if differ:
        raise SsgError(
            [
                Diagnostic(
                    f"this journal is of another run ({k}: {json.dumps(found.get(k))}, "
                    f"now {json.dumps(header[k])}); use the same grammar, scenes and options "
                    "to resume it, or run without --resume to start again",
                    file,
                )
                for k in differ
            ]
        )


def _older(found: Any, ours: str) -> bool:
    """Whether `found` names an earlier version of the journal format `ours` ("name/N")."""
    if not isinstance(found, str) or "/" not in found:
        return False
    name, _, version = found.rpartition("/")
    our_name, _, our_version = ours.rpartition("/")
    return name == our_name and version.isdigit() and int(version) < int(our_version)


def write_parse_output(
    f: TextIO, grammar_name: str, results: Iterable[dict[str, Any]]
) -> list[dict[str, Any]]:
    """Stream `{"grammar": ..., "scenes": [...]}` into `f`, byte for byte what
    `dumps_json` makes of the whole document, one scene in memory at a time.

    Returns the name, status, phase and message of every scene without a parse (infeasible,
    no_parse or error), so
    the caller can report them without keeping all the results.
    """
    failed: list[dict[str, Any]] = []
    f.write('{\n "grammar": ' + json.dumps(grammar_name) + ',\n "scenes": [')
    count = 0
    for result in results:
        f.write(",\n  " if count else "\n  ")
        f.write(dumps_json(result).rstrip("\n").replace("\n", "\n  "))
        count += 1
        if result["status"] in FAILED:
            failed.append({k: result.get(k, "") for k in ("name", "status", "phase", "message")})
    f.write("\n ]\n}\n" if count else "]\n}\n")
    return failed
