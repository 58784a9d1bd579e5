"""Re-parse the scenes of a profile's `--cases` file (issue 11): before/after on a work set.

    python tests/parse_cases.py CASES.json OUT.json [CAUSE_PREFIXES]

CASES.json is what `python tests/parse_profile.py --cases CASES.json` wrote (seed 0); every
scene whose `micp` cause starts with one of the comma-separated prefixes (default: all) is
parsed again alone with each method under `--time-limit 10`, and one row per parse (status,
phase, certified, gap, CPU seconds by `time.process_time`, whether the answer is false) goes
to OUT.json.  Run it with `PYTHONPATH` at another checkout for the "before" column.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from parse_profile import SCORE_TOL, case, certified, micp_cause

from ssgc.parse.parser import Parser


def rerun(cases: list[dict[str, Any]], prefixes: tuple[str, ...]) -> list[dict[str, Any]]:
    keys = sorted(
        {
            (e["grammar"], e["scene"])
            for e in cases
            if e["method"] == "micp" and str(e["cause"]).startswith(prefixes)
        }
    )
    grammars: dict[int, Any] = {}
    rows = []
    for gi, name in keys:
        if gi not in grammars:
            grammars[gi] = case(0, gi)
        grammar, scenes, _ = grammars[gi]
        scene = next(s for s in scenes if s.name == name)
        truth = float(scene.log_prob)
        for method in ("ip", "micp"):
            parser = Parser(grammar, method=method)
            c0 = time.process_time()
            result = parser.parse(scene, time_limit=10)
            cpu = time.process_time() - c0
            best = result.parses[0] if result.parses else None
            below = best is not None and best.score < truth - SCORE_TOL * max(1.0, abs(truth))
            row = {
                "grammar": gi,
                "scene": name,
                "method": method,
                "status": result.status,
                "phase": result.phase,
                "certified": certified(result),
                "gap": best.gap if best is not None and np.isfinite(best.gap) else None,
                "cpu": round(cpu, 3),
                "false": bool(result.status == "optimal" and below),
            }
            if method == "micp":
                row["cause"] = micp_cause(grammar, parser, scene, result)
            rows.append(row)
    return rows


def main() -> None:
    cases = json.loads(Path(sys.argv[1]).read_text())
    prefixes = tuple(sys.argv[3].split(",")) if len(sys.argv) > 3 else ("",)
    rows = rerun(cases, prefixes)
    Path(sys.argv[2]).write_text(json.dumps(rows, indent=0))
    for m in ("ip", "micp"):
        mine = [r for r in rows if r["method"] == m]
        print(
            m,
            "certified",
            sum(r["certified"] for r in mine),
            "of",
            len(mine),
            "no_parse",
            sum(r["status"] == "no_parse" for r in mine),
            "cpu",
            round(sum(r["cpu"] for r in mine), 1),
            "false",
            sum(r["false"] for r in mine),
        )


if __name__ == "__main__":
    main()
