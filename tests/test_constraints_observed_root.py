"""Constraints that name an observed root with noise (docs/constraints.md, "The root under
`observation: noise`").

Noise on an observed root moves the root's rules to its true node `~node:NAME` at the root
pose; the observed object becomes a noisy leaf under `~scene` (ssgc/observation.py).  A
constraint written about the root type means that true node: its frame, its children, its
pose.  Before, every such constraint read the leaf: a frame no object had (every scene with an
object rejected), no children, the noisy pose.

The margins here are recomputed from each scene's tree with code of their own (no
`ssgc.constraints`), from the true node's pose.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

import ssgc
from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.errors import GrammarError

RUNNER = CliRunner()
TEA = """\
grammar: tea
root: {type: Table, pose: {xyz: [0, 0, 0.375]}}
types:
  Table:
    observed: true
    repeat:
      count: {probs: [0.2, 0.4, 0.4]}
      rule:
        child: Teacup
        translation: {parent_normal_offset: {mean: [0, 0, 0.405], variance: 0.04, pin: [z]}}
        rotation: {revolute: {axis: [0, 0, 1]}}
  Teacup: {observed: true}
constraints:
  onTable:
    inside_box: {types: [Teacup], frame: Table, min: [-0.3, -0.3, 0], max: [0.3, 0.3, null]}
  two: {count: {type: Teacup, min: 2}}
  up: {upright: {types: [Teacup], frame: Table, max_angle_deg: 10}}
  kids: {children: {of: Table, min: 1}}
  home: {inside_box: {types: [Table], min: [-0.001, -0.001, 0.374], max: [0.001, 0.001, 0.376]}}
  apart: {clearance: {types: [Table, Teacup], radius: {Table: 0.1, Teacup: 0.05}}}
"""
NOISE = "observation:\n  noise:\n    Table: {position: 0.005, rotation_deg: 3}\n"
BOX_LO, BOX_HI = np.array([-0.3, -0.3, 0.0]), np.array([0.3, 0.3, np.inf])


def grammar(tmp_path: Path, noise: bool = True) -> Path:
    path = tmp_path / ("tea_noise.yaml" if noise else "tea.yaml")
    path.write_text(TEA + (NOISE if noise else ""))
    return path


def rotation(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (w, x, y, z), written out here."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def nodes_of(doc: dict[str, Any]) -> list[dict[str, Any]]:
    return list(doc["tree"]["nodes"])


def pose(node: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    return np.array(node["pose"]["xyz"], float), np.array(node["pose"]["quat_wxyz"], float)


def true_table(nodes: list[dict[str, Any]]) -> dict[str, Any]:
    """The one `~node:Table` node: the table as it is, at the root pose."""
    (node,) = [n for n in nodes if n["type"] == "~node:Table"]
    return node


def on_table_margin(table: dict[str, Any], cups: list[dict[str, Any]]) -> float | None:
    """The `onTable` margin in the frame of `table`; None without a cup."""
    if not cups:
        return None
    p, q = pose(table)
    local = np.array([rotation(q).T @ (pose(c)[0] - p) for c in cups])
    gaps = np.concatenate([local - BOX_LO, BOX_HI - local], axis=1)
    return float(gaps.min())


def sample_cli(path: Path, out: Path, constraints: str, n: int, *extra: str) -> tuple[float, list]:
    """(acceptance % the command reports, the scene documents)."""
    args = ["sample", str(path), "-n", str(n), "--seed", "0", "--constraints", constraints]
    result = RUNNER.invoke(app, [*args, "-o", str(out), *extra])
    assert result.exit_code == 0, result.output
    accepted = float(re.search(r"([\d.]+)% accepted", result.output).group(1))  # type: ignore[union-attr]
    docs = [json.loads(f.read_text()) for f in sorted(out.glob("*.json"))]
    assert len(docs) == n
    return accepted, docs


def cups(nodes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [n for n in nodes if n["type"] == "Teacup"]


def test_a_frame_named_by_the_noisy_root_is_the_true_table(tmp_path: Path) -> None:
    """`frame: Table` with noise on the Table root: the teacups are kept in the box of the true
    table, as often as without noise.  (Before, no Teacup had a `Table` ancestor: 20% of the
    candidates were accepted, those with no teacup, and 0 teacups were in 300 scenes.)"""
    plain, plain_docs = sample_cli(grammar(tmp_path, False), tmp_path / "a", "onTable", 300)
    noisy, docs = sample_cli(grammar(tmp_path), tmp_path / "b", "onTable", 300)
    assert abs(noisy - plain) < 5.0, (noisy, plain)  # 72.9% without noise
    plain_cups = np.mean([len(cups(nodes_of(d))) for d in plain_docs])
    noisy_cups = np.mean([len(cups(nodes_of(d))) for d in docs])
    assert noisy_cups > 0.8 and abs(noisy_cups - plain_cups) < 0.2, (noisy_cups, plain_cups)
    moved = 0
    for d in docs:
        nodes = nodes_of(d)
        table = true_table(nodes)
        assert np.allclose(pose(table)[0], [0, 0, 0.375]) and np.allclose(
            pose(table)[1], [1, 0, 0, 0]
        )
        want = on_table_margin(table, cups(nodes))
        got = d["metadata"]["constraints"]["onTable"]
        if want is None:
            assert got is None
            continue
        assert got >= 0 and got == pytest.approx(want, abs=1e-9)
        (seen,) = [n for n in nodes if n["type"] == "Table"]  # the noisy observation
        moved += not np.isclose(on_table_margin(seen, cups(nodes)) or 0.0, want, atol=1e-9)
    assert moved > 100  # the observed table's frame would have given other margins


def test_all_constraints_with_a_count_end(tmp_path: Path) -> None:
    """`onTable` with `two: {count: min 2}`: every candidate was rejected (a teacup has no
    frame, and a scene without one fails the count), and without --max-tries it never ended."""
    accepted, docs = sample_cli(
        grammar(tmp_path), tmp_path / "o", "onTable,two", 50, "--max-tries", "20000"
    )
    assert accepted > 10
    for d in docs:
        nodes = nodes_of(d)
        assert len(cups(nodes)) == 2
        margin = d["metadata"]["constraints"]["onTable"]
        assert margin >= 0 and margin == pytest.approx(
            on_table_margin(true_table(nodes), cups(nodes))
        )


def api_scenes(tmp_path: Path, constraints: str, n: int) -> list[Any]:
    g = ssgc.load_grammar(grammar(tmp_path))
    return g.sample(n, seed=0, constraints=constraints, max_tries=20_000)


def tree_nodes(scene: Any) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """(type names, parents, positions, rotations) of a scene's tree (API scene)."""
    tree = scene.data.tree
    names = [scene.grammar.ir.types[t].name for t in tree.type]
    return names, np.asarray(tree.parent), np.asarray(tree.xyz), np.asarray(tree.quat)


