"""The scene readers docs/scenes.md names take what `ssgc.load_grammar` returns.

They took only its `.ir` and raised an AttributeError deep inside ('Grammar' object has no
attribute 'type_ids') for the grammar a notebook holds; render and view already took both.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import ssgc
from ssgc.io.scene import load_scenes, read_scene_file, read_sink_yaml

ROOT = Path(__file__).resolve().parents[1]
SINK = ROOT / "grammars" / "sink.yaml"
DATA = ROOT / "ssgc" / "data" / "sink" / "saved_scenes.yaml"


def test_the_readers_take_a_loaded_grammar(tmp_path):
    g = ssgc.load_grammar(SINK)
    g.sample(1, seed=0)[0].save(tmp_path / "one.json")
    assert len(read_scene_file(tmp_path / "one.json", g).types) > 0
    assert len(load_scenes(tmp_path, g)) == 1
    assert len(read_sink_yaml(DATA, g)) == 80
    assert len(load_scenes(DATA, g.ir)) == 80  # the compiled form still works


@pytest.mark.parametrize("reader", [read_scene_file, load_scenes, read_sink_yaml])
def test_anything_else_is_a_type_error(reader):
    with pytest.raises(TypeError, match="expected a Grammar"):
        reader(DATA, str(SINK))
