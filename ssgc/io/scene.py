"""Scenes on disk: the ssgc JSON scene format, and the sink dataset's YAML format.

A scene is the set of observed objects, each with a grammar type and a pose.  The JSON format
(docs/scenes.md, schemas/scene.schema.json)::

    {"objects": [{"type": "MugColeHardwareClassicBlue",
                  "pose": {"xyz": [0.5, 0.1, 0.2], "quat_wxyz": [1, 0, 0, 0]}}],
     "name": "...", "metadata": {...},          # optional
     "tree": {"nodes": [...]}, "log_prob": -4.2} # written by `ssg sample`

`rpy` (Drake roll-pitch-yaw, radians) is accepted instead of `quat_wxyz` on input.  A sampled
scene carries its whole tree, so it can be re-scored; every node names its parent's rule by its
index in the parent's rule list.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Protocol

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from ssgc.dsl import Finite, Position, Strict, Vec3, Vec4
from ssgc.errors import Diagnostic, SceneError, SsgError, one_line
from ssgc.geometry import QUAT_NORM_TOL, quat_canonical, rpy_to_quat
from ssgc.ir import Grammar, HoldsGrammar, as_ir
from ssgc.tree import Trees
from ssgc.yamlio import SourceMap, load_located, read_text, validation_diagnostics

MAX_SCENE_BYTES = 256 * 1024 * 1024
FORMAT = "ssgc.scene/1"


# ------------------------------------------------------------------ file schema ---


class ScenePose(Strict):
    xyz: Position
    quat_wxyz: Vec4 | None = None
    rpy: Vec3 | None = Field(None, description="Roll-pitch-yaw (rad), R = Rz(y) Ry(p) Rx(r).")

    @model_validator(mode="after")
    def _one_rotation(self) -> ScenePose:
        if self.quat_wxyz is not None and self.rpy is not None:
            raise ValueError("give the rotation one way only, got quat_wxyz and rpy")
        return self


class SceneObject(Strict):
    type: Annotated[str, Field(min_length=1)]
    pose: ScenePose
    metadata: dict[str, Any] = Field(default_factory=dict)


class TreeNode(Strict):
    id: Annotated[int, Field(ge=0)]
    type: Annotated[str, Field(min_length=1)]
    parent: Annotated[int, Field(ge=0)] | None = None
    rule: Annotated[int, Field(ge=0)] | None = Field(
        None, description="Index of the producing rule in the parent type's rule list."
    )
    observed: bool | None = None
    pose: ScenePose


class TreeDoc(Strict):
    nodes: list[TreeNode]


# A scene's name is in every message about it: one of 100,000 characters printed 200 KB of
# one line for each scene without a parse.
MAX_NAME = 1000


def name_problem(name: str) -> str | None:
    """Why `name` cannot name a scene: names go into one-line messages and output files."""
    if one_line(name) != name:
        return f"a scene name must be one line of printable text, got '{shown(one_line(name))}'"
    if len(name) > MAX_NAME:
        return (
            f"a scene name is at most {MAX_NAME:,} characters (it is in every message about "
            f"the scene), got {len(name):,}: '{shown(name)}'"
        )
    return None


def _printable(name: str) -> str:
    problem = name_problem(name)
    if problem:
        raise ValueError(problem)
    return name


SceneName = Annotated[str, AfterValidator(_printable)]  # in scene files and parse results


class SceneDoc(Strict):
    """One scene: observed objects, optionally the tree that produced them."""

    format: str | None = Field(None, description=f"'{FORMAT}'")
    name: SceneName | None = None
    grammar: str | None = None
    seed: int | None = None
    index: int | None = None
    log_prob: Finite | None = None
    objects: list[SceneObject]
    metadata: dict[str, Any] = Field(default_factory=dict)
    tree: TreeDoc | None = None


# ---------------------------------------------------------------- in memory ---


@dataclass(frozen=True)
class Scene:
    """Observed objects with grammar type ids and poses, as arrays."""

    name: str
    types: NDArray[np.int64]
    xyz: NDArray[np.float64]
    quat: NDArray[np.float64]
    metadata: tuple[dict[str, Any], ...] = ()
    tree: Trees | None = None
    log_prob: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    # the `seed` and `index` of a file `ssg sample` wrote: kept so that the API can save the
    # scene again as a file `--resume` accepts (the commands write their own, or none)
    run: tuple[int, int] | None = None

    def __len__(self) -> int:
        return int(self.types.shape[0])


def scene_from_tree(
    grammar: Grammar, tree: Trees, name: str, log_prob: float | None = None
) -> Scene:
    """The observed nodes of a single tree, in node order."""
    obs = grammar.tables.type_observed[tree.type]
    return Scene(
        name,
        tree.type[obs].copy(),
        tree.xyz[obs].copy(),
        tree.quat[obs].copy(),
        tree=tree,
        log_prob=log_prob,
    )


def _poses_json(
    xyz: NDArray[np.float64], quat: NDArray[np.float64]
) -> list[dict[str, list[float]]]:
    """Each row's pose as a file holds it; the signs of all quaternions chosen at once (one
    call per pose was a sixth of the time `ssg sample` spends writing a scene)."""
    xyz_rows = np.asarray(xyz, float).reshape(-1, 3).tolist()
    quat_rows = quat_canonical(np.asarray(quat, float).reshape(-1, 4)).tolist()
    return [{"xyz": x, "quat_wxyz": q} for x, q in zip(xyz_rows, quat_rows, strict=True)]


def scene_to_json(grammar: Grammar, scene: Scene, **header: Any) -> dict[str, Any]:
    """The JSON document of a scene (and its tree, when it has one).  The `metadata` the
    scene was read with, its own and its objects', is written back as it was (a `metadata`
    in `header` adds to the scene's).  The document is the caller's: the metadata is copied,
    so that editing the document cannot change the scene."""
    out: dict[str, Any] = {"format": FORMAT, "name": scene.name, "grammar": grammar.name}
    metadata = copy.deepcopy({**scene.extra, **(header.pop("metadata", None) or {})})
    out.update({k: v for k, v in header.items() if v is not None})
    if metadata:
        out["metadata"] = metadata
    if scene.log_prob is not None:
        out["log_prob"] = float(scene.log_prob)
    kept = copy.deepcopy(scene.metadata) or ({},) * len(scene)
    out["objects"] = [
        {"type": grammar.types[t].name, "pose": p, **({"metadata": m} if m else {})}
        for t, p, m in zip(scene.types, _poses_json(scene.xyz, scene.quat), kept, strict=True)
    ]
    if scene.tree is not None:
        out["tree"] = tree_to_json(grammar, scene.tree)
    return out


# A JSON string literal, or a list of numbers (a list that starts with one and holds no string,
# list or object).  Strings are matched first so that text inside them that looks like a list
# ("mug[1,   2]") is passed over, never rewritten.  The string pattern is unrolled (runs of
# plain characters, then one escape): one alternative per character took 3.3 s on 20 MB.
_STRING_OR_NUMBER_LIST = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"|\[\s*(-?[0-9][^\[\]{}"]*?)\s*\]')


def tree_to_json(grammar: Grammar, tree: Trees) -> dict[str, Any]:
    """A single tree as {"nodes": [...]}: parents first, rules named by their index in the
    parent type's rule list."""
    tb = grammar.tables
    poses = _poses_json(tree.xyz, tree.quat)
    return {
        "nodes": [
            {
                "id": i,
                "type": grammar.types[tree.type[i]].name,
                "parent": int(tree.parent[i]) if tree.parent[i] >= 0 else None,
                "rule": int(tb.rule_index[tree.rule[i]]) if tree.rule[i] >= 0 else None,
                "observed": bool(tb.type_observed[tree.type[i]]),
                "pose": poses[i],
            }
            for i in range(len(tree))
        ]
    }


