"""The certified maximum over a latent rotation (ssgc/parse/bound_rotation.py, issue 11).

Property: over random anisotropic parent-frame offsets (rotating precisions), world-frame
Normals, Bingham terms, observed positions, a free / boxed / pinned position and a full or
revolute rotation domain, the branch-and-bound bound is never below the score at any rotation
(dense samples, and points around the search's own best), also when its cell budget is cut
short; where its cell bounds are second-order (no precision lowered) it closes to within
tolerance of the score at the pose it returns.  End to end: a latent set under a uniform or a
revolute rotation whose children are placed by `parent_normal_offset` with unequal variances
parses certified and match-or-beat (on main: `feasible`, gap ~1, trees up to 130 nats below).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from grammar_gen import compile_spec
from grammar_gen import sampled_scenes as gen_scenes
from hypothesis import example, given, settings
from hypothesis import strategies as hs

from ssgc.geometry import quat_multiply, quat_to_matrix, random_quat, rpy_to_quat
from ssgc.parse.bound_rotation import (
    MAX_CELLS,
    TOL_REL,
    Rotating,
    _cell_bound,
    _exact,
    _problem,
    branch_and_bound,
    rotation_search,
)
from ssgc.parse.parser import Parser
from ssgc.parse.set_terms import IDENTITY, _Terms

ANISO = np.diag([50.0, 100.0, 25.0])  # precisions of variances (0.02, 0.01, 0.04)
ARC = (-0.2, 0.35)  # half-angles of a revolute arc about z


def _case(seed: int, rotating: int, aniso_world: bool, position: str, arc: bool, n: int = 2):
    """n rows of one random problem (terms, rotating terms), its observations drawn around a
    true pose as a sampled scene's are: the set's prior mean and its children near where
    the pose puts them (0.2 m noise, about twice the laws' deviations)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.full((n, 3), -np.inf), np.full((n, 3), np.inf)
    t_true = rng.normal(size=(n, 3)) * 0.1
    if position == "box":
        lo, hi = np.tile([-0.1, -0.2, -0.1], (n, 1)), np.tile([0.2, 0.1, 0.3], (n, 1))
    elif position == "pinned":
        lo, hi = t_true - 1e-9, t_true + 1e-9
    elif position == "flat":  # held at its height, free across (a shelf pinned in z)
        lo[:, 2], hi[:, 2] = t_true[:, 2] - 1e-9, t_true[:, 2] + 1e-9
    if arc:
        psi = rng.uniform(*ARC, size=n)
        q_true = np.stack([np.cos(psi), 0 * psi, 0 * psi, np.sin(psi)], axis=1)
    else:
        q_true = random_quat(rng, n)
    R_true = quat_to_matrix(q_true)
    c = (t_true + rng.normal(size=(n, 3)) * 0.2)[:, None, :]
    P = np.tile(ANISO if aniso_world else 100.0 * np.eye(3), (n, 1, 1, 1))
    flat = np.diag([1.0, 1.0, 0.0]) if position == "flat" else np.eye(3)
    P = flat @ P @ flat  # no term pulls it in height: only the box holds it there
    A = rng.normal(size=(4, 4))
    B = np.tile(2.0 * (A + A.T), (n, 1, 1))
    V = np.zeros((n, 4, 2))
    V[:, 0, 0], V[:, 3, 1] = 1.0, 1.0  # q = (cos ψ, 0, 0, sin ψ): turns about z
    terms = _Terms(
        c,
        np.zeros((1, 3)),
        P,
        B,
        np.zeros(n),
        lo,
        hi,
        np.full((n, 4), np.nan),
        False,
        False,
        V,
        np.tile(ARC, (n, 1)) if arc else np.zeros((n, 2)),
        np.full(n, arc),
    )
    off = quat_to_matrix(random_quat(rng, rotating))
    if position == "flat":  # children pinned in the set's frame: no precision in its z
        off = np.broadcast_to(np.eye(3), (rotating, 3, 3))
    PA = np.einsum("jab,bc,jdc->jad", off, flat @ ANISO @ flat, off)
    m = rng.normal(size=(rotating, 3)) * 0.7
    cA = t_true[:, None, :] + np.einsum("nij,kj->nki", R_true, m)
    rot = Rotating(
        cA + rng.normal(size=(n, rotating, 3)) * 0.2,
        m,
        np.tile(PA, (n, 1, 1, 1)),
        np.zeros(n),
    )
    return terms, rot


def _rotations(rng: np.random.Generator, arc: bool, around: np.ndarray) -> np.ndarray:
    """Dense samples of the domain, and a cloud around each row's returned rotation."""
    if arc:
        psi = np.linspace(*ARC, 4001)
        dense = np.stack([np.cos(psi), 0 * psi, 0 * psi, np.sin(psi)], axis=1)
        near = np.clip(
            np.arctan2(around[:, 3], around[:, 0])[:, None] + np.linspace(-1e-3, 1e-3, 41), *ARC
        )
        cloud = np.stack([np.cos(near), 0 * near, 0 * near, np.sin(near)], axis=-1).reshape(-1, 4)
        return np.concatenate([dense, cloud])
    small = rpy_to_quat(rng.normal(size=(400, 3)) * 1e-3)
    cloud = quat_multiply(np.repeat(around, 400, axis=0), np.tile(small, (len(around), 1)))
    return np.concatenate([random_quat(rng, 20_000), cloud])


@settings(max_examples=12, deadline=None)
@given(
    seed=hs.integers(0, 2**31 - 1),
    rotating=hs.integers(0, 2),
    aniso_world=hs.booleans(),
    position=hs.sampled_from(["free", "box", "pinned", "flat"]),
    arc=hs.booleans(),
    short=hs.booleans(),
)
# a position that follows the turn (a flat maximum): open at the budget before the coupled bound
@example(seed=0, rotating=1, aniso_world=True, position="free", arc=False, short=False)
@example(seed=5, rotating=1, aniso_world=True, position="box", arc=False, short=False)
# held at its height only, no term pulling it there (a latent shelf): open at the budget before
# the curvature paid for the rounding slope across and the stiff pinned axis (_curved_slack)
@example(seed=0, rotating=1, aniso_world=False, position="flat", arc=False, short=False)
@example(seed=1, rotating=2, aniso_world=True, position="flat", arc=True, short=False)
def test_bound_holds_and_closes(seed, rotating, aniso_world, position, arc, short):
    _check_case(seed, rotating, aniso_world, position, arc, short)


@pytest.mark.parametrize("seed", [0, 5])
def test_cell_bound_excess_is_a_few_times_the_curvature(seed: int) -> None:
    """A cell of half-diagonal δ centred on the maximum: its bound exceeds the maximum by
    O(δ²), with a constant of the order of the score's own curvature there (here 1-3 along
    the flattest turn, 45-100 along the steepest).  Pairing the position's move with the best
    turn separately (the bound before `_coupled_turn`) gave 130-205."""
    terms, rot = _case(seed, 1, True, "free", False)
    p = _problem(terms, rot)
    _, _, quat = branch_and_bound(p, max_cells=600_000)
    R, rows = quat_to_matrix(quat), np.arange(len(quat))
    best, t0 = _exact(p, rows, R)
    for delta in (1e-2, 1e-3):
        excess = _cell_bound(p, rows, R, np.full(len(rows), delta), t0) - best
        assert np.all(excess >= 0) and np.all(excess <= 10 * delta**2), excess / delta**2


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(
    seed=hs.integers(0, 2**31 - 1),
    rotating=hs.integers(0, 3),
    aniso_world=hs.booleans(),
    position=hs.sampled_from(["free", "box", "pinned", "flat"]),
    arc=hs.booleans(),
    short=hs.booleans(),
)
def test_bound_holds_and_closes_long(seed, rotating, aniso_world, position, arc, short):
    _check_case(seed, rotating, aniso_world, position, arc, short)


def _check_case(seed, rotating, aniso_world, position, arc, short):  # type: ignore[no-untyped-def]
    if rotating == 0 and not aniso_world and position == "free":
        rotating = 1  # isotropic and unboxed: the relaxation is exact, nothing to search
    budget = 300 if short else MAX_CELLS
    terms, rot = _case(seed, rotating, aniso_world, position, arc)
    n = len(terms.c)
    p = _problem(terms, rot)
    upper, _, quat = branch_and_bound(p, max_cells=budget)
    R = quat_to_matrix(_rotations(np.random.default_rng(seed), arc, quat))
    for i in range(n):
        sampled, _ = _exact(p, np.full(len(R), i), R)
        assert upper[i] >= sampled.max() - 1e-9 * max(1.0, abs(sampled.max())), (i, upper[i])
    at_pose, _ = _exact(p, np.arange(n), quat_to_matrix(quat))
    assert np.all(upper >= at_pose - 1e-9)
    # the second-order cell bound closes every row, an active box and anisotropic
    # world-frame terms next to rotating ones included (first-order cells did not); held at
    # its height only, with two rotating terms over all rotations, most rows stay open at
    # the budget (the curvature across is spent on the turn's gain: measured, seeds 0-2)
    if budget == MAX_CELLS and not (position == "flat" and rotating >= 2 and not arc):
        tol = 2 * TOL_REL * np.maximum(1.0, np.abs(at_pose))
        assert np.all(upper - at_pose <= tol), (upper - at_pose, tol)


def test_search_selects_rows():
    """Rows with rotating terms are searched (their bound drops far below the supremum's);
    rows whose rotation is pinned pass through untouched."""
    terms, rot = _case(3, 1, False, "free", False)
    upper = np.array([1e3, 1e3])
    start = np.tile(IDENTITY, (2, 1))
    searched = rotation_search(terms, rot, upper, np.zeros((2, 3)), start)[0]
    assert np.all(searched < 1e2)
    terms.pin[:] = IDENTITY
    out = rotation_search(terms, rot, upper, np.zeros((2, 3)), start)
    assert np.array_equal(out[0], upper)


def _anisotropic_grammar(rotation):  # type: ignore[no-untyped-def]
    offset = {"variance": [0.02, 0.01, 0.04]}
    return compile_spec(
        {
            "grammar": "anisotropic_offsets",
            "root": "L0",
            "types": {
                "A": {"observed": True},
                "B": {"observed": True},
                "L0": {
                    "and": [
                        {
                            "child": "L1",
                            "translation": {"world_normal": {"mean": [0, 0, 0], "variance": 0.01}},
                            "rotation": rotation,
                        }
                    ]
                },
                "L1": {
                    "and": [
                        {
                            "child": "A",
                            "translation": {
                                "parent_normal_offset": {"mean": [1.0, 0.5, 0.0], **offset}
                            },
                            "rotation": "uniform",
                        },
                        {
                            "child": "B",
                            "translation": {
                                "parent_normal_offset": {"mean": [0.3, -0.2, 0.1], **offset}
                            },
                            "rotation": "uniform",
                        },
                    ]
                },
            },
        }
    )


@pytest.mark.parametrize("rotation", ["uniform", {"revolute": {"axis": [0, 0, 1]}}])
def test_anisotropic_offsets_certified(rotation):
    """On main every one of these scenes was `feasible` with a gap near 1 (the rotating
    precision counted its supremum) and most trees far below the sampled one."""
    grammar = _anisotropic_grammar(rotation)
    parser = Parser(grammar, method="micp")
    for scene in gen_scenes(grammar, 4, 0):
        result = parser.parse(scene)
        assert result.status == "optimal", (scene.name, result.message)
        best = result.parses[0]
        assert best.gap <= 1e-6
        assert best.score >= scene.log_prob - 1e-6 * max(1.0, abs(scene.log_prob))


def test_deadline_stops_with_a_valid_bound():
    """Past its deadline the search stops after its first cells: a looser bound, still above
    the score at every sampled rotation."""
    terms, rot = _case(7, 2, False, "free", False)
    p = _problem(terms, rot)
    stopped = branch_and_bound(p, deadline=time.perf_counter())[0]
    closed = branch_and_bound(p)[0]
    assert np.all(stopped > closed + 1e-3)
    R = quat_to_matrix(random_quat(np.random.default_rng(0), 20_000))
    for i in range(len(stopped)):
        assert stopped[i] >= _exact(p, np.full(len(R), i), R)[0].max()


def _boxed_rotating_grammar():  # type: ignore[no-untyped-def]
    """Grammar 94 of the issue-11 profile (`parse_profile.case(0, 94)`): L1s placed by a world
    box offset from the root, turned by a parent Bingham, each with a child B placed by an
    anisotropic parent-frame Normal (a rotating precision) under a world Bingham."""
    return compile_spec(
        {
            "grammar": "boxed_rotating",
            "root": "L0",
            "types": {
                "A": {"observed": True},
                "B": {"observed": True},
                "L0": {
                    "repeat": {
                        "count": {"probs": [0.3, 0.4, 0.3]},
                        "rule": {
                            "child": "L1",
                            "translation": {
                                "world_box_offset": {
                                    "min": [0.9, 0.4, -0.1],
                                    "max": [1.1, 0.6, 0.1],
                                }
                            },
                            "rotation": {
                                "parent_bingham": {
                                    "mode": {"rpy_deg": [0, 0, 0]},
                                    "concentration": 20,
                                }
                            },
                        },
                    }
                },
                "L1": {
                    "independent": [
                        {
                            "child": "B",
                            "translation": {
                                "parent_normal_offset": {
                                    "mean": [0.0, 0.0, 0.0],
                                    "variance": [0.02, 0.01, 0.04],
                                }
                            },
                            "rotation": {
                                "world_bingham": {
                                    "mode": {"rpy_deg": [20, 0, 45]},
                                    "concentration": [100, 100, 0],
                                }
                            },
                            "p": 0.6,
                        }
                    ]
                },
            },
        }
    )


def test_box_active_with_rotating_offset_certified():
    """A rotating term under a box active at the optimum: first-order cell bounds ran out of
    cells (on main these two scenes were `feasible`, gaps 4e-4 and 2e-3); the second-order
    cell bound closes them."""
    grammar = _boxed_rotating_grammar()
    parser = Parser(grammar, method="micp")
    scenes = {s.name: s for s in gen_scenes(grammar, 10, 94)}
    for name in ("s6", "s7"):
        scene = scenes[name]
        result = parser.parse(scene)
        assert result.status == "optimal", (name, result.message, result.parses[0].gap)
        best = result.parses[0]
        assert best.gap <= 1e-6
        assert best.score >= scene.log_prob - 1e-6 * max(1.0, abs(scene.log_prob))


SCALES = """grammar: scales
root: {type: Root}
types:
  Root:
    observed: true
    and: [{child: Pairs}]
  Pairs:
    repeat:
      count: {probs: [0, 1]}
      rule:
        child: Pair
        translation: {world_normal: {mean: [0, 0, 1], variance: [1e6, 1e-12, 1]}}
        rotation: {world_bingham: {concentration: [20, 20, 0.5]}}
  Pair:
    and:
      - child: Object
        translation:
          parent_normal_offset: {mean: [0.15, 0.25, 0], variance: [1e-12, 1e6, 1e-12]}
        rotation: {parent_bingham: {concentration: 100}}
      - child: Object
        translation:
          parent_normal_offset: {mean: [-0.15, -0.25, 0], variance: [1e-12, 1e6, 1e-12]}
        rotation: {parent_bingham: {concentration: 100}}
  Object: {observed: true}
"""


def test_precisions_of_very_different_scales_are_bounded():
    """Variances of 1e-12 and 1e6 in one law made the position solve of the rotation bound
    singular in floating point: LinAlgError, an internal error of parse, explain and fit."""
    from ssgc.compile import compile_text

    g = compile_text(SCALES, "scales.yaml")
    parser = Parser(g)
    for scene in gen_scenes(g, 2, seed=0):
        result = parser.parse(scene, time_limit=5)  # ill-conditioned: not all proposals found
        assert result.status in ("optimal", "feasible", "no_parse"), result.message
        if result.status == "optimal":
            assert result.parses[0].score >= scene.log_prob - 1e-6
