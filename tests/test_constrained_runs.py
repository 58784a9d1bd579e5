"""`ssg sample --constraints` runs: -j, --resume, --export/--settle and the limits (exit 2).

Scene files are compared byte for byte between runs: scene i depends only on the seed and i,
for any number of processes and however a run was interrupted and resumed.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.sample.constrained import BLOCK, Tally, Unmet, _judged, _unmet, sample_blocks, select

RUNNER = CliRunner()
BIN = str(GRAMMARS / "bin_packing.yaml")
N = BLOCK + 44  # two blocks


def run(*args: object) -> tuple[int, str]:
    result = RUNNER.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


def scenes(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.glob("bin_packing_*.json"))}


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("ref") / "scenes"
    code, text = run("sample", BIN, "-n", N, "--seed", 4, "--constraints", "all", "-o", out, "-q")
    assert code == 0, text
    files = scenes(out)
    assert len(files) == N
    return files


def test_jobs_give_the_same_scenes(tmp_path: Path, reference: dict[str, bytes]) -> None:
    out = tmp_path / "j2"
    code, text = run(
        "sample", BIN, "-n", N, "--seed", 4, "--constraints", "all", "-j", 2, "-o", out, "-q"
    )
    assert code == 0, text
    assert scenes(out) == reference


def test_library_blocks_are_the_same_for_any_jobs() -> None:
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    cs = select(g, "all")
    one = list(sample_blocks(g, cs, N, 9))
    two = list(sample_blocks(g, cs, N, 9, jobs=2))
    assert [b.index for b in two] == [0, 1]
    for a, b in zip(one, two, strict=True):
        assert (a.logp == b.logp).all() and (a.trees.xyz == b.trees.xyz).all()
    # only the blocks asked for (what --resume draws)
    (last,) = sample_blocks(g, cs, N, 9, blocks=[1])
    assert last.index == 1 and (last.logp == one[1].logp).all()


def test_the_scenes_found_are_the_scenes_kept_when_a_limit_stops_the_run() -> None:
    """A block's last attempt may pass more scenes than the block needs; those are not kept,
    so they are not 'found' either (the message said 277 of 300 when 256 were written)."""
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    cs = select(g, "all")
    whole = Tally()
    list(sample_blocks(g, cs, BLOCK, 9, tally=whole))
    assert whole.kept == BLOCK
    assert whole.passed > BLOCK  # what the acceptance rate counts (seed 9: the last attempt's)
    written = []
    with pytest.raises(Unmet) as caught:  # block 1 starts with every try spent
        for block in sample_blocks(g, cs, BLOCK + 1, 9, max_tries=whole.drawn):
            written.append(block.trees.n_scenes)
    assert written == [BLOCK]
    head = caught.value.diagnostics[0].message
    assert head.startswith(f"found {BLOCK:,} of the {BLOCK + 1:,} requested scene(s)")


def test_resume_finishes_a_constrained_run(tmp_path: Path, reference: dict[str, bytes]) -> None:
    out = tmp_path / "scenes"
    args = ("sample", BIN, "-n", N, "--seed", 4, "--constraints", "all", "-o", out)
    code, text = run(*args, "-q")
    assert code == 0, text
    names = sorted(scenes(out))
    for name in names[3:7] + names[BLOCK + 1 :]:  # holes in block 0, block 1 mostly gone
        (out / name).unlink()
    (out / names[10]).write_text('{"format": "ssgc-scene/1", "name": ')  # cut short by a kill
    code, text = run(*args, "--resume")
    assert code == 0, text
    assert "kept" in text
    assert scenes(out) == reference
    # a resumed run of other constraints is another run: refused, nothing written
    (out / names[0]).unlink()
    code, text = run(*args[:-4], "--constraints", "in_bin", "-o", out, "--resume", "-q")
    assert code != 0 and "constraints" in text
    assert not (out / names[0]).exists()


def test_export_with_constraints(tmp_path: Path) -> None:
    out = tmp_path / "scenes"
    code, text = run(
        "sample", BIN, "-n", 3, "--constraints", "all", "--export", "sdf", "-o", out, "-q"
    )
    assert code == 0, text
    files = sorted(out.glob("bin_packing_*.json"))
    assert len(files) == 3
    doc = json.loads(files[0].read_text())
    assert doc["metadata"]["sampler"] == {"method": "rejection", "exact": True}
    assert set(doc["metadata"]["constraints"]) == {"in_bin", "no_overlap"}
    assert len([p for p in (out / "sdf").rglob("*.sdf")]) >= 3


def test_settle_with_constraints(tmp_path: Path) -> None:
    pytest.importorskip("mujoco")
    out = tmp_path / "scenes"
    code, text = run("sample", BIN, "-n", 2, "--constraints", "all", "--settle", "-o", out, "-q")
    assert code == 0, text
    files = sorted(out.glob("bin_packing_*.json"))
    assert len(files) == 2
    settle = json.loads(files[0].read_text())["metadata"]["settle"]
    assert settle["sampler"]["method"] == "rejection"
    assert settle["constraints"]["no_overlap"] >= 0  # the sampled poses, before settling


def _impossible(tmp_path: Path) -> Path:
    """Four or more discs (count), none overlapping with 10 cm keep-out radii: fewer than
    one candidate in a thousand passes both."""
    text = (GRAMMARS / "bin_packing.yaml").read_text().split("\nconstraints:")[0]
    path = tmp_path / "crowded.yaml"
    path.write_text(
        text + "\nconstraints:\n  many: {count: {type: Disc, min: 4}}\n"
        "  apart: {clearance: {types: [Disc], radius: {Disc: 0.1}}}\n"
    )
    return path


@pytest.mark.parametrize("limit", [("--max-tries", "3000"), ("--time-limit", "0.3")])
def test_unmet_constraints_exit_2_with_a_report(tmp_path: Path, limit: tuple[str, str]) -> None:
    out = tmp_path / "out"
    args = ["sample", str(_impossible(tmp_path)), "-n", "5", "--constraints", "all"]
    result = RUNNER.invoke(app, [*args, *limit, "-o", str(out), "-q"])
    assert result.exit_code == 2, result.output
    err = result.stderr
    assert "requested scene(s) satisfying the constraints" in err
    assert limit[0] in err
    # which constraint rejected how many, and how close the best rejected one came
    assert "constraint 'many' rejected" in err and "constraint 'apart' rejected" in err
    assert "the closest rejected came to -" in err
    assert "Traceback" not in result.output
    # nothing half-written: no scene file, no temporary file, no manifest of a run with none,
    # and not the directory the run made for them
    assert not out.exists()


def test_a_chain_method_says_it_judged_chain_draws(tmp_path: Path) -> None:
    """HMC judges a pose constraint on each of a chain's draws (four per candidate): 'rejected
    0 of the 512 candidates it judged' after 128 candidates read as a miscount."""
    g = load_grammar(_impossible(tmp_path))
    cs = select(g, "all")  # many: a count (structure); apart: a clearance (pose)
    tally = Tally(128, 0, 0, {"many": 128, "apart": 512}, {"many": 70, "apart": 9}, {})
    tally.best = {"many": -1.0, "apart": -0.01}
    for method, apart in [("hmc", "chain draws"), ("rejection", "candidates")]:
        lines = [d.message for d in _unmet(g, tally, 5, "x", _judged(cs, method)).diagnostics]
        assert "constraint 'many' rejected 70 of the 128 candidates it judged" in lines[1]
        assert f"constraint 'apart' rejected 9 of the 512 {apart} it judged" in lines[2]


