"""The samplers beyond rejection: gradients in law coordinates, NUTS, RJMCMC, HMC, projection.

Default run: gradients against finite differences, NUTS on a Gaussian, RJMCMC's count law on
the bin example against brute-force rejection (χ²), seeding and scene metadata.  Slow: the
fixed-structure HMC's bin histogram (it must fail the χ² test) and the comparison table of
every method against rejection (`python -m pytest tests/test_mcmc.py -m slow -s`).
"""

from __future__ import annotations

import functools
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from ssgc.compile import compile_text, load_grammar
from ssgc.constraints.gradients import margin_gradient
from ssgc.sample.constrained import METHODS, choose_method, sample_blocks, scene_metadata
from ssgc.sample.forward import sample_chunk
from ssgc.sample.hmc import FixedTrees, HmcSettings, hmc_batch
from ssgc.sample.lawspace import Coords
from ssgc.sample.nuts import DualAveraging, Nuts
from ssgc.sample.poses import Levels, local_poses, pullback, world_poses
from ssgc.sample.rjmcmc import RjSettings, regrow, rjmcmc_batch
from ssgc.sample.staged import rejection_batch
from ssgc.score import score_trees
from ssgc.tree import Trees

GRAMMARS = Path(__file__).resolve().parents[1] / "grammars"


@functools.cache
def _grammar(name: str):  # type: ignore[no-untyped-def]
    return load_grammar(GRAMMARS / name)


def _pose_constraints(g):  # type: ignore[no-untyped-def]
    return [c for c in g.constraints if c.kind == "pose"]


@pytest.mark.parametrize("name", ["bin_packing.yaml", "dimsum_table.yaml"])
def test_law_coordinates_round_trip(name: str) -> None:
    """world_poses(local_poses(T)) is T, and z -> u -> z is the identity."""
    g = load_grammar(GRAMMARS / name)
    trees, _ = sample_chunk(g, np.random.default_rng(0), 64)
    u, r = local_poses(g, trees)
    back = world_poses(g, trees, u, r)
    assert np.allclose(back.xyz, trees.xyz, atol=1e-9)
    assert np.allclose(np.abs(np.sum(back.quat * trees.quat, axis=1)), 1.0, atol=1e-9)
    coords = Coords.of(g, trees.rule)
    assert np.allclose(coords.to_u(coords.to_z(u), u), u, atol=1e-9)


@pytest.mark.parametrize("name", ["bin_packing.yaml", "dimsum_table.yaml"])
def test_margin_gradients_in_law_coordinates_match_finite_differences(name: str) -> None:
    """Each pose constraint's margin, differentiated through the tree (z -> u -> xyz), against
    central differences along a random direction, tree by tree (away from ties: a tree whose
    closest pair changes within the step is skipped, which the step makes rare)."""
    g = load_grammar(GRAMMARS / name)
    rng = np.random.default_rng(1)
    trees, _ = sample_chunk(g, rng, 128)
    levels = Levels.of(trees)
    u, r = local_poses(g, trees)
    coords = Coords.of(g, trees.rule)
    z = coords.to_z(u)
    d = np.where(coords.free, rng.standard_normal(z.shape), 0.0)
    h = 1e-6
    checked = 0
    for c in _pose_constraints(g):

        def f(zz: np.ndarray, c=c) -> np.ndarray:  # type: ignore[no-untyped-def]
            return c.margin(world_poses(g, trees, coords.to_u(zz, u), r, levels))

        m0, g_xyz = margin_gradient(c, world_poses(g, trees, coords.to_u(z, u), r, levels))
        g_z = coords.pull_to_z(z, pullback(g, trees, g_xyz, levels))
        analytic = np.bincount(trees.scene, np.sum(g_z * d, axis=1), minlength=trees.n_scenes)
        with np.errstate(invalid="ignore"):  # inf - inf: nothing to check in that tree
            fd = (f(z + h * d) - f(z - h * d)) / (2 * h)
        ok = np.isfinite(m0) & np.isfinite(fd)
        close = np.isclose(analytic[ok], fd[ok], rtol=1e-4, atol=1e-5)
        assert close.mean() > 0.95, (c.name, analytic[ok][~close][:5], fd[ok][~close][:5])
        checked += int(ok.sum())
    assert checked > 100


