"""The overlap reason of `ssg explain` (ssgc/overlaps.py, docs/explain.md "Overlaps"): objects
that overlap under the grammar's `non_penetration` constraint while the parse relates neither
to the other."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import GRAMMARS

from ssgc.compile import load_grammar
from ssgc.constraints.penetration import NonPenetration
from ssgc.explain import blocks, explain_tree, match_objects
from ssgc.io.scene import Scene
from ssgc.overlaps import overlaps, related
from ssgc.parse.parser import Parser

pytest.importorskip("fcl")


@pytest.fixture(scope="module")
def sink():
    return load_grammar(GRAMMARS / "sink_detailed.yaml")


def crowded(g, middle_x: float = 0.5) -> Scene:
    """The bin; a bowl on a plate (hollow dishes: the bowl's base rests 1 cm above the plate's
    inner floor); three mugs (radius 4.5 cm) on the floor in a row at x = 0.45, `middle_x`,
    0.55: at 0.5 the middle one overlaps each neighbour by 4 cm."""
    names = ["DishBin", "PlateRoomEssentialsSaladTurquoise", "BowlColeHardwareScirocco"]
    names += ["MugThresholdBeadWhite"] * 3
    xyz = np.array(
        [
            [0.5, 0.0, 0.0],
            [0.40, -0.15, 0.015],
            [0.40, -0.15, 0.035],
            [0.45, 0.0, 0.016],
            [middle_x, 0.0, 0.016],
            [0.55, 0.0, 0.016],
        ]
    )
    types = np.array([g.type_ids[n] for n in names])
    return Scene("crowded", types, xyz, np.tile([1.0, 0.0, 0.0, 0.0], (len(names), 1)))


@pytest.fixture(scope="module")
def crowded_parse(sink):
    scene = crowded(sink)  # mug 4 overlaps mugs 3 and 5 by 4 cm each
    return (scene, *parsed(sink, scene))


def parsed(g, scene):
    tree = Parser(g).parse(scene, top=1).parses[0].tree
    return tree, match_objects(g, scene, tree)


def test_an_object_overlapping_unrelated_ones_ranks_first_and_a_stack_is_not_penalised(
    sink, crowded_parse
):
    scene, tree, _ = crowded_parse
    e = explain_tree(sink, scene, tree)
    first = e.objects[0]
    assert first.index == 4
    words = [r.text for r in first.reasons if r.kind == "overlap"]
    assert len(words) == 2 and all("neither carries the other" in w for w in words)
    assert "MugThresholdBeadWhite #3" in " ".join(words)
    by_index = {o.index: o for o in e.objects}
    assert first.overlap > by_index[3].overlap > 0
    # the bowl lies in the plate's well: hollow dishes do not overlap (the solid cylinders did,
    # by 0.8 cm), and neither is penalised
    check = next(c for c in sink.constraints if isinstance(c, NonPenetration))
    i, j, dist = check.pair_distances(_batch(scene))
    pair = np.flatnonzero(((i == 1) & (j == 2)) | ((i == 2) & (j == 1)))
    assert 0 <= dist[pair[0]] < 0.02
    assert by_index[1].overlap == by_index[2].overlap == 0.0
    assert not [r for r in by_index[2].reasons if r.kind == "overlap"]
    assert e.to_json()["objects"][0]["overlap"] == pytest.approx(first.overlap)


def test_overlap_nats_grow_with_depth(sink):
    """Deeper overlap, more nats: the middle mug pushed further into mug 3 (the nats of mug 3,
    which overlaps only the middle one)."""
    nats, depth = [], []
    for x in (0.53, 0.49):
        scene = crowded(sink, middle_x=x)
        tree, obj_of = parsed(sink, scene)
        found = overlaps(sink, scene, tree, blocks(sink, tree), obj_of)
        depth.append(sum(v.depth for v in found if 3 in (v.a, v.b)))
        nats.append({o.index: o for o in explain_tree(sink, scene, tree).objects}[3].overlap)
    assert depth == pytest.approx([0.01, 0.05], abs=1e-3)
    assert 0 < nats[0] < nats[1]


def test_related_pairs_are_carrier_and_carried(sink, crowded_parse):
    scene, tree, obj_of = crowded_parse
    rel = related(tree, blocks(sink, tree), obj_of, len(scene))
    assert rel[1, 2] and rel[2, 1]  # the bowl on the plate
    assert rel[0, 1] and rel[0, 4]  # the bin carries everything
    assert not rel[3, 4] and not rel[1, 3]
    assert not rel.diagonal().any()


class _batch:
    def __init__(self, scene: Scene) -> None:
        n = len(scene)
        self.xyz, self.quat, self.type = scene.xyz, scene.quat, scene.types
        self.scene, self.parent, self.n_scenes = np.zeros(n, np.int64), np.full(n, -1), 1


TRAY_AND_MESH = """grammar: trayx
root: {type: Floor, pose: {xyz: [0.0, 0.0, 0.0]}}
types:
  Floor:
    and:
      - {child: Tray, translation: {offset: [0, 0, 0.05]}}
      - {child: Block, translation: {offset: [0.3, 0, 0.05]}}
  Tray:
    observed: true
    geometry: GEOMETRY
  Block:
    observed: true
    geometry: {box: {size: [0.1, 0.1, 0.1]}}
