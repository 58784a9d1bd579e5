"""A plain-data summary of a compiled grammar, for `ssg inspect` (tables or JSON)."""

from __future__ import annotations

from typing import Any

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
        # what the `observation` section added this type for (docs/grammar.md 9), else None
        "synthetic": t.synthetic or None,
    }


def _choice(t: NodeType) -> str:
    if t.kind in (Kind.OR, Kind.INDEPENDENT):
        return "p = " + ", ".join(format_prob(float(p)) for p in t.probs)
    if t.kind == Kind.REPEAT and t.count is not None:
        probs = t.count.probs
        return f"count 0..{t.count.max_count}: " + ", ".join(format_prob(float(p)) for p in probs)
    return ""


def format_prob(p: float, digits: int = 3) -> str:
    """A probability with `digits` significant digits, more if fewer would print one strictly
    between 0 and 1 as "1" (0.999 at 2 digits) or "0": only a rule that always (never) fires
    reads "1" ("0").  Beyond 8 digits it prints ">0.99999999"."""
    if not 0.0 < p < 1.0:
        return f"{p:.{digits}g}"
    for d in range(digits, 9):
        text = f"{p:.{d}g}"
        if 0.0 < float(text) < 1.0:
            return text
    return ">0.99999999"


def _rule_row(grammar: Grammar, r: Rule) -> dict[str, Any]:
    return {
        "id": r.id,
        "name": grammar.rule_name(r.id),
        "translation": r.translation.describe(),
        "rotation": r.rotation.describe(),
    }
