"""Grammars whose scorer tables would not fit are refused at the type that makes them wide.

The tables hold one row per type, as wide as the widest type's rules and its longest count
law: 20,000 types under one `or` of 20,000 rules (a 957 KB file) asked for 3 GB per table and
stopped `ssg validate` with exit 70 (session-35 resources hunt).  The limit is lowered here so
that small grammars show the rule."""

from __future__ import annotations

import pytest

import ssgc.compile as compile_module
from ssgc.compile import compile_text
from ssgc.errors import GrammarError


def wide_or(n: int) -> str:
    rules = "".join(f"      - {{child: T{i}}}\n" for i in range(n))
    kinds = "".join(f"  T{i}: {{observed: true}}\n" for i in range(n))
    return f"grammar: wide\nroot: Root\ntypes:\n  Root:\n    or:\n{rules}{kinds}"


def long_count(n: int) -> str:
    probs = ", ".join(["0"] * n + ["1"])
    return (
        "grammar: long\nroot: Root\ntypes:\n  Root:\n    repeat:\n"
        f"      count: {{probs: [{probs}]}}\n      rule: {{child: T}}\n  T: {{observed: true}}\n"
    )


def test_a_type_too_wide_for_the_tables_is_one_located_error(monkeypatch):
    monkeypatch.setattr(compile_module, "MAX_TABLE_CELLS", 40 * 41 - 1)
    with pytest.raises(GrammarError) as info:
        compile_text(wide_or(40), "wide.yaml")
    (error,) = info.value.diagnostics
    assert (error.line, error.column) == (4, 3)
    assert "type 'Root' has 40 rules and the grammar 41 types" in error.message
    monkeypatch.setattr(compile_module, "MAX_TABLE_CELLS", 40 * 41)
    assert len(compile_text(wide_or(40), "wide.yaml").types) == 41


def test_a_count_law_too_long_for_the_tables_is_refused(monkeypatch):
    monkeypatch.setattr(compile_module, "MAX_TABLE_CELLS", 2 * 301 - 1)
    with pytest.raises(GrammarError, match="type 'Root' has 301 counts and the grammar 2 types"):
        compile_text(long_count(300), "long.yaml")
