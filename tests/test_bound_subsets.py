"""The bound's rows for a `repeat` member list every subset of its candidates up to its
copies, and gave up past `MAX_ASSIGNMENTS` only after listing them: three latent groups of ten
objects each (30 candidates, 10 copies: 53 million subsets) ran out of memory, exit 70, past
its time limit (session-35 resources hunt).  The subsets are now counted first."""

from __future__ import annotations

import itertools

import numpy as np

import ssgc
from ssgc.parse import bound

GROUPS = """
grammar: groups
root: {type: Root, pose: {xyz: [0, 0, 0]}}
types:
  Root:
    observed: true
    repeat:
      count: {probs: [0, 0, 1]}
      rule:
        child: Group
        translation: {world_normal: {mean: [0, 0, 0], variance: [4, 4, 0.01]}}
        rotation: {revolute: {axis: [0, 0, 1]}}
  Group:
    repeat:
      count: {probs: [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1]}
      rule:
        child: Obj
        translation: {parent_normal_offset: {mean: [0, 0, 0], variance: [0.01, 0.01, 0.0001]}}
        rotation: same
  Obj: {observed: true}
"""


def test_too_many_subsets_are_refused_before_they_are_listed(tmp_path, monkeypatch):
    """Two groups of ten: 20 candidates and 10 copies are 616,666 subsets; none is listed,
    the bound gives up on that member (the parse goes on without it), and the parse still
    finds a tree at least as probable as the one that made the scene."""
    listed = []
    real = itertools.combinations

    def counting(items, r):  # the bound imports it inside its function, at call time
        for s in real(items, r):
            listed.append(1)
            yield s

    monkeypatch.setattr(itertools, "combinations", counting)
    path = tmp_path / "groups.yaml"
    path.write_text(GROUPS)
    g = ssgc.load_grammar(path)
    scene = g.sample(1, seed=0)[0]
    result = ssgc.parse(g, scene, time_limit=60)
    assert len(listed) <= bound.MAX_ASSIGNMENTS
    assert result.status in ("optimal", "feasible"), result.message
    assert result.parses[0].score >= scene.log_prob - 1e-6
    assert np.isfinite(result.parses[0].score)
