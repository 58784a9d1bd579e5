"""`revolve` geometry: hollow solids of revolution (ssgc/constraints/revolved.py) — their
signed distances, reach, meshes, penetration depths, and what `non_penetration`, the container
box and `ssg explain` read from them (docs/grammar.md, docs/explain.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.constraints.penetration import NonPenetration
from ssgc.constraints.revolved import Revolved
from ssgc.constraints.shapes import Extents, frame_extents
from ssgc.geometry import profile_problem, quat_to_matrix

BOWL = [[0, 0], [0.045, 0], [0.08, 0.062], [0.076, 0.062], [0.041, 0.005], [0, 0.005]]
MUG = [[0, 0], [0.04, 0], [0.045, 0.1], [0.041, 0.1], [0.036, 0.005], [0, 0.005]]

coord = st.floats(-0.3, 0.3, allow_nan=False)
point = st.tuples(coord, coord, coord)
unit_quat = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1)


def _dish_grammar(geometry: str, constraint: str = "") -> str:
    return f"""
grammar: dishes
root: {{type: Bin}}
types:
  Bin:
    observed: true
    and:
      - child: Bowl
        translation: {{world_normal_offset: {{mean: [0, 0, 0], variance: 0.01}}}}
      - child: Mug
        translation: {{world_normal_offset: {{mean: [0.1, 0, 0], variance: 0.01}}}}
  Bowl:
    observed: true
    geometry: {geometry}
  Mug:
    observed: true
    geometry: {{revolve: {{profile: {MUG}}}}}
{constraint}"""


NON_PENETRATION = """constraints:
  apart:
    non_penetration: {types: [Bowl, Mug]}
