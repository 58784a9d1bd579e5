"""The parse's clock: one exception and one check shared by every step a time limit covers.

A leaf module (no imports from the parser's own modules), so that proposals, the unrolled
model and the bound can all stop at the same deadline without importing each other.
"""

from __future__ import annotations

import time


class OutOfTime(Exception):
    """The deadline passed while a step was running (proposals, model building)."""


def past(deadline: float | None) -> bool:
    """Whether `deadline` (a `time.perf_counter()` value; None: never) has passed."""
    return deadline is not None and time.perf_counter() >= deadline


def check_deadline(deadline: float | None) -> None:
    """Raise OutOfTime once `deadline` has passed."""
    if past(deadline):
        raise OutOfTime
