"""A plain-data summary of a compiled grammar, for `ssg inspect` (tables or JSON)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ssgc.ir import Grammar, Kind, NodeType, Rule
from ssgc.supertree_size import supertree_size


def grammar_summary(grammar: Grammar) -> dict[str, Any]:
    return {
        "grammar": grammar.name,
        "file": grammar.file,
        "root": grammar.types[grammar.root].name,
        "root_pose": {"xyz": grammar.root_xyz.tolist(), "quat_wxyz": grammar.root_quat.tolist()},
        "types": [_type_row(grammar, t) for t in grammar.types],
        "rules": [_rule_row(grammar, r) for r in grammar.rules],
        "supertree_nodes": supertree_size(grammar),
    }


def _type_row(grammar: Grammar, t: NodeType) -> dict[str, Any]:
    return {
        "name": t.name,
        "kind": t.kind.name.lower(),
        "observed": t.observed,
        "rules": list(t.rules),
        "choice": _choice(t),
        "max_nesting": t.max_nesting,
        "model": t.model,
    }


def _choice(t: NodeType) -> str:
    if t.kind in (Kind.OR, Kind.INDEPENDENT):
        return "p = " + ", ".join(f"{p:.3g}" for p in t.probs)
    if t.kind == Kind.REPEAT and t.count is not None:
        probs = np.round(t.count.probs, 3)
        return f"count 0..{t.count.max_count}: " + ", ".join(f"{p:g}" for p in probs)
    return ""


def _rule_row(grammar: Grammar, r: Rule) -> dict[str, Any]:
    return {
        "id": r.id,
        "name": grammar.rule_name(r.id),
        "translation": r.translation.describe(),
        "rotation": r.rotation.describe(),
    }