def test_unmet_with_jobs_counts_every_process(tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = ["sample", str(_impossible(tmp_path)), "-n", str(2 * BLOCK + 1), "--constraints"]
    result = RUNNER.invoke(app, [*args, "all", "-j", "2", "--max-tries", "1500", "-o", str(out)])
    assert result.exit_code == 2, result.output
    head = result.stderr.splitlines()[1]  # after the "sampling under ..." line
    drawn = int(head.split(" after ")[1].split(" candidates")[0].replace(",", ""))
    assert drawn >= 2 * 1024  # both first blocks' first attempts (1,024 each) are counted
    assert not out.exists() or not list(out.iterdir())


def test_a_limit_reached_before_any_candidate_says_so() -> None:
    """Not "after 0 candidates" with "rejected 0 of the 0 candidates it judged" per constraint."""
    g = load_grammar(GRAMMARS / "bin_packing.yaml")
    with pytest.raises(Unmet) as caught:
        list(sample_blocks(g, select(g, "all"), 3, 0, time_limit=1e-12))
    lines = [d.message for d in caught.value.diagnostics]
    assert lines == [
        "found 0 of the 3 requested scene(s) satisfying the constraints before the first "
        "candidate (--time-limit 1e-12 s)"
    ]


def test_an_overwrite_that_finds_no_scene_leaves_the_old_run(tmp_path: Path) -> None:
    """--overwrite deletes the other run only when a scene of this one is ready: a run whose
    constraints never hold (exit 2, no scene) once left the directory empty."""
    out = tmp_path / "bp"
    code, text = run("sample", BIN, "-n", 3, "-o", out, "-q")
    assert code == 0, text
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    args = ["sample", _impossible(tmp_path), "-n", 5, "--constraints", "all", "--max-tries", 3000]
    code, text = run(*args, "-o", out, "--overwrite", "-q")
    assert code == 2, text
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
