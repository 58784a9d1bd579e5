"""Latent poses held by hard laws from both sides (issue 11: `no_parse` for sampled scenes).

Each case in tests/data/parse_hard/ is a grammar of the random-grammar profile and a scene
sampled from it for which main found no tree at all (`no_parse`, phase `proposals`): its latent
poses are held by boxes, fixed offsets and revolute arcs from their parents and their children,
and no proposal met all of them.  `ssgc.parse.hard_laws` solves those laws; these scenes must
now parse, with a tree no false certificate is claimed for.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from ssgc.compile import compile_text
from ssgc.geometry import quat_multiply, quat_normalize, quat_rotate
from ssgc.io.scene import parse_scene_text
from ssgc.parse.hard_laws import IDENTITY, Arc, Laws, _pin_pair_arcs, rotations
from ssgc.parse.parser import GAP_TOL, Parser

CASES = sorted((Path(__file__).parent / "data" / "parse_hard").glob("*.json"))


def _case(path: Path):  # type: ignore[no-untyped-def]
    doc = json.loads(path.read_text())
    grammar = compile_text(doc["grammar"])
    scene = parse_scene_text(json.dumps(doc["scene"]), str(path), grammar)
    return grammar, scene


@pytest.mark.parametrize("method", ["ip", "micp"])
@pytest.mark.parametrize("path", CASES, ids=[p.stem for p in CASES])
def test_sampled_scene_held_by_hard_laws_parses(path: Path, method: str) -> None:
    grammar, scene = _case(path)
    result = Parser(grammar, method=method).parse(scene)
    assert result.status in ("optimal", "feasible"), (result.status, result.message)
    best = result.parses[0]
    assert np.isfinite(best.score)
    truth = float(scene.log_prob)
    if result.status == "optimal":  # a certificate: never below the sampled tree
        assert best.gap <= GAP_TOL
        assert best.score >= truth - 1e-6 * max(1.0, abs(truth))


def test_cases_are_there() -> None:
    assert len(CASES) >= 5


def _quat(v: list[float]) -> np.ndarray:
    return quat_normalize(np.asarray(v, float))


quats = hs.lists(hs.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.3)
axes = hs.lists(hs.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.3)


@settings(max_examples=40, deadline=None)
@given(quats, axes, axes, hs.floats(-3.0, 3.0), hs.floats(-3.0, 3.0))
def test_two_arcs_through_one_rotation_meet_there(qv, av, bv, alpha, beta) -> None:  # type: ignore[no-untyped-def]
    """Two revolute families built to pass through one rotation q (q = L R(a, α) and
    q = R(b, -β)-side) are solved to q (or a rotation on both arcs, where they are one plane)."""
    q = _quat(qv)
    a = np.asarray(av) / np.linalg.norm(av)
    b = np.asarray(bv) / np.linalg.norm(bv)
    left = quat_multiply(q, _axis_angle(a, -alpha))  # q = left ⊗ R(a, α)
    child = quat_multiply(q, _axis_angle(b, beta))  # child = q ⊗ R(b, β): q = child ⊗ R(b, -β)
    arcs = [
        Arc(left, a, alpha - 0.1, alpha + 0.1, IDENTITY),
        Arc(child, b, -beta - 0.1, -beta + 0.1, IDENTITY),
    ]
    found = rotations(Laws(arcs, [], [], [], [], []), np.zeros((0, 4)))
    assert len(found)
    for arc in arcs:
        assert arc.holds(found).all()


@settings(max_examples=40, deadline=None)
@given(quats, axes, axes)
def test_two_pins_hold_the_rotation_to_an_arc_through_the_truth(qv, m1, m2) -> None:  # type: ignore[no-untyped-def]
    """Two children at fixed offsets m1, m2 of a pose (x, q): the pin pair's arc holds q."""
    q = _quat(qv)
    x = np.array([0.3, -0.2, 0.5])
    m1, m2 = np.asarray(m1), np.asarray(m2)
    if np.linalg.norm(m1 - m2) < 1e-3:
        return
    c1, c2 = x + quat_rotate(q, m1), x + quat_rotate(q, m2)
    laws = Laws([], [], [(c1, m1), (c2, m2)], [], [], [])
    (arc,) = _pin_pair_arcs(laws)
    assert arc.holds(q.reshape(1, 4), tol=1e-6).all()
    # every rotation on it puts both children where they are, from one position
    on = arc.at(np.linspace(-3, 3, 7))
    x1 = c1 - quat_rotate(on, np.broadcast_to(m1, (7, 3)))
    x2 = c2 - quat_rotate(on, np.broadcast_to(m2, (7, 3)))
    assert np.allclose(x1, x2, atol=1e-9)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    return np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]
