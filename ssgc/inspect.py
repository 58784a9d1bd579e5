"""A plain-data summary of a compiled grammar, for `ssg inspect` (tables or JSON)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ssgc.ir import Grammar, Kind, NodeType, RKind, Rule, TKind
from ssgc.supertree import supertree_size


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
        "translation": _translation(r),
        "rotation": _rotation(r),
    }


def _translation(r: Rule) -> str:
    t = r.translation
    if t.kind == TKind.FIXED:
        return "same" if not np.any(t.offset) else f"offset {np.round(t.offset, 4).tolist()}"
    name = t.kind.name.lower()
    if t.normal is not None:
        pinned = "".join("xyz"[i] for i in range(3) if not t.free[i])
        pin = f", pin {pinned}" if pinned else ""
        return (
            f"{name} mean {np.round(t.offset, 4).tolist()} "
            f"var {np.round(t.normal.variance, 5).tolist()}{pin}"
        )
    assert t.box is not None
    return f"{name} [{np.round(t.box.lo, 4).tolist()}, {np.round(t.box.hi, 4).tolist()}]"


def _rotation(r: Rule) -> str:
    rot = r.rotation
    if rot.kind == RKind.FIXED:
        return (
            "same" if rot.offset[0] >= 1 - 1e-12 else f"offset {np.round(rot.offset, 4).tolist()}"
        )
    if rot.kind == RKind.UNIFORM:
        return "uniform"
    if rot.bingham is not None:
        conc = np.round(rot.bingham.concentration, 3).tolist()
        return f"{rot.kind.name.lower()} mode {np.round(rot.bingham.mode, 3).tolist()} conc {conc}"
    assert rot.revolute is not None and rot.axis is not None
    return (
        f"revolute axis {np.round(rot.axis, 3).tolist()} "
        f"[{rot.revolute.lo:.3g}, {rot.revolute.hi:.3g}]"
    )
