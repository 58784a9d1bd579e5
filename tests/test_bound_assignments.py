"""The assignment bound's MILP (`ssgc.parse.bound.assignment_problem(upper=True)`, issue 11).

A row of a latent set names its children; its bound counts all their edges.  The MILP may
attach a named optional child (a `repeat`'s) to another instance instead: the row then must
not count that child's edge as well.  Grammar 6 of the issue-11 profile
(`parse_profile.case(0, 6)`): on main scene s5 was `feasible` with a gap of 0.62 although
every row's bound was exact (one L1 claimed both A's, another one of them).
"""

from __future__ import annotations

import numpy as np
from grammar_gen import compile_spec, sampled_scenes

from ssgc.parse.bound import assignment_problem, set_bounds
from ssgc.parse.parser import Parser
from ssgc.parse.posed import candidate_poses


def _repeat_grammar():  # type: ignore[no-untyped-def]
    return compile_spec(
        {
            "grammar": "repeat_of_repeats",
            "root": "L0",
            "types": {
                "A": {"observed": True},
                "B": {"observed": True},
                "L0": {
                    "repeat": {
                        "count": {"geometric": {"p": 0.5, "max": 2}},
                        "rule": {
                            "child": "L1",
                            "translation": {
                                "world_normal_offset": {"mean": [0, 0, 0], "variance": 0.05}
                            },
                            "rotation": {"offset": {"rpy_deg": [0, 90, 0]}},
                        },
                    }
                },
                "L1": {
                    "repeat": {
                        "count": {"probs": [0.3, 0.4, 0.3]},
                        "rule": {
                            "child": "A",
                            "translation": {
                                "world_normal_offset": {
                                    "mean": [1.0, 0.5, 0.0],
                                    "variance": [0.02, 0.01, 0.04],
                                }
                            },
                            "rotation": {"revolute": {"axis": [1, 0, 0]}},
                        },
                    }
                },
            },
        }
    )


def test_optional_child_attached_elsewhere_is_not_counted_twice():
    grammar = _repeat_grammar()
    scene = {s.name: s for s in sampled_scenes(grammar, 10, 6)}["s5"]
    parser = Parser(grammar, method="micp")
    result = parser.parse(scene)
    assert result.status == "optimal", (result.message, result.parses[0].gap)
    best = result.parses[0]
    assert best.gap <= 1e-6
    assert best.score >= scene.log_prob - 1e-6 * max(1.0, abs(scene.log_prob))
    # the bound's MILP itself: every row is exact here, so its optimum is the MAP score
    st = parser.supertree
    cand = candidate_poses(grammar, st, scene)
    bounds = set_bounds(grammar, st, cand)
    assert bounds is not None
    problem = assignment_problem(grammar, st, scene, cand, bounds, upper=True)
    sol = parser.open_session(problem.milp).solve()
    assert sol.status == "optimal"
    assert np.isclose(sol.objective, best.score, rtol=0, atol=1e-6)
