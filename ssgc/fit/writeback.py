"""Writing fitted numbers back into a grammar's YAML text, changing nothing else.

The user keeps editing a fitted grammar, so their comments, key order, quoting, layout and
indentation must survive and a diff should show only new numbers: the text is loaded with
ruamel.yaml's round-trip loader, numbers are set in that tree (lists element by element, so a
flow list stays one) and it is dumped with the file's own indentation.  A mapping reached
through an anchor and its aliases is one object, so its parameters are tied: `shared_nodes`
lets the fitter pool them, and two different values for one of them are an error.
"""

from __future__ import annotations

import copy
import io
import math
import re
from collections import Counter
from dataclasses import dataclass
from decimal import ROUND_DOWN, Context
from numbers import Integral, Real
from typing import Any

import numpy as np
from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.representer import RoundTripRepresenter

from ssgc.geometry import quat_to_rpy
from ssgc.laws.base import Orientation
from ssgc.yamlio import load_quietly

Loc = tuple[str | int, ...]

_FORMS = ("rpy", "rpy_deg", "quat_wxyz")  # how an orientation can be written (docs/grammar.md)
_NOISE = 1e-12  # angle / quaternion parts below this are rounding noise: written as 0.0
_DOC_START = re.compile(r"(?:[ \t]*(?:[#%].*)?\n)*---[ \t]*(?:#.*)?\n")
_DOC_END = re.compile(r"\n\.\.\.[ \t]*(?:#.*)?(?:\n[ \t]*(?:#.*)?)*\Z")


class SharedValueConflict(ValueError):
    """One YAML node (an anchor, its aliases, a `<<` merge) would get two fitted values."""


@dataclass(frozen=True)
class Update:
    """Set `values[key]` in the mapping at document path `path` (keys/indices from the root).
    A value is a float, an int, a (nested) list of floats, an `Orientation`, or a mapping of
    numbers (a tail's `{rate, mean}`: edited key by key where one is written)."""

    path: Loc
    values: dict[str, Any]


class _Rounded(float):
    """A float already rounded to the requested digits: dumped in its shortest exact form."""


class _Representer(RoundTripRepresenter):
    """ruamel's, but a fitted float is written by `_shortest`: ruamel's own `repr` can give
    `1e+16`, which YAML 1.1 readers (they want a dot) take for a string."""


def _shortest(x: float) -> str:
    """The shorter of the positional and scientific forms that read back exactly as `x`."""
    positional = np.format_float_positional(x, unique=True, trim="0")
    scientific = np.format_float_scientific(x, unique=True, trim="0")
    return positional if len(positional) <= len(scientific) else scientific


_Representer.add_representer(
    _Rounded, lambda r, x: r.represent_scalar("tag:yaml.org,2002:float", _shortest(float(x)))
)


def format_number(value: float, digits: int = 8) -> str:
    """`value` rounded to `digits` significant digits, as the YAML text `apply_updates` writes."""
    return _shortest(float(_number(value, digits, "value")))


def _number(value: Any, digits: int, where: str) -> int | _Rounded:
    """An int stays an int (a count, a max); a float is rounded; anything else is a bug."""
    if isinstance(value, bool) or not isinstance(value, Real):
        raise ValueError(f"{where}: expected a number, got {value!r}")
    if isinstance(value, Integral):
        return int(value)
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"{where}: cannot write the non-finite value {x} to YAML")
    rounded = float(f"{x:.{digits}g}")
    if math.isinf(rounded):  # 1.8e308 rounds up to inf: round down instead
        rounded = float(Context(prec=digits, rounding=ROUND_DOWN).create_decimal(x))
    return _Rounded(rounded)