MAX_STEM = 100  # characters: a stem, its suffix and a temporary file's name fit in 255 bytes


def scene_stem(name: str) -> str:
    """A grammar's or a scene's name as a file-name stem: never a path, never hidden, never
    longer than MAX_STEM (a long name is cut and ends in a hash of the whole name, so two
    long names that share their start still name two files)."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).lstrip(".") or "scene"
    if len(stem) > MAX_STEM:
        digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:12]
        stem = f"{stem[: MAX_STEM - 13]}-{digest}"
    return stem


def distinct_stems(names: list[str], suffix: str, source: str | None = None) -> list[str]:
    """Each scene name's file stem (`scene_stem`), checked before anything is written: two
    names with one stem ('a b', 'a/b') would write one file, the second scene silently
    replacing the first, so that is the user's mistake, said about `source`."""
    seen: dict[str, str] = {}
    for name in names:
        stem = scene_stem(name)
        if stem in seen:
            first = seen[stem]
            both = f"scenes '{first}' and '{name}'" if first != name else f"two scenes '{name}'"
            raise SsgError.single(
                f"{both} would both be written to {stem}{suffix}; rename one", source
            )
        seen[stem] = name
    return list(seen)


def dumps_json(doc: Any) -> str:
    """Indented JSON with number lists (poses) kept on one line, for readable files.  The
    lists are found in the serialised text, skipping its string literals: a name or a
    metadata value is written exactly as it was read."""
    return _STRING_OR_NUMBER_LIST.sub(_one_line_list, json.dumps(doc, indent=1)) + "\n"


