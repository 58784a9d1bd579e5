"""Placement and count laws: one class per law, one file per class (see `base`)."""

from ssgc.laws import (  # noqa: F401  (importing a law module registers its law)
    fixed,
    position_box,
    position_normal,
    rotation_bingham,
    rotation_revolute,
    rotation_uniform,
)