"""


@given(point)
def test_a_cylinder_profile_has_the_cylinder_signed_distance(p):
    r, h = 0.1, 0.2
    q = np.asarray(p)
    radial, axial = np.hypot(q[0], q[1]) - r, abs(q[2]) - h / 2
    exact = (
        max(radial, axial)
        if radial <= 0 and axial <= 0
        else np.hypot(max(radial, 0.0), max(axial, 0.0))
    )
    got = Revolved.cylinder(r, h).signed_distance(q[None])[0]
    assert got == pytest.approx(exact, abs=1e-12)


def test_surface_points_lie_on_the_surface_and_the_cavity_is_outside():
    bowl = Revolved(BOWL)
    assert np.abs(bowl.signed_distance(bowl.surface_points)).max() < 1e-12
    inside_cavity, in_wall = [0.0, 0.0, 0.03], [0.078 * np.cos(1.0), 0.078 * np.sin(1.0), 0.061]
    d = bowl.signed_distance(np.array([inside_cavity, in_wall]))
    assert d[0] > 0.02 and d[1] < 0


def test_the_mesh_is_closed_with_the_volume_of_pappus():
    trimesh = pytest.importorskip("trimesh")
    solid = Revolved(BOWL)
    v, f = solid.mesh(sections=256)
    mesh = trimesh.Trimesh(v, f, process=True)
    assert mesh.is_watertight and mesh.is_winding_consistent
    p = np.asarray(BOWL, float)
    r, z = p[:, 0], p[:, 1]
    cross = r * np.roll(z, -1) - np.roll(r, -1) * z
    area = cross.sum() / 2
    centroid_r = ((r + np.roll(r, -1)) * cross).sum() / (6 * area)
    assert mesh.volume == pytest.approx(2 * np.pi * centroid_r * area, rel=1e-3)


@given(unit_quat)
@settings(max_examples=50)
def test_reach_matches_the_surface_under_any_rotation(q):
    """`frame_extents` of a revolve: the extreme coordinates of its surface, in closed form."""
    solid = Revolved(BOWL)
    rot = quat_to_matrix(np.asarray(q) / np.linalg.norm(q))
    ext = Extents(np.array([5]), np.zeros((1, 3)), np.array([[0.0, 0.0, 0.01]]), (solid,))
    lo, hi = frame_extents(ext, np.array([0]), rot[None])
    v, _ = solid.mesh(sections=2048)
    turned = (v + np.array([0.0, 0.0, 0.01])) @ rot.T
    assert lo[0] == pytest.approx(turned.min(axis=0), abs=2e-5)
    assert hi[0] == pytest.approx(turned.max(axis=0), abs=2e-5)


@pytest.mark.parametrize(
    ("profile", "fragment"),
    [
        ([[0, 0], [0.1, 0], [0.1, 0.1]], "starts and ends on the axis"),
        ([[0, 0], [-0.1, 0], [0, 0.1]], "r of a profile is >= 0"),
        ([[0, 0], [0.1, 0], [0, 0.05], [0.1, 0.1], [0, 0.1]], "only a profile's first and last"),
        ([[0, 0], [0.1, 0], [0, 0]], "encloses no area"),
        ([[0, 0], [0.1, 0.1], [0.1, 0], [0.05, 0.2], [0, 0.1]], "cross each other"),
    ],
)
def test_a_bad_profile_is_a_located_error(tmp_path: Path, profile, fragment):
    assert profile_problem(profile) is not None
    path = tmp_path / "bad.yaml"
    path.write_text(_dish_grammar(f"{{revolve: {{profile: {profile}}}}}"))
    run = CliRunner().invoke(app, ["validate", str(path)])
    assert run.exit_code == 1 and "Traceback" not in run.output
    assert f"{path}:14:16:" in run.output and fragment in run.output


def _pair(grammar_text: str, mug_xyz, mug_quat=(1.0, 0.0, 0.0, 0.0)):
    g = compile_text(grammar_text, "dishes.yaml")
    check = next(c for c in g.constraints if isinstance(c, NonPenetration))

    class Batch:
        type = np.array([g.type_ids["Bowl"], g.type_ids["Mug"]])
        xyz = np.array([[0.0, 0.0, 0.0], mug_xyz], float)
        quat = np.array([[1.0, 0.0, 0.0, 0.0], mug_quat], float)
        scene, parent, n_scenes = np.zeros(2, np.int64), np.full(2, -1), 1

    return check, Batch()


def test_a_mug_in_a_hollow_bowl_does_not_overlap_it_where_a_solid_cylinder_did():
    hollow = _dish_grammar(f"{{revolve: {{profile: {BOWL}}}}}", NON_PENETRATION)
    solid = _dish_grammar(
        "{cylinder: {radius: 0.08, length: 0.062}, origin: [0, 0, 0.031]}", NON_PENETRATION
    )
    on_the_floor = [0.0, 0.0, 0.006]  # the mug stands on the bowl's inner floor
    check, batch = _pair(hollow, on_the_floor)
    assert check.margin(batch)[0] >= 0
    check, batch = _pair(solid, on_the_floor)
    assert check.margin(batch)[0] < -0.02


def test_a_mug_through_the_bowl_wall_is_measured_by_how_far_it_must_move():
    """The walls are 4 mm thick: the depth on surface points (the constraint's margin) is about
    that, while `ssg explain`'s separation is how far the mug must move to be free."""
    hollow = _dish_grammar(f"{{revolve: {{profile: {BOWL}}}}}", NON_PENETRATION)
    check, batch = _pair(hollow, [0.08, 0.0, 0.01])  # the mug's axis on the bowl's rim
    margin = check.margin(batch)[0]
    _, _, dist = check.pair_distances(batch, separation=True)
    assert -0.01 < margin < 0
    assert dist[0] < -0.03  # up and out of the bowl (10 cm), or sideways out of the wall
    assert dist[0] >= -0.1


def test_a_tilted_hollow_bowl_reaches_less_far_below_its_base_than_its_cylinder():
    solid = Revolved(BOWL)
    cylinder = Revolved([[0, 0], [0.08, 0], [0.08, 0.062], [0, 0.062]])
    tilt = np.radians(14.0)
    axis = np.array([[np.sin(tilt), 0.0, np.cos(tilt)]])
    assert solid.reach(axis)[0][0, 2] == pytest.approx(-0.045 * np.sin(tilt))
    assert cylinder.reach(axis)[0][0, 2] == pytest.approx(-0.08 * np.sin(tilt))


def test_a_revolve_exports_render_and_loads_as_a_mesh(tmp_path: Path):
    from ssgc.assets import load_shapes

    g = compile_text(_dish_grammar(f"{{revolve: {{profile: {BOWL}}}}}"), str(tmp_path / "g.yaml"))
    shapes = load_shapes(g, collision=True)
    bowl = shapes[g.type_ids["Bowl"]]
    assert bowl.kind == "mesh" and bowl.mesh.is_watertight and bowl.mass > 0
    # its exact convex pieces (the default for a revolve: one per profile trapezoid and
    # sector, none filling the cavity); `collision: hull` would be one piece
    assert bowl.exact_pieces and len(bowl.collision) > 1


@given(
    st.tuples(*[st.floats(-0.12, 0.12)] * 2, st.floats(-0.05, 0.1)),
    unit_quat,
)
@settings(max_examples=40, deadline=None)
def test_the_separation_is_at_least_the_deepest_surface_point(at, q):
    """No translation shorter than a surface point's depth can free it, so `ssg explain`'s
    separation (a search over directions) is never below the depth the margin uses (up to
    the facets of the FCL mesh, 0.2% of a radius)."""
    hollow = _dish_grammar(f"{{revolve: {{profile: {BOWL}}}}}", NON_PENETRATION)
    check, batch = _pair(hollow, at, np.asarray(q) / np.linalg.norm(q))
    depth = -check.margin(batch)[0]
    _, _, dist = check.pair_distances(batch, separation=True)
    if depth > 0:
        assert -dist[0] >= depth - 5e-4
    else:
        assert dist[0] == pytest.approx(-depth)
