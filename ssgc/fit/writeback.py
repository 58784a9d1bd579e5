"""Writing fitted numbers back into a grammar's YAML text, changing nothing else.

The user keeps editing a fitted grammar, so their comments, key order, quoting, layout and
indentation must survive and a diff should show only new numbers: the text is loaded with
ruamel.yaml's round-trip loader, numbers are set in that tree (lists element by element, so a
flow list stays one) and it is dumped with the file's own indentation.  A mapping reached
through an anchor and its aliases is one object, so its parameters are tied: `shared_nodes`
lets the fitter pool them, and two different values for one of them are an error.  A list or
number reached that way is one object too, so a write shows through every alias:
`shared_with_kept` finds the ones that a fit would change where it must not (the root pose, a
`fixed` law) before the fit starts.
"""

from __future__ import annotations

import copy
import io
import math
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from decimal import ROUND_DOWN, Context
from numbers import Integral, Real
from typing import Any

import numpy as np
from ruamel.yaml import YAML
from ruamel.yaml.anchor import Anchor
from ruamel.yaml.comments import CommentedMap, CommentedSeq, merge_attrib
from ruamel.yaml.representer import RoundTripRepresenter
from ruamel.yaml.scalarbool import ScalarBoolean
from ruamel.yaml.scalarstring import DoubleQuotedScalarString

from ssgc.geometry import quat_to_rpy
from ssgc.laws.base import Orientation
from ssgc.yamlio import load_quietly

Loc = tuple[str | int, ...]

_FORMS = ("rpy", "rpy_deg", "quat_wxyz")  # how an orientation can be written (docs/grammar.md)
_NOISE = 1e-12  # angle / quaternion parts below this are rounding noise: written as 0.0
# a `---` line (or `--- ` before a flow mapping or list on its line) and what comes before it
_DOC_START = re.compile(r"(?:[ \t]*(?:[#%].*)?\n)*---(?:[ \t]*(?:#.*)?\n|[ \t]+(?=[{\[]))")
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
    """A float already rounded to the requested digits: dumped in its shortest exact form.
    `anchor` is that of the number it replaced where that one was written `&name 1.0`, so the
    aliases of it stay aliases (`_relink`).  It is kept where ruamel's own numbers keep theirs,
    and read where its representer looks."""

    @property
    def anchor(self) -> Anchor | None:
        return getattr(self, Anchor.attrib, None)


class _Representer(RoundTripRepresenter):
    """ruamel's, but a fitted float is written by `_shortest`: ruamel's own `repr` can give
    `1e+16`, which YAML 1.1 readers (they want a dot) take for a string."""


def _shortest(x: float) -> str:
    """The shorter of the positional and scientific forms that read back exactly as `x`."""
    positional = np.format_float_positional(x, unique=True, trim="0")
    scientific = np.format_float_scientific(x, unique=True, trim="0")
    return positional if len(positional) <= len(scientific) else scientific


def _represent_rounded(representer: RoundTripRepresenter, x: _Rounded) -> Any:
    text = _shortest(float(x))
    return representer.represent_scalar("tag:yaml.org,2002:float", text, anchor=x.anchor)


_Representer.add_representer(_Rounded, _represent_rounded)


def format_number(value: float, digits: int = 8) -> str:
    """`value` rounded to `digits` significant digits, as the YAML text `apply_updates` writes."""
    return _shortest(float(_number(value, digits, "value")))


def _number(value: Any, digits: int, where: str) -> int | _Rounded:
    """An int stays an int (a count, a max); a float is rounded; anything else is a bug.
    A number strictly between 0 and 1 gets more digits where it would round to 1 (0.9999999996)
    or 0: a probability written as exactly 1 or 0 makes the other outcomes or this one
    impossible, which fitting must not do (docs/fitting.md 4.2)."""
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
    while 0 < x < 1 and not 0 < rounded < 1:  # 17 digits always read back as x itself
        digits += 1
        rounded = float(f"{x:.{digits}g}")
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


