"""Constraint fixes of a bug hunt: overlaps and frames that sampling took for satisfied.

1. python-fcl signs the contact depth of a sphere against a triangle mesh (a tray, a mesh)
   negative: `non_penetration` gave such a collision a positive margin and kept the scene.
2. A closed OBJ surface with `vt` or `vn` indices read as open (its vertices split at the
   seams), so an object buried inside it was kept.
3. `-n 10**12 --constraints` built lists of every block (memory ran out before any scene), and
   after a try limit called every later block.
4. `ssg validate` accepted an `inside_box` frame that clutter objects of a listed type lack;
   sampling then dropped every scene with such a clutter object.
"""

from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ssgc
from ssgc import dsl
from ssgc.compile import compile_text
from ssgc.constraints.penetration import NonPenetration
from ssgc.constraints.shapes import closed_surface, surface_mesh
from ssgc.errors import GrammarError, SsgError
from ssgc.sample.forward import sample_trees

TRAY = "{tray: {size: [0.5, 0.4, 0.2], wall: 0.05}}"
CUBE = "{mesh: {file: cube.obj}}"  # the cube of side 0.5 about the origin
CORNERS = [(x, y, z) for x in (-0.25, 0.25) for y in (-0.25, 0.25) for z in (-0.25, 0.25)]
QUADS = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]


def _cube_obj(path: Path, corner: str = "{v}") -> None:
    """The closed cube, each face corner written as `corner` formats its vertex `v`, the
    corner's place in its square face `t` (1..4, a texture index) and the face `n` (1..6, a
    normal index): `{v}/{t}` and `{v}//{n}` make trimesh split the vertices at the seams."""
    lines = [f"v {x} {y} {z}" for x, y, z in CORNERS]
    lines += ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1"]
    lines += ["vn 1 0 0", "vn -1 0 0", "vn 0 1 0", "vn 0 -1 0", "vn 0 0 1", "vn 0 0 -1"]
    for n, quad in enumerate(QUADS, start=1):
        a, b, c, d = (corner.format(v=v, t=t, n=n) for t, v in enumerate(quad, start=1))
        lines += [f"f {a} {b} {c}", f"f {a} {c} {d}"]
    path.write_text("\n".join(lines) + "\n")


def _grammar(tmp_path: Path, outer: str, inner: str, translation: str) -> ssgc.api.Grammar:
    _cube_obj(tmp_path / "cube.obj")
    (tmp_path / "g.yaml").write_text(f"""grammar: pair
root: R
types:
  R:
    observed: true
    geometry: {outer}
    and: [{{child: A, translation: {translation}, rotation: uniform}}]
  A: {{observed: true, geometry: {inner}}}
constraints:
  np: {{non_penetration: {{types: [R, A]}}}}
""")
    return ssgc.load_grammar(tmp_path / "g.yaml")


def _constraint(g: ssgc.api.Grammar) -> NonPenetration:
    (c,) = [c for c in g.ir.constraints if isinstance(c, NonPenetration)]
    return c


# ------------------------------------------------------------ 1. sphere vs triangles ---


@pytest.mark.parametrize(
    ("outer", "radius", "at", "depth"),
    [
        (TRAY, 0.02, [0, 0.19, 0.02], 0.01),  # a ball in the tray's +y wall, 1 cm out of it
        (CUBE, 0.05, [0.25, 0, 0], 0.05),  # a ball centred on the cube's face
    ],
)
def test_a_sphere_through_a_tray_or_mesh_has_a_negative_margin(
    tmp_path: Path, outer: str, radius: float, at: list[float], depth: float
) -> None:
    """FCL's contact depth read -0.01 and -0.05 here: the margins were +0.01 and +0.05."""
    g = _grammar(tmp_path, outer, f"{{sphere: {{radius: {radius}}}}}", f"{{offset: {at}}}")
    trees, _ = sample_trees(g.ir, 1, 0)
    assert _constraint(g).margin(trees)[0] == pytest.approx(-depth)


