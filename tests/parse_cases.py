"""Re-run the uncertified parses that `parse_profile.py --cases FILE` listed (issue 11).

    python tests/parse_cases.py CASES.json [--method micp] [--cause coupled] [--with ip]
        [--time-limit 10] [--out RESULTS.json]

rebuilds each listed grammar with `parse_profile.case(seed, index)`, parses the listed scenes
with the given method, and prints one line per parse (grammar, scene, status, certified,
gap, CPU seconds) and a JSON summary: parses, certified, false answers, CPU.  Entries are
kept when their method matches and their cause starts with `--cause` (if given; several
prefixes separated by commas); `--with`
parses them with another method (e.g. `ip` on the scenes of `micp`'s causes).  The list of
one measurement becomes the work set of the next, before and after a change.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))

from parse_profile import case, check_scene

from ssgc.parse.parser import Parser


def rerun(
    entries: list[dict[str, Any]], method: str, time_limit: float | None, seed: int = 0
) -> list[dict[str, Any]]:
    """One result per listed (grammar, scene), grammars in order."""
    wanted: dict[int, set[str]] = {}
    for entry in entries:
        wanted.setdefault(int(entry["grammar"]), set()).add(str(entry["scene"]))
    out = []
    for index, names in sorted(wanted.items()):
        grammar, scenes, _ = case(seed, index)
        parser = Parser(grammar, method=method)
        for scene in (s for s in scenes if s.name in names):
            c0 = time.process_time()
            v = check_scene(grammar, parser, scene, time_limit)
            cpu = time.process_time() - c0
            gap = v.result.parses[0].gap if v.result is not None and v.result.parses else None
            row = {"grammar": index, "scene": scene.name, "status": v.status}
            row |= {"certified": v.certified, "gap": gap, "false": v.false, "cpu": cpu}
            out.append(row)
            print(index, scene.name, v.status, v.certified, gap, round(cpu, 3), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases")
    ap.add_argument("--method", default="micp")
    ap.add_argument(
        "--cause", default="", help="keep entries whose cause starts with this (comma: any of)"
    )
    ap.add_argument("--with", dest="parse_with", help="parse with this method instead")
    ap.add_argument("--time-limit", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out")
    a = ap.parse_args()
    entries = json.loads(Path(a.cases).read_text())
    entries = [
        e
        for e in entries
        if e["method"] == a.method
        and str(e.get("cause") or "").startswith(tuple(a.cause.split(",")))
    ]
    results = rerun(entries, a.parse_with or a.method, a.time_limit or None, a.seed)
    summary = {
        "parses": len(results),
        "certified": sum(r["certified"] for r in results),
        "false": sum(bool(r["false"]) for r in results),
        "cpu_seconds": round(sum(r["cpu"] for r in results), 2),
    }
    print(json.dumps(summary))
    if a.out:
        Path(a.out).write_text(json.dumps(results, indent=0))


if __name__ == "__main__":
    main()
