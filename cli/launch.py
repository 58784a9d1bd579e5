"""The `ssg` entry point.  The command line's modules take about a second to import (the
compiler, numpy, scipy), and a Ctrl-C in that second is the user's: one line and exit 130, as
during a command (`ssgc.cli.app`), not a traceback through the import system."""

from __future__ import annotations

import sys


def main() -> None:
    try:
        from ssgc.cli.app import main as run
    except KeyboardInterrupt:
        sys.stderr.write("ssg: interrupted\n")
        raise SystemExit(130) from None
    run()
