"""The JSON of `ssg parse` and `ssg explain` for each scene, and the run that writes a parse
output through its journal.

A parse result alone does not say everything a user needs: a scene proven infeasible gets the
diagnosis of the objects and rules that rule it out (`ssgc.explain.diagnose`), a parse under a
grammar with clutter names the objects left unexplained, and `--explain` adds the explanation.
These documents are built here, once, for the commands and the Python API alike; the commands
only print and exit.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ssgc.explain import diagnose, explain_tree, reparse_budget, unexplained_objects
from ssgc.io.journal import ParseJournal, journal_path, run_header, write_parse_output
from ssgc.io.outputs import Output, write_output
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.parse.parser import Parser, SceneParses, result_to_json

DIAGNOSE_S = 20.0  # seconds (at most) to find the objects that rule out an infeasible scene
TEXT_LIMIT = 10  # objects and rules `ssg explain`'s text lists (a line counts the rest)

Note = Callable[[str], None]  # a line for the user (stderr), e.g. "only 1 distinct tree exists"
Step = Callable[[int], None]  # scenes just finished, for a progress bar


def parse_document(
    parser: Parser,
    scene: Scene,
    result: SceneParses,
    top: int = 1,
    explain: bool = False,
    time_limit: float | None = None,
    note: Note | None = None,
) -> dict[str, Any]:
    """`ssg parse`'s JSON of one scene: the parses, the diagnosis of a scene proven infeasible
    (its message names the objects and rules that rule it out), the objects each parse leaves
    to clutter (`observation: clutter`), and the explanation when asked; `note` hears that
    fewer than `top` distinct trees exist."""
    g = parser.grammar
    row = result_to_json(g, result)
    if result.status == "infeasible":
        d = diagnose(g, scene, parser, time_limit=min(time_limit or DIAGNOSE_S, DIAGNOSE_S))
        row["message"] = d.message
        row["diagnosis"] = d.to_json()
    elif result.parses:
        if g.observation is not None and g.observation.clutter is not None:
            for parse, p in zip(row["parses"], result.parses, strict=True):
                parse["unexplained"] = unexplained_objects(g, scene, p.tree)
        if explain:
            budget = reparse_budget(time_limit, result.timing["total_s"])
            e = explain_tree(g, scene, result.parses[0].tree, parser, budget)
            row["explanation"] = e.to_json()
        if len(result.parses) < top and note is not None:
            note(f"{scene.name}: {result.message}")
    return row


def explain_document(
    grammar: Grammar, parser: Parser, scene: Scene, time_limit: float | None = None
) -> tuple[dict[str, Any], str]:
    """`ssg explain`'s JSON of one scene and its text: the explanation, the diagnosis of a
    scene proven infeasible (`diagnose` runs only then), or, for no_parse, the step that gave
    up."""
    result = parser.parse(scene, top=1, time_limit=time_limit)
    if result.parses:
        budget = reparse_budget(time_limit, result.timing["total_s"])
        best = result.parses[0]
        e = explain_tree(grammar, scene, best.tree, parser, budget)
        e.status = result.status
        e.gap = float(best.gap) if np.isfinite(best.gap) else None
        return e.to_json(), e.text(TEXT_LIMIT)
    if result.status == "infeasible":
        d = diagnose(grammar, scene, parser, time_limit=time_limit or DIAGNOSE_S)
        return {"scene": scene.name, "status": "infeasible", "diagnosis": d.to_json()}, d.message
    row = {"scene": scene.name, "status": result.status}  # no_parse (not proven) or error
    return row | ({"phase": result.phase} if result.phase else {}), result.message


def parse_to_output(
    dest: Output,
    grammar_file: Path,
    scenes_file: Path,
    parser: Parser,
    scenes: Sequence[Scene],
    top: int = 1,
    time_limit: float | None = None,
    explain: bool = False,
    resume: bool = False,
    step: Step | None = None,
    note: Note | None = None,
) -> list[dict[str, Any]]:
    """Parse every scene into `dest`; returns the scenes without a parse (name, status,
    message).  A file output is journalled scene by scene (`--resume` continues it) and
    written whole, atomically, at the end; a stream (stdout, a device) gets the document once
    every scene is parsed.  `note` also hears that an old journal is being replaced."""
    g, step = parser.grammar, step or (lambda k: None)

    def document(scene: Scene) -> dict[str, Any]:
        result = parser.parse(scene, top=top, time_limit=time_limit)
        return parse_document(parser, scene, result, top, explain, time_limit, note)

    if dest.stream:  # nothing to resume: the results are kept in memory
        results = []
        for scene in scenes:
            results.append(document(scene))
            step(1)
        with write_output(dest) as f:
            return write_parse_output(f, g.name, results)
    method = parser.method
    header = run_header(g.name, grammar_file, scenes_file, scenes, top, method, time_limit, explain)
    with ParseJournal(journal_path(dest.target), header, resume) as journal:
        if journal.discarded and note is not None:
            note(
                f"note: starting again; the journal {journal.path} of an interrupted run is "
                "replaced (--resume continues it)"
            )
        step(journal.done)
        for index in range(journal.done, len(scenes)):
            journal.append(index, document(scenes[index]))
            step(1)
        with write_output(dest, kept=journal.path) as f:
            failed = write_parse_output(f, g.name, journal.results())
    journal.delete()
    return failed
