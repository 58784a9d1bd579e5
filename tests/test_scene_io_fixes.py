"""Scene files and outputs: the fixes of a report-only hunt (text in strings kept as written,
size limits on streams, every bad file of a directory reported, dangling links, long output
names)."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Any

import pytest
from conftest import GRAMMARS
from typer.testing import CliRunner

import ssgc.io.scene as scene_io
from ssgc.cli.app import app
from ssgc.compile import load_grammar
from ssgc.errors import SceneError, SsgError
from ssgc.io import atomic, outputs
from ssgc.io.journal import journal_path
from ssgc.io.scene import dumps_json, json_files, load_scenes
from ssgc.yamlio import MAX_GRAMMAR_BYTES, read_text

GMM = GRAMMARS / "gmm.yaml"
SINK = GRAMMARS / "sink.yaml"
runner = CliRunner()
NAME_MAX = 255  # bytes in one file name (Linux, macOS)
TEMP_EXTRA = len("..12345678.tmp")  # what a temporary file's name adds to its target's
needs_fifo = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")


def run(*args: Any):
    return runner.invoke(app, [str(a) for a in args])


def point_scene(name: str, type_: str = "Point", xyz: Any = (0.5, -1.0, 0.5)) -> dict:
    """A scene of gmm.yaml: the root marker at the origin and one point."""
    objects = [
        {"type": "Root", "pose": {"xyz": [0.0, 0.0, 0.0]}},
        {"type": type_, "pose": {"xyz": list(xyz)}},
    ]
    return {"name": name, "objects": objects}


def write(path: Path, doc: Any) -> Path:
    path.write_text(json.dumps(doc))
    return path


# ------------------------------------------- 1: text in strings is never rewritten ---


ODD_STRINGS = ["mug[1,   2]", "shelf [3 ,4 ] moved", "[ 7 ]", 'a\\" [1,  2] "[ 3 ]', "[-1,\n 2]"]


@pytest.mark.parametrize("text", ODD_STRINGS)
def test_dumps_json_writes_strings_as_they_are(text):
    doc = {"name": text, "metadata": {text: [text]}, "xyz": [1.0, 2.0, 3.0]}
    out = dumps_json(doc)
    assert json.loads(out) == doc
    assert '"xyz": [1.0, 2.0, 3.0]' in out  # number lists are still on one line


def test_dumps_json_layout_of_number_lists_is_kept():
    doc = {"a": [1, 2.5, -3], "b": {"c": [[1, 2], [3, 4]], "e": []}, "s": "x", "n": [1, None]}
    expected = (
        '{\n "a": [1, 2.5, -3],\n "b": {\n  "c": [\n   [1, 2],\n   [3, 4]\n  ],\n'
        '  "e": []\n },\n "s": "x",\n "n": [1, null]\n}\n'
    )
    assert dumps_json(doc) == expected


def test_parse_output_keeps_a_scene_name_that_looks_like_a_list(tmp_path):
    src = write(tmp_path / "s.json", point_scene("mug[1,   2]"))
    out = tmp_path / "p.json"
    result = run("parse", src, "-g", GMM, "-o", out)
    assert result.exit_code == 0, result.output
    assert json.loads(out.read_text())["scenes"][0]["name"] == "mug[1,   2]"


# ---------------------------------------- 2: the size limit of devices and pipes ---


def _feed(fifo: Path, size: int) -> threading.Thread:
    """A writer that puts `size` bytes into `fifo` (and gives up when the reader stops)."""

    def write_all() -> None:
        try:
            with open(fifo, "wb") as f:
                for start in range(0, size, 1 << 16):
                    f.write(b"#" * min(1 << 16, size - start))
        except BrokenPipeError:
            pass

    thread = threading.Thread(target=write_all, daemon=True)
    thread.start()
    return thread


@needs_fifo
def test_a_fifo_over_the_limit_is_refused(tmp_path):
    fifo = tmp_path / "in.json"
    os.mkfifo(fifo)
    _feed(fifo, 10_000)
    with pytest.raises(SsgError) as exc:
        read_text(fifo, 1000, "scene file")
    assert str(exc.value) == (
        f"{fifo}: error: scene file is more than 1,000 bytes, over the limit of 1,000 bytes"
    )


@needs_fifo
def test_a_grammar_fifo_over_4_mib_is_refused(tmp_path):
    fifo = tmp_path / "g.yaml"
    os.mkfifo(fifo)
    _feed(fifo, MAX_GRAMMAR_BYTES + 100)
    with pytest.raises(SsgError, match=r"grammar file is more than 4,194,304 bytes, over the"):
        read_text(fifo, MAX_GRAMMAR_BYTES, "grammar file")


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="no /dev/zero here")
def test_dev_zero_is_refused_not_read_for_ever():
    with pytest.raises(SsgError, match="more than 4,096 bytes, over the limit"):
        read_text(Path("/dev/zero"), 4096, "scene file")


@needs_fifo
def test_ssg_parse_of_a_large_stream_is_one_message_and_exit_1(tmp_path, monkeypatch):
    monkeypatch.setattr(scene_io, "MAX_SCENE_BYTES", 1000)
    fifo = tmp_path / "in.json"
    os.mkfifo(fifo)
    _feed(fifo, 5000)
    result = run("parse", fifo, "-g", GMM, "-o", tmp_path / "p.json")
    assert result.exit_code == 1
    assert result.output.strip().endswith("over the limit of 1,000 bytes"), result.output
    assert not (tmp_path / "p.json").exists()


def test_a_small_stream_is_still_read(tmp_path):
    """A size that is exactly the limit is read: only more than it is refused."""
    path = tmp_path / "a.txt"
    path.write_text("x" * 1000)
    assert read_text(path, 1000, "scene file") == "x" * 1000


# ---------------------------------------- 3: every bad file of a directory is said ---


def test_a_directory_reports_every_bad_file(tmp_path, sink):
    good = {"objects": [{"type": "DishBin", "pose": {"xyz": [0, 0, 0]}}]}
    write(tmp_path / "a_good.json", good)
    (tmp_path / "b_nan.json").write_text(
        '{"objects": [{"type": "DishBin", "pose": {"xyz": [NaN, 0, 0]}}]}'
    )
    for name, type_ in (("c_unknown", "NoSuchType"), ("d_latent", "Plate")):
        write(tmp_path / f"{name}.json", {"objects": [{"type": type_, "pose": {"xyz": [0, 0, 0]}}]})
    with pytest.raises(SceneError) as exc:
        load_scenes(tmp_path, sink)
    files = [Path(d.file or "").name for d in exc.value.diagnostics]
    assert files == ["b_nan.json", "c_unknown.json", "d_latent.json"]
    assert all(d.line is not None for d in exc.value.diagnostics)


def test_ssg_parse_of_a_directory_prints_the_first_30_mistakes(tmp_path):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for i in range(40):
        write(scenes / f"s{i:02d}.json", point_scene(f"s{i}", type_="Nope"))
    result = run("parse", scenes, "-g", GMM, "-o", tmp_path / "p.json")
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 31 and lines[-1] == "... and 10 more", result.output
    assert lines[1].startswith(str(scenes / "s01.json")), lines[1]
    assert not (tmp_path / "p.json").exists()


# ------------------------------------------------- 4: a dangling link is an error ---


def test_a_dangling_link_in_a_directory_is_a_located_error(tmp_path):
    write(tmp_path / "a.json", point_scene("a"))
    (tmp_path / "b.json").symlink_to(tmp_path / "missing.json")
    with pytest.raises(SceneError) as exc:
        load_scenes(tmp_path, load_grammar(GMM))
    assert str(exc.value) == (
        f"{tmp_path / 'b.json'}: error: scene file not found (a symbolic link to a missing file)"
    )


@needs_fifo
def test_json_files_keep_dangling_links_and_skip_fifos_and_directories(tmp_path):
    write(tmp_path / "a.json", point_scene("a"))
    (tmp_path / "b.json").symlink_to("nowhere.json")
    (tmp_path / "c.json").mkdir()
    os.mkfifo(tmp_path / "d.json")
    (tmp_path / "e.json").symlink_to("a.json")
    assert [p.name for p in json_files(tmp_path)] == ["a.json", "b.json", "e.json"]


def test_ssg_parse_of_a_directory_with_a_dangling_link_exits_1(tmp_path):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    write(scenes / "a.json", point_scene("a"))
    (scenes / "b.json").symlink_to(tmp_path / "gone.json")
    result = run("parse", scenes, "-g", GMM, "-o", tmp_path / "p.json")
    assert result.exit_code == 1
    assert "b.json: error: scene file not found" in result.output, result.output
    assert not (tmp_path / "p.json").exists()


# ------------------------------------------ 6c: long output names and their helpers ---


def test_fitted_name_keeps_short_names_and_shortens_long_ones():
    assert atomic.fitted_name("out.json", TEMP_EXTRA) == "out.json"
    assert atomic.fitted_name("a" * 241, 14) == "a" * 241
    long_a, long_b = "é" * 120 + "a.json", "é" * 120 + "b.json"
    fitted = {atomic.fitted_name(n, TEMP_EXTRA) for n in (long_a, long_b)}
    assert len(fitted) == 2
    for name in fitted:
        assert len(os.fsencode(name)) + TEMP_EXTRA <= NAME_MAX
        assert name.startswith("é" * 10)


@pytest.mark.parametrize("length", [236, 245])
def test_aux_names_of_a_long_output_fit_in_a_file_name(tmp_path, length):
    out = tmp_path / ("a" * length + ".json")
    journal = journal_path(out)
    assert len(os.fsencode(journal.name)) <= NAME_MAX
    for name in (out.name, journal.name):
        assert len(os.fsencode(f".{atomic.temp_part(name)}.12345678.tmp")) <= NAME_MAX
        assert len(os.fsencode(f".{outputs.lock_part(name)}.lock")) <= NAME_MAX


@pytest.mark.parametrize("command", ["parse", "explain"])
def test_a_long_output_name_is_written(tmp_path, command):
    src = write(tmp_path / "s.json", point_scene("s"))
    outs = tmp_path / "o"
    outs.mkdir()
    out = outs / ("a" * 245 + ".json")
    stale = outs / f".{atomic.temp_part(out.name)}.abcd1234.tmp"  # a killed run's temporary file
    stale.write_text("{")
    result = run(command, src, "-g", GMM, "-o", out)
    assert result.exit_code == 0, result.output
    scene = json.loads(out.read_text())["scenes"][0]
    assert scene["name" if command == "parse" else "scene"] == "s"
    assert {p.name for p in outs.iterdir()} - {stale.name} == {out.name}  # no lock, no journal
    if command == "parse":  # its journal's start removes a killed run's temporary files
        assert not stale.exists()


def test_a_scene_name_of_more_than_1000_characters_is_refused(tmp_path: Path) -> None:
    """A 100,000-character name was printed whole, twice, in each no-parse line (200 KB)."""
    from ssgc.io.scene import MAX_NAME

    doc = {"name": "n" * (MAX_NAME + 1), "objects": []}
    (tmp_path / "long.json").write_text(json.dumps(doc))
    result = runner.invoke(app, ["parse", str(tmp_path / "long.json"), "-g", str(SINK)])
    assert result.exit_code == 1
    assert "a scene name is at most 1,000 characters" in result.output
    assert len(result.output) < 1000
