"""The perturbation check of `ssg explain` (issue 16): on each real sink scene, change one
object — move it 15 cm in a random horizontal direction, turn it upside down (half a turn about
the world x axis through its position), or give it another of the dataset's types — and see
whether the explanation ranks it first.  A scene the change makes unparseable counts as ranked
first only if the diagnosis (`ssgc.explain.diagnose`) names exactly that object.

    python tests/perturbation.py GRAMMAR [SCENES] [--start I] [--limit J] [--kinds move,flip,retype]
        [--no-natural] [--all-objects]

scenes I up to (not including) J.

`--all-objects` changes every object of every scene in turn (one changed scene per object, its
change seeded by scene and object) instead of one random object per scene: a rate over the
dataset's 406 objects rather than 80 draws, so it does not depend on which object the seed picks.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

import numpy as np

from ssgc.compile import load_grammar
from ssgc.explain import ObjectExplanation, diagnose, explain_tree
from ssgc.geometry import axis_angle_to_quat, quat_multiply
from ssgc.io.scene import Scene, load_scenes
from ssgc.ir import Grammar
from ssgc.parse.parser import Parser

KINDS = ("move", "flip", "retype", "move3d")
# How the check's grammar is fitted: `ssg fit ssgc/data/sink/saved_scenes.yaml -g
# grammars/sink_detailed.yaml -o FIT.yaml --top 1 --iterations 3` (hard EM on each scene's best
# tree: the default top 10 took minutes for single scenes of this grammar).
FIT = ("--top", "1", "--iterations", "3", "--max-concentration", "400")
# What was measured on all 80 scenes (docs/perturbation.md, its first section): grammars/
# sink_detailed.yaml fitted with FIT, its dishes `revolve` shapes, its bin required; one literal
# run of move, flip and retype, with the tails the fit writes: move 61 / 80, flip 74 / 80,
# retype 64 / 80 (65 since session 25), less a margin of about three scenes: a regression
# guard.  Issue 16 asks for 0.9 per kind; docs/perturbation.md says why move and retype fall
# short.
FLOORS = {"move": 0.72, "flip": 0.88, "retype": 0.76}
DETECTABLE = 2.0  # nats: the change lowers the best tree's log-probability at least this much
SINK = "ssgc/data/sink/saved_scenes.yaml"


def perturb(
    scene: Scene, kind: str, rng: np.random.Generator, types: np.ndarray, o: int | None = None
) -> tuple[Scene, int]:
    """Change object `o` (a random one when None) of `scene` by `kind`."""
    if o is None:
        o = int(rng.integers(len(scene)))
    xyz, quat, t = scene.xyz.copy(), scene.quat.copy(), scene.types.copy()
    if kind == "move":
        phi = rng.uniform(0, 2 * np.pi)
        xyz[o] += 0.15 * np.array([np.cos(phi), np.sin(phi), 0.0])
    elif kind == "move3d":  # a direction uniform on the sphere
        v = rng.standard_normal(3)
        xyz[o] += 0.15 * v / np.linalg.norm(v)
    elif kind == "flip":
        quat[o] = quat_multiply(axis_angle_to_quat(np.array([1.0, 0, 0]), np.pi), quat[o])
    else:
        t[o] = rng.choice(types[types != t[o]])
    return replace(scene, xyz=xyz, quat=quat, types=t, tree=None), o


def without_slot_surprise(o: ObjectExplanation) -> float:
    """An object's `unusual` as ranked before the slot surprise joined it (pose gain plus the
    positive surprise of its count and choice terms): for the rates "with each change"."""
    discrete = sum(
        -r.share / r.log_prob * max(0.0, r.excess)
        for r in o.reasons
        if r.kind in ("count", "choice") and r.log_prob != 0
    )
    return o.pose_gain + discrete


def category(grammar: Grammar, t: int) -> str:
    """A dataset type's category, read from its model name: plate, bowl, cup or the bin."""
    name = grammar.types[int(t)].name
    return next((c for c in ("Plate", "Bowl", "Mug") if name.startswith(c)), name)


