"""Before/after measurements of parsing and explaining the real sink scenes (docs/parsing.md
"The pose-instantiated model: cost and reductions", docs/explain.md "Cost").

    python tests/measure_parse_speed.py parse GRAMMAR OUT.json
    python tests/measure_parse_speed.py explain GRAMMAR OUT.json [--scenes 0:20]
    python tests/measure_parse_speed.py compare BEFORE.json AFTER.json

`parse` writes each scene's status, best score, model size and CPU seconds
(`time.process_time()`, so other jobs on the machine count little); `explain` each scene's
objects in ranked order with their `unusual` and `pose_gain`, the re-parse record and CPU
seconds.  `compare` says whether two runs agree (statuses, best scores to 1e-6; the same object
order and gains to 1e-6) and prints their CPU medians and maxima.  Run it once on main (e.g.
`PYTHONPATH=/path/to/main python tests/measure_parse_speed.py ...`) and once on a branch.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

import ssgc
from ssgc.compile import load_grammar
from ssgc.explain import explain
from ssgc.io.scene import load_scenes
from ssgc.parse.parser import Parser

DATA = Path(__file__).resolve().parent.parent / "ssgc" / "data" / "sink" / "saved_scenes.yaml"
TOL = 1e-6


def measure_parse(grammar_path: str) -> list[dict[str, Any]]:
    grammar = load_grammar(grammar_path)
    parser = Parser(grammar)
    rows = []
    for i, scene in enumerate(load_scenes(DATA, grammar)):
        c0 = time.process_time()
        result = parser.parse(scene, top=1)
        cpu = time.process_time() - c0
        best = result.parses[0] if result.parses else None
        rows.append(
            {
                "i": i,
                "status": result.status,
                "score": None if best is None else best.score,
                "cpu_s": cpu,
                "model": result.model,
            }
        )
        print(i, result.status, rows[-1]["score"], f"{cpu:.3f}", result.model, flush=True)
    return rows


def measure_explain(grammar_path: str, scenes: range) -> list[dict[str, Any]]:
    grammar = load_grammar(grammar_path)
    data = load_scenes(DATA, grammar)
    rows = []
    for i in scenes:
        c0 = time.process_time()
        doc = explain(grammar, data[i]).to_json()
        cpu = time.process_time() - c0
        objects = doc["objects"]
        rows.append(
            {
                "i": i,
                "cpu_s": cpu,
                "log_prob": doc["log_prob"],
                "order": [o["index"] for o in objects],
                "unusual": [o["unusual"] for o in objects],
                "pose_gain": [o["pose_gain"] for o in objects],
                "reparse": doc.get("reparse"),
            }
        )
        print(i, f"{cpu:.2f}", rows[-1]["order"], flush=True)
    return rows


def compare(before: list[dict[str, Any]], after: list[dict[str, Any]]) -> int:
    """Print the differences and the CPU summaries; the number of scenes that differ."""
    differ = 0
    for b, a in zip(before, after, strict=True):
        if "order" in b:
            same = b["order"] == a["order"] and np.allclose(b["unusual"], a["unusual"], atol=TOL)
        else:
            same = b["status"] == a["status"] and (
                b["score"] == a["score"] or abs(b["score"] - a["score"]) <= TOL
            )
        if not same:
            differ += 1
            print("differs:", b, a)
    for name, rows in (("before", before), ("after", after)):
        cpu = np.array([r["cpu_s"] for r in rows])
        print(
            f"{name}: CPU per scene median {np.median(cpu):.3f} s, max {cpu.max():.3f} s, "
            f"total {cpu.sum():.1f} s"
        )
    print(f"{len(after)} scenes, {differ} differ")
    return differ


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("parse", "explain", "compare"))
    ap.add_argument("first")
    ap.add_argument("second")
    ap.add_argument("--scenes", default="0:20", help="explain: scenes START:STOP")
    args = ap.parse_args()
    if args.what == "compare":
        before, after = (json.loads(Path(p).read_text()) for p in (args.first, args.second))
        raise SystemExit(1 if compare(before, after) else 0)
    print("ssgc from", ssgc.__file__, flush=True)
    if args.what == "parse":
        rows = measure_parse(args.first)
    else:
        start, stop = (int(x) for x in args.scenes.split(":"))
        rows = measure_explain(args.first, range(start, stop))
    Path(args.second).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
