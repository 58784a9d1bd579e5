"""`ssg parse` outputs read back: the one checked reader of them, for `ssg render`, `ssg view`,
`ssg export` and `ssg settle`.

A parse output (docs/parsing.md#output) lists scenes, each with its parses best first; each
parse holds a tree in the scene format's tree form (`ssgc.io.scene.TreeDoc`) and the
log-probability of each node's rule.  Its other keys (timing, model size, diagnoses) are
left alone.  A tree is checked as a scene file's tree is (`ssgc.io.scene.read_tree`), its
mistakes located at their place in the file (``scenes[k].parses[0].tree.nodes[j]...``).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict

from ssgc.errors import Diagnostic, SceneError
from ssgc.io.scene import (
    Locator,
    NodeTable,
    Scene,
    SceneName,
    TreeDoc,
    read_tree,
    scene_from_tree,
    trees_of,
    validated,
)
from ssgc.ir import Grammar


class _Loose(BaseModel):
    """Keys a reader does not need are ignored (a parse output holds many); the values it
    reads are not coerced (``"1.5"`` is not a number)."""

    model_config = ConfigDict(extra="ignore", strict=True)


class RuleScore(_Loose):
    node: int
    rule: str | None = None
    log_prob: float | None = None


class Parse(_Loose):
    score: float | None = None
    tree: TreeDoc
    rules: list[RuleScore] = []


class ParsedScene(_Loose):
    name: SceneName | None = None
    status: str = ""
    parses: list[Parse] = []


class ParseDoc(_Loose):
    scenes: list[ParsedScene]


def read_parse_doc(data: Any, text: str, file: str) -> ParseDoc:
    """A decoded parse output checked against its schema (mistakes located in `text`)."""
    return validated(ParseDoc, data, text, file)  # type: ignore[no-any-return]


def best_tree(doc: ParseDoc, k: int, grammar: Grammar | None, source: Locator) -> NodeTable | None:
    """Scene `k`'s best tree, checked (with `grammar`, also its types and rules), or None if
    the scene has no parse; raises the located mistakes."""
    parses = doc.scenes[k].parses
    if not parses:
        return None
    errors: list[Diagnostic] = []
    table = read_tree(parses[0].tree, grammar, source, errors, ("scenes", k, "parses", 0, "tree"))
    if table is None:
        raise SceneError(errors)
    return table


def parsed_scenes(doc: ParseDoc, grammar: Grammar, source: Locator, file: str) -> list[Scene]:
    """Each parsed scene's best tree as the scene of its observed nodes (what `ssg export`
    and `ssg settle` read).  A scene without a parse (infeasible, failed) is skipped."""
    scenes = []
    for k, parsed in enumerate(doc.scenes):
        table = best_tree(doc, k, grammar, source)
        if table is not None:
            tree = trees_of(table, grammar)
            scenes.append(scene_from_tree(grammar, tree, parsed.name or f"scene_{k}"))
    if not scenes:
        raise SceneError.single("the parse output holds no parsed scene", file)
    return scenes
