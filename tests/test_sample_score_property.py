"""Sampling then scoring: the scorer gives every sampled tree the log-probability the sampler
drew it with, over random grammars of the whole language (tests/grammar_gen.py with `rare`:
recursion bounded by `max_nesting`, `or` weights of 0, `independent` p = 0, count laws with
zeros, pinned axes, every translation and rotation law).

Parsing, explaining and fitting all score trees with `ssgc.score`; a tree the sampler draws
but the scorer scores otherwise is a scene the parser would misjudge.  This test is cheap (no
parse), so it runs many more grammars than the parser's property tests."""

from __future__ import annotations

import numpy as np
from grammar_gen import compile_spec, grammars, to_yaml
from hypothesis import HealthCheck, given, settings

from ssgc.sample.forward import sample_trees
from ssgc.score import score_trees


@settings(
    max_examples=100,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(spec=grammars(extras=True, rare=True))
def test_the_scorer_scores_each_sampled_tree_as_drawn(spec) -> None:  # type: ignore[no-untyped-def]
    grammar = compile_spec(spec)
    trees, logp = sample_trees(grammar, 40, 0)
    scored = score_trees(grammar, trees)
    drawn = np.isfinite(logp)
    assert drawn.any(), f"no tree drawn\ngrammar:\n{to_yaml(spec)}"
    ok = np.isclose(scored[drawn], logp[drawn], rtol=1e-9, atol=1e-9)
    if not ok.all():
        i = int(np.flatnonzero(drawn)[np.argmin(ok)])
        raise AssertionError(
            f"tree {i}: sampled with log p {logp[i]!r}, scored {scored[i]!r}\n"
            f"grammar:\n{to_yaml(spec)}"
        )
