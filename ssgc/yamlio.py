"""Reading YAML (and JSON, a subset of it) so that every value keeps its line and column.

The round-trip loader of ruamel.yaml keeps positions and comments; `load_located` turns its tree
into plain Python data for pydantic and keeps the tree in a `SourceMap`, so an error found
anywhere downstream (pydantic, the compiler) can be reported as ``file:line:col``.  The same tree
is what `ssg fit` will edit to write fitted numbers back with the user's comments kept.

Loading is safe: no tags, no object construction, a size limit and a limit on the number of
values (which also defuses alias bombs).
"""

from __future__ import annotations

import datetime
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError
from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.error import MarkedYAMLError, YAMLError
from ruamel.yaml.nodes import MappingNode, ScalarNode, SequenceNode
from ruamel.yaml.reader import ReaderError
from ruamel.yaml.scalarbool import ScalarBoolean

from ssgc.errors import Diagnostic, SsgError

MAX_GRAMMAR_BYTES = 4 * 1024 * 1024
MAX_VALUES = 2_000_000

Loc = tuple[str | int, ...]


@dataclass(frozen=True)
class SourceMap:
    """Maps a path of keys/indices in a loaded document back to its position in the file."""

    file: str
    tree: Any

    def walk(
        self, loc: Iterable[Any]
    ) -> tuple[list[Any], Any, tuple[int, int], tuple[int, int]]:
        """Follow `loc` into the document as far as it exists.

        Returns the segments found, the node reached, and the 0-based positions of its value
        and of its key (the same for a list item or the document itself).  Segments that are not
        keys of the document (pydantic's union tags, a missing key) are skipped, so a pydantic
        error location can be passed as it is.
        """
        node = self.tree
        lc = getattr(node, "lc", None)
        pos = (lc.line, lc.col) if lc is not None and lc.line is not None else (0, 0)
        key_pos, found = pos, []
        for seg in loc:
            if isinstance(node, CommentedMap) and isinstance(seg, str) and seg in node:
                if node.lc.data and seg in node.lc.data:  # not so for keys merged with `<<`
                    key_pos, pos = node.lc.key(seg), node.lc.value(seg)
            elif isinstance(node, CommentedSeq) and isinstance(seg, int) and 0 <= seg < len(node):
                key_pos = pos = node.lc.item(seg)
            else:
                continue
            node = node[seg]
            found.append(seg)
        return found, node, pos, key_pos

    def locate(self, loc: Iterable[Any]) -> tuple[int, int]:
        """1-based (line, col) of the deepest value along `loc` that exists in the file.

        A mapping, list or empty value is reported at its key: a block collection starts on
        the next line (at its first child, which is not what is wrong) and an empty value has no
        position of its own.
        """
        _, node, pos, key_pos = self.walk(loc)
        if node is None or isinstance(node, (CommentedMap, CommentedSeq)):
            pos = key_pos
        return pos[0] + 1, pos[1] + 1

    def locate_key(self, loc: Iterable[Any], key: Any) -> tuple[int, int]:
        """Position of `key` itself inside the mapping at `loc` (for unknown-key errors)."""
        node = self.walk(loc)[1]
        if isinstance(node, CommentedMap) and key in node and node.lc.data and key in node.lc.data:
            line, col = node.lc.key(key)
            return line + 1, col + 1
        return self.locate(loc)

    def diagnostic(self, loc: Iterable[Any], message: str, severity: str = "error") -> Diagnostic:
        line, col = self.locate(loc)
        return Diagnostic(message, self.file, line, col, severity)  # type: ignore[arg-type]