constraints:
  apart: {non_penetration: {types: [Tray, Block]}}
"""


class _Pair:
    """A batch of one scene: the `Tray` at (0, 0, 0.05) and the `Block` at `xyz`."""

    def __init__(self, g, xyz) -> None:
        self.xyz = np.array([[0, 0, 0.05], xyz], float)
        self.quat = np.tile([1.0, 0, 0, 0], (2, 1))
        self.type = np.array([g.type_ids["Tray"], g.type_ids["Block"]])
        self.scene, self.parent, self.n_scenes = np.zeros(2, np.int64), np.full(2, -1), 1


@pytest.mark.parametrize("kind", ["tray", "mesh"])
def test_explain_measures_a_tray_or_mesh_overlap_as_the_move_that_frees_it(tmp_path, kind):
    """FCL's contact depth of a triangle mesh (how a tray or mesh goes to FCL) is the depth of
    triangles, not of the solid: a block pushed 2 cm up through a tray's 1 cm floor read
    4.4 cm, and one centred on a wall (5.5 cm from free) read 6.6 cm.  Explain's overlap is how
    far the block must move, as for a revolve.  The tray's open box is written as a mesh file
    for the `mesh` case."""
    geometry = "{tray: {size: [0.4, 0.4, 0.1], wall: 0.01}}"
    if kind == "mesh":
        import trimesh

        from ssgc import dsl

        tray = dsl.TrayG.model_validate({"tray": {"size": [0.4, 0.4, 0.1], "wall": 0.01}})
        vertices, faces = tray.tray.mesh()
        trimesh.Trimesh(vertices, faces, process=False).export(tmp_path / "tray.obj")
        geometry = "{mesh: {file: tray.obj}}"
    (tmp_path / "g.yaml").write_text(TRAY_AND_MESH.replace("GEOMETRY", geometry))
    g = load_grammar(tmp_path / "g.yaml")
    (c,) = [c for c in g.constraints if isinstance(c, NonPenetration)]
    cases = [  # block centre, how far it must move to be free
        ([0.22, 0.0, 0.05], 0.03),  # 3 cm into the outside of a wall
        ([0.0, 0.0, -0.03], 0.02),  # 2 cm up through the floor from below
        ([0.195, 0.0, 0.05], 0.055),  # centred on a wall: out by half a block and half a wall
    ]
    for xyz, depth in cases:
        _, _, dist = c.pair_distances(_Pair(g, xyz), separation=True)
        assert -dist[0] == pytest.approx(depth, abs=1.5e-3), (xyz, dist)
    _, _, dist = c.pair_distances(_Pair(g, [0.0, 0.0, 0.061]), separation=True)
    assert dist[0] == pytest.approx(0.001, abs=1e-6)  # resting inside on the floor: free
