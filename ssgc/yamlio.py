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
import difflib
import math
import re
import warnings
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError
from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq, TaggedScalar
from ruamel.yaml.error import MarkedYAMLError, ReusedAnchorWarning, YAMLError
from ruamel.yaml.events import AliasEvent
from ruamel.yaml.nodes import MappingNode, ScalarNode, SequenceNode
from ruamel.yaml.reader import ReaderError
from ruamel.yaml.scalarbool import ScalarBoolean

from ssgc.errors import Diagnostic, SsgError

MAX_GRAMMAR_BYTES = 4 * 1024 * 1024
MAX_VALUES = 2_000_000
MAX_DEPTH = 200
_PLAIN_TAGS = {
    f"tag:yaml.org,2002:{t}" for t in ("map", "seq", "str", "int", "float", "bool", "null")
}

Loc = tuple[str | int, ...]
_SURROGATE = re.compile("[\ud800-\udfff]")


@dataclass(frozen=True)
class SourceMap:
    """Maps a path of keys/indices in a loaded document back to its position in the file."""

    file: str
    tree: Any
    notes: tuple[Diagnostic, ...] = ()  # the loader's warnings (an anchor defined twice)

    def walk(self, loc: Iterable[Any]) -> tuple[list[Any], Any, tuple[int, int], tuple[int, int]]:
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


def _looks_utf16(data: bytes) -> bool:
    """A UTF-16 byte-order mark, or ASCII text stored as UTF-16 (every other byte NUL): its
    NUL bytes would otherwise make it "not a text file"."""
    head = data[:512]
    if head.startswith((b"\xff\xfe", b"\xfe\xff")):
        return True
    even, odd = head[0::2].strip(b"\0"), head[1::2].strip(b"\0")
    return len(head) >= 2 and bool(even) != bool(odd)  # all NUL bytes is not text at all