def _one_line_list(match: re.Match[str]) -> str:
    """A number list on one line; a string literal as it is."""
    if match[1] is None:
        return match[0]
    return "[" + ", ".join(v.strip() for v in match[1].split(",")) + "]"


def dumps_scene(grammar: Grammar, scene: Scene, **header: Any) -> str:
    return dumps_json(scene_to_json(grammar, scene, **header))


# ------------------------------------------------------------------ reading ---


def shown(name: str, limit: int = 60) -> str:
    """A user's name as a message quotes it: a long one cut, so that a 100,000-character
    type name cannot flood the terminal (the file and position say which it is)."""
    return name if len(name) <= limit else name[:limit] + "…"


def read_scene_text(path: Path, what: str = "scene file") -> str:
    """A scene file's text (`read_text`: UTF-8, a UTF-16 file said to be that)."""
    return read_text(path, MAX_SCENE_BYTES, what)


def read_scene_file(path: str | Path, grammar: Grammar | HoldsGrammar) -> Scene:
    """Read one JSON scene; every mistake becomes a located `SceneError`.  `grammar` is either
    form a user holds (`as_ir`): docs/scenes.md names these readers for notebooks."""
    grammar = as_ir(grammar)
    path = Path(path)
    text = read_scene_text(path)
    # a file's name is not checked as a scene's "name" is: it gets its odd characters escaped
    return parse_scene_text(text, str(path), grammar, default_name=one_line(path.stem))


def parse_scene_text(text: str, file: str, grammar: Grammar, default_name: str = "scene") -> Scene:
    data = loads_json(text, file)
    if is_parse_result(data):
        said = EXPLAIN_RESULT_IS_NO_SCENE if is_explain_result(data) else PARSE_RESULT_IS_NO_SCENE
        raise _json_error(text, file, said, ("scenes",))
    doc = validated(SceneDoc, data, text, file)
    return _scene_from_doc(doc, grammar, _LazySource(text, file), default_name)


PARSE_RESULT_IS_NO_SCENE = (
    "this is an `ssg parse` output, not a scene: `ssg parse`, `explain` and `fit` read "
    "scenes; `ssg render`, `view`, `export` and `settle` read parse outputs"
)


EXPLAIN_RESULT_IS_NO_SCENE = (
    "this is an `ssg explain --json` output, not a scene: `ssg parse`, `explain` and `fit` "
    "read scenes, such as the files `ssg sample` writes"
)


def is_explain_result(data: Any) -> bool:
    """An `ssg explain --json` output: a parse output's shape (`is_parse_result`) whose
    scenes are explanations (`neg_log_prob`, which no parse entry has)."""
    scenes = data.get("scenes") if isinstance(data, dict) else None
    if not isinstance(scenes, list):
        return False
    return any(isinstance(s, dict) and "neg_log_prob" in s for s in scenes)