def _plain(value: Any, digits: int, where: str) -> Any:
    """`value` with every number rounded, lists as lists; also what ties are compared by.
    None (say, a pinned axis's variance) means: keep what is written there."""
    if value is None:
        return None
    if isinstance(value, Orientation):
        q = np.asarray(value.quat_wxyz, dtype=float)
        if q.shape != (4,) or not 0 < np.linalg.norm(q) < np.inf:
            raise ValueError(f"{where}: not a quaternion: {value.quat_wxyz!r}")
        w, x, y, z = (float(v) for v in q / np.linalg.norm(q))
        return Orientation((w, x, y, z))
    if isinstance(value, (list, tuple)):
        return [_plain(v, digits, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):  # a small mapping of numbers, such as a tail's {rate, mean}
        return {k: _plain(v, digits, f"{where}.{k}") for k, v in value.items()}
    return _number(value, digits, where)


def _where(path: Loc, key: str | None = None) -> str:
    """`types.A.or[0].p`, to name a place in an error message."""
    parts = (*path, key) if key is not None else path
    text = "".join(f"[{s}]" if isinstance(s, int) else f".{s}" for s in parts).lstrip(".")
    return text or "the document"


def _loader(text: str) -> YAML:
    """A round-trip YAML that dumps with the file's indentation and never re-wraps lines."""
    yaml = YAML(typ="rt", pure=True)
    yaml.preserve_quotes = True
    yaml.width = 1 << 30
    yaml.brace_single_entry_mapping_in_flow_sequence = True  # keep `[{child: A}]` as it is
    yaml.Representer = _Representer
    mapping, sequence, offset = _indents(text)
    yaml.indent(mapping=mapping, sequence=sequence, offset=offset)
    return yaml


def _indents(text: str) -> tuple[int, int, int]:
    """The mapping indent, sequence indent and dash offset the file uses most (ruamel dumps
    with one of each), from each `key:` line and the next.  `load_yaml_guess_indent` takes the
    mapping indent from the first sequence: wrong for `or:` + `      - child:` (2, 4, 2)."""
    maps: Counter[int] = Counter()
    seqs: Counter[tuple[int, int]] = Counter()
    opener: int | None = None  # column of the key of a `key:` line that opens a block
    for line in text.splitlines():
        body = line.lstrip(" ")
        if not body or body.startswith("#"):
            continue
        col = len(line) - len(body)
        if opener is not None and (body == "-" or body.startswith("- ")):
            content = col + 1 + len(body[1:]) - len(body[1:].lstrip(" "))
            seqs[(content - opener, col - opener)] += 1
        elif opener is not None and col > opener:
            maps[col - opener] += 1
        stripped = re.sub(r"\s+#.*$", "", body)
        key_col = col + len(body) - len(body.lstrip("- ")) if body.startswith("- ") else col
        opener = key_col if stripped.endswith(":") else None
    mapping = maps.most_common(1)[0][0] if maps else 2
    sequence, offset = seqs.most_common(1)[0][0] if seqs else (mapping, 0)
    return mapping, max(sequence, offset + 2), offset


def _resolve(tree: Any, path: Loc, file: str) -> CommentedMap:
    """The mapping at `path`; a path that is not in the document is the caller's bug."""
    node = tree
    for depth, seg in enumerate(path):
        if isinstance(node, CommentedMap) and isinstance(seg, str) and seg in node:
            node = node[seg]
        elif isinstance(node, CommentedSeq) and type(seg) is int and 0 <= seg < len(node):
            node = node[seg]
        else:
            raise ValueError(f"{file}: {_where(path[: depth + 1])} is not in the document")
    if not isinstance(node, CommentedMap):
        raise ValueError(f"{file}: {_where(path)} is not a mapping")
    return node


def _owner(node: CommentedMap, key: str) -> CommentedMap:
    """The mapping that really holds `key`: for a key merged in with `<<`, its source."""
    if key in node and key not in dict(node.non_merged_items()):
        for _, source in node.merge:
            if key in source:
                return _owner(source, key)
    return node


def apply_updates(
    text: str, updates: list[Update], file: str = "<grammar>", digits: int = 8
) -> str:
    """The grammar text with the updates applied; everything else byte-for-byte as it was
    where possible.  A path not in the document, a non-finite number or two different values
    for one anchored node raise ValueError (the caller's bug, or a tie the fit broke)."""
    head, body, tail = _split_document(text)
    yaml = _loader(body)
    tree = load_quietly(yaml, body)
    written: dict[Any, tuple[str, Any]] = {}  # what each node got, to catch broken ties
    for update in updates:
        node = _resolve(tree, update.path, file)
        for key, value in update.values.items():
            where = f"{file}: {_where(update.path, key)}"
            owner, new = _owner(node, key), _plain(value, digits, where)
            _claim(written, owner, key, new, _where(update.path, key))
            try:
                _set(owner, key, new, digits)
            except ValueError as exc:
                raise ValueError(f"{where}: {exc}") from None
    if not isinstance(tree, (CommentedMap, CommentedSeq)):  # ruamel would add `...`
        return text
    out = io.StringIO()
    yaml.dump(tree, out)
    result = head + out.getvalue()[: None if body.endswith("\n") else -1] + tail
    return result.replace("\n", "\r\n") if "\r\n" in text else result


def _claim(
    written: dict[Any, tuple[str, Any]], owner: CommentedMap, key: str, new: Any, place: str
) -> None:
    """Record what `key` of `owner` gets: a node reached twice (an anchor and its aliases)
    cannot be written with two different values.  `place` is the document path, for messages
    (the caller names the file)."""
    old = owner.get(key)  # a list or mapping edited in place may be aliased on its own
    for slot in [(id(owner), key), *([id(old)] if isinstance(old, (dict, list)) else [])]:
        if slot in written and written[slot][1] != new:
            raise SharedValueConflict(
                f"{place} is the YAML node of {written[slot][0]} too (an anchor and its "
                "aliases, or a `<<` merge), which was fitted to a different value"
            )
        written[slot] = (place, new)


def _split_document(text: str) -> tuple[str, str, str]:
    """A `---` line with the comments and directives before it, the body, and a final `...`:
    ruamel would drop the first and last (and those comments), so they are kept verbatim."""
    start = _DOC_START.match(text)
    head = start.group(0) if start else ""
    end = _DOC_END.search(text, len(head))
    tail = end.group(0) if end else ""
    return head, text[len(head) : len(text) - len(tail)], tail


def shared_nodes(text: str, paths: list[Loc], file: str = "<grammar>") -> list[list[Loc]]:
    """Groups (two or more, in the order given) of `paths` that reach the same mapping: one
    parameter set written through an anchor and its aliases, so the fitter pools them."""
    tree = load_quietly(YAML(typ="rt", pure=True), text)
    groups: dict[int, list[Loc]] = {}
    for path in paths:
        groups.setdefault(id(_resolve(tree, path, file)), []).append(path)
    return [group for group in groups.values() if len(group) > 1]


def _set(mapping: CommentedMap, key: str, value: Any, digits: int) -> None:
    """Write `value` (rounded) at `key`: in place where a node exists, else as a new key."""
    if isinstance(value, Orientation):  # in the form (rpy, rpy_deg, quat_wxyz) used there
        holder = mapping.get(key)
        if not isinstance(holder, CommentedMap):  # none yet: a new `{rpy_deg: [...]}`
            holder = _node({})
            _set(mapping, key, holder, digits)
        if not holder:  # `mode: {}`: ruamel does not mark an empty mapping as flow
            holder.fa.set_flow_style()
        form = next((f for f in _FORMS if f in holder), "rpy_deg")
        value = _orientation_numbers(value.quat_wxyz, form, holder.get(form), digits)
        mapping, key = holder, form
    if key in mapping:
        _assign(mapping, key, value)
    elif value is not None:
        _insert(mapping, key, _node(value))


def _assign(container: Any, key: Any, value: Any) -> None:
    """Replace a value; a list of the same length is edited element by element, as a new list
    object would lose its flow/block style and its comments."""
    old = container[key]
    if value is None:
        return
    if isinstance(value, list) and isinstance(old, CommentedSeq) and len(old) == len(value):
        for i, item in enumerate(value):
            _assign(old, i, item)
    elif isinstance(value, dict) and isinstance(old, CommentedMap):  # its keys, in place
        for k, item in value.items():
            if k in old:
                _assign(old, k, item)
            else:
                _insert(old, k, _node(item))
    else:
        container[key] = _node(value)


def _node(value: Any) -> Any:
    """A new YAML value; lists and mappings in flow style, the way grammars write numbers."""
    if isinstance(value, (CommentedMap, CommentedSeq)):
        return value
    if value is None:
        raise ValueError("None (keep the value written) where no value of that shape is written")
    if isinstance(value, dict):
        node: Any = CommentedMap((k, _node(v)) for k, v in value.items())
    elif isinstance(value, list):
        node = CommentedSeq(_node(v) for v in value)
    else:
        return value
    node.fa.set_flow_style()
    return node


def _orientation_numbers(quat: Any, form: str, previous: Any, digits: int) -> list[_Rounded]:
    """The rotation's numbers in `form`, rounded like the rest, with noise written as 0."""
    q = np.asarray(quat, dtype=float)
    if form == "quat_wxyz":  # of q and -q, the one nearer the old value keeps the diff small
        old = previous if isinstance(previous, list) and len(previous) == 4 else [1, 0, 0, 0]
        values = -q if float(np.dot(q, [float(v) for v in old])) < 0 else q
    else:
        values = quat_to_rpy(q)
        values = np.degrees(values) if form == "rpy_deg" else values
    return [_Rounded(f"{0.0 if abs(v) < _NOISE else float(v):.{digits}g}") for v in values]


def _insert(mapping: CommentedMap, key: str, value: Any) -> None:
    """Add a key where a reader expects it: `p` after `child`, `mode` first, else last.  In a
    block mapping, the comment and blank lines after the previous entry introduce what follows
    it, so they move below the new line."""
    keys = [k for k, _ in mapping.non_merged_items()]
    pos = keys.index("child") + 1 if key == "p" and "child" in keys else len(keys)
    pos = 0 if key == "mode" else pos
    moved = None if pos == 0 or mapping.fa.flow_style() else _split_tail(mapping, keys[pos - 1])
    mapping.insert(pos, key, value)
    if moved is not None:
        mapping.ca.items[key] = [None, None, moved, None]


def _split_tail(mapping: CommentedMap, key: str) -> Any:
    """Cut the lines after entry `key` off its comment and return them as a new comment."""
    container, last = mapping, key
    value = container[last]
    while isinstance(value, (CommentedMap, CommentedSeq)) and value and not value.fa.flow_style():
        container = value
        last = len(value) - 1 if isinstance(value, CommentedSeq) else list(value)[-1]
        value = container[last]
    entry = container.ca.items.get(last)
    token = entry[0 if isinstance(container, CommentedSeq) else 2] if entry else None
    first, _, rest = token.value.partition("\n") if token is not None else ("", "", "")
    if not rest:  # nothing below the entry's own line
        return None
    token.value = first + "\n"
    moved = copy.copy(token)
    moved.value = "\n" + rest
    return moved
