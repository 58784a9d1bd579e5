"""Progress of a long command when standard error is not a terminal (a log file, CI, a pipe):
plain lines instead of rich's bar, which is only drawn on a terminal."""

from __future__ import annotations

import time
from typing import Any

LINE_EVERY_S = 1.0  # at most one line a second (a sink scene parses in 0.1-0.6 s)


class SceneLines:
    """`iteration K: scene I/N parsed (T s)` after each scene, at most one line a second, and
    always after an iteration's last scene; silent when `enabled` is false."""

    def __init__(self, console: Any, total: int, enabled: bool, iteration: int = 1) -> None:
        self.console, self.total, self.enabled = console, total, enabled
        self.start(iteration, 0)

    def start(self, iteration: int, done: int) -> None:
        self.iteration, self.done = iteration, done
        self.t0 = self.last = time.monotonic()

    def scene(self) -> None:
        self.done += 1
        now = time.monotonic()
        if not self.enabled or (now - self.last < LINE_EVERY_S and self.done < self.total):
            return
        self.last = now
        self.console.print(
            f"iteration {self.iteration}: scene {self.done}/{self.total} parsed "
            f"({now - self.t0:.1f} s)",
            markup=False,
            highlight=False,
        )

    def say(self, what: str) -> None:
        """One line of what is done now (when the lines are on)."""
        if self.enabled:
            self.console.print(f"{what} ...", markup=False, highlight=False)