def read_text(path: Path, limit: int, what: str) -> str:
    """Read a UTF-8 text file with a size limit and a clear message for every failure.  The
    size of a regular file is checked before reading; a device, a FIFO or a pipe (`<(...)`)
    has none, so at most one byte past the limit is read (`/dev/zero` never ends)."""
    name = str(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        dangling = " (a symbolic link to a missing file)" if path.is_symlink() else ""
        raise SsgError.single(f"{what} not found{dangling}", name) from None
    except OSError as exc:
        raise SsgError.single(f"cannot read {what}: {exc.strerror}", name) from None
    if path.is_dir():
        raise SsgError.single(f"expected a {what}, got a directory", name)
    if size > limit:
        raise SsgError.single(f"{what} is {size:,} bytes, over the limit of {_bytes(limit)}", name)
    try:
        with path.open("rb") as stream:
            data = stream.read(limit + 1)
    except OSError as exc:
        raise SsgError.single(f"cannot read {what}: {exc.strerror}", name) from None
    if len(data) > limit:
        raise SsgError.single(
            f"{what} is more than {limit:,} bytes, over the limit of {_bytes(limit)}", name
        )
    if _looks_utf16(data):
        raise SsgError.single(
            f"{what} looks like UTF-16 text (a UTF-16 byte-order mark or every other byte "
            "NUL); ssgc reads UTF-8: save it as UTF-8",
            name,
        )
    if b"\x00" in data:
        line, col = _position(data, data.index(b"\x00"))
        raise SsgError.single(f"{what} is not a text file (it contains NUL bytes)", name, line, col)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        start = exc.start + (3 if data.startswith(b"\xef\xbb\xbf") else 0)
        line, col = _position(data, start)
        raise SsgError.single(
            f"{what} is not valid UTF-8 (byte {start}: {exc.reason})", name, line, col
        ) from None


def _bytes(n: int) -> str:
    """`n` bytes exactly, and in MiB when that is round: a size just over a limit rounded
    to one decimal read as equal to it ("4.2 MB, over the 4.2 MB limit")."""
    mib = f" ({n // 2**20} MiB)" if n % 2**20 == 0 else ""
    return f"{n:,} bytes{mib}"


def _position(data: str | bytes, index: int) -> tuple[int, int]:
    """1-based line and column of character (or byte) `index`, so an editor can jump to it."""
    newline = b"\n" if isinstance(data, bytes) else "\n"
    line_start = data.rfind(newline, 0, index) + 1  # type: ignore[arg-type]
    return data.count(newline, 0, index) + 1, index - line_start + 1  # type: ignore[arg-type]


def load_located(text: str, file: str) -> tuple[Any, SourceMap]:
    """Parse YAML/JSON text into plain data plus a `SourceMap` of the round-trip tree."""
    _refuse_deep_flow(text, file)
    yaml = YAML(typ="rt", pure=True)
    yaml.allow_duplicate_keys = False
    try:
        tree = load_quietly(yaml, text)
    except MarkedYAMLError as exc:
        raise SsgError([_syntax_diagnostic(exc, file)]) from None
    except ReaderError as exc:  # a control character: ruamel gives its offset, not a mark
        line, col = _position(text, exc.position)
        char = exc.character
        shown = f"#x{char:04x}" if isinstance(char, int) else repr(char)
        raise SsgError.single(
            f"invalid YAML: unacceptable character {shown} ({exc.reason})", file, line, col
        ) from None
    except YAMLError as exc:
        raise SsgError.single(f"invalid YAML: {str(exc).splitlines()[0]}", file) from None
    except RecursionError:
        where = _deepest_line(text)
        raise SsgError.single("invalid YAML: nested too deeply", file, *where) from None
    except (ValueError, KeyError, TypeError, OverflowError):
        # ruamel constructs some values without catching their errors (`2024-13-45`,
        # `!!int abc`, `!!bool maybe`, a key that is a mapping holding a list): find the node
        # that fails, for its position.
        raise SsgError([_unreadable_value(text, file)]) from None
    source = SourceMap(file, tree, _reused_anchors(text, file) if "&" in text else ())
    plain = _Plain(source)
    plain.refuse_bomb(tree)
    return plain.convert(tree, ()), source


# What hides a bracket from the flow-depth count: quoted scalars and comments.
_HIDES_BRACKETS = re.compile(
    r""""(?:[^"\\]|\\.)*"?"""  # a double-quoted scalar, escapes included
    r"|'(?:[^']|'')*'?"  # a single-quoted scalar ('' is a quote)
    r"|(?:^|(?<=\s))#[^\n]*",  # a comment
    re.M,
)


def _refuse_deep_flow(text: str, file: str) -> None:
    """Refuse flow collections (`[[[`, `{a: {a:`) nested deeper than `MAX_DEPTH`, before
    ruamel reads them: its scanner does work proportional to the open depth for every token, so
    2,000 open brackets took it 5 s to refuse (a RecursionError).  The count skips quoted
    scalars and comments (blanked, so positions stay); brackets inside plain or block scalars
    count too, which can only refuse a document with more than `MAX_DEPTH` of them unclosed,
    never pass a deep one.  One array pass: a 4 MiB file of brackets takes a fraction of a
    second."""
    if text.count("[") + text.count("{") <= MAX_DEPTH:
        return
    bare = _HIDES_BRACKETS.sub(lambda m: " " * len(m.group()), text)
    chars = np.frombuffer(bare.encode("utf-32-le"), dtype=np.uint32)  # one code point each
    opens = (chars == ord("[")) | (chars == ord("{"))
    closes = (chars == ord("]")) | (chars == ord("}"))
    walk = np.cumsum(opens.astype(np.int32) - closes)
    depth = walk - np.minimum.accumulate(np.minimum(walk, 0))  # a stray closer resets to 0
    deepest = np.flatnonzero(depth > MAX_DEPTH)
    if deepest.size:
        message = f"document is nested more than {MAX_DEPTH} levels deep"
        raise SsgError.single(message, file, *_position(text, int(deepest[0])))


def _deepest_line(text: str) -> tuple[int, int] | tuple[()]:
    """Where block nesting goes deepest (the first most-indented line and its first
    character): what a RecursionError of the reader points at, which has no mark of its own.
    Nothing when no line is indented (nesting on one line, `- - - - ...`)."""
    lines = text.split("\n")
    indents = [len(line) - len(line.lstrip(" ")) if line.strip() else -1 for line in lines]
    deepest = max(indents, default=-1)
    if deepest <= 0:
        return ()
    k = indents.index(deepest)
    return k + 1, deepest + 1


def load_quietly(yaml: YAML, text: str) -> Any:
    """`yaml.load(text)` without ruamel's warning about an anchor defined twice, which it
    prints as its own text (its source file, '<unicode string>'); `_reused_anchors` says it
    in ssg's words where a user should hear it."""
    with _anchors_quiet():
        return yaml.load(text)


@contextmanager
def _anchors_quiet() -> Iterator[None]:
    """Silence ruamel's ReusedAnchorWarning for whatever composes the text inside."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReusedAnchorWarning)
        yield


def _reused_anchors(text: str, file: str) -> tuple[Diagnostic, ...]:
    """A warning where an anchor is defined again: YAML allows it, and every later alias then
    means the new value, which in a grammar is most often a copied line left unrenamed."""
    first: dict[str, tuple[int, int]] = {}
    found = []
    for event in YAML(typ="rt", pure=True).parse(text):
        name = getattr(event, "anchor", None)
        if name is None or isinstance(event, AliasEvent):  # `*p` names the anchor it uses
            continue
        at = (event.start_mark.line + 1, event.start_mark.column + 1)
        if name in first:
            line, col = first[name]
            message = (
                f"anchor &{name} is defined again (first at line {line}, column {col}); "
                f"the aliases *{name} after this point mean this value"
            )
            found.append(Diagnostic(message, file, *at, severity="warning"))
        first[name] = at
    return tuple(found)


def _syntax_diagnostic(exc: MarkedYAMLError, file: str) -> Diagnostic:
    """A YAML syntax error, located where it is most useful, with a hint for common causes.

    ruamel reports an unclosed quote or bracket at the end of the file; the place where it was
    opened (the "context" mark) is where the user has to look.
    """
    problem = (exc.problem or exc.context or "invalid YAML").strip()
    if "duplicate key" in problem or "found duplicate key" in str(exc):
        problem = _duplicate_key_message(exc)
    mark, ctx = exc.problem_mark or exc.context_mark, exc.context_mark
    at_end = "end of stream" in problem or "<stream end>" in problem
    if ctx is not None and exc.context and (at_end or mark is None):
        mark, problem = ctx, f"{problem} {exc.context.strip()} that starts here (unclosed?)"
    elif ctx is not None and exc.context and ctx is not mark:
        problem += f" ({exc.context.strip()} at line {ctx.line + 1}, column {ctx.column + 1})"
    if "'\\t'" in problem:
        problem += "; indent with spaces, YAML does not allow tabs"
    elif "cannot start any token" in problem:
        problem += "; quote the value if it is text"
    elif "<block end>" in problem or "mapping values are not allowed" in problem:
        problem += "; check the indentation (and quote values that contain ': ')"
    line, col = (mark.line + 1, mark.column + 1) if mark else (None, None)
    return Diagnostic(f"invalid YAML: {problem}", file, line, col)


def _unreadable_value(text: str, file: str) -> Diagnostic:
    """Locate the first collection key or scalar of `text` that ruamel cannot construct."""
    yaml = YAML(typ="rt", pure=True)
    try:
        with _anchors_quiet():  # the loader said it already, in ssg's words
            stack = [yaml.compose(text)]
    except (YAMLError, ValueError, KeyError, TypeError, OverflowError, RecursionError):
        stack = []  # the failure was not in construction after all
    while stack:
        node = stack.pop()
        if isinstance(node, MappingNode):
            for key, _ in node.value:
                if not isinstance(key, ScalarNode):  # may be unhashable: never constructed
                    mark = key.start_mark
                    return Diagnostic(
                        "mapping keys must be strings, got a collection",
                        file,
                        mark.line + 1,
                        mark.column + 1,
                    )
            stack += [x for pair in reversed(node.value) for x in reversed(pair)]
        elif isinstance(node, SequenceNode):
            stack += reversed(node.value)
        elif isinstance(node, ScalarNode):
            try:
                yaml.constructor.construct_object(node, deep=True)
            except (ValueError, KeyError, TypeError, OverflowError) as exc:
                tag = str(node.tag).replace("tag:yaml.org,2002:", "!!")
                why = f" ({_short(str(exc), 80)})" if isinstance(exc, ValueError) else ""
                if "integer string conversion" in why:  # Python's guard against slow ints
                    why = " (an integer of more than 4300 digits)"
                mark = node.start_mark
                return Diagnostic(
                    f"invalid YAML: cannot read '{_short(str(node.value), 40)}' as {tag}{why}",
                    file,
                    mark.line + 1,
                    mark.column + 1,
                )
    return Diagnostic("invalid YAML: a value cannot be read", file)


def _short(text: str, limit: int) -> str:
    """`text` cut to `limit` characters, so a quoted value cannot flood a message."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _duplicate_key_message(exc: MarkedYAMLError) -> str:
    """ruamel's first line without the values it quotes, which can be whole mappings."""
    text = str(exc.problem or "")
    return text.split("\n")[0].split(" with value ")[0] if text else "duplicate key"


class _Plain:
    """Converts the ruamel tree to plain dict/list/str/int/float/bool/None, refusing the rest."""

    def __init__(self, source: SourceMap) -> None:
        self.source = source
        self.budget = MAX_VALUES

    def fail(self, loc: Loc, message: str) -> SsgError:
        return SsgError([self.source.diagnostic(loc, message)])

    def text(self, value: str, loc: Loc, key: Any = None) -> str:
        """A string (the value at `loc`, or its `key`) with escaped UTF-16 surrogate pairs
        (``"\\ud83d\\ude00"``, which ruamel keeps as two characters) joined; a lone
        surrogate is not text and is refused."""
        if not _SURROGATE.search(value):
            return value
        try:
            return value.encode("utf-16", "surrogatepass").decode("utf-16")
        except UnicodeDecodeError:
            message = "a string holds a lone UTF-16 surrogate escape (\\ud800-\\udfff)"
            if key is None:
                raise self.fail(loc, message) from None
            line, col = self.source.locate_key(loc, key)
            raise SsgError.single(message, self.source.file, line, col) from None

    def refuse_bomb(self, tree: Any) -> None:
        """Refuse a document whose aliases expand past `MAX_VALUES` before expanding any.

        An alias is the same Python object as its anchor, so the expanded size of every
        collection is counted once and reused: a bomb of a hundred anchors is measured in a
        hundred steps, where `convert` would copy two million values (15 s) to find it.  The
        error is placed where `convert` would place it: the value at which the count passes
        the limit, found by stepping over whole collections that fit.
        """
        sizes: dict[int, int] = {}
        if _expanded_size(tree, sizes, set(), 0) <= MAX_VALUES:
            return
        node, loc, left = tree, (), MAX_VALUES
        while True:  # into the first child that does not fit in what is left
            left -= 1
            if left < 0 or not isinstance(node, (CommentedMap, CommentedSeq)):
                raise self.fail(loc, f"document has more than {MAX_VALUES} values (alias bomb?)")
            pairs = node.items() if isinstance(node, CommentedMap) else enumerate(node)
            for key, child in pairs:
                size = sizes.get(id(child), 1)
                if size > left:
                    node, loc = child, (*loc, key)
                    break
                left -= size

    def convert(self, node: Any, loc: Loc) -> Any:
        self.budget -= 1
        if self.budget < 0:
            raise self.fail(loc, f"document has more than {MAX_VALUES} values (alias bomb?)")
        if len(loc) > MAX_DEPTH:
            raise self.fail(loc, f"document is nested more than {MAX_DEPTH} levels deep")
        tag = getattr(getattr(node, "tag", None), "value", None)
        if isinstance(node, TaggedScalar) and tag == "tag:yaml.org,2002:str":
            return self.text(str(node.value), loc)  # `!!str 2024-01-01`: quoting with a tag
        if tag is not None and tag not in _PLAIN_TAGS:  # `!!python/object:...` keeps its tag
            shown = str(tag).replace("tag:yaml.org,2002:", "!!")
            raise self.fail(loc, f"YAML tags are not allowed here (found {shown})")
        if isinstance(node, CommentedMap):
            out = {}
            for key, value in node.items():
                if not isinstance(key, str):
                    line, col = self.source.locate_key(loc, key)
                    raise SsgError.single(
                        f"mapping keys must be strings, got {key!r}; quote it",
                        self.source.file,
                        line,
                        col,
                    )
                out[self.text(str(key), loc, key)] = self.convert(value, (*loc, key))
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
            return self.text(str(node), loc)
        if isinstance(node, (datetime.date, datetime.datetime)):
            raise self.fail(loc, f"dates are not allowed here (got {node}); quote it if it is text")
        what = {"bytes": "binary data (!!binary)", "CommentedSet": "a set (!!set)"}
        name = type(node).__name__
        raise self.fail(loc, f"unsupported YAML value: {what.get(name, name)}")


def _expanded_size(node: Any, sizes: dict[int, int], open_: set[int], depth: int) -> int:
    """How many values `node` holds once its aliases are expanded, memoised in `sizes` by
    object.  A collection that holds itself counts once (`convert` reports its depth), and the
    walk stops below `MAX_DEPTH`, where `convert` stops too."""
    if not isinstance(node, (CommentedMap, CommentedSeq)):
        return 1
    key = id(node)
    if key in sizes:
        return sizes[key]
    if key in open_ or depth > MAX_DEPTH:
        return 1
    open_.add(key)
    children = [v for _, v in node.items()] if isinstance(node, CommentedMap) else node
    size = 1 + sum(_expanded_size(c, sizes, open_, depth + 1) for c in children)
    open_.discard(key)
    sizes[key] = size
    return size


def validation_diagnostics(
    exc: ValidationError, source: SourceMap, said: set[tuple[Any, ...]] | None = None
) -> list[Diagnostic]:
    """Turn pydantic errors into located diagnostics, one per place, the most useful first.

    When a value fails every member of a union, pydantic reports one error per member.  One
    that only says "wrong type" is dropped when another member got further (an error at the
    same place or inside the value); when all of them say "wrong type", they become a single
    "expected a number or a list, got '0.5'".

    A part shared through a YAML alias (`*r`) is validated at each use, under a different
    path but at one place: its mistake is said once, with the first path (docs/grammar.md
    section 6), not once per use (34 uses filled the message cap).  `said` holds the
    mistakes already said (place, the path's steps past it — a missing key's name — and the
    message without its path), for a caller that validates again.
    """
    said = set() if said is None else said
    entries: list[tuple[tuple[Any, ...], tuple[int, int], dict[str, Any]]] = []
    for err in exc.errors(include_url=False):
        loc, kind, value = tuple(err["loc"]), err["type"], err.get("input")
        found = source.walk(loc)[0]
        path = tuple(found) if found or not loc else _tag_free(loc)
        if kind == "missing" and (not path or path[-1] != loc[-1]):
            path = (*path, loc[-1])
        if kind == "unknown_key":
            place = source.locate_key(loc, err["ctx"]["key"])
        elif kind == "invalid_choice" and isinstance(value, dict) and len(value) == 1:
            place = source.locate_key(loc, next(iter(value)))  # the unknown variant's name
        elif len(loc) >= 2 and loc[-1] == "[key]":  # a mapping key is invalid (a type name)
            place, path = source.locate_key(loc[:-2], loc[-2]), path[:-1]
        else:
            place = source.locate(loc)
        entries.append((path, place, err))

    def wrong_type(err: dict[str, Any]) -> bool:
        return bool(err["type"].endswith("_type"))

    specific = [(p, e) for p, _, e in entries if not wrong_type(e)]
    by_place: dict[tuple[tuple[Any, ...], tuple[int, int]], list[dict[str, Any]]] = {}
    for path, place, err in entries:
        if wrong_type(err) and any(q[: len(path)] == path for q, _ in specific):
            continue
        by_place.setdefault((path, place), []).append(err)
    diagnostics, seen = [], set()
    for (path, (line, col)), errs in by_place.items():
        texts = [_describe(e, path) for e in errs if not wrong_type(e)]
        if any(wrong_type(e) for e in errs):
            texts.append(_expected([e for e in errs if wrong_type(e)], path))
        for text in texts:
            beyond = tuple(path[len(source.walk(path)[0]) :])
            mistake = (line, col, beyond, text.removeprefix(_with_path(path, "")))
            if text not in seen and mistake not in said:
                seen.add(text)
                said.add(mistake)
                diagnostics.append(Diagnostic(text, source.file, line, col))
    return diagnostics


_TYPE_WORDS = {
    "float_type": "a number",
    "int_type": "an integer",
    "string_type": "a string",
    "bool_type": "true or false",
    "list_type": "a list",
    "dict_type": "a mapping",
    "model_type": "a mapping",
}


def _tag_free(loc: tuple[Any, ...]) -> tuple[Any, ...]:
    """`loc` without pydantic's internal and repeated union-tag segments (no document to ask)."""
    out: list[Any] = []
    for seg in loc:
        if isinstance(seg, int):
            out.append(seg)
        elif "[" not in seg and "-" not in seg and (not out or out[-1] != seg):
            out.append(seg)
    return tuple(out)


def _with_path(path: tuple[Any, ...], msg: str) -> str:
    where = "".join(f"[{s}]" if isinstance(s, int) else f".{s}" for s in path).lstrip(".")
    return f"{where}: {msg}" if where else msg


def _show(value: Any) -> str:
    """A user's value as it would be written in YAML, shortened."""
    if value is None:
        return "nothing (an empty value)"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _describe(err: dict[str, Any], path: tuple[Any, ...]) -> str:
    kind, msg, value = err["type"], err["msg"], err.get("input")
    if kind == "missing":
        msg = "missing required key"
    elif kind.startswith("value_error"):
        msg = msg.removeprefix("Value error, ")
    elif kind == "invalid_choice":
        msg += _choice_hint(value, msg.rpartition("one of ")[2].split(", "))  # see dsl._choice
    elif kind != "unknown_key":
        for theirs, ours in (
            ("Input should be", "must be"),
            ("String should", "must"),
            ("List should", "must"),
            ("Dictionary should", "must"),
            (" after validation, not", ", got"),
        ):
            msg = msg.replace(theirs, ours)
        if value is None or isinstance(value, (str, int, float)):
            msg += f", got {_show(value)}"
    return _with_path(path, msg)


def _expected(errs: list[dict[str, Any]], path: tuple[Any, ...]) -> str:
    """One message for a value that has the wrong type for every member of a union."""
    words = list(dict.fromkeys(_TYPE_WORDS.get(e["type"], e["msg"]) for e in errs))
    value = errs[0].get("input")
    msg = f"expected {' or '.join(words)}, got {_show(value)}"
    if isinstance(value, str) and _is_number(value):
        msg += " (write numbers without quotes)"
    return _with_path(path, msg)


def _is_number(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _choice_hint(value: Any, choices: list[str]) -> str:
    """What was given instead of one of `choices`, and the closest choice if any."""
    if isinstance(value, dict) and len(value) != 1:
        keys = ", ".join(str(k) for k in value)
        return (
            f"; got {len(value)} keys ({keys}), give exactly one"
            if value
            else ("; got an empty mapping")
        )
    name = next(iter(value)) if isinstance(value, dict) else value
    if not isinstance(name, str):
        return f"; got {_show(value)}"
    close = difflib.get_close_matches(name, choices, n=1)
    return f"; got '{name}'" + (f" (did you mean '{close[0]}'?)" if close else "")