def _covariance_digits(value: Any, digits: int) -> int:
    """The digits a covariance needs to stay positive definite once rounded (17 read back
    exactly): a fitted covariance of spreads of metres along a line and a millimetre across
    it lost its smallest eigenvalue to 8-digit rounding, and the fitted grammar was refused.
    Pinned axes (None) are kept as written and left out of the check."""
    if not isinstance(value, list):  # None: kept as written
        return digits
    free = [i for i, row in enumerate(value) if row is not None and row[i] is not None]
    for places in range(digits, 18):
        rounded = [[float(f"{value[i][j]:.{places}g}") for j in free] for i in free]
        if not free or np.all(np.linalg.eigvalsh(np.asarray(rounded)) > 0):
            return places
    return 17


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
    """The mapping that really holds `key`: for a key merged in with `<<`, its source (the
    first that has it, as YAML says), so a merged number is written once, at the anchor."""
    if key in node and key not in dict(node.non_merged_items()):
        for source in _merge_sources(node):
            if key in source:
                return _owner(source, key)
    return node


def _merge_sources(node: CommentedMap) -> list[CommentedMap]:
    """The mappings merged into `node` with `<<`, in order.  ruamel.yaml 0.19 keeps a list of
    the mappings, older versions a list of (position, mapping) pairs; `node.merge` would add
    an empty list to a mapping without merges."""
    merged = getattr(node, merge_attrib, [])
    return [m[1] if isinstance(m, tuple) else m for m in merged]


def apply_updates(
    text: str, updates: list[Update], file: str = "<grammar>", digits: int = 8
) -> str:
    """The grammar text with the updates applied; everything else byte-for-byte as it was
    where possible.  A path not in the document, a non-finite number or two different values
    for one anchored node raise ValueError (the caller's bug, or a tie the fit broke).

    A byte-order mark and CRLF line ends are taken off before ruamel reads the text and put
    back after: a `\r` it reads stays in the comments, and would be doubled."""
    bom = "\ufeff" if text.startswith("\ufeff") else ""
    crlf = "\r\n" in text
    result = _apply(text[len(bom) :].replace("\r\n", "\n"), updates, file, digits)
    return bom + (result.replace("\n", "\r\n") if crlf else result)


def _apply(text: str, updates: list[Update], file: str, digits: int) -> str:
    """`apply_updates` on a text with `\n` line ends and no byte-order mark."""
    head, body, tail = _split_document(text)
    yaml = _loader(body)
    tree = load_quietly(yaml, body)
    written: dict[Any, tuple[str, Any]] = {}  # what each node got, to catch broken ties
    quoted = isinstance(tree, CommentedMap) and _quotes_keys(tree, False)
    for update in updates:
        node = _resolve(tree, update.path, file)
        for key, value in update.values.items():
            where = f"{file}: {_where(update.path, key)}"
            places = _covariance_digits(value, digits) if key == "covariance" else digits
            owner, new = _owner(node, key), _plain(value, places, where)
            _claim(written, owner, key, new, _where(update.path, key))
            try:
                _set(owner, key, new, digits, _quotes_keys(owner, quoted))
            except ValueError as exc:
                raise ValueError(f"{where}: {exc}") from None
    if not isinstance(tree, (CommentedMap, CommentedSeq)):  # ruamel would add `...`
        return text
    _relink(tree)
    _keep_anchors(tree)
    out = io.StringIO()
    yaml.dump(tree, out)
    return head + out.getvalue()[: None if body.endswith("\n") else -1] + tail


def _claim(
    written: dict[Any, tuple[str, Any]],
    owner: CommentedMap | CommentedSeq,
    key: Any,
    new: Any,
    place: str,
) -> None:
    """Record what `key` of `owner` gets: a node reached twice (an anchor and its aliases)
    cannot be written with two different values.  The items of a list are claimed one by one,
    as they are written: two items may be one node too (`[&w 1.0, *w]`, rows `[*r, *r]`).
    `place` is the document path, for messages (the caller names the file)."""
    old = owner.get(key) if isinstance(owner, CommentedMap) else owner[key]
    shared = isinstance(old, (dict, list)) or _anchor(old) is not None
    for slot in [(id(owner), key), *([id(old)] if shared else [])]:
        if slot in written and written[slot][1] != new:
            raise SharedValueConflict(
                f"{place} is the YAML node of {written[slot][0]} too (an anchor and its "
                "aliases, or a `<<` merge), which was fitted to a different value"
            )
        written[slot] = (place, new)
    if isinstance(new, list) and isinstance(old, CommentedSeq) and len(old) == len(new):
        for i, item in enumerate(new):
            if item is not None:  # None: kept as written
                _claim(written, old, i, item, f"{place}[{i}]")


