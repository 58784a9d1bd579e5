"""Interrupted runs (SIGKILL, Ctrl-C) of `ssg sample` and `ssg parse`, and `--resume`.

An interrupted run must leave only complete files (and, after SIGKILL, temporary files that
`--resume` removes), and `--resume` must finish it with exactly what one uninterrupted run
writes.  The kill tests run the real command in a subprocess and kill it while it writes.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import GRAMMARS, SINK_DATA
from typer.testing import CliRunner

import ssgc.cli.app as cli
import ssgc.sample.forward as forward
from ssgc.compile import load_grammar
from ssgc.io.atomic import temp_target
from ssgc.io.journal import ParseJournal, journal_path, run_header, write_parse_output
from ssgc.io.resume import MANIFEST, run_manifest, write_manifest
from ssgc.io.scene import dumps_json, load_scenes

SINK = GRAMMARS / "sink.yaml"
N_REF = 1000  # scenes of the reference sample run (~2 s); killed runs stop at ~300
runner = CliRunner()


def run(*args: Any):
    return runner.invoke(cli.app, [str(a) for a in args])


started: list[subprocess.Popen[str]] = []


@pytest.fixture(autouse=True)
def _no_stray_processes() -> Iterator[None]:
    """A failing test must not leave its `ssg` subprocesses running."""
    yield
    while started:
        proc = started.pop()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def start(*args: Any) -> subprocess.Popen[str]:
    """`ssg ARGS` in a subprocess, with Ctrl-C raising KeyboardInterrupt as in a terminal
    (a child inherits an ignored SIGINT from a background job otherwise)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ssgc.cli.app", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    started.append(proc)
    return proc


def interrupt_when(
    proc: subprocess.Popen[str], ready: Callable[[], bool], sig: signal.Signals
) -> tuple[int, str]:
    """Send `sig` as soon as `ready()`; the run must still be going then."""
    deadline = time.monotonic() + 60
    while not ready():
        assert proc.poll() is None, f"finished before it could be interrupted: {proc.args}"
        assert time.monotonic() < deadline, "no progress within 60 s"
        time.sleep(0.01)
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=60)
    return proc.returncode, stderr


def scene_files(directory: Path) -> list[str]:
    return [n for n in os.listdir(directory) if n.endswith(".json") and not n.startswith(".")]


