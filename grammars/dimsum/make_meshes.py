"""Regenerate the dimsum example meshes: `python grammars/dimsum/make_meshes.py`.

Each dish is a profile (radius, height) revolved about +z, sized like the primitive it
replaces in `dimsum_table.yaml` and centred on its bounding box, so the grammar's offsets hold.
The meshes are the project's own work, under the project's licence (README.md here).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).parent
SECTIONS = 32  # facets around the axis: small files, round enough for a table of dishes

# (radius, z) profiles from the axis at the bottom, around the outside, back along the inside
# (or over the top) to the axis: a closed outline, so the revolved solid is watertight.
PROFILES = {
    "serving_bowl": [  # 0.24 m across, 0.08 m high, 8 mm walls
        (0.0, 0.0),
        (0.07, 0.0),
        (0.105, 0.025),
        (0.12, 0.08),
        (0.112, 0.08),
        (0.097, 0.03),
        (0.065, 0.008),
        (0.0, 0.008),
    ],
    "plate": [  # 0.2 m across, 0.02 m high, a shallow well
        (0.0, 0.0),
        (0.07, 0.0),
        (0.1, 0.018),
        (0.1, 0.02),
        (0.07, 0.006),
        (0.0, 0.006),
    ],
    "teacup": [  # 0.07 m across, 0.06 m high
        (0.0, 0.0),
        (0.025, 0.0),
        (0.035, 0.06),
        (0.031, 0.06),
        (0.022, 0.005),
        (0.0, 0.005),
    ],
    "teapot": [  # 0.14 m across and high: a squat pot with a lid knob
        (0.0, 0.0),
        (0.05, 0.0),
        (0.07, 0.05),
        (0.06, 0.1),
        (0.03, 0.12),
        (0.012, 0.125),
        (0.012, 0.14),
        (0.0, 0.14),
    ],
}


def revolve(profile: list[tuple[float, float]]) -> trimesh.Trimesh:
    mesh = trimesh.creation.revolve(np.array(profile), sections=SECTIONS)
    if mesh.volume < 0:
        mesh.invert()
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def main() -> None:
    for name, profile in PROFILES.items():
        mesh = revolve(profile)
        assert mesh.is_watertight, name
        mesh.export(HERE / f"{name}.obj", digits=6, include_normals=False)


if __name__ == "__main__":
    main()
