"""Grammars a test writes as YAML text, loaded from a file as a user's grammar is."""

from __future__ import annotations

from pathlib import Path

import ssgc


def grammar_from_text(tmp_path: Path, text: str) -> ssgc.Grammar:
    """The grammar of `text`, written to tmp_path/g.yaml and loaded from there: through
    `ssgc.load_grammar`, as users load theirs, rather than compiled from the string."""
    path = tmp_path / "g.yaml"
    path.write_text(text)
    return ssgc.load_grammar(path)