def _anchor(value: Any) -> Anchor | None:
    """The anchor written on a number (`&v 1.0`), if any.  (Its `anchor` property would add
    an empty one.)"""
    anchor = getattr(value, Anchor.attrib, None)
    return anchor if anchor is not None and anchor.value is not None else None


def _relink(tree: Any) -> None:
    """Put a number written at an anchor (`&v 1.0`) in place of the old one at each of its
    aliases (`*v`), so they stay aliases of the new value: a tie kept, as for a list, which is
    edited in place.  `_claim` has made sure that no alias was written with another value."""
    new: dict[int, _Rounded] = {}  # id of the anchor -> the number written there
    for _, _, value in _entries(tree):
        anchor = _anchor(value)
        if anchor is not None and isinstance(value, _Rounded):
            new.setdefault(id(anchor), value)
    for container, key, value in _entries(tree):
        anchor = _anchor(value)
        if anchor is not None and id(anchor) in new and value is not new[id(anchor)]:
            container[key] = new[id(anchor)]


def _keep_anchors(tree: Any) -> None:
    """Mark every anchor on a mapping or list to be written: ruamel.yaml writes such an anchor
    only where an alias uses it, so `&law` on a law no rule aliases (yet) was deleted from the
    user's file.  (Its anchored numbers and strings are already marked when read.)"""
    for node in [tree, *(value for _, _, value in _entries(tree))]:
        anchor = _anchor(node) if isinstance(node, (CommentedMap, CommentedSeq)) else None
        if anchor is not None:
            anchor.always_dump = True


def _entries(node: Any, seen: set[int] | None = None) -> Iterator[tuple[Any, Any, Any]]:
    """(container, key, value) for every value written in the document (merged keys are
    written at their anchor), each container once."""
    seen = set() if seen is None else seen
    if id(node) in seen or not isinstance(node, (CommentedMap, CommentedSeq)):
        return
    seen.add(id(node))
    pairs = node.non_merged_items() if isinstance(node, CommentedMap) else enumerate(node)
    for key, value in list(pairs):
        yield node, key, value
        yield from _entries(value, seen)


def _split_document(text: str) -> tuple[str, str, str]:
    """A `---` line with the comments and directives before it, the body, and a final `...`:
    ruamel would drop the first and last (and those comments), so they are kept verbatim."""
    start = _DOC_START.match(text)
    head = start.group(0) if start else ""
    end = _DOC_END.search(text, len(head))
    tail = end.group(0) if end else ""
    return head, text[len(head) : len(text) - len(tail)], tail


def without_section(text: str, key: str) -> str:
    """The grammar `text` without its top-level `key`: `ssg fit` compiles it without its
    `observation` section to tell which laws that section's noise made (`ssgc.fit.em`)."""
    head, body, tail = _split_document(text.lstrip("\ufeff").replace("\r\n", "\n"))
    yaml = _loader(body)
    tree = load_quietly(yaml, body)
    if not isinstance(tree, CommentedMap) or key not in tree:
        return text
    del tree[key]
    out = io.StringIO()
    yaml.dump(tree, out)
    return head + out.getvalue() + tail


def shared_nodes(text: str, paths: list[Loc], file: str = "<grammar>") -> list[list[Loc]]:
    """Groups (two or more, in the order given) of `paths` that reach the same mapping: one
    parameter set written through an anchor and its aliases, so the fitter pools them."""
    tree = load_quietly(YAML(typ="rt", pure=True), text)
    groups: dict[int, list[Loc]] = {}
    for path in paths:
        groups.setdefault(id(_resolve(tree, path, file)), []).append(path)
    return [group for group in groups.values() if len(group) > 1]