def read_text(path: Path, limit: int, what: str) -> str:
    """Read a UTF-8 text file with a size limit and a clear message for every failure."""
    name = str(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise SsgError.single(f"{what} not found", name) from None
    except OSError as exc:
        raise SsgError.single(f"cannot read {what}: {exc.strerror}", name) from None
    if path.is_dir():
        raise SsgError.single(f"expected a {what} file, got a directory", name)
    if size > limit:
        raise SsgError.single(
            f"{what} is {size / 1e6:.1f} MB, over the {limit / 1e6:.1f} MB limit", name
        )
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SsgError.single(f"cannot read {what}: {exc.strerror}", name) from None
    if b"\x00" in data:
        line, col = _byte_position(data, data.index(b"\x00"))
        raise SsgError.single(f"{what} is not a text file (it contains NUL bytes)", name, line, col)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        start = exc.start + (3 if data.startswith(b"\xef\xbb\xbf") else 0)
        line, col = _byte_position(data, start)
        raise SsgError.single(
            f"{what} is not valid UTF-8 (byte {start}: {exc.reason})", name, line, col
        ) from None


def _byte_position(data: bytes, index: int) -> tuple[int, int]:
    """1-based line and column of byte `index`, so an editor can jump to a bad byte."""
    line_start = data.rfind(b"\n", 0, index) + 1
    return data.count(b"\n", 0, index) + 1, index - line_start + 1


def load_located(text: str, file: str) -> tuple[Any, SourceMap]:
    """Parse YAML/JSON text into plain data plus a `SourceMap` of the round-trip tree."""
    yaml = YAML(typ="rt", pure=True)
    yaml.allow_duplicate_keys = False
    try:
        tree = yaml.load(text)
    except MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = (exc.problem or exc.context or "invalid YAML").strip()
        if "duplicate key" in problem or "found duplicate key" in str(exc):
            problem = _duplicate_key_message(exc)
        line, col = (mark.line + 1, mark.column + 1) if mark else (None, None)
        raise SsgError.single(f"invalid YAML: {problem}", file, line, col) from None
    except YAMLError as exc:
        raise SsgError.single(f"invalid YAML: {str(exc).splitlines()[0]}", file) from None
    except RecursionError:
        raise SsgError.single("invalid YAML: nested too deeply", file) from None
    source = SourceMap(file, tree)
    return _Plain(source).convert(tree, ()), source


def _duplicate_key_message(exc: MarkedYAMLError) -> str:
    text = str(exc.problem or "")
    return text.split("\n")[0] if text else "duplicate key"


class _Plain:
    """Converts the ruamel tree to plain dict/list/str/int/float/bool/None, refusing the rest."""

    def __init__(self, source: SourceMap) -> None:
        self.source = source
        self.budget = MAX_VALUES

    def fail(self, loc: Loc, message: str) -> SsgError:
        return SsgError([self.source.diagnostic(loc, message)])

    def convert(self, node: Any, loc: Loc) -> Any:
        self.budget -= 1
        if self.budget < 0:
            raise self.fail(loc, f"document has more than {MAX_VALUES} values (alias bomb?)")
        if len(loc) > 200:
            raise self.fail(loc, "document is nested more than 200 levels deep")
        tag = getattr(getattr(node, "tag", None), "value", None)
        if tag is not None and not str(tag).startswith("tag:yaml.org,2002:"):
            raise self.fail(loc, f"YAML tags are not allowed here (found {tag})")
        if isinstance(node, CommentedMap):
            out = {}
            for key, value in node.items():
                if not isinstance(key, str):
                    raise self.fail(loc, f"mapping keys must be strings, got {key!r}")
                out[str(key)] = self.convert(value, (*loc, key))
            return out
        if isinstance(node, CommentedSeq):
            return [self.convert(v, (*loc, i)) for i, v in enumerate(node)]
        if node is None or isinstance(node, (bool, ScalarBoolean)):
            return None if node is None else bool(node)
        if isinstance(node, int):
            return int(node)
        if isinstance(node, float):
            return float(node)
        if isinstance(node, str):
            return str(node)
        if isinstance(node, (datetime.date, datetime.datetime)):
            raise self.fail(loc, f"dates are not allowed here (got {node}); quote it if it is text")
        raise self.fail(loc, f"unsupported YAML value of type {type(node).__name__}")


def validation_diagnostics(exc: ValidationError, source: SourceMap) -> list[Diagnostic]:
    """Turn pydantic errors into located diagnostics, one per place, the most useful first.

    When a value fails every member of a union, pydantic reports one error per member; those
    that only say "wrong type" are dropped when a more specific error exists at the same place.
    """
    by_place: dict[tuple[int, int], list[dict[str, Any]]] = {}
    for err in exc.errors(include_url=False):
        loc = tuple(err["loc"])
        if err["type"] == "unknown_key":
            place = source.locate_key(loc, err["ctx"]["key"])
        else:
            place = source.locate(loc)
        by_place.setdefault(place, []).append(err)
    diagnostics = []
    for (line, col), errs in by_place.items():
        specific = [e for e in errs if not e["type"].endswith("_type")] or errs
        seen = set()
        for err in specific:
            text = _describe(err)
            if text not in seen:
                seen.add(text)
                diagnostics.append(Diagnostic(text, source.file, line, col))
    return diagnostics


def _describe(err: dict[str, Any]) -> str:
    segments: list[str] = []
    for seg in err["loc"]:
        if isinstance(seg, int):
            segments.append(f"[{seg}]")
        elif "[" not in seg and "-" not in seg and (not segments or segments[-1] != seg):
            segments.append(seg)  # skip pydantic's internal and repeated union-tag segments
    path = ".".join(segments).replace(".[", "[")
    msg = err["msg"]
    if err["type"] == "missing":
        msg = "missing required key"
    elif err["type"].startswith("value_error"):
        msg = msg.removeprefix("Value error, ")
    return f"{path}: {msg}" if path else msg