def test_upright_in_the_frame_of_the_noisy_root_through_the_api(tmp_path: Path) -> None:
    """`upright` with `frame: Table` (the table observed turned by 3°): each teacup turns about
    the true table's z axis, so its margin is the whole 10°.  (Before: no frame, every scene
    with a teacup rejected.)"""
    scenes = api_scenes(tmp_path, "up", 100)
    with_cups = 0
    for s in scenes:
        names, _, _, quat = tree_nodes(s)
        table = quat[names.index("~node:Table")]
        mine = [rotation(quat[k])[:, 2] for k, n in enumerate(names) if n == "Teacup"]
        margin = s.metadata["constraints"]["up"]
        if not mine:
            assert margin is None
            continue
        with_cups += 1
        angle = max(np.arccos(np.clip(m @ rotation(table)[:, 2], -1, 1)) for m in mine)
        assert margin >= 0 and margin == pytest.approx(np.radians(10) - angle, abs=1e-6)
    assert with_cups > 60  # 80% of the unconstrained scenes have a teacup


def test_children_of_the_noisy_root_are_the_true_nodes_children(tmp_path: Path) -> None:
    """`children: {of: Table, min: 1}` counts the teacups under the true table: one or two, as
    often as each other (count law 0.2/0.4/0.4).  (Before: the observed leaf has no children,
    and every candidate was rejected.)"""
    scenes = api_scenes(tmp_path, "kids", 300)
    counts = []
    for s in scenes:
        names, parent, _, _ = tree_nodes(s)
        node = names.index("~node:Table")
        n = int(np.sum(parent == node))
        assert n == sum(name == "Teacup" for name in names) >= 1
        assert s.metadata["constraints"]["kids"] == n - 1
        counts.append(n)
    assert abs(np.mean(np.array(counts) == 1) - 0.5) < 0.1