def is_parse_result(data: Any) -> bool:
    """An `ssg parse` output: `scenes` and no `objects` of its own.  Only the top-level keys
    decide: a diagnosis or an explanation in it holds `objects` too."""
    return isinstance(data, dict) and "scenes" in data and "objects" not in data


def loads_json(text: str, file: str, invalid: str = "invalid JSON") -> Any:
    """Decode a JSON input strictly: a duplicate key (which `json` resolves by keeping the
    last) and a lone surrogate escape are mistakes, located; `invalid` starts the message
    of text that is not JSON at all."""
    try:
        data = json.loads(text, object_pairs_hook=_no_duplicate_keys)
    except _DuplicateKey as exc:
        raise _json_error(text, file, f"invalid JSON: duplicate key '{shown(exc.key)}'") from None
    except (json.JSONDecodeError, RecursionError) as exc:
        line, col = (
            (exc.lineno, exc.colno) if isinstance(exc, json.JSONDecodeError) else (None, None)
        )
        message = exc.msg if isinstance(exc, json.JSONDecodeError) else "nested too deeply"
        raise SceneError.single(f"{invalid}: {message}", file, line, col) from None
    except ValueError:  # an integer of more than 4300 digits (Python's own limit)
        raise _json_error(text, file, "invalid JSON: an integer of more than 4300 digits") from None
    if _SURROGATE_ESCAPE.search(text) and not _is_unicode(data):  # such as "\ud800"
        raise _json_error(text, file, "a string holds a lone UTF-16 surrogate escape")
    return data


