"""Shared fixtures: paths of the bundled grammars and the vendored sink dataset."""

from __future__ import annotations

from pathlib import Path

import pytest

from ssgc.compile import load_grammar
from ssgc.ir import Grammar

ROOT = Path(__file__).resolve().parent.parent
GRAMMARS = ROOT / "grammars"
SINK_DATA = ROOT / "ssgc" / "data" / "sink" / "saved_scenes.yaml"


@pytest.fixture(scope="session")
def sink() -> Grammar:
    return load_grammar(GRAMMARS / "sink.yaml")
