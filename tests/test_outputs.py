"""Outputs that never damage what is there (issue 12, docs/robustness.md "Outputs").

Every output of `ssg parse`, `ssg fit` and `ssg sample` is tried where a new user might send
it: devices, directories, the inputs, symbolic links, FIFOs, a closed pipe, a full disk, a
read-only directory; and every write is made to fail (a fake disk that fills up at a chosen
byte) or is killed (SIGKILL at random moments).  Afterwards every file is its old content or
the complete new content, no device or link has changed, no temporary file is left, and a
journal is left only when `--resume` finishes the run from it.

The number of byte faults per command is `SSG_FAULTS`, of SIGKILLed runs per command
`SSG_KILLS` (defaults: a quick run); `-s` prints the counts::

    SSG_FAULTS=40 SSG_KILLS=8 python -m pytest tests/test_outputs.py -q -s -k "fault or sigkill"
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import random
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import GRAMMARS
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import ssgc.io.atomic as atomic
from ssgc.cli.app import app
from ssgc.io.atomic import temp_target
from ssgc.io.resume import MANIFEST

GMM = GRAMMARS / "gmm.yaml"
SINK = GRAMMARS / "sink.yaml"
FAULTS = int(os.environ.get("SSG_FAULTS", "0")) or None  # byte faults per command
KILLS = int(os.environ.get("SSG_KILLS", "0")) or None  # SIGKILLed runs per command
runner = CliRunner()


def run(*args: Any):
    return runner.invoke(app, [str(a) for a in args])


def ssg(*args: Any, **kwargs: Any) -> subprocess.CompletedProcess[bytes]:
    """`ssg ARGS` as a real process (standard output, pipes and devices are real)."""
    return subprocess.run(
        [sys.executable, "-m", "ssgc.cli.app", *map(str, args)], timeout=300, **kwargs
    )


def no_bug(text: str) -> None:
    assert "bug in ssgc" not in text and "Traceback" not in text, text


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Six scenes of the GMM grammar: a dataset quick to parse and fit."""
    out = tmp_path_factory.mktemp("data") / "points"
    assert run("sample", GMM, "-n", 6, "--seed", 5, "-o", out, "-q").exit_code == 0
    return out


@pytest.fixture(scope="module")
def scene(data: Path) -> Path:
    return data / "gmm_000000.json"


def device(path: str) -> tuple[int, int, int]:
    st = os.lstat(path)
    return st.st_mode, st.st_rdev, st.st_ino


DEVICES = ("/dev/null", "/dev/full")


@pytest.fixture
def devices_unchanged() -> Iterator[None]:
    before = {d: device(d) for d in DEVICES}
    link = os.readlink("/dev/stdout")
    yield
    assert {d: device(d) for d in DEVICES} == before
    assert os.path.islink("/dev/stdout") and os.readlink("/dev/stdout") == link


FIT = ("--iterations", 2, "--top", 1, "-q")


# ------------------------------------------------ the cases of the issue, one by one ---


@pytest.mark.usefixtures("devices_unchanged")
def test_devices_are_written_as_streams_never_replaced(scene: Path, data: Path) -> None:
    null = run("parse", scene, "-g", GMM, "-o", "/dev/null", "-q")
    assert null.exit_code == 0, null.output
    full = run("parse", scene, "-g", GMM, "-o", "/dev/full", "-q")
    assert full.exit_code == 1
    assert "/dev/full: error: cannot write the output: No space left on device" in full.output
    no_bug(full.output)
    fit_full = run("fit", data, "-g", GMM, "-o", "/dev/full", *FIT)
    assert (
        fit_full.exit_code == 1 and "/dev/full: error: cannot write the output" in fit_full.output
    )
    report_full = run("fit", data, "-g", GMM, "-o", "/dev/null", "--report", "/dev/full", *FIT)
    assert report_full.exit_code == 1
    assert "/dev/full: error: cannot write the report: No space left on device" in (
        report_full.output
    )
    fit_null = run("fit", data, "-g", GMM, "-o", "/dev/null", "--report", "/dev/null", *FIT)
    assert fit_null.exit_code == 0, fit_null.output
    for journal in Path("/dev").glob("*.partial.jsonl"):
        pytest.fail(f"a journal in /dev: {journal}")
    sample_null = run("sample", GMM, "-n", 2, "-o", "/dev/null")
    assert sample_null.exit_code == 1 and "is not a directory" in sample_null.output