def validated(model: Any, data: Any, text: str, file: str) -> Any:
    """`data` as `model`, or the located mistakes.  Positions are computed only now: the
    fast path keeps large datasets fast."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        _, source = _located(text, file)
        raise SceneError(validation_diagnostics(exc, source)) from None


_SURROGATE_ESCAPE = re.compile(r"\\u[dD][89a-fA-F]")


def _is_unicode(data: Any) -> bool:
    """False if the decoded JSON holds a lone surrogate (JSON joins pairs, not lone ones):
    such a string cannot be printed or written as UTF-8."""
    try:
        json.dumps(data, ensure_ascii=False).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


class _DuplicateKey(ValueError):
    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def _json_error(text: str, file: str, message: str, key: tuple[str, ...] = ()) -> SceneError:
    """A mistake that `json` finds without its position (a duplicate key, a huge integer, a
    lone surrogate), located where the YAML reader, which keeps positions, finds it: JSON is
    YAML, so the first problem it reports is this one.  With `key`, a top-level key of a
    document that reads: the mistake is located at it."""
    try:
        _, source = load_located(text, file)
    except SsgError as exc:
        first = exc.diagnostics[0]
        return SceneError.single(message, file, first.line, first.column)
    if key:
        return SceneError.single(message, file, *source.locate_key((), key[0]))
    return SceneError.single(message, file)


def _located(text: str, file: str) -> tuple[Any, SourceMap]:
    try:
        return load_located(text, file)
    except SsgError as exc:
        raise SceneError(exc.diagnostics) from None


class Locator(Protocol):
    def diagnostic(self, loc: tuple[Any, ...], message: str) -> Diagnostic: ...


class _LazySource:
    """Positions for semantic errors, computed only if there is an error to report."""

    def __init__(self, text: str, file: str) -> None:
        self.text, self.file = text, file
        self._map: SourceMap | None = None

    def diagnostic(self, loc: tuple[Any, ...], message: str) -> Diagnostic:
        if self._map is None:
            self._map = _located(self.text, self.file)[1]
        return self._map.diagnostic(loc, message)


def lazy_source(text: str, file: str) -> Locator:
    """Where the mistakes in `text` are, found only when there is one to report."""
    return _LazySource(text, file)


def _pose_arrays(
    pose: ScenePose, loc: tuple[Any, ...], source: Locator, errors: list[Diagnostic]
) -> tuple[list[float], NDArray[np.float64]]:
    if pose.rpy is not None:
        return pose.xyz, rpy_to_quat(np.asarray(pose.rpy, float))
    if pose.quat_wxyz is None:
        return pose.xyz, np.array([1.0, 0, 0, 0])
    q = np.asarray(pose.quat_wxyz, float)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        errors.append(
            source.diagnostic(
                (*loc, "quat_wxyz"), f"quaternion must have unit norm, got norm {norm:.6g}"
            )
        )
        return pose.xyz, np.array([1.0, 0, 0, 0])
    return pose.xyz, q / norm


def _finite_metadata(
    metadata: dict[str, Any], loc: tuple[Any, ...], source: Locator, errors: list[Diagnostic]
) -> None:
    """Metadata is kept and written back as JSON, which has no NaN or infinity (`json`
    reads them, and would write them as bare `NaN`, which no JSON reader takes).  The walk
    is a loop: metadata as deep as the decoder allows must not overflow the stack."""
    stack: list[tuple[tuple[Any, ...], Any]] = [(loc, metadata)]
    while stack:
        at, value = stack.pop()
        if isinstance(value, float) and not math.isfinite(value):
            message = (
                "metadata must hold finite numbers (JSON has no NaN or Infinity), "
                f"got {json.dumps(value)}"
            )
            errors.append(source.diagnostic(at, message))
            return
        if isinstance(value, dict):
            stack += [((*at, k), v) for k, v in reversed(value.items())]
        elif isinstance(value, list):
            stack += [((*at, i), v) for i, v in reversed(list(enumerate(value)))]


@dataclass(frozen=True)
class NodeTable:
    """A tree as its file lists it, checked: ids 0..n-1 in order, parents listed before
    their children, `parent` and `rule` given together, unit quaternions; with a grammar,
    also each type and each rule index.  Rendering needs no grammar; parsing does
    (`trees_of`)."""

    types: tuple[str, ...]
    parent: NDArray[np.int64]  # -1 at a root
    rule: NDArray[np.int64]  # index in the parent type's rule list, -1 at a root
    xyz: NDArray[np.float64]
    quat: NDArray[np.float64]
    observed: tuple[bool | None, ...]  # as the file says (None: it does not say)

    def observed_mask(self, grammar: Grammar | None) -> NDArray[np.bool_] | None:
        """Which nodes are objects: the grammar's word, else the file's (None if unsaid)."""
        if grammar is not None:
            return np.array([grammar.types[grammar.type_ids[t]].observed for t in self.types])
        if any(o is None for o in self.observed):
            return None
        return np.array(self.observed, bool).reshape(-1)


def read_tree(
    doc: TreeDoc,
    grammar: Grammar | None,
    source: Locator,
    errors: list[Diagnostic],
    at: tuple[Any, ...] = ("tree",),
) -> NodeTable | None:
    """The checked tree (`NodeTable`) at `at` in the file, or None with its mistakes added
    to `errors`."""
    n = len(doc.nodes)
    xyz, quat = np.zeros((n, 3)), np.zeros((n, 4))
    typed = np.zeros(n, bool)
    start = len(errors)
    for i, node in enumerate(doc.nodes):
        loc = (*at, "nodes", i)
        problem = _node_problem(doc, i, grammar, typed)
        if problem is not None:
            if problem[1]:
                errors.append(source.diagnostic((*loc, *problem[0]), problem[1]))
            continue
        xyz[i], quat[i] = _pose_arrays(node.pose, (*loc, "pose"), source, errors)
    if len(errors) > start:
        return None
    return NodeTable(
        types=tuple(nd.type for nd in doc.nodes),
        parent=np.array([-1 if nd.parent is None else nd.parent for nd in doc.nodes], np.int64),
        rule=np.array([-1 if nd.rule is None else nd.rule for nd in doc.nodes], np.int64),
        xyz=xyz,
        quat=quat,
        observed=tuple(nd.observed for nd in doc.nodes),
    )


def _node_problem(
    doc: TreeDoc, i: int, grammar: Grammar | None, typed: NDArray[np.bool_]
) -> tuple[tuple[str, ...], str] | None:
    """What is wrong with node `i` (where in it, and the message), or None.  A node whose id
    or type is wrong has no type to check its children's rules against: its own error is the
    one to report, and a child's is an empty message (skipped, not reported)."""
    node, n = doc.nodes[i], len(doc.nodes)
    if node.id != i:
        return ("id",), f"node ids must be 0..{n - 1} in order"
    if grammar is not None and node.type not in grammar.type_ids:
        name = shown(node.type)
        return (
            "type",
        ), f"node {i} has unknown type '{name}', not a type in grammar '{grammar.name}'"
    typed[i] = True
    if (node.parent is None) != (node.rule is None):
        return (), "give both `parent` and `rule`, or neither"
    if node.parent is None or node.rule is None:
        return None
    if node.parent >= i:
        return ("parent",), "a node's parent must be listed before it"
    if not typed[node.parent]:
        return (), ""
    if grammar is None:
        return None
    up = grammar.types[grammar.type_ids[doc.nodes[node.parent].type]]
    if node.rule >= len(up.rules):
        return ("rule",), f"type '{up.name}' has {len(up.rules)} rule(s), no rule {node.rule}"
    return None


