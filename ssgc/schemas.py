"""JSON Schemas of the file formats, generated from the pydantic models.

Editors use them to complete and check YAML (`# yaml-language-server: $schema=...`).  The
committed copies in schemas/ are checked against these by the test suite.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ssgc.dsl import GrammarDoc
from ssgc.io.scene import SceneDoc

SCHEMA_FILES = {"grammar.schema.json": GrammarDoc, "scene.schema.json": SceneDoc}


def schema_text(model: Any) -> str:
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        **model.model_json_schema(by_alias=True),
    }
    return json.dumps(schema, indent=2, sort_keys=True) + "\n"


def write_schemas(directory: str | Path) -> list[Path]:
    from ssgc.io.atomic import write_text_atomic

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, model in SCHEMA_FILES.items():
        path = directory / name
        write_text_atomic(path, schema_text(model))
        paths.append(path)
    return paths