def contents(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


def assert_only_complete_scenes(directory: Path, temps_allowed: bool) -> None:
    """Every scene file parses and is whole; anything else is a removable temporary file."""
    for p in directory.iterdir():
        if p.name in (MANIFEST, ".ssg.lock"):  # the run's manifest; a killed run's lock file
            continue
        if temp_target(p.name) is not None:
            assert temps_allowed, f"temporary file left behind: {p.name}"
            continue
        assert p.suffix == ".json", p.name
        doc = json.loads(p.read_bytes())
        assert {"objects", "tree", "log_prob", "index"} <= set(doc), p.name


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One uninterrupted `ssg sample` run: what every resumed run must equal."""
    out = tmp_path_factory.mktemp("reference") / "scenes"
    result = run("sample", SINK, "-n", N_REF, "-o", out, "-q")
    assert result.exit_code == 0, result.output
    return out


# ------------------------------------------------------------------------ ssg sample ---


def test_sample_killed_with_sigkill_then_resumed(reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "scenes"
    proc = start("sample", SINK, "-n", N_REF, "-o", out, "-q")
    code, _ = interrupt_when(
        proc, lambda: out.is_dir() and len(scene_files(out)) >= 300, signal.SIGKILL
    )
    assert code == -signal.SIGKILL
    assert_only_complete_scenes(out, temps_allowed=True)
    killed_temps = sum(temp_target(name) is not None for name in os.listdir(out))
    names = sorted(scene_files(out))
    assert names == [f"sink_{i:06d}.json" for i in range(len(names))]  # written in order
    assert len(names) < N_REF
    # What a crash can leave besides: a temporary file, and a cut-off file (not by ssgc, whose
    # writes are atomic, but e.g. by a copy that was interrupted): both are redone.
    (out / ".sink_000007.json.k1ll3d_x.tmp").write_text('{"format": "ssgc.sc')
    cut = out / names[-1]
    cut.write_bytes(cut.read_bytes()[:100])
    (out / "notes.txt").write_text("not ours")  # other files are left alone

    result = run("sample", SINK, "-n", N_REF, "-o", out, "--resume")
    assert result.exit_code == 0, result.output
    assert f"kept {len(names) - 1} complete scene file(s)" in result.output
    assert f"removed {killed_temps + 1} temporary file(s)" in result.output
    (out / "notes.txt").unlink()
    assert contents(out) == contents(reference)


def test_sample_interrupted_with_ctrl_c_then_resumed(reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "scenes"
    proc = start("sample", SINK, "-n", N_REF, "-o", out, "-q")
    code, stderr = interrupt_when(
        proc, lambda: out.is_dir() and len(scene_files(out)) >= 300, signal.SIGINT
    )
    assert code == 130 and "interrupted" in stderr and "Traceback" not in stderr, (code, stderr)
    assert_only_complete_scenes(out, temps_allowed=False)
    assert 300 <= len(scene_files(out)) < N_REF
    result = run("sample", SINK, "-n", N_REF, "-o", out, "--resume", "-q")
    assert result.exit_code == 0, result.output
    assert contents(out) == contents(reference)


def test_sample_resume_draws_only_the_chunks_with_missing_scenes(
    reference: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "scenes"
    out.mkdir()
    write_manifest(out, run_manifest("sink", SINK, 0, 600, 6))
    for i in range(600):  # chunks 0 and 1 complete, chunk 2 (512..599) misses scene 550
        if i != 550:
            name = f"sink_{i:06d}.json"
            (out / name).write_bytes((reference / name).read_bytes())
    drawn: list[int] = []
    real = forward.sample_chunk

    def counting(grammar: Any, rng: Any, size: int = forward.CHUNK) -> Any:
        drawn.append(1)
        return real(grammar, rng, size)

    monkeypatch.setattr(forward, "sample_chunk", counting)
    result = run("sample", SINK, "-n", 600, "-o", out, "--resume")
    assert result.exit_code == 0, result.output
    assert len(drawn) == 1
    assert "wrote 1 scene(s)" in result.output and "kept 599 complete" in result.output
    assert (out / "sink_000550.json").read_bytes() == (reference / "sink_000550.json").read_bytes()


def test_sample_resume_never_mixes_runs(tmp_path: Path) -> None:
    out = tmp_path / "scenes"
    assert run("sample", SINK, "-n", 5, "--seed", 3, "-o", out, "-q").exit_code == 0
    before = contents(out)

    other_seed = run("sample", SINK, "-n", 5, "--seed", 4, "-o", out, "--resume")
    assert other_seed.exit_code == 1
    assert f"{MANIFEST}: error: these scenes are of another run (seed: 3, now 4)" in (
        other_seed.output
    )
    assert "--resume never mixes two runs" in other_seed.output
    other_count = run("sample", SINK, "-n", 6, "--seed", 3, "-o", out, "--resume")
    assert other_count.exit_code == 1 and "(count: 5, now 6)" in other_count.output
    assert contents(out) == before

    # A scene file edited behind the manifest's back is still caught, file by file.
    doc = json.loads(before["sink_000000.json"])
    doc["seed"] = 4
    (out / "sink_000000.json").write_text(dumps_json(doc))
    edited_file = run("sample", SINK, "-n", 5, "--seed", 3, "-o", out, "--resume")
    assert edited_file.exit_code == 1
    assert "sink_000000.json: error: this scene file has seed 4, but this run writes seed 3" in (
        edited_file.output
    )
    (out / "sink_000000.json").write_bytes(before["sink_000000.json"])

    doc = json.loads(before["sink_000002.json"])
    doc["grammar"] = "sink_v2"
    (out / "sink_000002.json").write_text(dumps_json(doc))
    renamed = run("sample", SINK, "-n", 5, "--seed", 3, "-o", out, "--resume")
    assert renamed.exit_code == 1
    assert 'sink_000002.json: error: this scene file has grammar "sink_v2"' in renamed.output
    (out / "sink_000002.json").write_bytes(before["sink_000002.json"])

    # The same grammar name with other numbers draws other scenes: caught when the chunk
    # holding a missing scene is drawn again, before anything is written.
    edited = tmp_path / "sink.yaml"
    edited.write_text(SINK.read_text().replace("p: 0.3", "p: 0.4", 1))
    assert edited.read_text() != SINK.read_text()
    (out / "sink_000004.json").unlink()
    changed = run("sample", edited, "-n", 5, "--seed", 3, "-o", out, "--resume")
    assert changed.exit_code == 1
    assert "(grammar_sha256: " in changed.output  # the manifest records the grammar's digest
    # Behind the manifest, every done scene of a chunk drawn again is compared as it is drawn.
    write_manifest(out, run_manifest("sink", edited, 3, 5, 6))
    changed = run("sample", edited, "-n", 5, "--seed", 3, "-o", out, "--resume")
    assert changed.exit_code == 1
    assert "the grammar (or the ssgc or numpy version) changed" in changed.output
    (out / MANIFEST).write_bytes(before[MANIFEST])
    assert not (out / "sink_000004.json").exists()
    assert contents(out) == {k: v for k, v in before.items() if k != "sink_000004.json"}


# ------------------------------------------------------------------------- ssg parse ---


def without_timing(path: Path) -> dict[str, Any]:
    doc = json.loads(path.read_text())
    for scene in doc["scenes"]:
        del scene["timing"]  # seconds: the only part of the output that varies between runs
    return doc


def _first_sink_scenes(count: int, path: Path) -> Path:
    """The real dataset's first `count` scenes (its top-level keys are the only lines that
    start in column 0), as a dataset file of its own."""
    lines = SINK_DATA.read_text().splitlines(keepends=True)
    starts = [i for i, line in enumerate(lines) if line[:1] not in ("", " ", "#", "\n")]
    path.write_text("".join(lines[: starts[count]]))
    return path


def test_parse_killed_interrupted_and_resumed(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """SIGKILL, then Ctrl-C of the resumed run, then a resume that finishes: OUT.json stays
    the previous version until the end, and ends equal to an uninterrupted run's.  The first
    40 real scenes: the kill comes after 10, the Ctrl-C 10 later, and 20 are left to finish."""
    data = _first_sink_scenes(40, tmp_path_factory.mktemp("data") / "scenes.yaml")
    ref = tmp_path / "ref.json"
    reference = start("parse", data, "-g", SINK, "-o", ref, "-q")  # alongside: 2 cores
    out = tmp_path / "out.json"
    out.write_text("the previous version\n")
    journal = journal_path(out)

    def journalled(n: int) -> Callable[[], bool]:
        return lambda: journal.exists() and journal.read_bytes().count(b"\n") >= n + 1

    code, _ = interrupt_when(
        start("parse", data, "-g", SINK, "-o", out), journalled(10), signal.SIGKILL
    )
    assert code == -signal.SIGKILL
    assert out.read_text() == "the previous version\n"
    lines = journal.read_bytes().split(b"\n")
    assert [json.loads(x)["index"] for x in lines[1:-1]] == list(range(len(lines) - 2))

    resumed = start("parse", data, "-g", SINK, "-o", out, "--resume")
    code, stderr = interrupt_when(resumed, journalled(len(lines) + 10), signal.SIGINT)
    assert code == 130 and "interrupted" in stderr and "Traceback" not in stderr, (code, stderr)
    assert out.read_text() == "the previous version\n"
    # out.json's own: the reference run may be writing ref.json's at this moment
    assert [p.name for p in tmp_path.iterdir() if temp_target(p.name) == out.name] == []

    finished = start("parse", data, "-g", SINK, "-o", out, "--resume")
    _, stderr = finished.communicate(timeout=120)
    assert finished.returncode == 0, stderr
    assert not journal.exists()
    assert reference.communicate(timeout=120)[1] == "" and reference.returncode == 0
    assert without_timing(out) == without_timing(ref)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json", "ref.json"]


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("small") / "scenes"
    assert run("sample", SINK, "-n", 4, "--seed", 5, "-o", out, "-q").exit_code == 0
    return out


def test_parse_resume_needs_an_output_file(small_dataset: Path) -> None:
    result = run("parse", small_dataset, "-g", SINK, "--resume")
    assert result.exit_code == 1
    assert "--resume needs -o OUT.json" in result.output


def test_parse_resume_ignores_a_cut_off_last_line(small_dataset: Path, tmp_path: Path) -> None:
    whole = tmp_path / "whole.json"
    assert run("parse", small_dataset, "-g", SINK, "-o", whole, "-q").exit_code == 0
    g = load_grammar(SINK)
    header = run_header(g.name, SINK, small_dataset, load_scenes(small_dataset, g), 1, "auto", None)
    out = tmp_path / "out.json"
    first = json.loads(whole.read_text())["scenes"][0]
    with ParseJournal(journal_path(out), header, resume=False) as journal:
        journal.append(0, first)
    with open(journal_path(out), "ab") as f:
        f.write(b'{"index": 1, "result": {"name": "sink_0')  # a kill in mid-write
    result = run("parse", small_dataset, "-g", SINK, "-o", out, "--resume", "-q")
    assert result.exit_code == 0, result.output
    assert without_timing(out) == without_timing(whole)
    assert json.loads(out.read_text())["scenes"][0] == first  # taken from the journal
    assert not journal_path(out).exists()


def test_parse_resume_refuses_a_journal_of_another_run(small_dataset: Path, tmp_path: Path) -> None:
    g = load_grammar(SINK)
    header = run_header(g.name, SINK, small_dataset, load_scenes(small_dataset, g), 1, "auto", None)
    out = tmp_path / "out.json"
    ParseJournal(journal_path(out), header, resume=False).close()
    result = run("parse", small_dataset, "-g", SINK, "-o", out, "--top", 2, "--resume")
    assert result.exit_code == 1
    assert "this journal is of another run (top: 1, now 2)" in result.output
    assert journal_path(out).exists() and not out.exists()
    # --explain too: resumed, half the scenes would have explanations and half not
    result = run("parse", small_dataset, "-g", SINK, "-o", out, "--explain", "--resume")
    assert result.exit_code == 1 and "(explain: false, now true)" in result.output
    other = tmp_path / "other"
    other.mkdir()
    (other / "a.json").write_bytes((small_dataset / "sink_000000.json").read_bytes())
    result = run("parse", other, "-g", SINK, "-o", out, "--resume")
    assert result.exit_code == 1
    assert "(scenes: " in result.output and "scene_count: 4, now 1" in result.output
    # Without --resume the old journal is replaced, with a note.
    result = run("parse", other, "-g", SINK, "-o", out)
    assert result.exit_code == 0, result.output
    assert "of an interrupted run is replaced" in result.output
    assert not journal_path(out).exists() and len(json.loads(out.read_text())["scenes"]) == 1


def test_streamed_output_is_byte_identical_to_dumps_json() -> None:
    scenes = [
        {"name": "a", "status": "optimal", "parses": [{"score": -1.5, "tree": {"xyz": [1, 2]}}]},
        {"name": "b", "status": "infeasible", "parses": [], "message": "no"},
    ]
    for grammar, results in (("sink", scenes), ('odd "name"', []), ("x", scenes[:1])):
        f = io.StringIO()
        failed = write_parse_output(f, grammar, results)
        assert f.getvalue() == dumps_json({"grammar": grammar, "scenes": results})
        assert failed == [
            {
                "name": r["name"],
                "status": r["status"],
                "phase": r.get("phase", ""),
                "message": r.get("message", ""),
            }
            for r in results
            if r["status"] in ("infeasible", "no_parse", "error")
        ]


# ----------------------------------------------------------------------------- ssg fit ---

GMM_START = (
    (GRAMMARS / "gmm.yaml")
    .read_text()
    .replace("p: 0.2", "p: 0.34")
    .replace("p: 0.4", "p: 0.33")
    .replace("mean: [-1.0, 0.0, 0.0]", "mean: [-0.5, 0.3, 0.0]")
)
FIT_ARGS = ("--top", 3, "--iterations", 4, "--tol", 0)
GMM_POINTS = 60  # scenes: the kill lands in iteration 2, the Ctrl-C in iteration 3 (of 4)


@pytest.fixture(scope="module")
def gmm_fit_inputs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("gmm")
    start = base / "start.yaml"
    start.write_text(GMM_START)
    data = base / "points"
    sampled = run("sample", GRAMMARS / "gmm.yaml", "-n", GMM_POINTS, "--seed", 3, "-o", data, "-q")
    assert sampled.exit_code == 0
    return data, start


def report_without_seconds(path: Path) -> dict[str, Any]:
    doc = json.loads(path.read_text())
    for r in doc["iterations"]:
        del r["seconds"], r["mstep_seconds"]
    return doc


def test_fit_killed_interrupted_and_resumed(
    gmm_fit_inputs: tuple[Path, Path], tmp_path: Path
) -> None:
    """SIGKILL in iteration 2, Ctrl-C of the resumed run in iteration 3, then a resume that
    finishes: the output stays the previous version until the end, and the fitted grammar
    and report equal an uninterrupted run's byte for byte (but the seconds)."""
    data, start_yaml = gmm_fit_inputs
    ref, ref_report = tmp_path / "ref.yaml", tmp_path / "ref.json"
    reference = start("fit", data, "-g", start_yaml, "-o", ref, "--report", ref_report, *FIT_ARGS)
    out, report = tmp_path / "out.yaml", tmp_path / "out.json"
    out.write_text("the previous version\n")
    journal = journal_path(out)
    n = GMM_POINTS

    def journalled(lines: int) -> Callable[[], bool]:
        return lambda: journal.exists() and journal.read_bytes().count(b"\n") >= lines

    args = ("fit", data, "-g", start_yaml, "-o", out, "--report", report, *FIT_ARGS)
    code, _ = interrupt_when(start(*args), journalled(1 + n + 1 + 20), signal.SIGKILL)
    assert code == -signal.SIGKILL
    assert out.read_text() == "the previous version\n" and not report.exists()
    code, stderr = interrupt_when(
        start(*args, "--resume"), journalled(1 + 2 * (n + 1) + 20), signal.SIGINT
    )
    assert code == 130 and "interrupted" in stderr and "Traceback" not in stderr, (code, stderr)
    assert out.read_text() == "the previous version\n" and not report.exists()
    assert [p.name for p in tmp_path.iterdir() if temp_target(p.name)] == []

    finished = start(*args, "--resume")
    _, stderr = finished.communicate(timeout=120)
    assert finished.returncode == 0, stderr
    assert "(from the journal)" in stderr  # finished iterations were not redone
    reference.communicate(timeout=120)
    assert reference.returncode == 0
    assert out.read_bytes() == ref.read_bytes()
    assert report_without_seconds(report) == report_without_seconds(ref_report)
    assert not journal.exists()