def test_hmc_target_gradient_matches_finite_differences() -> None:
    """The whole HMC log-density (laws + penalties) and its gradient, with a penalty wide
    enough that the step stays within one smooth piece."""
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    rng = np.random.default_rng(2)
    trees, _ = sample_chunk(g, rng, 64)
    target = FixedTrees(g, trees, list(g.constraints), eps=0.05)
    z = target.z0
    d = np.where(target.free, rng.standard_normal(z.shape), 0.0)
    _lp, grad = target(z)
    h = 1e-6
    fd = (target(z + h * d)[0] - target(z - h * d)[0]) / (2 * h)
    analytic = np.bincount(trees.scene, np.sum(grad * d, axis=1), minlength=trees.n_scenes)
    close = np.isclose(analytic, fd, rtol=1e-4, atol=1e-4)
    assert close.mean() > 0.95, (analytic[~close][:5], fd[~close][:5])


def test_nuts_samples_a_gaussian_and_adapts_its_step() -> None:
    """Many chains of different dimensions in lockstep: the marginal spreads come out right."""
    n = 60
    chain = np.repeat(np.arange(n), 2)
    free = np.ones((2 * n, 3), bool)
    free[1::2, 2] = False  # chains of 5 coordinates
    scale = np.array([1.0, 3.0, 0.1])

    def target(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lp = -0.5 * np.sum(np.where(free, (z / scale) ** 2, 0.0), axis=1)
        return np.bincount(chain, lp, minlength=n), np.where(free, -z / scale**2, 0.0)

    nuts = Nuts(target, chain, free, n, np.random.default_rng(3), max_depth=5)
    z = np.zeros((2 * n, 3))
    lp, grad = target(z)
    adapt = DualAveraging(np.full(n, 1.0))
    for _ in range(60):
        z, lp, grad, st = nuts.step(z, lp, grad, adapt.step)
        adapt.update(st["accept"])
    draws = []
    for _ in range(50):
        z, lp, grad, st = nuts.step(z, lp, grad, adapt.final())
        draws.append(z[0::2].copy())
    spread = np.std(np.concatenate(draws), axis=0)
    assert np.allclose(spread, scale, rtol=0.1)
    assert 0.6 < np.mean(st["accept"]) < 0.99


def test_regrow_keeps_the_rest_of_the_tree_and_scores_finitely() -> None:
    """A subtree redrawn below a node: the nodes outside it are unchanged, the result is a
    tree of the grammar (finite log-probability), parents before children."""
    g = load_grammar(GRAMMARS / "dimsum_table.yaml")
    rng = np.random.default_rng(4)
    trees, _ = sample_chunk(g, rng, 32)
    shared = g.type_id("SharedStuff")
    chosen = np.full(32, -1, np.int64)
    at = np.flatnonzero(trees.type == shared)
    chosen[trees.scene[at]] = at
    new = regrow(g, trees, chosen, rng)
    assert np.all(np.isfinite(score_trees(g, new)))
    assert np.all(new.parent < np.arange(len(new)))
    settings = g.type_id("PlaceSetting")
    for t in (trees, new):  # the place settings are outside the redrawn subtree
        assert np.bincount(t.scene[t.type == settings], minlength=32).tolist() == [4] * 32
    old_pl = trees.xyz[trees.type == settings]
    new_pl = new.xyz[new.type == settings]
    assert np.allclose(old_pl, new_pl)


def _disc_counts(trees: Trees, disc: int) -> np.ndarray:
    return np.bincount(trees.scene[trees.type == disc], minlength=trees.n_scenes)


def _same_law(a: np.ndarray, b: np.ndarray) -> float:
    top = int(max(a.max(), b.max())) + 1
    table = np.stack([np.bincount(a, minlength=top), np.bincount(b, minlength=top)])
    return float(stats.chi2_contingency(table[:, table.sum(axis=0) > 0])[1])


def _rejection(g, cs, n: int, seed: int) -> Trees:  # type: ignore[no-untyped-def]
    return Trees.concatenate([b.trees for b in sample_blocks(g, cs, n, seed)])


def test_rjmcmc_bin_count_histogram_matches_brute_force_rejection() -> None:
    """Thesis 2.7.3's example: RJMCMC's law of the number of discs is P(N | constraints), the
    law of exact rejection (χ² test), not the prior's."""
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    cs = list(g.constraints)
    disc = g.type_id("Disc")
    exact = _disc_counts(_rejection(g, cs, 768, 11), disc)
    # every chain starts from P(T): the burn-in and the moves are what is tested
    settings = RjSettings(min_sweeps=20, max_sweeps=120, start_candidates=0)
    out = rjmcmc_batch(g, cs, 768, np.random.default_rng(12), settings=settings)
    assert out.trees.n_scenes > 700
    ours = _disc_counts(out.trees, disc)
    for c in cs:
        assert np.all(out.margins[c.name] >= 0)
    assert _same_law(exact, ours) > 1e-3
    assert np.mean(ours >= 4) < 0.03  # the prior puts 7/11 there


def test_chain_methods_keep_the_seeding_guarantee_and_record_their_statistics(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Scene i depends only on the seed and i; scene files record method and chain stats."""
    short = functools.partial(
        rjmcmc_batch, settings=RjSettings(min_sweeps=20, max_sweeps=40, start_candidates=0)
    )
    monkeypatch.setitem(METHODS, "rjmcmc", short)
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    cs = list(g.constraints)
    a = next(iter(sample_blocks(g, cs, 3, 5, "rjmcmc")))
    b = next(iter(sample_blocks(g, cs, 5, 5, "rjmcmc")))
    assert np.array_equal(a.trees.xyz, b.trees.first(3).xyz)
    meta = scene_metadata("rjmcmc", [c.name for c in cs], a.margins, 0, a.chain)
    assert meta["sampler"]["method"] == "rjmcmc"
    assert 0 < meta["sampler"]["chain"]["subtree_acceptance"] <= 1
    assert set(meta["constraints"]) == {c.name for c in cs}
    assert choose_method("auto", cs) == "rejection"


def test_hmc_reports_only_scenes_that_satisfy_every_constraint() -> None:
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    cs = list(g.constraints)
    settings = HmcSettings(warmup=15, samples=5, max_chains=16, max_depth=4)
    out = hmc_batch(g, cs, 16, np.random.default_rng(6), settings=settings)
    assert out.trees.n_scenes > 0
    for c in cs:
        assert np.all(c.margin(out.trees) >= 0)
    assert set(out.chain) >= {"acceptance", "step_size", "divergences"}


# ----------------------------------------------------------------------- slow ones ---


@pytest.mark.slow
def test_fixed_structure_hmc_over_represents_big_bins() -> None:
    """2.7.3: HMC keeps each tree's structure, so its law of the number of discs is not
    P(N | constraints): the χ² test against rejection fails."""
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    cs = list(g.constraints)
    disc = g.type_id("Disc")
    hmc = Trees.concatenate([b.trees for b in sample_blocks(g, cs, 150, 21, "hmc")])
    exact = _disc_counts(_rejection(g, cs, 2000, 22), disc)
    ours = _disc_counts(hmc, disc)
    print("\nN    rejection  hmc")
    for k in range(11):
        print(k, np.mean(exact == k).round(4), np.mean(ours == k).round(4))
    assert _same_law(exact, ours) < 1e-6


@pytest.mark.slow
def test_methods_against_rejection_table() -> None:
    """Every method against rejection on the bin (rejection is cheap there): χ² p-value of
    the disc-count histogram and MMD² of the disc poses (and MMD² between two rejection
    samples, for the noise level).  Prints the table of docs/constraints.md."""
    from ssgc.fit.metrics import mmd2

    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    cs = list(g.constraints)
    disc = g.type_id("Disc")
    n = {"rejection": 600, "rjmcmc": 600, "hmc": 200, "project": 200}
    ref = _rejection(g, cs, 600, 31)
    rows = {}
    for k, method in enumerate(n):
        t = Trees.concatenate([b.trees for b in sample_blocks(g, cs, n[method], 40 + k, method)])
        a, b = ref.type == disc, t.type == disc
        rows[method] = (
            _same_law(_disc_counts(ref, disc), _disc_counts(t, disc)),
            mmd2(ref.xyz[a], ref.quat[a], t.xyz[b], t.quat[b]),
            np.bincount(_disc_counts(t, disc), minlength=6)[:6] / t.n_scenes,
        )
    print("\nmethod | scenes | χ² p (counts) | MMD² (disc poses) | P(N=0..5)")
    for m, (p, d, h) in rows.items():
        print(f"{m} | {n[m]} | {p:.3g} | {d:.2e} | {np.round(h, 3).tolist()}")
    assert rows["rjmcmc"][0] > 1e-3
    assert rows["hmc"][0] < 1e-3  # structures by P(S), not P(S | C)
    noise = abs(rows["rejection"][1])
    assert rows["rjmcmc"][1] < 5 * max(noise, 1e-4)


def test_upright_gradient_is_zero_and_margin_kept() -> None:
    """`upright` depends on rotations only: zero position gradient, the margin unchanged."""
    from ssgc.constraints.pose import Upright

    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    trees, _ = sample_chunk(g, np.random.default_rng(7), 8)
    up = Upright(name="up", path=(), types=np.array([False, True]), max_angle=0.1)
    m, grad = margin_gradient(up, trees)
    assert np.array_equal(m, up.margin(trees)) and not grad.any()
    moved = replace(trees, xyz=trees.xyz + 0.01)
    assert np.array_equal(up.margin(moved), m)


def test_rejection_is_still_the_reference() -> None:
    """The rejection method the comparisons rely on is the staged one (exact)."""
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    out = rejection_batch(g, list(g.constraints), 256, np.random.default_rng(8))
    assert out.trees.n_scenes > 20


@pytest.mark.slow
def test_methods_against_rejection_on_a_fixed_structure() -> None:
    """Three discs always (the count fixed), no overlap: structure plays no part, so HMC should
    match rejection too; projection's scenes pile up at contact.  χ²-free comparison: MMD² of
    the disc poses and a KS test of each scene's closest pair distance.  Prints the table."""
    from ssgc.compile import compile_text
    from ssgc.fit.metrics import mmd2

    text = (GRAMMARS / "bin_packing.yaml").read_text()
    text = text.replace(
        "count: {probs: [1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1]}", "count: {probs: [0, 0, 0, 1]}"
    )
    g = compile_text(text, "three_discs.yaml")
    cs = list(g.constraints)
    disc = g.type_id("Disc")

    def closest(t: Trees) -> np.ndarray:
        x = t.xyz[t.type == disc, :2].reshape(t.n_scenes, 3, 2)
        d = [np.hypot(*(x[:, i] - x[:, j]).T) for i, j in ((0, 1), (0, 2), (1, 2))]
        return np.min(d, axis=0)

    ref = _rejection(g, cs, 400, 51)
    other = _rejection(g, cs, 400, 52)
    rows = {"rejection (2nd sample)": other}
    for k, method in enumerate(("rjmcmc", "hmc", "project")):
        rows[method] = Trees.concatenate(
            [b.trees for b in sample_blocks(g, cs, 200, 60 + k, method)]
        )
    a = ref.type == disc
    print("\nmethod | scenes | MMD² (disc poses) | KS p (closest pair distance) | mean closest (m)")
    print(f"rejection (reference) | {ref.n_scenes} | - | - | {closest(ref).mean():.4f}")
    result = {}
    for name, t in rows.items():
        b = t.type == disc
        d2 = mmd2(ref.xyz[a], ref.quat[a], t.xyz[b], t.quat[b])
        p = stats.ks_2samp(closest(ref), closest(t)).pvalue
        result[name] = (d2, p)
        print(f"{name} | {t.n_scenes} | {d2:.2e} | {p:.3g} | {closest(t).mean():.4f}")
    assert result["rjmcmc"][1] > 1e-3
    assert result["project"][1] < 1e-3


@pytest.mark.parametrize("command", ["sample", "bench"])
def test_unknown_method_is_one_message(tmp_path: Path, command: str) -> None:
    """A misspelt --method: one line naming the methods, exit 1, nothing written."""
    from typer.testing import CliRunner

    from ssgc.cli.app import app

    grammar = str(GRAMMARS / "bin_packing.yaml")
    out = tmp_path / "out"
    args = (
        ["sample", grammar, "-n", "2", "--constraints", "all", "--method", "mcmc", "-o", str(out)]
        if command == "sample"
        else ["bench", "sample", grammar, "--constraints", "all", "--method", "mcmc", "-n", "2"]
    )
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1
    assert "unknown sampling method 'mcmc'" in result.output
    assert "rjmcmc" in result.output and "Traceback" not in result.output
    assert not out.exists()


def test_chain_method_on_the_command_line_writes_chain_statistics(tmp_path: Path) -> None:
    """`ssg sample --method rjmcmc`: scene files with the method, exact false, the chain's
    acceptance rates and every margin (non-negative)."""
    import json

    from typer.testing import CliRunner

    from ssgc.cli.app import app

    short = functools.partial(
        rjmcmc_batch, settings=RjSettings(min_sweeps=10, max_sweeps=20, start_candidates=0)
    )
    METHODS["rjmcmc"], saved = short, METHODS["rjmcmc"]
    try:
        out = tmp_path / "out"
        args = ["sample", str(GRAMMARS / "bin_packing.yaml"), "-n", "2", "--seed", "1"]
        result = CliRunner().invoke(
            app, [*args, "--constraints", "all", "--method", "rjmcmc", "-o", str(out)]
        )
    finally:
        METHODS["rjmcmc"] = saved
    assert result.exit_code == 0, result.output
    scenes = sorted(out.glob("*_*.json"))
    assert len(scenes) == 2
    meta = json.loads(scenes[0].read_text())["metadata"]
    assert meta["sampler"]["method"] == "rjmcmc" and meta["sampler"]["exact"] is False
    assert 0 <= meta["sampler"]["chain"]["walk_acceptance"] <= 1
    assert all(v is None or v >= 0 for v in meta["constraints"].values())


@given(seed=st.integers(0, 2**32 - 1), name=st.sampled_from(["dimsum_table.yaml", "sink.yaml"]))
@settings(max_examples=15, deadline=None)
def test_pullback_is_the_adjoint_of_moving_local_translations(seed: int, name: str) -> None:
    """With rotations held, positions are affine in the local translations u, so for any
    directions d (in u) and g (in positions): <g, x(u + d) - x(u)> = <pullback(g), d>; and
    world_poses(local_poses(T)) = T."""
    g = _grammar(name)
    rng = np.random.default_rng(seed)
    trees, _ = sample_chunk(g, rng, 8)
    levels = Levels.of(trees)
    u, r = local_poses(g, trees)
    base = world_poses(g, trees, u, r, levels)
    assert np.allclose(base.xyz, trees.xyz, atol=1e-9)
    d = rng.standard_normal(u.shape)
    d[trees.parent < 0] = 0.0  # roots do not move
    g_xyz = rng.standard_normal(u.shape)
    moved = world_poses(g, trees, u + d, r, levels)
    lhs = np.sum(g_xyz * (moved.xyz - base.xyz))
    rhs = np.sum(pullback(g, base, g_xyz, levels) * d)
    assert np.isclose(lhs, rhs, rtol=1e-9, atol=1e-9)


STACKED = """
grammar: stacked
root: L
types:
  L:
    and:
      - {child: A, translation: same, rotation: {revolute: {axis: [0, 0, 1]}}}
      - {child: A, translation: same, rotation: uniform}
  A: {observed: true, geometry: {sphere: {radius: 0.02}}}
constraints:
  apart: {non_penetration: {types: [A]}}
"""


def test_a_tree_with_nothing_to_move_is_rejected_quietly(capfd):  # type: ignore[no-untyped-def]
    """Every position fixed by its rule (`same`): no coordinate for the projection to move
    (SLSQP was called with none, and LAPACK printed two lines per tree), no `repeat` or
    `independent` site for RJMCMC's birth or death move (it indexed an empty array).  Every
    tree violates `apart`: the projection runs out of tries and says so, the chains stay
    infeasible."""
    import ssgc.api
    from ssgc.sample.constrained import Unmet

    g = compile_text(STACKED)
    with pytest.raises(Unmet):
        ssgc.api.Grammar(g, STACKED).sample(
            2, seed=0, constraints="all", method="project", max_tries=8
        )
    printed = capfd.readouterr()
    assert "On entry" not in printed.out + printed.err  # OpenBLAS's xerbla prints to stdout
    short = RjSettings(min_sweeps=2, max_sweeps=4, start_candidates=16)
    out = rjmcmc_batch(g, list(g.constraints), 4, np.random.default_rng(0), settings=short)
    assert out.trees.n_scenes == 0  # every chain still violates `apart`
