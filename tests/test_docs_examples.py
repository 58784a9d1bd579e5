"""The examples of docs/grammar.md and docs/scenes.md are real.

Every ```yaml block of grammar.md with a top-level `grammar:` key compiles (without warnings);
every ```json block of scenes.md with `"objects"` reads with a bundled grammar (sink.yaml, or the
one named by a `<!-- grammar: grammars/NAME.yaml -->` line just before the block), and so does
every sink-format ```yaml block of scenes.md.  The messages, numbers and outputs the docs quote
are checked against what ssgc produces.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from ruamel.yaml import YAML

from ssgc import dsl
from ssgc.compile import compile_text, load_grammar
from ssgc.distributions.discrete import CountLaw
from ssgc.errors import SsgError
from ssgc.io.scene import dumps_scene, parse_scene_text, read_sink_yaml, scene_from_tree
from ssgc.ir import Grammar
from ssgc.sample.forward import chunk_rng, sample_chunk, sample_trees
from ssgc.score import score_trees

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
GRAMMARS = ROOT / "grammars"
MARKER = re.compile(r"^<!--\s*grammar:\s*(\S+)\s*-->$")


@dataclass(frozen=True)
class Block:
    lang: str
    text: str
    line: int  # line of the opening fence, 1-based
    grammar: str | None  # from a marker comment on the line before the fence

    def __str__(self) -> str:
        return f"{self.lang}@{self.line}"


@cache
def doc(name: str) -> str:
    return (DOCS / name).read_text(encoding="utf-8")


@cache
def blocks(name: str) -> tuple[Block, ...]:
    """Fenced code blocks of a doc, in order."""
    out: list[Block] = []
    lines = doc(name).splitlines()
    i = 0
    while i < len(lines):
        opening = re.match(r"^```(\S*)\s*$", lines[i])
        if not opening:
            i += 1
            continue
        end = i + 1
        while end < len(lines) and not lines[end].startswith("```"):
            end += 1
        assert end < len(lines), f"{name}:{i + 1}: unclosed code block"
        before = lines[i - 1].strip() if i > 0 else ""
        marker = MARKER.match(before)
        text = "\n".join(lines[i + 1 : end]) + "\n"
        out.append(Block(opening[1], text, i + 1, marker[1] if marker else None))
        i = end + 1
    return tuple(out)


def top_level_keys(text: str) -> set[str]:
    return {m[1] for m in re.finditer(r"^([A-Za-z_][A-Za-z0-9_]*):", text, re.M)}


def grammar_blocks() -> list[Block]:
    return [
        b for b in blocks("grammar.md") if b.lang == "yaml" and "grammar" in top_level_keys(b.text)
    ]


def scene_blocks() -> list[Block]:
    return [b for b in blocks("scenes.md") if b.lang == "json" and '"objects"' in b.text]


def dataset_blocks() -> list[Block]:
    return [b for b in blocks("scenes.md") if b.lang == "yaml"]


def text_blocks(name: str) -> list[str]:
    return [b.text for b in blocks(name) if b.lang in ("text", "console")]


@cache
def bundled(path: str) -> Grammar:
    return load_grammar(ROOT / path)


def grammar_for(block: Block) -> Grammar:
    return bundled(block.grammar or "grammars/sink.yaml")


def block_compiling(grammar_name: str) -> Block:
    pattern = re.compile(rf"^grammar: {grammar_name}$", re.M)
    (found,) = [b for b in grammar_blocks() if pattern.search(b.text)]
    return found


def messages(exc: SsgError) -> list[str]:
    return [str(d) for d in exc.diagnostics]


def shown(message: str, name: str) -> bool:
    """Whether `message` is one of the lines of a text/console block of the doc."""
    return any(message in block.splitlines() for block in text_blocks(name))


# ------------------------------------------------------------------- grammar.md ---


def test_grammar_doc_has_examples() -> None:
    assert len(grammar_blocks()) >= 10


# A box with a pinned axis (min == max) makes ssgc/ir.py take log(0) before masking the axis out;
# the result is right, the RuntimeWarning is noise (the CLI silences numpy warnings).
@pytest.mark.filterwarnings("ignore:divide by zero encountered in log:RuntimeWarning")
@pytest.mark.parametrize("block", grammar_blocks(), ids=str)
def test_grammar_example_compiles(block: Block) -> None:
    grammar = compile_text(block.text, f"docs/grammar.md@{block.line}")
    assert grammar.warnings == (), [str(w) for w in grammar.warnings]


def test_every_yaml_block_of_grammar_doc_is_a_grammar() -> None:
    yaml_blocks = [b for b in blocks("grammar.md") if b.lang == "yaml"]
    assert yaml_blocks == grammar_blocks()


def test_overview_example_counts_and_error() -> None:
    block = block_compiling("kitchen_shelf")
    g = compile_text(block.text, "kitchen_shelf.yaml")
    assert shown(
        f"kitchen_shelf.yaml: ok ({len(g.types)} types, {len(g.rules)} rules)", "grammar.md"
    )
    broken = block.text.replace("        p: 0.3\n", "", 1)
    assert broken != block.text
    with pytest.raises(SsgError) as exc:
        compile_text(broken, "kitchen_shelf.yaml")
    (message,) = messages(exc.value)
    assert shown(message, "grammar.md"), message


def test_recursion_error_and_stack_probabilities() -> None:
    block = block_compiling("stack")
    unbounded = re.sub(r"^\s*max_nesting: 3.*\n", "", block.text, flags=re.M)
    assert unbounded != block.text
    with pytest.raises(SsgError) as exc:
        compile_text(unbounded, "stack.yaml")
    (message,) = messages(exc.value)
    assert shown(message, "grammar.md"), message

    # A sampled tree's log_prob is exact here (fixed offsets): one per (height, top), summed.
    g = compile_text(block.text)
    trees, logp = sample_trees(g, 1000, 0)

    def count(name: str) -> np.ndarray:
        is_type = (trees.type == g.type_id(name)).astype(float)
        return np.bincount(trees.scene, is_type, minlength=trees.n_scenes).astype(int)

    outcomes = {}
    for height, lid, p in zip(count("Tray"), count("Lid"), np.exp(logp), strict=True):
        outcomes[int(height), int(lid)] = float(p)
    assert len(outcomes) == 6
    heights = {h: sum(p for (k, _), p in outcomes.items() if k == h) for h in (1, 2, 3)}
    assert heights == pytest.approx({1: 0.4, 2: 0.24, 3: 0.36})
    assert "with probabilities 0.4, 0.24 and 0.36" in " ".join(doc("grammar.md").split())


def test_raw_bingham_example_equals_mode_form() -> None:
    g = compile_text(block_compiling("binghams").text)
    by_child = {g.types[r.child].name: r for r in g.rules}
    upright, raw = by_child["Upright"], by_child["Raw"]
    tb = g.tables
    assert np.allclose(tb.r_quadratic[upright.id], tb.r_quadratic[raw.id])
    assert tb.r_lognorm[upright.id] == pytest.approx(tb.r_lognorm[raw.id])
    assert tb.r_kind[upright.id] == tb.r_kind[raw.id]


def test_orientation_example_writes_one_rotation_three_ways() -> None:
    g = compile_text(block_compiling("orientations").text)
    quarter = np.array([np.sqrt(0.5), 0, 0, np.sqrt(0.5)])
    for r in g.rules:
        assert np.allclose(r.rotation.offset, quarter, atol=1e-7)
    assert np.allclose(g.root_quat, quarter, atol=1e-7)


def test_geometric_count_numbers() -> None:
    law = CountLaw.geometric(0.3, 10, 1)
    assert round(float(law.probs[1]), 3) == 0.309
    assert round(float(law.probs[2]), 3) == 0.216
    assert round(float(law.probs[10]), 3) == 0.012
    assert law.probs[0] == 0
    text = doc("grammar.md")
    assert "≈ 0.309" in text and "P(2) ≈ 0.216" in text and "P(10) ≈ 0.012" in text


def test_concentration_table() -> None:
    text = doc("grammar.md")
    for c, rad, deg in (
        (20, "0.32", "18"),
        (100, "0.14", "8.1"),
        (1000, "0.045", "2.6"),
        (10000, "0.014", "0.81"),
    ):
        std = np.sqrt(2 / c)
        assert f"{std:.2g}" == rad and f"{np.degrees(std):.2g}" == deg
        assert re.search(rf"\| {c}[^|]*\| {rad} rad ≈ {deg}° \|", text), c


def test_grammar_doc_names_every_key_and_variant() -> None:
    text = doc("grammar.md")
    keys: set[str] = set()
    for model in vars(dsl).values():
        if isinstance(model, type) and issubclass(model, dsl.Strict) and model is not dsl.Strict:
            keys |= {f.alias or name for name, f in model.model_fields.items()}
    keys |= {"same", "uniform"}
    missing = sorted(
        k for k in keys if f"`{k}`" not in text and f"`{k}:" not in text and f"{{{k}:" not in text
    )
    assert not missing


def test_grammar_doc_lists_every_bundled_grammar() -> None:
    section = doc("grammar.md").split("## 7. The bundled grammars", 1)[1]
    listed = set(re.findall(r"^\| `([a-z_]+\.yaml)` \|", section, re.M))
    assert listed == {p.name for p in GRAMMARS.glob("*.yaml")}


def test_schema_comment_is_the_bundled_grammars_first_line() -> None:
    line = "# yaml-language-server: $schema=../schemas/grammar.schema.json"
    assert shown(line, "grammar.md")
    assert all(p.read_text().splitlines()[0] == line for p in GRAMMARS.glob("*.yaml"))


# -------------------------------------------------------------------- scenes.md ---


def test_scene_doc_has_examples() -> None:
    assert len(scene_blocks()) >= 2 and len(dataset_blocks()) >= 2


@pytest.mark.parametrize("block", scene_blocks(), ids=str)
def test_scene_example_reads(block: Block) -> None:
    g = grammar_for(block)
    scene = parse_scene_text(block.text, f"docs/scenes.md@{block.line}", g)
    data = json.loads(block.text)
    assert len(scene) == len(data["objects"])
    if scene.tree is not None:
        tree = scene.tree
        observed = g.tables.type_observed[tree.type]
        assert np.array_equal(scene.types, tree.type[observed])
        assert np.allclose(scene.xyz, tree.xyz[observed])
        (score,) = score_trees(g, tree)
        assert score == pytest.approx(data["log_prob"], abs=1e-9)


def test_sampled_scene_is_what_ssg_sample_writes() -> None:
    (block,) = [b for b in scene_blocks() if '"tree"' in b.text]
    data = json.loads(block.text)
    g = grammar_for(block)
    assert data["grammar"] == g.name and data["index"] < 256
    # Exactly what `ssg sample` does for scene `index` of chunk 0 (ssgc/sample/run.py).
    trees, logp = sample_chunk(g, chunk_rng(data["seed"], 0))
    i = data["index"]
    scene = scene_from_tree(g, trees.tree(i), data["name"], float(logp[i]))
    assert dumps_scene(g, scene, seed=data["seed"], index=i) == block.text
    command = f"ssg sample grammars/sink.yaml -n 3 --seed {data['seed']} -o scenes"
    assert command in doc("scenes.md") and f"scenes/{data['name']}.json" in doc("scenes.md")


def test_scene_error_messages() -> None:
    block = scene_blocks()[0]
    broken = block.text.replace('"PlateEcoformsAvocado"', '"Plate"', 1).replace(
        "[0.0, 1.0, 0.0, 0.0]", "[0.0, 1.0, 0.0, 0.1]", 1
    )
    assert broken.count('"Plate"') == 1 and "0.1]" in broken
    with pytest.raises(SsgError) as exc:
        parse_scene_text(broken, "my_sink.json", grammar_for(block))
    found = messages(exc.value)
    assert len(found) == 2
    for message in found:
        assert shown(message, "scenes.md"), message


def test_scene_files_may_not_carry_a_schema_key() -> None:
    with pytest.raises(SsgError):
        parse_scene_text('{"$schema": "x", "objects": []}', "s.json", bundled("grammars/sink.yaml"))


@pytest.mark.parametrize("block", dataset_blocks(), ids=str)
def test_dataset_example_reads(block: Block, tmp_path: Path) -> None:
    path = tmp_path / "my_dataset.yaml"
    path.write_text(block.text, encoding="utf-8")
    g = grammar_for(block)
    scenes = read_sink_yaml(path, g)
    data = YAML(typ="safe", pure=True).load(block.text)
    assert [s.name for s in scenes] == list(data)
    for scene, entry in zip(scenes, data.values(), strict=True):
        world = (entry.get("world_description") or {}).get("models", [])
        assert len(scene) == len(world) + len(entry["objects"])


def test_dataset_examples_match_as_documented(tmp_path: Path) -> None:
    by_model, by_label = dataset_blocks()
    path = tmp_path / "my_dataset.yaml"
    path.write_text(by_model.text, encoding="utf-8")
    g = grammar_for(by_model)
    (scene,) = read_sink_yaml(path, g)
    names = [g.types[t].name for t in scene.types]
    assert names == ["DishBin", "PlateEcoformsAvocado", "MugColeHardwareClassicBlue"]
    assert scene.metadata[0] == {"model_file": "bin.sdf", "class": "bin"}

    path.write_text(by_label.text, encoding="utf-8")
    g = grammar_for(by_label)
    (scene,) = read_sink_yaml(path, g)
    assert [g.types[t].name for t in scene.types] == ["Table", "Plate", "Teacup"]

    broken = by_model.text.replace(
        "plates_cups_and_bowls/plates/Ecoforms_Plate_S20Avocado/model_simplified.sdf",
        "plates/Mystery_Plate.sdf",
        1,
    )
    path = tmp_path / "saved_scenes.yaml"
    path.write_text(broken, encoding="utf-8")
    with pytest.raises(SsgError) as exc:
        read_sink_yaml(path, bundled("grammars/sink.yaml"))
    (message,) = messages(exc.value)
    assert shown(message.replace(str(tmp_path) + "/", ""), "scenes.md"), message


def test_vendored_dataset_is_described() -> None:
    folder = ROOT / "ssgc" / "data" / "sink"
    license_text = (folder / "LICENSE").read_text()
    assert license_text.startswith("MIT License") and "2020 Greg Izatt" in license_text
    assert "ssgc/data/sink/saved_scenes.yaml" in doc("scenes.md")