def test_fit_time_limit_returns_the_last_finished_iteration(
    gmm_fit_inputs: tuple[Path, Path], tmp_path: Path
) -> None:
    """The limit ends the fit with status time_limit; the output is the grammar of the last
    finished iteration, and the journal stays so that --resume can go on."""
    data, start_yaml = gmm_fit_inputs
    out, report = tmp_path / "out.yaml", tmp_path / "out.json"
    args = ("fit", data, "-g", start_yaml, "-o", out, "--report", report, *FIT_ARGS)
    result = run(*args, "--time-limit", 0.05)
    assert result.exit_code == 0, result.output
    assert json.loads(report.read_text())["status"] == "time_limit"
    assert out.read_text() == GMM_START  # no iteration finished: the input, unchanged
    assert journal_path(out).exists()
    result = run(*args, "--resume")
    assert result.exit_code == 0, result.output
    assert json.loads(report.read_text())["status"] == "iterations"
    assert not journal_path(out).exists()


def test_fit_resume_refuses_a_journal_of_another_run(
    gmm_fit_inputs: tuple[Path, Path], tmp_path: Path
) -> None:
    data, start_yaml = gmm_fit_inputs
    out = tmp_path / "out.yaml"
    run("fit", data, "-g", start_yaml, "-o", out, "--time-limit", 0.05, "--top", 3)
    assert journal_path(out).exists()
    result = run("fit", data, "-g", start_yaml, "-o", out, "--top", 2, "--resume")
    assert result.exit_code == 1
    assert "this journal is of another run (top: 3, now 2)" in result.output