@dataclass(frozen=True)
class KeptShare:
    """A value the fit writes (at document path `fitted`) that is one YAML node with a value it
    must keep as written (at `kept`); `line` and `column` (from 1) locate the fitted key."""

    fitted: str
    kept: str
    line: int | None
    column: int | None


def shared_with_kept(text: str, fitted: list[tuple[Loc, str]]) -> KeptShare | None:
    """The first value written at a fitted place (key `k` of the mapping at path `p`, for each
    `(p, k)` in `fitted`, and everything under it) that is also reached from a place the fit
    does not write, through an anchor and its aliases or a `<<` merge.  Writing it would change
    that place too: a list is edited in place, a number is written at its anchor (`_relink`),
    and a merged key at the mapping it comes from.  None if there is none."""
    tree = load_quietly(YAML(typ="rt", pure=True), text)
    first: dict[Any, dict[bool, tuple[Loc, CommentedMap | CommentedSeq, Any]]] = {}
    for path, is_fitted, container, key in _occurrences(tree, (), False, set(fitted)):
        for identity in _identities(container, key):
            seen = first.setdefault(identity, {})
            seen.setdefault(is_fitted, (path, container, key))
            if len(seen) == 2:
                (fitted_path, holder, name), (kept_path, _, _) = seen[True], seen[False]
                return KeptShare(_where(fitted_path), _where(kept_path), *_position(holder, name))
    return None


def _occurrences(
    node: Any, path: Loc, inside: bool, fitted: set[tuple[Loc, str]]
) -> Iterator[tuple[Loc, bool, CommentedMap | CommentedSeq, Any]]:
    """(path, whether the fit writes there, container, key) for every value in the document,
    at every path it is reached by (through aliases, and merged keys where they are merged)."""
    if isinstance(node, CommentedMap):
        for key, value in node.items():
            here = inside or (path, key) in fitted
            yield (*path, key), here, node, key
            yield from _occurrences(value, (*path, key), here, fitted)
    elif isinstance(node, CommentedSeq):
        for i, value in enumerate(node):
            yield (*path, i), inside, node, i
            yield from _occurrences(value, (*path, i), inside, fitted)


def _identities(container: CommentedMap | CommentedSeq, key: Any) -> list[Any]:
    """What a write at `container[key]` changes: that entry (of the mapping a merged key comes
    from), and the list, mapping or `&name` number there, which its aliases show too."""
    if isinstance(container, CommentedMap):
        container = _owner(container, key)
    value = container[key]
    shared = isinstance(value, (CommentedMap, CommentedSeq)) or _anchor(value) is not None
    return [(id(container), key), *([id(value)] if shared else [])]


def _position(container: CommentedMap | CommentedSeq, key: Any) -> tuple[int | None, int | None]:
    """Line and column (from 1) of `key` in `container`: a mapping's key, a list's item; the
    container's own for a merged key, which is not written there."""
    lc = container.lc
    if isinstance(container, CommentedMap) and key in lc.data:
        line, column = lc.key(key)
    elif isinstance(container, CommentedSeq) and key in lc.data:
        line, column = lc.item(key)
    else:
        line, column = lc.line, lc.col
    return (None, None) if line is None else (line + 1, column + 1)


def _set(mapping: CommentedMap, key: str, value: Any, digits: int, quoted: bool) -> None:
    """Write `value` (rounded) at `key`: in place where a node exists, else as a new key.
    `quoted`: whether keys added in a mapping without keys yet are written quoted (JSON)."""
    if isinstance(value, Orientation):  # in the form (rpy, rpy_deg, quat_wxyz) used there
        holder = mapping.get(key)
        if not isinstance(holder, CommentedMap):  # none yet: a new `{rpy_deg: [...]}`
            holder = _node({}, quoted)
            _set(mapping, key, holder, digits, quoted)
        if not holder:  # `mode: {}`: ruamel does not mark an empty mapping as flow
            holder.fa.set_flow_style()
        form = next((f for f in _FORMS if f in holder), "rpy_deg")
        value = _orientation_numbers(value.quat_wxyz, form, holder.get(form), digits)
        mapping, key = holder, form
    if key in mapping:
        _assign(mapping, key, value, quoted)
    elif value is not None:
        _insert(mapping, key, _node(value, quoted), quoted)


