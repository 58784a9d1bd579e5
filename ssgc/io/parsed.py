"""`ssg parse` outputs read back: the one checked reader of them, for `ssg render`, `ssg view`,
`ssg export` and `ssg settle`.

A parse output (docs/parsing.md#output) lists scenes, each with its parses best first; each
parse holds a tree in the scene format's tree form (`ssgc.io.scene.TreeDoc`) and the
log-probability of each node's rule.  Its other keys (timing, model size, diagnoses) are
left alone.  A tree is checked as a scene file's tree is (`ssgc.io.scene.read_tree`), its
mistakes located at their place in the file (``scenes[k].parses[0].tree.nodes[j]...``).
"""

from __future__ import annotations

import json
import math
from typing import Any

from pydantic import BaseModel, ConfigDict

from ssgc.errors import Diagnostic, SceneError
from ssgc.io.scene import (
    Locator,
    NodeTable,
    Scene,
    SceneName,
    TreeDoc,
    lazy_source,
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
    """A decoded parse output checked against its schema and its scores (mistakes located in
    `text`)."""
    doc: ParseDoc = validated(ParseDoc, data, text, file)
    errors = _score_errors(doc, lazy_source(text, file))
    if errors:
        raise SceneError(errors)
    return doc


def _score_errors(doc: ParseDoc, source: Locator) -> list[Diagnostic]:
    """Each parse's score and rule log-probabilities are numbers or −∞ (a rule that could
    not have made the child, drawn in the lowest colour): JSON's reader takes `1e999` as +∞
    and `NaN` too, which no parse writes, and which would be drawn as the best rule there is
    and shown as `log p = Infinity`."""
    errors: list[Diagnostic] = []
    for k, scene in enumerate(doc.scenes):
        for j, parse in enumerate(scene.parses):
            at = ("scenes", k, "parses", j)
            if _bad_log(parse.score):
                errors.append(source.diagnostic((*at, "score"), _said(parse.score)))
            for i, rule in enumerate(parse.rules):
                if _bad_log(rule.log_prob):
                    errors.append(
                        source.diagnostic((*at, "rules", i, "log_prob"), _said(rule.log_prob))
                    )
    return errors


def _bad_log(value: float | None) -> bool:
    """A log-probability that is neither a finite number nor −∞ (+∞, NaN)."""
    return value is not None and not (math.isfinite(value) or value == -math.inf)


def _said(value: float | None) -> str:
    return (
        "a log-probability must be a finite number or -Infinity (a rule that could not have "
        f"made the child), got {json.dumps(value)}"
    )


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