def child_pids(pid: int) -> list[int]:
    """Processes whose parent is `pid` (Linux /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry))
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_fit_with_jobs_killed_leaves_no_workers_and_resumes(
    gmm_fit_inputs: tuple[Path, Path], tmp_path: Path
) -> None:
    data, start_yaml = gmm_fit_inputs
    ref = tmp_path / "ref.yaml"
    assert run("fit", data, "-g", start_yaml, "-o", ref, "-q", *FIT_ARGS).exit_code == 0
    out = tmp_path / "out.yaml"
    journal = journal_path(out)
    args = ("fit", data, "-g", start_yaml, "-o", out, "-j", 2, *FIT_ARGS)
    proc = start(*args)
    workers: list[int] = []

    def working() -> bool:
        workers[:] = child_pids(proc.pid)
        return len(workers) == 2 and journal.exists() and journal.read_bytes().count(b"\n") > 30

    code, _ = interrupt_when(proc, working, signal.SIGKILL)
    assert code == -signal.SIGKILL and not out.exists()
    deadline = time.monotonic() + 10
    while any(Path(f"/proc/{w}").exists() for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(Path(f"/proc/{w}").exists() for w in workers), "orphaned workers"
    result = run(*args, "--resume", "-q")
    assert result.exit_code == 0, result.output
    assert out.read_bytes() == ref.read_bytes()


def _sdf_run(out: Path, *more: Any) -> tuple[Any, ...]:
    return ("sample", SINK, "-n", 3, "-o", out, "--export", "sdf", "-q", *more)


def test_a_scene_is_exported_before_its_file_is_written(tmp_path: Path, monkeypatch) -> None:
    """The scene file is what --resume takes for a finished scene: a run stopped while
    exporting scene 1 must not have written it (once it had, and the resumed run never
    exported sink_000001.sdf)."""
    import ssgc.cli.export as export_cli

    real = export_cli.export_scene

    def stopped_at_scene_1(g: Any, scene: Any, *args: Any) -> Path:
        if scene.name.endswith("_000001"):
            raise KeyboardInterrupt
        return real(g, scene, *args)

    monkeypatch.setattr(export_cli, "export_scene", stopped_at_scene_1)
    out = tmp_path / "ex"
    assert run(*_sdf_run(out)).exit_code == 130
    assert sorted(p.name for p in out.glob("*.json")) == ["sink_000000.json"]
    monkeypatch.setattr(export_cli, "export_scene", real)
    assert run(*_sdf_run(out, "--resume")).exit_code == 0
    names = sorted(p.stem for p in out.glob("*.json"))
    assert names == [f"sink_00000{i}" for i in range(3)]
    assert sorted(p.stem for p in (out / "sdf").glob("*.sdf")) == names


def test_resume_removes_the_temporary_files_of_exports(tmp_path: Path) -> None:
    """A run killed while writing an export leaves its temporary file in OUTPUT/FORMAT/ or
    OUTPUT/FORMAT/meshes/: --resume removes them as it does the scene files'."""
    out = tmp_path / "ek"
    assert run(*_sdf_run(out)).exit_code == 0
    temps = [out / "sdf" / ".sink_000002.sdf.abcd1234.tmp", out / "sdf/meshes/.X.obj.k2j4_x9q.tmp"]
    for temp in temps:
        temp.write_text("half a file")
    (out / "sink_000002.json").unlink()
    result = run("sample", SINK, "-n", 3, "-o", out, "--export", "sdf", "--resume")
    assert result.exit_code == 0, result.output
    assert "removed 2 temporary file(s)" in result.output
    assert not [t for t in temps if t.exists()]
    assert (out / "sink_000002.json").is_file()


def _files(directory: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(directory)): p.read_bytes() for p in directory.rglob("*") if p.is_file()
    }


def test_sample_export_never_changes_the_meshes_of_an_earlier_export(tmp_path: Path) -> None:
    """Mesh files are shared by every scene exported into OUTPUT/FORMAT/: a run of another
    version of the grammar is refused before anything is written or deleted, as `ssg export`
    refuses (it once replaced them under the old run's scenes), even with --overwrite."""
    out = tmp_path / "exo"
    assert run(*_sdf_run(out)).exit_code == 0
    mesh = sorted((out / "sdf" / "meshes").glob("*.obj"))[0]
    mesh.write_text(mesh.read_text() + "# another version of the grammar\n")
    before = _files(out)
    result = run("sample", SINK, "-n", 2, "--seed", 7, "-o", out, "--export", "sdf", "--overwrite")
    assert result.exit_code == 1, result.output
    assert f"{mesh}: error: already holds a different version of this file" in result.output
    assert _files(out) == before