def trees_of(table: NodeTable, grammar: Grammar) -> Trees:
    """The `Trees` of a tree read with `grammar` (`read_tree` checked its types and rules)."""
    ntype = np.array([grammar.type_ids[t] for t in table.types], np.int64).reshape(-1)
    rule = np.full(len(ntype), -1, np.int64)
    for i in np.flatnonzero(table.parent >= 0):
        rule[i] = grammar.types[ntype[table.parent[i]]].rules[table.rule[i]]
    return Trees(
        np.zeros(len(ntype), np.int64), ntype, table.parent, rule, table.xyz, table.quat, 1
    )


@dataclass(frozen=True)
class SceneRead:
    """A scene file's objects (type names, poses) and its tree, checked (`read_scene_doc`)."""

    types: tuple[str, ...]
    xyz: NDArray[np.float64]
    quat: NDArray[np.float64]
    tree: NodeTable | None


def read_scene_doc(doc: SceneDoc, grammar: Grammar | None, source: Locator) -> SceneRead:
    """Check a scene beyond its schema: unit quaternions, finite metadata, a well-formed tree
    whose observed nodes are the objects; with a grammar, also that each object is of an
    observed type and the tree's types and rules are the grammar's."""
    errors: list[Diagnostic] = []
    types, xyz, quat = _read_objects(doc, grammar, source, errors)
    _finite_metadata(doc.metadata, ("metadata",), source, errors)
    table = read_tree(doc.tree, grammar, source, errors) if doc.tree is not None else None
    if table is not None and not errors:
        _check_objects_match_tree(table, grammar, types, xyz, quat, source, errors)
    if errors:
        raise SceneError(errors)
    return SceneRead(types, xyz, quat, table)


def _read_objects(
    doc: SceneDoc, grammar: Grammar | None, source: Locator, errors: list[Diagnostic]
) -> tuple[tuple[str, ...], NDArray[np.float64], NDArray[np.float64]]:
    xyz, quat = np.zeros((len(doc.objects), 3)), np.tile([1.0, 0, 0, 0], (len(doc.objects), 1))
    for i, obj in enumerate(doc.objects):
        _finite_metadata(obj.metadata, ("objects", i, "metadata"), source, errors)
        if grammar is not None and _observed_type(grammar, obj.type) is None:
            what = "is not observed" if obj.type in grammar.type_ids else "is not a type"
            errors.append(
                source.diagnostic(
                    ("objects", i, "type"),
                    f"object {i} has type '{shown(obj.type)}', which {what} in grammar "
                    f"'{grammar.name}'",
                )
            )
            continue
        xyz[i], quat[i] = _pose_arrays(obj.pose, ("objects", i, "pose"), source, errors)
    return tuple(o.type for o in doc.objects), xyz, quat


def _observed_type(grammar: Grammar, name: str) -> int | None:
    tid = grammar.type_ids.get(name)
    return tid if tid is not None and grammar.types[tid].observed else None