def _assign(container: Any, key: Any, value: Any, quoted: bool) -> None:
    """Replace a value; a list of the same length is edited element by element, as a new list
    object would lose its flow/block style and its comments.  A number equal to the one
    written keeps its text (`0` stays `0`, not `0.0`), so a diff shows only changed numbers."""
    old = container[key]
    if value is None or _same_number(old, value):
        return
    if isinstance(value, list) and isinstance(old, CommentedSeq) and len(old) == len(value):
        for i, item in enumerate(value):
            _assign(old, i, item, quoted)
    elif isinstance(value, dict) and isinstance(old, CommentedMap):  # its keys, in place
        inner = _quotes_keys(old, quoted)
        for k, item in value.items():
            if k in old:
                _assign(old, k, item, inner)
            else:
                _insert(old, k, _node(item, inner), inner)
    else:
        container[key] = _keep_anchor(_node(value, quoted), old)


def _same_number(old: Any, new: Any) -> bool:
    """Whether `new` is the number written as `old`, as the grammar reads it (`0` and `0.0`
    are one value; compared exactly as floats).  Booleans are not numbers here."""
    numbers = (old, new)
    if not all(isinstance(x, Real) and not isinstance(x, (bool, ScalarBoolean)) for x in numbers):
        return False
    return float(old) == float(new)


def _quotes_keys(mapping: CommentedMap, default: bool) -> bool:
    """Whether a key added to `mapping` is written "quoted": as all its keys are (a JSON
    grammar stays JSON), or, for a mapping without keys yet (a new `mode` or `tail`, which
    has no neighbours to copy), as `default`: what the mapping around it does."""
    keys = [k for k, _ in mapping.non_merged_items()]
    if not keys:
        return default
    return all(isinstance(k, DoubleQuotedScalarString) for k in keys)


def _keep_anchor(new: Any, old: Any) -> Any:
    """`new`, with the anchor of `old` where that was a number written `&v 1.0`: the number
    is then written there and its aliases become aliases of the new value (`_relink`)."""
    if not isinstance(new, _Rounded) or _anchor(old) is None:
        return new
    anchored = _Rounded(new)
    setattr(anchored, Anchor.attrib, _anchor(old))
    return anchored


def _node(value: Any, quoted: bool) -> Any:
    """A new YAML value; lists and mappings in flow style, the way grammars write numbers.
    `quoted`: the keys of a new mapping are written "quoted" (in a JSON grammar)."""
    if isinstance(value, (CommentedMap, CommentedSeq)):
        return value
    if value is None:
        raise ValueError("None (keep the value written) where no value of that shape is written")
    if isinstance(value, dict):
        node: Any = CommentedMap((_key(k, quoted), _node(v, quoted)) for k, v in value.items())
    elif isinstance(value, list):
        node = CommentedSeq(_node(v, quoted) for v in value)
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


def _key(key: str, quoted: bool) -> str:
    """`key` as a new key is written: "quoted" where the keys around it are (JSON)."""
    return DoubleQuotedScalarString(key) if quoted else key


def _insert(mapping: CommentedMap, key: str, value: Any, quoted: bool) -> None:
    """Add a key where a reader expects it: `p` after `child`, `mode` first, else last.  In a
    block mapping, the comment and blank lines after the previous entry introduce what follows
    it, so they move below the new line.  The key is quoted as `_quotes_keys` says (`quoted`:
    for a mapping that has no keys yet)."""
    keys = [k for k, _ in mapping.non_merged_items()]
    pos = keys.index("child") + 1 if key == "p" and "child" in keys else len(keys)
    pos = 0 if key == "mode" else pos
    moved = None if pos == 0 or mapping.fa.flow_style() else _split_tail(mapping, keys[pos - 1])
    key = _key(key, _quotes_keys(mapping, quoted))
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