def run(
    grammar_path: str,
    scenes_path: str = SINK,
    limit: int | None = None,
    start: int = 0,
    with_natural: bool = True,
    seed: int = 0,
    kinds: tuple[str, ...] = KINDS,
    all_objects: bool = False,
) -> dict:
    g = load_grammar(grammar_path)
    every = load_scenes(scenes_path, g)
    types = np.unique(np.concatenate([s.types for s in every]))
    scenes = every[start:limit]  # scenes start..limit-1 (each perturbed as in the full run)
    parser = Parser(g)
    base = [parser.parse(s, top=1) for s in scenes]
    # the most unusual object of each unchanged scene: how unusual real objects already are
    # (one more explanation per scene, which re-parses per object: skipped with natural=False)
    natural = [
        explain_tree(g, s, b.parses[0].tree, parser).objects[0].unusual
        if b.parses and with_natural
        else float("nan")
        for s, b in zip(scenes, base, strict=True)
    ]
    out: dict = {
        "scenes": len(scenes),
        "changed_objects": "all" if all_objects else "one random object per scene",
        "detectable_nats": DETECTABLE,
        "natural_max_unusual_median": float(np.median(natural)) if with_natural else None,
    }
    for k, kind in enumerate(KINDS):
        if kind not in kinds:
            continue
        first = unparseable = named = detectable = first_detectable = above_natural = 0
        first_plain = 0  # ranked first without the slot surprise (unparseable ones added below)
        first_no_overlap = 0  # ranked first without the overlap reason (likewise)
        first_no_support = 0  # without floating / through the floor or walls (likewise)
        misses = []
        retypes = {"within": [0, 0], "across": [0, 0]}  # [ranked first, changed] per kind
        cases = [
            (j, o) for j, s in enumerate(scenes) for o in (range(len(s)) if all_objects else [None])
        ]
        for j, which in cases:
            scene = scenes[j]
            i = start + j  # the scene's index in the dataset (and the object's) seeds its change
            key = [seed, k, i] if which is None else [seed, k, i, which]
            changed, o = perturb(scene, kind, np.random.default_rng(key), types, which)
            result = parser.parse(changed, top=1)
            mine = 0.0
            if result.parses:
                e = explain_tree(g, changed, result.parses[0].tree, parser)
                ok = bool(e.objects[0].index == o)
                plain = max(e.objects, key=lambda x: (without_slot_surprise(x), -x.index))
                first_plain += bool(not e.objects[0].unexplained and plain.index == o)
                bare = max(e.objects, key=lambda x: (x.unusual - x.overlap, -x.index))
                first_no_overlap += bool(not e.objects[0].unexplained and bare.index == o)
                grounded = max(e.objects, key=lambda x: (x.unusual - x.support, -x.index))
                first_no_support += bool(not e.objects[0].unexplained and grounded.index == o)
                mine = next(x.unusual for x in e.objects if x.index == o)
                above_natural += bool(mine > natural[j])
                drop = base[j].parses[0].score - result.parses[0].score
                if drop >= DETECTABLE:
                    detectable += 1
                    first_detectable += ok
            else:
                unparseable += 1
                d = diagnose(g, changed, parser, time_limit=60.0)
                ok = bool(d.objects == [o])
                named += ok
            first += ok
            if kind == "retype":
                same = category(g, scene.types[o]) == category(g, changed.types[o])
                tally = retypes["within" if same else "across"]
                tally[0] += ok
                tally[1] += 1
            detail = f"unusual {mine:.2f} natural {natural[j]:.2f}" if result.parses else ""
            if kind == "retype":
                was, now = g.types[scene.types[o]].name, g.types[changed.types[o]].name
                detail += f" {was} -> {now} ({'within' if same else 'across'})"
            print(
                kind,
                i,
                scene.name,
                f"#{o}",
                "first" if ok else "missed",
                detail,
                file=sys.stderr,
                flush=True,
            )
            if not ok:
                misses.append(scene.name if which is None else f"{scene.name}#{o}")
        out[kind] = {
            "changes": len(cases),
            "rate": first / len(cases),
            "ranked_first": first,
            "ranked_first_without_slot_surprise": first_plain + named,
            "ranked_first_without_overlap": first_no_overlap + named,
            "ranked_first_without_support": first_no_support + named,
            "unparseable": unparseable,
            "unparseable_named_exactly": named,
            "parsed_and_detectable": detectable,
            "ranked_first_of_detectable": first_detectable,
            "changed_above_natural_max": above_natural if with_natural else None,
            "misses": misses,
        }
        if kind == "retype":  # extra information: the kind is "any other type"
            for part, key in (("within", "within_category"), ("across", "across_categories")):
                out[kind][key] = {"ranked_first": retypes[part][0], "of": retypes[part][1]}
    return out


def _arguments(argv: list[str]) -> argparse.Namespace:
    """The command line; an unknown kind or option is an error (a misspelt kind ran nothing)."""
    parser = argparse.ArgumentParser(prog="python tests/perturbation.py")
    parser.add_argument("grammar")
    parser.add_argument("scenes", nargs="?", default=SINK)
    parser.add_argument("--start", type=int, default=0, help="first scene (index)")
    parser.add_argument("--limit", type=int, default=None, help="scene index to stop before")
    parser.add_argument("--kinds", default=",".join(KINDS), help="of " + ",".join(KINDS))
    parser.add_argument("--no-natural", action="store_true")
    parser.add_argument("--all-objects", action="store_true")
    args = parser.parse_args(argv)
    unknown = [k for k in args.kinds.split(",") if k not in KINDS]
    if unknown:
        parser.error(f"unknown kind(s) {', '.join(unknown)}; choose from {', '.join(KINDS)}")
    return args


if __name__ == "__main__":
    a = _arguments(sys.argv[1:])
    out = run(
        a.grammar,
        a.scenes,
        limit=a.limit,
        kinds=tuple(a.kinds.split(",")),
        start=a.start,
        with_natural=not a.no_natural,
        all_objects=a.all_objects,
    )
    print(json.dumps(out, indent=1))