@pytest.mark.parametrize(
    "outer", [TRAY, CUBE, "{sphere: {radius: 0.2}}", "{box: {size: [0.5, 0.4, 0.2]}}"]
)
@pytest.mark.parametrize(
    "inner",
    [
        "{sphere: {radius: 0.03}}",
        "{sphere: {radius: 0.3}}",  # larger than the other: it swallows a mesh's triangles
        "{box: {size: [0.06, 0.05, 0.04]}}",
        "{cylinder: {radius: 0.03, length: 0.06}}",
        "{revolve: {profile: [[0, 0], [0.04, 0], [0.05, 0.03], [0.045, 0.03], [0, 0.005]]}}",
        TRAY,
        CUBE,
    ],
)
def test_the_margin_is_negative_exactly_when_fcl_says_they_collide(
    tmp_path: Path, outer: str, inner: str
) -> None:
    """Every shape pair at random poses: a pair FCL's collision test finds colliding has a
    negative margin (sphere against a tray or a mesh: none had), one it finds apart a
    non-negative margin unless one is buried in the other's closed surface."""
    import fcl

    box = "{world_box: {min: [-0.35, -0.35, -0.3], max: [0.35, 0.35, 0.3]}}"
    g = _grammar(tmp_path, outer, inner, box)
    c = _constraint(g)
    trees, _ = sample_trees(g.ir, 60, 1)
    margin = c.margin(trees)
    collide = np.array(
        [
            fcl.collide(
                c._object(trees, 2 * s),
                c._object(trees, 2 * s + 1),
                fcl.CollisionRequest(),
                fcl.CollisionResult(),
            )
            > 0
            for s in range(trees.n_scenes)
        ]
    )
    assert collide.any()
    assert np.all(margin[collide] < 0)
    apart = np.flatnonzero(~collide)
    buried = [c._buried(trees, 2 * s, 2 * s + 1) for s in apart]
    assert np.all((margin[apart] >= 0) | np.array(buried, bool))


def test_sampling_keeps_no_scene_with_a_ball_in_the_tray_wall(tmp_path: Path) -> None:
    """`ssg sample r1.yaml --constraints all` accepted every candidate, margin +0.0099."""
    g = _grammar(tmp_path, TRAY, "{sphere: {radius: 0.02}}", "{offset: [0, 0.19, 0.02]}")
    with pytest.raises(SsgError, match="found 0 of the 1 requested"):
        g.sample(1, constraints="all", max_tries=100)


# ------------------------------------------------------- 2. OBJ with vt / vn indices ---


@pytest.mark.parametrize("corner", ["{v}", "{v}/{t}", "{v}//{n}", "{v}/{t}/{n}"])
def test_a_closed_obj_with_texture_or_normal_indices_is_closed(tmp_path: Path, corner: str) -> None:
    """trimesh splits the cube's vertices at texture and normal seams (20 or 24, not 8), so
    no edge was shared by two triangles and the surface read as open."""
    _cube_obj(tmp_path / "c.obj", corner)
    surface = closed_surface(dsl.MeshG(mesh=dsl.MeshGeometry(file="c.obj")), tmp_path)
    assert surface is not None
    assert surface.inside(np.array([0.01, 0.02, 0.03]))
    assert not surface.inside(np.array([0.3, 0.0, 0.0]))


@pytest.mark.parametrize("corner", ["{v}/{t}", "{v}//{n}"])
def test_a_ball_buried_in_a_cube_with_vt_or_vn_is_refused(tmp_path: Path, corner: str) -> None:
    """The ball lies 24 cm inside the cube's faces: the margin was +0.22 (FCL: apart)."""
    g = _grammar(tmp_path, CUBE, "{sphere: {radius: 0.01}}", "{offset: [0, 0, 0]}")
    _cube_obj(tmp_path / "cube.obj", corner)
    g = ssgc.load_grammar(tmp_path / "g.yaml")
    trees, _ = sample_trees(g.ir, 1, 0)
    assert _constraint(g).margin(trees)[0] < 0


def test_merging_leaves_what_fcl_and_the_exports_read(tmp_path: Path) -> None:
    """Only the closedness test merges vertices: the surface FCL gets keeps the file's."""
    _cube_obj(tmp_path / "c.obj", "{v}/{t}")
    v, faces = surface_mesh(dsl.MeshG(mesh=dsl.MeshGeometry(file="c.obj")), tmp_path)
    assert len(v) > 8 and len(faces) == 12


