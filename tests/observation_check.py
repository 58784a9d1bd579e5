"""The observation-model checks of issue 16 ("Done means") on the 80 real sink scenes.

- **noise**: every pose of every scene moved by 5 mm in a random direction and turned by 2°
  about a random axis; parsed with `grammars/sink.yaml` plus `observation: noise` (5 mm,
  2°), each scene's best tree must match the best tree of the unperturbed scene under the
  grammar without noise: every object hangs under the same observed object through the same
  chain of types.
- **clutter**: one object of a type the grammar does not produce (`Sponge`) added to a scene;
  with `observation: clutter` it parses, and the sponge is the object flagged unexplained.

    python tests/observation_check.py [--limit N]     # prints one JSON object
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from ssgc.compile import compile_text, load_grammar
from ssgc.explain import blocks, match_objects, unexplained_objects
from ssgc.geometry import axis_angle_to_quat, quat_multiply
from ssgc.io.scene import Scene, load_scenes
from ssgc.ir import Grammar
from ssgc.parse.parser import Parser
from ssgc.tree import Trees

SINK_GRAMMAR = Path(__file__).resolve().parent.parent / "grammars" / "sink.yaml"
SINK = str(Path(__file__).resolve().parent.parent / "ssgc" / "data" / "sink" / "saved_scenes.yaml")
NOISE = "observation:\n  noise:\n    default: {position: 0.005, rotation_deg: 2}\n"
CLUTTER = (
    "observation:\n  clutter:\n    region: {min: [0.2, -0.4, -0.2], max: [0.8, 0.4, 0.4]}\n"
    "    rates: {Sponge: 0.1}\n"
)


def sink_with(section: str) -> Grammar:
    """grammars/sink.yaml with an `observation` section added."""
    text = SINK_GRAMMAR.read_text() + "\n" + section
    return compile_text(text, str(SINK_GRAMMAR), base_dir=SINK_GRAMMAR.parent)


def jitter(scene: Scene, rng: np.random.Generator, metres: float, degrees: float) -> Scene:
    """Every pose moved by `metres` and turned by `degrees`, in random directions."""
    n = len(scene)
    step = rng.standard_normal((n, 3))
    axis = rng.standard_normal((n, 3))
    step *= metres / np.linalg.norm(step, axis=1, keepdims=True)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    turn = np.stack([axis_angle_to_quat(a, np.deg2rad(degrees)) for a in axis])
    quat = quat_multiply(turn, scene.quat)
    return replace(scene, xyz=scene.xyz + step, quat=quat, tree=None)


def structure(g: Grammar, scene: Scene, tree: Trees) -> list[tuple[int, tuple[str, ...]]]:
    """For each object of the scene (in scene order): the object it hangs under (-1: none)
    and the names of the document's types on the way.  An object's node stands for the nodes
    of its block (joined by fixed rules: in `sink`, `Bowl` and the bowl object are one block);
    nodes the observation model adds are left out, and an observed root's own node
    (`~node:NAME`) stands for that object."""
    obj_of = match_objects(g, scene, tree)
    top = blocks(g, tree)
    owner = {int(top[n]): int(o) for n, o in enumerate(obj_of) if o >= 0}
    for n in range(len(tree.type)):
        t = g.types[int(tree.type[n])]
        if t.synthetic == "node":
            twin = g.type_ids[t.name.split(":", 1)[1]]
            owner[int(top[n])] = int(np.flatnonzero(scene.types == twin)[0])
    out = []
    for i in range(len(scene)):
        node = int(np.flatnonzero(obj_of == i)[0])
        chain: list[str] = []
        a = node
        while a >= 0 and owner.get(int(top[a]), i) == i:
            if not g.types[int(tree.type[a])].synthetic:
                chain.append(g.types[int(tree.type[a])].name)
            a = int(tree.parent[a])
        out.append((owner[int(top[a])] if a >= 0 else -1, tuple(chain)))
    return out


def noise_check(limit: int | None = None, seed: int = 0) -> dict:
    exact = load_grammar(SINK_GRAMMAR)
    noisy = sink_with(NOISE)
    scenes = load_scenes(SINK, exact)[:limit]
    plain, seen = Parser(exact), Parser(noisy)
    parsed = same = exact_parsed = 0
    differ: list[str] = []
    for i, scene in enumerate(scenes):
        base = plain.parse(scene, top=1).parses[0].tree
        moved = jitter(scene, np.random.default_rng([seed, i]), 0.005, 2.0)
        result = seen.parse(replace(moved, types=_retyped(exact, noisy, moved)), top=1)
        exact_parsed += bool(plain.parse(moved, top=1).parses)
        if not result.parses:
            differ.append(f"{scene.name}: {result.status}")
            continue
        parsed += 1
        ok = structure(exact, scene, base) == structure(noisy, moved, result.parses[0].tree)
        same += ok
        if not ok:
            differ.append(scene.name)
        print("noise", i, scene.name, "same" if ok else "differs", file=sys.stderr, flush=True)
    return {
        "scenes": len(scenes),
        "parsed": parsed,
        "same_tree": same,
        "differ": differ,
        "parsed_without_noise_model": exact_parsed,
    }


def clutter_check(limit: int | None = None, seed: int = 0) -> dict:
    exact = load_grammar(SINK_GRAMMAR)
    g = sink_with(CLUTTER)
    scenes = load_scenes(SINK, exact)[:limit]
    parser = Parser(g)
    sponge = g.type_id("Sponge")
    flagged_right = parsed = 0
    wrong: list[str] = []
    for i, scene in enumerate(scenes):
        rng = np.random.default_rng([seed, i])
        extra = np.array([rng.uniform(0.3, 0.7), rng.uniform(-0.3, 0.3), 0.05])
        s = Scene(
            scene.name,
            np.append(_retyped(exact, g, scene), sponge),
            np.vstack([scene.xyz, extra]),
            np.vstack([scene.quat, [1.0, 0, 0, 0]]),
        )
        result = parser.parse(s, top=1)
        if not result.parses:
            wrong.append(f"{scene.name}: {result.status}")
            continue
        parsed += 1
        flagged = unexplained_objects(g, s, result.parses[0].tree)
        ok = flagged == [len(scene)]
        flagged_right += ok
        if not ok:
            wrong.append(f"{scene.name}: flagged {flagged}")
        print("clutter", i, scene.name, flagged, file=sys.stderr, flush=True)
    return {
        "scenes": len(scenes),
        "parsed": parsed,
        "sponge_flagged_alone": flagged_right,
        "wrong": wrong,
    }


def _retyped(src: Grammar, dst: Grammar, scene: Scene) -> np.ndarray:
    """The scene's type ids of grammar `src` as ids of grammar `dst` (same names)."""
    return np.array([dst.type_id(src.types[int(t)].name) for t in scene.types], np.int64)


if __name__ == "__main__":
    lim = int(sys.argv[sys.argv.index("--limit") + 1]) if "--limit" in sys.argv else None
    print(json.dumps({"noise": noise_check(lim), "clutter": clutter_check(lim)}, indent=1))