@pytest.mark.usefixtures("devices_unchanged")
def test_dev_stdout_prints_and_stays_a_link(scene: Path, tmp_path: Path) -> None:
    for name in ("/dev/stdout", "-"):
        done = ssg("parse", scene, "-g", GMM, "-o", name, capture_output=True)
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout)["scenes"][0]["status"] == "optimal"
    done = ssg("fit", scene.parent, "-g", GMM, "-o", "/dev/stdout", *FIT, capture_output=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(GMM.read_bytes()[:60])  # the fitted grammar, comments kept
    assert not list(tmp_path.iterdir())


def test_resume_needs_a_file_not_a_stream(scene: Path) -> None:
    for out in ("/dev/null", "-"):
        result = run("parse", scene, "-g", GMM, "-o", out, "--resume")
        assert result.exit_code == 1 and "--resume needs -o OUT.json, a file" in result.output


def test_an_existing_directory_is_refused_before_any_work(
    scene: Path, data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import ssgc.parse.parser as parser

    def no_work(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("work started before the output was checked")

    monkeypatch.setattr(parser.Parser, "parse", no_work)
    target = tmp_path / "out"
    target.mkdir()
    for args in (
        ("parse", scene, "-g", GMM, "-o", target),
        ("fit", data, "-g", GMM, "-o", target, *FIT),
        ("fit", data, "-g", GMM, "-o", tmp_path / "f.yaml", "--report", target, *FIT),
    ):
        result = run(*args)
        assert result.exit_code == 1, result.output
        assert f"{target}: error: the " in result.output and "is a directory" in result.output
        no_bug(result.output)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no journal, no lock
    assert not list(target.iterdir())


@pytest.mark.parametrize("command", [["export", "-f", "glb"], ["settle"]])
def test_a_command_stopped_by_a_mistake_leaves_no_directory_it_made(
    command: list[str], data: Path, tmp_path: Path
) -> None:
    """The output directory (and its missing parents) are made when the command starts; a
    grammar mistake found after that removes them again.  A directory that was there stays."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("grammar: x\nroot: A\ntypes: {A: {observed: maybe}}\n")
    new = tmp_path / "new" / "deeper"
    result = run(*command, data, "-g", bad, "-o", new)
    assert result.exit_code == 1, result.output
    assert not (tmp_path / "new").exists()
    old = tmp_path / "old"
    old.mkdir()
    assert run(*command, data, "-g", bad, "-o", old).exit_code == 1
    assert old.is_dir()


def test_an_input_is_never_an_output(scene: Path, data: Path, tmp_path: Path) -> None:
    grammar = tmp_path / "g.yaml"
    shutil.copy(GMM, grammar)
    dataset = tmp_path / "scene.json"
    shutil.copy(scene, dataset)
    before = {p: p.read_bytes() for p in (grammar, dataset)}
    for args in (
        ("parse", dataset, "-g", grammar, "-o", dataset),
        ("parse", dataset, "-g", grammar, "-o", grammar),
        ("fit", dataset, "-g", grammar, "-o", dataset, *FIT),
        ("fit", dataset, "-g", grammar, "-o", tmp_path / "f.yaml", "--report", grammar, *FIT),
        ("fit", dataset, "-g", grammar, "-o", tmp_path / "f.yaml", "--report", dataset, *FIT),
    ):
        result = run(*args)
        assert result.exit_code == 1, result.output
        assert "is the input file" in result.output, result.output
    link = tmp_path / "link.json"  # the same file under another name
    link.symlink_to(dataset)
    result = run("parse", dataset, "-g", grammar, "-o", link)
    assert result.exit_code == 1 and "is the input file" in result.output
    # An output inside a dataset directory would be read as a scene by the next run.
    inside = run("parse", data, "-g", grammar, "-o", data / "parses.json")
    assert inside.exit_code == 1 and "where it would be read as a scene" in inside.output
    assert {p: p.read_bytes() for p in (grammar, dataset)} == before
    # `ssg fit -o` onto its own grammar is an in-place update, documented.
    in_place = run("fit", data, "-g", grammar, "-o", grammar, *FIT)
    assert in_place.exit_code == 0, in_place.output
    assert grammar.read_bytes() != before[grammar]
    fitted = tmp_path / "fitted.yaml"
    assert run("fit", data, "-g", GMM, "-o", fitted, *FIT).exit_code == 0
    assert grammar.read_bytes() == fitted.read_bytes()
    same = run("fit", data, "-g", GMM, "-o", fitted, "--report", fitted, *FIT)
    assert same.exit_code == 1 and "the report and the output are the same file" in same.output


@pytest.mark.parametrize("command", ["parse", "validate", "inspect"])
def test_a_full_stdout_is_exit_1_not_a_bug(command: str, scene: Path) -> None:
    args = {"parse": ("parse", scene, "-g", GMM), "validate": ("validate", GMM)}
    with open("/dev/full", "wb") as full:
        done = ssg(*args.get(command, ("inspect", GMM)), stdout=full, stderr=subprocess.PIPE)
    assert done.returncode == 1
    stderr = done.stderr.decode()
    assert stderr == "<stdout>: error: cannot write standard output: No space left on device\n"


@pytest.mark.parametrize("command", ["parse", "inspect", "inspect-table", "bench"])
def test_a_closed_pipe_ends_quietly(command: str, scene: Path) -> None:
    """Tables are printed by rich, which ended the program with exit 1 itself."""
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the first byte: `ssg ... | head -c 0`
    args = {
        "parse": ("parse", scene, "-g", GMM),
        "inspect": ("inspect", GMM, "--json"),
        "inspect-table": ("inspect", GMM),
        "bench": ("bench", "parse", GMM, "--scenes", 1),
    }[command]
    try:
        done = ssg(*args, stdout=write, stderr=subprocess.PIPE)
    finally:
        os.close(write)
    assert done.returncode == 141  # as a shell reports a command ended by SIGPIPE
    assert done.stderr == b""


def test_head_of_a_pipe(scene: Path) -> None:
    """`ssg parse ... | head -c 10`: the first bytes, then a quiet end."""
    shell = f"{sys.executable} -m ssgc.cli.app parse {scene} -g {GMM} | head -c 10"
    done = subprocess.run(
        ["bash", "-c", f"set -o pipefail; {shell}"], capture_output=True, timeout=300
    )
    assert done.stdout == b'{\n "gramma'
    assert done.returncode in (0, 141) and done.stderr == b""


def old_run(directory: Path, seed: int = 2, n: int = 30) -> dict[str, bytes]:
    assert run("sample", GMM, "-n", n, "--seed", seed, "-o", directory, "-q").exit_code == 0
    return {p.name: p.read_bytes() for p in directory.iterdir()}


def test_sample_refuses_a_directory_of_another_run(tmp_path: Path) -> None:
    out = tmp_path / "scenes"
    before = old_run(out)
    result = run("sample", GMM, "-n", 5, "--seed", 9, "-o", out)
    assert result.exit_code == 1
    assert 'holds the scenes of another run (30 scene(s) of grammar "gmm", seed 2)' in (
        result.output
    )
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # Without a manifest (a directory of scenes from elsewhere): refused just the same.
    (out / MANIFEST).unlink()
    assert run("sample", GMM, "-n", 5, "--seed", 9, "-o", out).exit_code == 1
    assert run("sample", GMM, "-n", 5, "--seed", 9, "-o", out, "--resume").exit_code == 1
    # The same run again rewrites its own files: allowed.
    again = tmp_path / "again"
    first = old_run(again, seed=9, n=5)
    assert old_run(again, seed=9, n=5) == first
    # --overwrite clears the other run's scenes first; other files stay.
    (out / "README.md").write_text("notes")
    over = run("sample", GMM, "-n", 5, "--seed", 9, "-o", out, "--overwrite", "-q")
    assert over.exit_code == 0, over.output
    assert {p.name: p.read_bytes() for p in out.iterdir()} == {**first, "README.md": b"notes"}
    # ... but never a .json file that `ssg sample` did not name: it would be read as a scene.
    (out / "labels.json").write_text("{}")
    kept = run("sample", GMM, "-n", 5, "--seed", 3, "-o", out, "--overwrite")
    assert kept.exit_code == 1 and "labels.json" in kept.output
    # ... so without --overwrite the message does not suggest it
    told = run("sample", GMM, "-n", 5, "--seed", 3, "-o", out)
    assert told.exit_code == 1 and "labels.json" in told.output
    assert "--overwrite deletes only scene files" in told.output
    both = run("sample", GMM, "-n", 5, "-o", out, "--overwrite", "--resume")
    assert both.exit_code == 1 and "give one" in both.output


def test_sample_into_a_locked_directory_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "scenes"
    before = old_run(out, seed=4, n=5)
    fd = os.open(out / ".ssg.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)  # another writer is running
    try:
        for extra in ((), ("--resume",), ("--overwrite",)):
            result = run("sample", GMM, "-n", 5, "--seed", 4, "-o", out, *extra)
            assert result.exit_code == 1, result.output
            assert "another ssg run is writing this output directory" in result.output
    finally:
        os.close(fd)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == {**before, ".ssg.lock": b""}


def test_a_running_sample_is_not_disturbed_by_a_resume(tmp_path: Path) -> None:
    """`ssg sample -o DIR &` then `ssg sample -o DIR --resume`: the resume is refused by the
    lock and deletes nothing; the first run finishes whole."""
    out = tmp_path / "scenes"
    args = [sys.executable, "-m", "ssgc.cli.app", "sample", SINK, "-n", 1500, "-o", out, "-q"]
    first = subprocess.Popen(list(map(str, args)), stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not (out.is_dir() and len(list(out.glob("*.json"))) >= 20):
            assert first.poll() is None and time.monotonic() < deadline
            time.sleep(0.01)
        for seed in (0, 1):
            resumed = run("sample", SINK, "-n", 1500, "--seed", seed, "-o", out, "--resume")
            assert resumed.exit_code == 1 and "another ssg run is writing" in resumed.output
        assert first.wait(timeout=300) == 0, first.stderr.read() if first.stderr else ""
    finally:
        if first.poll() is None:
            first.kill()
        first.communicate()
    assert len(list(out.glob("*.json"))) == 1500
    assert not [p for p in out.iterdir() if temp_target(p.name)]


def test_two_writers_of_one_file_output(scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "p.json"
    fd = os.open(tmp_path / ".p.json.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        result = run("parse", scene, "-g", GMM, "-o", out)
        assert result.exit_code == 1 and "another ssg run is writing this output" in result.output
    finally:
        os.close(fd)
    assert run("parse", scene, "-g", GMM, "-o", out, "-q").exit_code == 0
    # The lock file a finished (or killed) run left is taken, then removed.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.json"]


def test_unwritable_report_is_found_before_any_work(
    data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import ssgc.fit.em as em

    def no_work(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("work started before the outputs were checked")

    monkeypatch.setattr(em, "fit_grammar", no_work)
    fitted = tmp_path / "fitted.yaml"
    for report in (tmp_path / "missing" / "r.json", tmp_path / "fitted.yaml" / "r.json"):
        result = run("fit", data, "-g", GMM, "-o", fitted, "--report", report, *FIT)
        assert result.exit_code == 1, result.output
        assert f"{report}: error: cannot write the report" in result.output
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------- links, FIFOs, mounts ---


def test_symbolic_links_are_written_through(scene: Path, tmp_path: Path) -> None:
    real = tmp_path / "real.json"
    real.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to(real)
    assert run("parse", scene, "-g", GMM, "-o", link, "-q").exit_code == 0
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert json.loads(real.read_text())["grammar"] == "gmm"
    to_null = tmp_path / "null.json"
    to_null.symlink_to("/dev/null")
    assert run("parse", scene, "-g", GMM, "-o", to_null, "-q").exit_code == 0
    assert os.readlink(to_null) == "/dev/null" and device("/dev/null")[0] & stat.S_IFCHR
    dangling = tmp_path / "dangling.json"
    dangling.symlink_to(tmp_path / "new.json")
    assert run("parse", scene, "-g", GMM, "-o", dangling, "-q").exit_code == 0
    assert dangling.is_symlink() and json.loads((tmp_path / "new.json").read_text())


def test_a_fifo_is_written_as_a_stream(scene: Path, data: Path, tmp_path: Path) -> None:
    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    for args in (("parse", scene, "-g", GMM), ("fit", data, "-g", GMM, *FIT)):
        got: list[bytes] = []
        reader = threading.Thread(target=lambda got=got: got.append(fifo.read_bytes()))
        reader.start()
        result = run(*args, "-o", fifo)
        reader.join(timeout=60)
        assert result.exit_code == 0, result.output
        assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
        assert got and got[0].strip()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.fifo"]


def mount(*args: str) -> bool:
    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


@pytest.fixture
def read_only_dir(tmp_path: Path) -> Iterator[Path]:
    """A directory on a read-only bind mount: root is refused there too (EROFS)."""
    source, target = tmp_path / "source", tmp_path / "ro"
    source.mkdir()
    target.mkdir()
    (source / "old.json").write_text("old")
    if not mount("--bind", str(source), str(target)):
        pytest.skip("cannot bind-mount here (the byte-fault tests cover EROFS)")
    try:
        if not mount("-o", "remount,bind,ro", str(target)):
            pytest.skip("cannot remount read-only here")
        yield target
    finally:
        subprocess.run(["umount", "-l", str(target)], check=False)


def test_read_only_directory(read_only_dir: Path, scene: Path, data: Path) -> None:
    old = read_only_dir / "old.json"
    for args in (
        ("parse", scene, "-g", GMM, "-o", old),
        ("parse", scene, "-g", GMM, "-o", read_only_dir / "new.json"),
        ("fit", data, "-g", GMM, "-o", read_only_dir / "f.yaml", *FIT),
        ("fit", data, "-g", GMM, "-o", "/dev/null", "--report", old, *FIT),
        ("sample", GMM, "-n", 2, "-o", read_only_dir),
        ("sample", GMM, "-n", 2, "-o", read_only_dir / "sub"),
    ):
        result = run(*args)
        assert result.exit_code == 1, result.output
        assert "Read-only file system" in result.output, result.output
    assert sorted(p.name for p in read_only_dir.iterdir()) == ["old.json"]
    assert old.read_text() == "old"


# ------------------------------------------------------------------ fault injection ---


class FillingDisk:
    """`atomic.write_all` on a disk with `room` bytes left: what fits is written, then the
    write fails with `code` (ENOSPC, EIO, ...), as a real device fails part-way."""

    def __init__(self, room: int | None, code: int = errno.ENOSPC) -> None:
        self.room, self.code, self.written, self.failed = room, code, 0, False
        self.real = atomic.write_all

    def __call__(self, fd: int, data: bytes) -> None:
        if self.room is not None and self.written + len(data) > self.room:
            part = self.room - self.written
            self.real(fd, data[:part])
            self.written += part
            self.failed = True
            raise OSError(self.code, os.strerror(self.code))
        self.real(fd, data)
        self.written += len(data)


def normal(path: Path) -> Any:
    """An output's content, without what differs between two runs (times)."""
    try:
        doc = json.loads(path.read_bytes())
    except ValueError:
        return path.read_bytes()
    return _drop(doc, {"timing", "seconds", "mstep_seconds"})


def _drop(doc: Any, keys: set[str]) -> Any:
    if isinstance(doc, dict):
        return {k: _drop(v, keys) for k, v in doc.items() if k not in keys}
    if isinstance(doc, list):
        return [_drop(v, keys) for v in doc]
    return doc


def leftovers(directory: Path) -> list[str]:
    return [p.name for p in directory.iterdir() if temp_target(p.name) or p.name.endswith(".lock")]


ERRNOS = (errno.ENOSPC, errno.EIO, errno.EROFS, errno.EACCES, errno.EDQUOT)


def fault_points(total: int, quick: int) -> list[int]:
    """Byte counts at which the disk fills: the edges and points spread over the run."""
    n = FAULTS or quick
    inner = sorted(random.Random(total).sample(range(1, total), min(n, total - 1)))
    return sorted({0, total - 1, *inner})[: max(n, 2)]


Command = Callable[[Path], list[Any]]


def commands(data: Path, scene: Path) -> dict[str, tuple[Command, list[str]]]:
    """Each command with its file outputs, all of which exist beforehand (old content)."""
    return {
        "parse": (lambda d: ["parse", data, "-g", GMM, "-o", d / "p.json", "-q"], ["p.json"]),
        "fit": (
            lambda d: ["fit", data, "-g", GMM, "-o", d / "f.yaml", "--report", d / "r.json", *FIT],
            ["f.yaml", "r.json"],
        ),
    }


@pytest.mark.parametrize("command", ["parse", "fit"])
def test_fault_injection_file_outputs(
    command: str, data: Path, scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk fills (or fails) at every chosen byte of a run: each output is its old content
    or the complete new one; no temporary file, no lock; a journal only if `--resume` then
    finishes the run with the new content."""
    make, names = commands(data, scene)[command]
    ref = tmp_path / "ref"
    ref.mkdir()
    counter = FillingDisk(None)
    monkeypatch.setattr(atomic, "write_all", counter)
    assert run(*make(ref)).exit_code == 0
    new = {n: normal(ref / n) for n in names}
    failed = damaged = 0
    points = fault_points(counter.written, quick=6)
    for k, room in enumerate(points):
        work = tmp_path / f"w{k}"
        work.mkdir()
        for n in names:
            (work / n).write_text("old " + n)
        disk = FillingDisk(room, ERRNOS[k % len(ERRNOS)])
        monkeypatch.setattr(atomic, "write_all", disk)
        result = run(*make(work))
        monkeypatch.setattr(atomic, "write_all", counter)
        assert disk.failed and result.exit_code == 1, (room, result.output)
        no_bug(result.output)
        assert "cannot write the" in result.output and os.strerror(disk.code) in result.output
        failed += 1
        for n in names:
            content = normal(work / n)
            damaged += content != f"old {n}".encode() and content != new[n]
        assert not leftovers(work), (room, leftovers(work))
        journals = list(work.glob("*.partial.jsonl"))
        if journals:  # kept: then --resume must finish the run
            assert "--resume" in result.output
            resumed = run(*make(work), "--resume")
            assert resumed.exit_code == 0, resumed.output
            assert {n: normal(work / n) for n in names} == new
    print(f"\n{command}: {failed} write points failed, {damaged} damaged files")
    assert damaged == 0


def test_fault_injection_sample(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ref = tmp_path / "ref"
    counter = FillingDisk(None)
    monkeypatch.setattr(atomic, "write_all", counter)
    assert run("sample", GMM, "-n", 40, "--seed", 1, "-o", ref, "-q").exit_code == 0
    new = {p.name: p.read_bytes() for p in ref.iterdir()}
    damaged = 0
    points = fault_points(counter.written, quick=6)
    for k, room in enumerate(points):
        work = tmp_path / f"w{k}"
        disk = FillingDisk(room, ERRNOS[k % len(ERRNOS)])
        monkeypatch.setattr(atomic, "write_all", disk)
        result = run("sample", GMM, "-n", 40, "--seed", 1, "-o", work, "-q")
        monkeypatch.setattr(atomic, "write_all", counter)
        assert disk.failed and result.exit_code == 1, result.output
        assert "cannot write the" in result.output
        no_bug(result.output)
        for p in work.iterdir() if work.exists() else []:  # a first write failed: not made
            if p.name != MANIFEST:
                damaged += p.read_bytes() != new.get(p.name)
        resumed = run("sample", GMM, "-n", 40, "--seed", 1, "-o", work, "-q", "--resume")
        assert resumed.exit_code == 0, resumed.output
        assert {p.name: p.read_bytes() for p in work.iterdir()} == new
    print(f"\nsample: {len(points)} write points failed, {damaged} damaged files")
    assert damaged == 0


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real file system of 512 KiB (tmpfs), where the test is allowed to mount one."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if not mount("-t", "tmpfs", "-o", "size=512k", "tmpfs", str(disk)):
        pytest.skip("cannot mount a tmpfs here (the byte-fault tests cover a full disk)")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def fill(disk: Path, leave: int) -> None:
    """Fill `disk` until at most `leave` bytes are free."""
    (disk / "filler").unlink(missing_ok=True)
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    with open(disk / "filler", "wb") as f:
        try:
            f.write(b"\0" * max(free - leave, 0))
        except OSError:
            pass


def test_nearly_full_file_system(small_disk: Path, data: Path, scene: Path) -> None:
    """Outputs on a real tmpfs with 0 to 64 KiB left: each run writes everything or fails
    with exit 1 leaving the old files (and a journal only if --resume can use it)."""
    make, _ = commands(data, scene)["parse"]
    outcomes = {"written": 0, "failed": 0}
    damaged = 0
    for leave in range(0, 64 * 1024 + 1, 8 * 1024):
        for p in small_disk.iterdir():
            p.unlink()
        (small_disk / "p.json").write_text("old")
        fill(small_disk, leave)
        result = run(*make(small_disk))
        no_bug(result.output)
        assert result.exit_code in (0, 1), result.output
        outcomes["written" if result.exit_code == 0 else "failed"] += 1
        content = normal(small_disk / "p.json")
        if result.exit_code == 0:
            damaged += not isinstance(content, dict)
        else:
            assert "No space left on device" in result.output
            damaged += content != b"old"
        assert not leftovers(small_disk)
        journals = list(small_disk.glob("*.partial.jsonl"))
        if journals:
            (small_disk / "filler").unlink()
            assert run(*make(small_disk), "--resume").exit_code == 0
            damaged += not isinstance(normal(small_disk / "p.json"), dict)
    print(f"\ntmpfs: {outcomes}, {damaged} damaged files")
    assert outcomes["failed"] and outcomes["written"] and damaged == 0


# ---------------------------------------------------------------- SIGKILL at random ---


def kill_runs(
    tmp_path: Path,
    name: str,
    argv: Callable[[Path], list[Any]],
    prepare: Callable[[Path], None],
    check: Callable[[Path], int],
    runs: int,
    rng: random.Random,
) -> tuple[int, int]:
    """Start `ssg` `runs` times and SIGKILL it after a random delay within a full run's
    time; returns (runs killed while writing, files damaged)."""
    ref = tmp_path / f"{name}-ref"
    ref.mkdir()
    prepare(ref)
    started = time.monotonic()
    assert ssg(*argv(ref), capture_output=True).returncode == 0
    full = time.monotonic() - started
    killed = damaged = 0
    for k in range(runs):
        work = tmp_path / f"{name}-{k}"
        work.mkdir()
        prepare(work)
        cmd = [sys.executable, "-m", "ssgc.cli.app", *map(str, argv(work))]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            proc.wait(timeout=rng.uniform(0.3, 1.0) * full)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGKILL)
        proc.wait()
        killed += proc.returncode == -signal.SIGKILL
        damaged += check(work)
    return killed, damaged


def test_sigkill_at_random_points(data: Path, tmp_path: Path) -> None:
    rng = random.Random(os.environ.get("SSG_FAULT_SEED", "12"))
    runs = KILLS or 1
    parsed_ref = tmp_path / "parse-ref" / "p.json"
    null = device("/dev/null")

    def prepare_parse(d: Path) -> None:
        (d / "real.json").write_text("old")
        (d / "p.json").symlink_to(d / "real.json")

    def check_parse(d: Path) -> int:
        ok = (d / "p.json").is_symlink()
        content = normal(d / "real.json")
        ok = ok and (content == b"old" or content == normal(parsed_ref))
        return int(not ok)

    fitted_ref = tmp_path / "fit-ref"

    def prepare_fit(d: Path) -> None:
        (d / "f.yaml").write_text("old")
        (d / "r.json").write_text("old")

    def check_fit(d: Path) -> int:
        bad = 0
        for n in ("f.yaml", "r.json"):
            content = normal(d / n)
            bad += content not in (b"old", normal(fitted_ref / n))
        return bad + (device("/dev/null") != null)

    sample_ref = tmp_path / "sample-ref"

    def check_sample(d: Path) -> int:
        out = d / "s"
        if not out.exists():
            return 0
        return sum(
            p.read_bytes() != (sample_ref / "s" / p.name).read_bytes()
            for p in out.iterdir()
            if p.name not in (MANIFEST, ".ssg.lock") and not temp_target(p.name)
        )

    total_killed = total_damaged = 0
    for name, argv, prepare, check in (
        (
            "parse",
            lambda d: ["parse", data, "-g", GMM, "-o", d / "p.json", "-q"],
            prepare_parse,
            check_parse,
        ),
        (
            "fit",
            lambda d: ["fit", data, "-g", GMM, "-o", d / "f.yaml", "--report", d / "r.json", *FIT],
            prepare_fit,
            check_fit,
        ),
        (
            "sample",
            lambda d: ["sample", SINK, "-n", 600, "-o", d / "s", "-q"],
            lambda d: None,
            check_sample,
        ),
    ):
        killed, damaged = kill_runs(tmp_path, name, argv, prepare, check, runs, rng)
        total_killed += killed
        total_damaged += damaged
    print(f"\nSIGKILL: {total_killed} of {3 * runs} runs killed, {total_damaged} damaged files")
    assert total_damaged == 0


# ------------------------------------------------------------- any output, fuzzed ---

FUZZ = os.environ.get("SSG_FUZZ", "quick")
OUTPUT_CASES = {"quick": 40, "long": 10_000}.get(FUZZ) or int(FUZZ)


def output_kinds(base: Path, inputs: dict[str, Path]) -> dict[str, str]:
    """Places a user might send an output to, made in `base` (fresh for each case)."""
    (base / "dir").mkdir()
    (base / "file.json").write_text("old")
    (base / "link").symlink_to(base / "file.json")
    (base / "dirlink").symlink_to(base / "dir")
    (base / "dangling").symlink_to(base / "gone" / "x.json")
    (base / "loop").symlink_to(base / "loop")
    (base / "devlink").symlink_to("/dev/null")
    return {
        "null": "/dev/null",
        "full": "/dev/full",
        "stdout": "/dev/stdout",
        "dash": "-",
        "dir": str(base / "dir"),
        "dir/": str(base / "dir") + "/",
        "file": str(base / "file.json"),
        "new": str(base / "new.json"),
        "link": str(base / "link"),
        "dirlink": str(base / "dirlink"),
        "dangling": str(base / "dangling"),
        "loop": str(base / "loop"),
        "devlink": str(base / "devlink"),
        "through a file": str(base / "file.json" / "x.json"),
        "missing parent": str(base / "no" / "such" / "x.json"),
        "long name": str(base / ("x" * 300)),
        "nul": str(base / "a\0b"),
        "dot": str(base) + "/.",  # never the working directory: the test must not write there
        **{f"input {k}": str(v) for k, v in inputs.items()},
    }


def state(path: Path) -> Any:
    """What must not change: the kind of file, a link's target, a device's identity."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    if stat.S_ISLNK(st.st_mode):
        return ("link", os.readlink(path))
    if stat.S_ISDIR(st.st_mode):
        return ("dir",)
    if stat.S_ISREG(st.st_mode):
        return ("file",)
    return ("special", st.st_mode, st.st_rdev, st.st_ino)


@settings(max_examples=OUTPUT_CASES, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    command=st.sampled_from(["parse", "fit", "sample"]),
    output=st.integers(0, 100),
    report=st.one_of(st.none(), st.integers(0, 100)),
)
def test_fuzz_output_paths(
    data: Path,
    tmp_path_factory: pytest.TempPathFactory,
    command: str,
    output: int,
    report: int | None,
) -> None:
    """Any command with any output (and `--report`): exit 0 or 1, a message, never a bug; no
    device, link or input changed; no temporary file or lock left."""
    base = tmp_path_factory.mktemp("out")
    grammar = base / "g.yaml"
    shutil.copy(GMM, grammar)
    scene = base / "scene.json"
    shutil.copy(data / "gmm_000000.json", scene)
    inputs = {"grammar": grammar, "scene": scene}
    kinds = output_kinds(base, inputs)
    names = sorted(kinds)
    out = kinds[names[output % len(names)]]
    watched = [Path(p) for p in (*DEVICES, "/dev/stdout", *kinds.values()) if "\0" not in p]
    before = {p: state(p) for p in watched}
    input_bytes = {p: p.read_bytes() for p in inputs.values()}
    args: list[Any]
    if command == "parse":
        args = ["parse", scene, "-g", grammar, "-o", out, "-q"]
    elif command == "fit":
        args = ["fit", scene, "-g", grammar, "-o", out, *FIT]
        if report is not None:
            args += ["--report", kinds[names[report % len(names)]]]
    else:
        args = ["sample", grammar, "-n", 2, "-o", out, "-q"]
    result = run(*args)
    shown = f"{args}\n{result.output}"
    usage = result.exit_code == 2 and "Invalid value" in result.output  # typer: a NUL in a name
    assert result.exit_code in (0, 1) or usage, shown
    assert result.exception is None or isinstance(result.exception, SystemExit), shown
    no_bug(result.output)
    if result.exit_code == 1:
        assert ": error: " in result.output, shown
    for p, was in before.items():
        now = state(p)
        if was is not None and was[0] in ("link", "special", "dir"):
            assert now == was, (p, shown)
    if out != str(grammar) or command != "fit":  # `fit -o GRAMMAR` updates it, on purpose
        assert {p: p.read_bytes() for p in inputs.values()} == input_bytes, shown
    for directory in (base, base / "dir"):
        assert not leftovers(directory), (leftovers(directory), shown)


# ------------------------------------- the outputs of the commands that came later ---
# `ssg render`, `ssg inspect --diagram`, `ssg explain -o`, `ssg export` and `ssg settle` go
# through the same checks (ssgc/io/outputs.py): the same cases, one test per command.


@pytest.mark.usefixtures("devices_unchanged")
def test_pictures_to_devices_and_stdout(scene: Path, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    null = run("render", scene, "-o", "/dev/null", "-q")
    assert null.exit_code == 0, null.output
    full = run("render", scene, "-o", "/dev/full", "-q")
    assert full.exit_code == 1 and "No space left on device" in full.output
    no_bug(full.output)
    piped = ssg("render", scene, "-o", "-", "-q", capture_output=True)
    assert piped.returncode == 0 and piped.stdout.startswith(b"\x89PNG"), piped.stderr
    diagram = run("inspect", GMM, "--diagram", "/dev/null")
    assert diagram.exit_code == 0, diagram.output
    onto_input = run("render", scene, "-o", scene)
    assert onto_input.exit_code == 1 and json.loads(scene.read_text())["objects"]
    folder = tmp_path / "a_dir.png"
    folder.mkdir()
    assert run("render", scene, "-o", folder).exit_code == 1 and folder.is_dir()


@pytest.mark.usefixtures("devices_unchanged")
def test_view_page_and_fit_plots_checked_first(scene: Path, tmp_path: Path) -> None:
    assert run("view", scene, "-o", "/dev/null", "-q").exit_code == 0
    full = run("view", scene, "-o", "/dev/full", "-q")
    assert full.exit_code == 1 and "No space left on device" in full.output
    no_bug(full.output)
    piped = ssg("view", scene, "-o", "-", "-q", capture_output=True)
    assert piped.returncode == 0 and piped.stdout.startswith(b"<!DOCTYPE html>"), piped.stderr
    before = scene.read_bytes()
    assert run("view", scene, "-o", scene).exit_code == 1 and scene.read_bytes() == before
    folder = tmp_path / "a_dir.html"
    folder.mkdir()
    assert run("view", scene, "-o", folder).exit_code == 1 and folder.is_dir()
    pytest.importorskip("matplotlib")
    fitted = tmp_path / "fitted.yaml"
    a_file = tmp_path / "plots"
    a_file.write_text("keep")
    for plots in (a_file, tmp_path / "missing", "/dev/null"):
        result = run("fit", scene, "-g", GMM, "-o", fitted, "--plot", plots)
        assert result.exit_code == 1, (plots, result.output)
        no_bug(result.output)
        assert not fitted.exists() and a_file.read_text() == "keep"


@pytest.mark.usefixtures("devices_unchanged")
def test_explain_output_checked_first(scene: Path, tmp_path: Path) -> None:
    before = scene.read_bytes()
    onto_input = run("explain", scene, "-g", GMM, "-o", scene)
    assert onto_input.exit_code == 1 and scene.read_bytes() == before
    full = run("explain", scene, "-g", GMM, "-o", "/dev/full")
    assert full.exit_code == 1 and "No space left on device" in full.output
    no_bug(full.output)
    assert run("explain", scene, "-g", GMM, "-o", "/dev/null").exit_code == 0


def test_export_and_settle_directories_checked_first(data: Path, tmp_path: Path) -> None:
    a_file = tmp_path / "file"
    a_file.write_text("keep")
    for args in (
        ("export", data, "-g", GMM, "--format", "glb", "-o", a_file),
        ("export", data, "-g", GMM, "--format", "glb", "-o", "/dev/null"),
        ("settle", data, "-g", GMM, "-o", a_file),
        ("settle", data, "-g", GMM, "-o", data),
    ):
        before = {p.name: p.read_bytes() for p in data.iterdir() if p.is_file()}
        result = run(*args)
        assert result.exit_code == 1, (args, result.output)
        no_bug(result.output)
        assert a_file.read_text() == "keep"
        assert {p.name: p.read_bytes() for p in data.iterdir() if p.is_file()} == before
    report = run(
        "settle", data, "-g", GMM, "-o", tmp_path / "s", "--report", tmp_path / "no/r.json"
    )
    assert report.exit_code == 1 and not (tmp_path / "s").exists(), report.output


# ------------------------------------------------------------- Ctrl-C while writing ---


def test_ctrl_c_taken_by_another_thread_leaves_no_temporary_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A Ctrl-C is delivered to whichever thread does not block SIGINT (rich's refresh thread,
    a worker's), and Python then raises KeyboardInterrupt in the main thread at its next
    bytecode, whatever the main thread's signal mask: here inside `mkstemp`, just after the
    temporary file was created (seen once in six runs of
    test_resume.py::test_sample_interrupted_with_ctrl_c_then_resumed, leaving
    .sink_000300.json.odu7vsfe.tmp).  The write must still end with the file removed.

    The other thread exists before the write (as those threads do) and sends the signal to
    itself, which delivers it before `pthread_kill` returns: the handler is pending in the main
    thread when `mkstemp` returns, however loaded the machine.  (A process-directed `os.kill`
    let the kernel pick a thread that might run only after the write had ended.)"""
    real = atomic.tempfile.mkstemp
    go, sent = threading.Event(), threading.Event()

    def other_thread() -> None:
        go.wait()
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)
        sent.set()

    def mkstemp_then_ctrl_c(*args: Any, **kwargs: Any) -> tuple[int, str]:
        made = real(*args, **kwargs)
        go.set()
        sent.wait()
        return made

    other = threading.Thread(target=other_thread)
    other.start()
    monkeypatch.setattr(atomic.tempfile, "mkstemp", mkstemp_then_ctrl_c)
    target = tmp_path / "scene.json"
    # Ctrl-C as in a terminal: pytest started as a background job inherits an ignored SIGINT
    ignored = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            atomic.write_text_atomic(target, "{}")
    finally:
        signal.signal(signal.SIGINT, ignored)
        go.set()
        other.join()
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    ("package", "option", "needs"),
    [("mujoco", ["--settle"], "MuJoCo"), ("pxr", ["--export", "usd"], "usd-core")],
)
def test_sample_refuses_a_missing_package_before_writing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, package: str, option: list[str], needs: str
) -> None:
    """It said so at the first scene, after the manifest: a directory of no scene was left."""
    monkeypatch.setitem(sys.modules, package, None)  # `import` then raises ImportError
    out = tmp_path / "scenes"
    result = run("sample", GMM, "-n", 2, "-o", out, *option)
    assert result.exit_code == 1, result.output
    assert needs in result.output and "Traceback" not in result.output
    assert not out.exists()


def test_a_picture_or_report_on_stdout_gets_no_closing_line_in_it(
    scene: Path, data: Path, tmp_path: Path
) -> None:
    """docs/robustness.md: output on stdout has no closing line.  `ssg inspect --diagram -`
    and `ssg render -o -` wrote "drew ... to -" after the PNG's last chunk, and `ssg settle
    --report -` its per-scene lines and summary into the JSON."""
    pytest.importorskip("matplotlib")
    for args in (["inspect", GMM, "--diagram", "-"], ["render", scene, "-o", "-"]):
        done = ssg(*args, capture_output=True)
        assert done.returncode == 0, done.stderr
        assert done.stdout.endswith(b"IEND\xaeB`\x82") and b"drew" in done.stderr
    pytest.importorskip("mujoco")
    args = ["settle", data, "-g", GMM, "-o", tmp_path / "s", "--report", "-"]
    done = ssg(*args, capture_output=True)
    assert done.returncode == 0, done.stderr
    assert set(json.loads(done.stdout)) == {"summary", "scenes"} and b"settled" in done.stderr


def test_ctrl_c_while_ssg_starts_is_one_line() -> None:
    """A Ctrl-C in the second the command line's modules take to import printed a traceback
    of the import system; it is `ssg: interrupted` and exit 130, as during a command."""
    code = (
        "import builtins, sys\n"
        "real = builtins.__import__\n"
        "def stop(name, *args, **kwargs):\n"
        "    if name == 'ssgc.cli.app':\n"
        "        raise KeyboardInterrupt\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = stop\n"
        "sys.argv = ['ssg', '--version']\n"
        "from ssgc.cli.launch import main\n"
        "main()\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stderr) == (130, "ssg: interrupted\n")


@pytest.mark.parametrize(
    "command",
    [
        ("parse", "{scene}", "-g", GMM, "-q", "-o"),
        ("explain", "{scene}", "-g", GMM, "-o"),
        ("fit", "{data}", "-g", GMM, *FIT, "-o"),
        ("fit", "{data}", "-g", GMM, *FIT, "-o", "{tmp}/fitted.yaml", "--report"),
        ("render", "{scene}", "-o"),
        ("view", "{scene}", "-o"),
        ("inspect", GMM, "--diagram"),
    ],
)
def test_a_trailing_slash_on_a_file_output_is_refused(
    command: tuple[Any, ...], scene: Path, data: Path, tmp_path: Path
) -> None:
    """`-o notes.txt/` asks for a directory (as `cp` reads it); pathlib drops the slash, which
    once wrote the output into the file `notes.txt`.  Real processes: the check reads argv."""
    notes = tmp_path / "notes.txt"
    notes.write_text("precious\n")
    *words, option = [str(w).format(scene=scene, data=data, tmp=tmp_path) for w in command]
    long = {"-o": "--output"}.get(option, option)
    for name, args in [
        (f"{notes}/", [option, f"{notes}/"]),
        (f"{tmp_path}/new.txt//", [f"{long}={tmp_path}/new.txt//"]),
    ]:
        done = ssg(*words, *args, capture_output=True)
        assert done.returncode == 1, done.stderr
        assert done.stderr.decode().strip().endswith(f"{name}: error: not a directory")
    assert notes.read_text() == "precious\n"
    assert not (tmp_path / "new.txt").exists()


def test_a_python_callers_path_is_not_read_against_the_process_words(tmp_path, monkeypatch):
    """The trailing-slash check reads the running `ssg` command's words; a Python caller's
    `Path("out")` was refused because the host process (a notebook, pytest) had `out/` on its
    own command line."""
    import sys

    from ssgc.io.outputs import check_output

    target = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["python", f"{target}/"])
    assert check_output(target, "page").target == target