def _scene_from_doc(doc: SceneDoc, grammar: Grammar, source: Locator, default_name: str) -> Scene:
    read = read_scene_doc(doc, grammar, source)
    return Scene(
        name=doc.name or default_name,
        types=np.array([grammar.type_ids[t] for t in read.types], np.int64).reshape(-1),
        xyz=read.xyz,
        quat=read.quat,
        metadata=tuple(o.metadata for o in doc.objects),
        tree=None if read.tree is None else trees_of(read.tree, grammar),
        log_prob=doc.log_prob,
        extra=dict(doc.metadata),
        run=None if doc.seed is None or doc.index is None else (doc.seed, doc.index),
    )


def _check_objects_match_tree(
    tree: NodeTable,
    grammar: Grammar | None,
    types: tuple[str, ...],
    xyz: NDArray[np.float64],
    quat: NDArray[np.float64],
    source: Locator,
    errors: list[Diagnostic],
) -> None:
    """A scene's objects are its tree's observed nodes, in node order: a file must agree.
    The message names the first object that does not, and the way out for a user who edited
    the objects of a sampled scene (to parse or explain it, the tree is not needed).  Without
    a grammar, the nodes' own `observed` say which are objects (unsaid: nothing to check)."""
    mask = tree.observed_mask(grammar)
    if mask is None:
        return
    obs = np.flatnonzero(mask)
    head = "`objects` must be the observed nodes of `tree`, in node order, with the same poses"
    way_out = "to change the objects, delete `tree` (parse and explain need only the objects)"
    if len(obs) != len(types):
        where: tuple[Any, ...] = ("objects",)
        why = f"the tree has {len(obs)} observed node(s), `objects` lists {len(types)}"
    else:
        named = np.array([tree.types[k] != t for k, t in zip(obs, types, strict=True)], bool)
        moved = ~np.all(np.isclose(tree.xyz[obs], xyz, rtol=0, atol=1e-9), axis=1)
        turned = np.abs(np.sum(tree.quat[obs] * quat, axis=1)) < 1 - 1e-9
        bad = np.flatnonzero(named.reshape(-1) | moved | turned)
        if not len(bad):
            return
        i = int(bad[0])
        where, name, node = ("objects", i), shown(types[i]), int(obs[i])
        if tree.types[node] != types[i]:
            why = f"object {i} is a {name}, its node ({node}) a {shown(tree.types[node])}"
        else:
            why = f"object {i} ({name}) is not at the pose of its node ({node})"
    errors.append(source.diagnostic(where, f"{head}: {why}; {way_out}"))


# ------------------------------------------------------------ sink dataset ---


class _SinkPose(Strict):
    xyz: Position
    rpy: Vec3


class _SinkObject(BaseModel):
    """Dataset objects carry extra keys (root_body_name, ...) that are kept out of the way."""

    model_config = ConfigDict(extra="ignore", strict=True)
    metadata: dict[str, Any] = Field(default_factory=dict)
    model_file: str | None = None
    pose: _SinkPose


def read_sink_yaml(path: str | Path, grammar: Grammar | HoldsGrammar) -> list[Scene]:
    """Read the sink dataset format: scene name → {objects, world_description.models}.

    Each object's type is found by its `model_file` (a type's `model`), else by its
    `metadata.class` (a type's `labels`).  World-description models (the bin) are scene
    objects too when the grammar has a type for them.
    """
    grammar = as_ir(grammar)
    path = Path(path)
    text = read_scene_text(path, "dataset file")
    data, source = _located(text, str(path))
    if not isinstance(data, dict):
        raise SceneError([source.diagnostic((), "expected a mapping of scene name -> scene")])
    if not data:  # like a directory without scene files: nothing to do is a mistake
        raise SceneError([source.diagnostic((), "the dataset has no scenes")])
    by_model = {t.model: t.id for t in grammar.types if t.observed and t.model}
    by_label = {label: t.id for t in grammar.types if t.observed for label in t.labels}
    scenes, errors = [], []
    for name, entry in data.items():
        objects = []
        if (problem := name_problem(name)) is not None:
            errors.append(source.diagnostic((name,), problem))
            continue
        if not isinstance(entry, dict) or not isinstance(entry.get("objects", []), list):
            errors.append(source.diagnostic((name,), "expected a mapping with a list `objects`"))
            continue
        world = entry.get("world_description") or {}
        models = (world.get("models") if isinstance(world, dict) else None) or []
        if not isinstance(world, dict) or not isinstance(models, list):
            errors.append(
                source.diagnostic(
                    (name, "world_description"), "expected a mapping with a list `models`"
                )
            )
            continue
        objects += [(("world_description", "models", i), m) for i, m in enumerate(models)]
        objects += [(("objects", i), o) for i, o in enumerate(entry.get("objects", []))]
        scene = _sink_scene(str(name), objects, by_model, by_label, source, errors)
        if scene is not None:
            scenes.append(scene)
    if errors:
        raise SceneError(errors)
    return scenes