def test_the_root_listed_in_types_is_judged_at_its_true_pose(tmp_path: Path) -> None:
    """`types: [Table]` means the table as it is (at the root pose), not its noisy observation:
    a 2 mm box about the root pose always holds, with margin 1 mm; a pair of the table with a
    teacup is measured from the true table.  (Before, the observed pose, 5 mm off, was judged.)"""
    for s in api_scenes(tmp_path, "home", 40):
        assert s.metadata["constraints"]["home"] == pytest.approx(0.001, abs=1e-12)
    for s in api_scenes(tmp_path, "apart", 40):
        names, _, xyz, _ = tree_nodes(s)
        at = xyz[names.index("~node:Table"), :2]
        gaps = [
            np.linalg.norm(xyz[k, :2] - at) - 0.15 for k, n in enumerate(names) if n == "Teacup"
        ]
        pairs = [
            np.linalg.norm(xyz[a, :2] - xyz[b, :2]) - 0.1
            for a in range(len(names))
            for b in range(a + 1, len(names))
            if names[a] == names[b] == "Teacup"
        ]
        margin = s.metadata["constraints"]["apart"]
        if not gaps:
            assert margin is None or margin == np.inf
            continue
        assert margin >= 0 and margin == pytest.approx(min(gaps + pairs), abs=1e-9)


def test_the_compiled_constraints_read_the_true_node(tmp_path: Path) -> None:
    """Every per-type entry a constraint has for the root type is the true node's: frame,
    `of`, types, radii, exempt pairs, shapes for `geometry` and `non_penetration`."""
    geometry = TEA.replace(
        "  Table:\n    observed: true\n",
        "  Table:\n    observed: true\n    geometry: {box: {size: [1.2, 1.2, 0.75]}}\n",
    ).replace(
        "  Teacup: {observed: true}",
        "  Teacup: {observed: true, geometry: {cylinder: {radius: 0.04, length: 0.08}}}",
    )
    extra = (
        "  walls:\n"
        "    inside_box: {types: [Table], min: [-1, -1, -1], max: [1, 1, 1], geometry: true}\n"
        "  solid: {non_penetration: {types: [Table, Teacup], exempt: [[Table, Teacup]]}}\n"
    )
    g = compile_text(geometry + extra + NOISE, "tea.yaml")
    table, node = g.type_ids["Table"], g.type_ids["~node:Table"]
    c = {k.name: k for k in g.constraints}
    assert c["onTable"].frame == node and c["up"].frame == node and c["kids"].of == node
    assert c["home"].types[node] and not c["home"].types[table]
    assert c["apart"].radius[node] == 0.1 and c["apart"].types[node]
    assert c["walls"].shapes is not None
    solid = c["solid"]
    assert solid.shapes[node] is not None and solid.shapes[table] is None
    assert solid.pairs_of.exempt[node, g.type_ids["Teacup"]]
    assert solid.pairs_of.radius[node] > 0


def test_validate_checks_the_noisy_root_as_the_grammar_is_written() -> None:
    """The can-never-hold checks hold for the true node as for the root without noise: a
    table has at most two children, a teacup is never its own frame."""
    with pytest.raises(GrammarError) as info:
        compile_text(
            TEA + "  many: {children: {of: Table, min: 3}}\n"
            "  self:\n"
            "    inside_box: {types: [Teacup], frame: Teacup, min: [0, 0, 0], max: [1, 1, 1]}\n"
            + NOISE,
            "tea.yaml",
        )
    text = "\n".join(str(d) for d in info.value.diagnostics)
    assert "children of 'Table' nodes is at most 2" in text
    assert "a 'Teacup' can occur without a 'Teacup' above it" in text


def test_the_sink_with_noise_on_every_pose_keeps_its_dishes_in_the_bin(tmp_path: Path) -> None:
    """grammars/sink.yaml with `noise: {default: ...}` (the bin, its root, gets noise too):
    `dishes_in_bin` (frame DishBin) was never met ("rejected 82,944 of the 82,944")."""
    text = (Path(__file__).parents[1] / "grammars" / "sink.yaml").read_text()
    path = tmp_path / "sink.yaml"
    path.write_text(
        text + "\nobservation: {noise: {default: {position: 0.005, rotation_deg: 2}}}\n"
    )
    _, docs = sample_cli(path, tmp_path / "o", "dishes_in_bin", 3, "--max-tries", "50000")
    assert all(d["metadata"]["constraints"]["dishes_in_bin"] >= 0 for d in docs)