# ---------------------------------------------------------------- 3. a huge -n ---

TN = """grammar: tn
root: Root
types:
  Root:
    and:
      - child: X
        translation: {world_normal: {mean: [0, 0, 0], variance: [1, 1, 0], pin: [z]}}
  X: {observed: true, geometry: {box: {size: [0.1, 0.1, 0.1]}}}
constraints:
  inbox: {inside_box: {types: [X], min: [0.5, -1, null], max: [2, null, null]}}
"""


def _limit_memory() -> None:
    limit = 3 * 2**30  # bytes of address space: the bookkeeping of 4e9 blocks needs more
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def test_a_huge_n_under_a_try_limit_draws_and_stops(tmp_path: Path) -> None:
    """`-n 10**12 --max-tries 100`: lists of all ⌈n/256⌉ blocks were built first (OOM-killed;
    'internal error: MemoryError', exit 70, under 3 GB).  Now the scenes of the first attempt
    are written and the try limit is reported, in seconds."""
    (tmp_path / "tn.yaml").write_text(TN)
    args = ["sample", str(tmp_path / "tn.yaml"), "-n", str(10**12), "--constraints", "all"]
    args += ["--max-tries", "100", "-o", str(tmp_path / "out")]
    run = subprocess.run(
        [sys.executable, "-m", "ssgc.cli.app", *args],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=_limit_memory,
    )
    assert run.returncode == 2, run.stderr
    assert "requested scene(s) satisfying the constraints" in run.stderr
    assert "--max-tries 100" in run.stderr
    assert len(list((tmp_path / "out").glob("tn_*.json"))) > 0


def test_the_blocks_a_resumed_run_misses() -> None:
    """The blocks of a resume, one array expression: those missing a scene, and how many
    scenes the whole ones hold (the last block may be short)."""
    from ssgc.sample.constrained import BLOCK
    from ssgc.sample.run import _blocks_missing

    n = 3 * BLOCK + 10
    done = np.ones(n, bool)
    done[BLOCK + 5] = False  # block 1 misses a scene
    todo, skipped = _blocks_missing(done, n)
    assert list(todo) == [1] and skipped == n - BLOCK
    done[-1] = False  # the short last block too
    todo, skipped = _blocks_missing(done, n)
    assert list(todo) == [1, 3] and skipped == 2 * BLOCK


# ------------------------------------------------------------- 4. clutter frames ---

FRC = """grammar: frc
root: {type: Table}
types:
  Table:
    observed: true
    and: [{child: Spoon, translation: {offset: [0, 0, 0.4]}}]
  Spoon: {observed: true}
constraints:
  onT: {KIND}
observation:
  clutter:
    region: {min: [-1, -1, 0], max: [1, 1, 1]}
    rates: {RATES}
"""
INSIDE = (
    "inside_box: {types: [Spoon], frame: Table, min: [-0.3, -0.3, null], max: [0.3, 0.3, null]}"
)
UPRIGHT = "upright: {types: [Spoon], frame: Table, max_angle_deg: 30}"


@pytest.mark.parametrize("kind", [INSIDE, UPRIGHT])
def test_a_frame_clutter_objects_lack_is_refused(kind: str) -> None:
    """Clutter spoons hang under `~clutter`, below no Table: validate said ok, and sampling
    kept only the scenes without clutter (37.8%, none of the 308 clutter spoons)."""
    text = FRC.replace("{KIND}", "{" + kind + "}").replace("{RATES}", "{Spoon: 1.0}")
    with pytest.raises(GrammarError) as err:
        compile_text(text, "frc.yaml")
    message = str(err.value)
    assert "frc.yaml:9:" in message  # the constraint's line: the `frame` key
    assert "a clutter 'Spoon' (observation.clutter.rates) has no 'Table' above it" in message
    assert "so it has no frame to be checked in" in message


def test_clutter_of_another_type_leaves_the_frame_alone() -> None:
    text = FRC.replace("{KIND}", "{" + INSIDE + "}").replace("{RATES}", "{Fork: 1.0}")
    g = compile_text(text, "frc.yaml")
    assert [c.name for c in g.constraints] == ["onT"]