def _sink_scene(
    name: str,
    objects: list[tuple[tuple[Any, ...], Any]],
    by_model: dict[str, int],
    by_label: dict[str, int],
    source: SourceMap,
    errors: list[Diagnostic],
) -> Scene | None:
    start = len(errors)
    types, xyz, rpy, meta = [], [], [], []
    for loc, raw in objects:
        full = (name, *loc)
        try:
            obj = _SinkObject.model_validate(raw)
        except ValidationError as exc:
            for d in validation_diagnostics(exc, source):
                line, col = source.locate(full)
                errors.append(Diagnostic(d.message, source.file, line, col))
            continue
        _finite_metadata(obj.metadata, (*full, "metadata"), source, errors)
        label = obj.metadata.get("class")
        tid = by_model.get(obj.model_file or "")
        if tid is None:
            tid = by_label.get(str(label)) if label is not None else None
        if tid is None:
            errors.append(
                source.diagnostic(
                    full,
                    f"scene '{shown(name)}': no observed type has model "
                    f"'{shown(str(obj.model_file))}' or label '{shown(str(label))}'",
                )
            )
            continue
        types.append(tid)
        xyz.append(obj.pose.xyz)
        rpy.append(obj.pose.rpy)
        meta.append({"model_file": obj.model_file, **obj.metadata})
    if len(errors) > start:
        return None
    quat = rpy_to_quat(np.asarray(rpy, float).reshape(-1, 3))
    return Scene(
        name,
        np.asarray(types, np.int64),
        np.asarray(xyz, float).reshape(-1, 3),
        np.asarray(quat).reshape(-1, 4),
        metadata=tuple(meta),
    )


def json_files(directory: Path) -> list[Path]:
    """The `*.json` files of a directory of scenes or parse results, sorted by name: regular
    files, links to them, and links to nothing.  A subdirectory named `x.json` is no scene,
    and a FIFO or a device so named would block the reader for ever, so they are skipped;
    a dangling link is kept, so that reading it says the file is missing (skipped, a
    dataset would silently lose a scene)."""
    return sorted(p for p in directory.glob("*.json") if p.is_file() or _dangling(p))


def _dangling(path: Path) -> bool:
    """A symbolic link to nothing (or to a loop of links)."""
    return path.is_symlink() and not path.exists()


def load_scenes(path: str | Path, grammar: Grammar | HoldsGrammar) -> list[Scene]:
    """A JSON scene, a directory of them, or a sink-format YAML dataset."""
    grammar = as_ir(grammar)
    path = Path(path)
    if path.is_dir():
        files = json_files(path)
        if not files:
            raise SceneError.single("no *.json scene files in this directory", str(path))
        return _read_scene_files(files, grammar)
    if path.suffix.lower() in (".yaml", ".yml"):
        return read_sink_yaml(path, grammar)
    return [read_scene_file(path, grammar)]


def _read_scene_files(files: list[Path], grammar: Grammar) -> list[Scene]:
    """Every file's scene, or one `SceneError` with every file's mistakes: a directory's
    mistakes are all said at once, as a single file's and a dataset's are (the command line
    prints the first 30 of them)."""
    scenes: list[Scene] = []
    errors: list[Diagnostic] = []
    for file in files:
        try:
            scenes.append(read_scene_file(file, grammar))
        except SsgError as exc:
            errors += exc.diagnostics
    if errors:
        raise SceneError(errors)
    return scenes
