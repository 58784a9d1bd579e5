"""Small random grammars over the whole language, for parser property tests (issue 11).

A grammar has 1–3 latent types (`L0` the root, then `L1`, `L2`), each of any kind (`and`, `or`,
`independent`, `repeat`), and two observed types (`A`, `B`).  A latent type's rules reach later
latent types or observed ones, so there are no cycles; every rule draws its translation from
every translation law and its rotation from every rotation law of docs/grammar.md.  With
`extras`, the observed types get geometry and pose constraints of every kind, and the grammar
maybe an `observation` section (noise, clutter, both), which adds types after the user's.

With `rare` (the parser's property tests ask for it), also the corners that hid parser bugs (a
`repeat` blocked by `max_nesting` was charged log P(0)): rules back to the type itself or an
earlier non-root type (cycles, each bounded by `max_nesting` 1–3 on the type it enters), `L`
types that are observed (observed types with rules, an observed root), pinned axes of Normal
and box translations, `or` weights of 0 or none at all, `independent` rules with p = 0, and
count laws with zeros in them.  Left out unless asked: the long profile's grammar `i`
(`parse_profile.case(seed, i)`, cited in docs/parsing.md) stays the same, and so do the other
tests that draw grammars of the family (tests/test_fuzz.py, tests/test_constraints.py).

One builder, two drivers: `make_spec(pick)` asks `pick(what, options)` for every choice, so
hypothesis (`grammars()`, which shrinks) and a numpy generator (`random_spec`, for the long
profile of thousands of grammars) make grammars of the same family.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import yaml

from ssgc.compile import compile_text
from ssgc.io.scene import Scene, scene_from_tree
from ssgc.ir import Grammar
from ssgc.sample.forward import sample_trees

TRANSLATIONS = (
    "same",
    "offset",
    "world_normal",
    "world_normal_offset",
    "parent_normal_offset",
    "world_box",
    "world_box_offset",
)
ROTATIONS = (
    "same",
    "uniform",
    "revolute",
    "bounded_revolute",
    "world_bingham",
    "parent_bingham",
    "offset",
)
KINDS = ("and", "or", "independent", "repeat")
COUNTS = ({"probs": [0.3, 0.4, 0.3]}, {"geometric": {"p": 0.5, "max": 2}})
RARE_COUNTS = (
    {"probs": [0, 1]},
    {"probs": [0.5, 0, 0.5]},
    {"probs": [0, 0.5, 0.5]},
    {"geometric": {"p": 0.5, "max": 2, "start": 1}},
)
OBSERVED = ("A", "B")
MAX_OBJECTS = 5  # scenes with more objects are left out (a property test, not a benchmark)

Pick = Callable[[str, Sequence[Any]], Any]


def translation(law: str, pick: Pick, rare: bool = False) -> Any:
    """The YAML of one translation law, with numbers from a few fixed choices; `rare`: maybe
    with pinned axes (`pin` of a Normal, `min == max` of a box)."""
    mean = list(pick("mean", ([0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [1.0, 0.5, 0.0])))
    variance = pick("variance", (0.01, 0.05, [0.02, 0.01, 0.04]))
    if law == "same":
        return "same"
    if law == "offset":
        return {"offset": mean}
    if law in ("world_normal", "world_normal_offset", "parent_normal_offset"):
        out = {"mean": mean, "variance": variance}
        if rare and (pin := pick("pin", ([], ["z"], ["x", "y"]))):
            out["pin"] = list(pin)
        return {law: out}
    half = pick("half", (0.1, 0.5))
    low, high = [m - half for m in mean], [m + half for m in mean]
    if rare and pick("box_pin", (False, True)):
        low[2] = high[2] = mean[2]  # z pinned
    return {law: {"min": low, "max": high}}


def rotation(law: str, pick: Pick) -> Any:
    """The YAML of one rotation law."""
    if law in ("same", "uniform"):
        return law
    axis = list(pick("axis", ([0, 0, 1], [1, 0, 0], [0, 1, 1])))
    if law == "revolute":
        return {"revolute": {"axis": axis}}
    if law == "bounded_revolute":
        return {"revolute": {"axis": axis, "min": -0.4, "max": 0.7}}
    conc = pick("concentration", (20, 200, [100, 100, 0]))
    mode = {"rpy_deg": list(pick("mode", ([0, 0, 0], [20, 0, 45], [0, 90, 0])))}
    if law in ("world_bingham", "parent_bingham"):
        return {law: {"mode": mode, "concentration": conc}}
    return {"offset": mode}


def observation(pick: Pick) -> dict[str, Any] | None:
    """An `observation` section (docs/grammar.md section 9), or None: noise on every observed
    type, clutter of a type only clutter makes (`C`) and of an observed terminal (`B`), or
    both.  Clutter adds types after the user's."""
    which = pick("observation", (None, "noise", "clutter", "both"))
    if which is None:
        return None
    out: dict[str, Any] = {}
    if which in ("noise", "both"):
        noise = {"position": pick("noise_position", (0.0, 0.01))}
        noise["rotation_deg"] = pick("noise_rotation", (0, 2))
        out["noise"] = {"default": noise}
    if which in ("clutter", "both"):
        out["clutter"] = {
            "region": {"min": [-1.0, -1.0, -1.0], "max": [1.5, 1.5, 1.5]},
            "rates": {"C": 0.3, "B": pick("clutter_b", (0.1, 0.5))},
            "max": 2,
        }
    return out


def constraints(pick: Pick) -> dict[str, Any]:
    """Pose constraints of every kind on the observed types (which then have geometry)."""
    kinds = pick(
        "constraints",
        (("non_penetration",), ("clearance", "upright"), ("inside_box", "non_penetration")),
    )
    out: dict[str, Any] = {}
    for kind in kinds:
        if kind == "non_penetration":
            out["apart"] = {"non_penetration": {"types": list(OBSERVED)}}
        elif kind == "clearance":
            out["spaced"] = {"clearance": {"types": list(OBSERVED), "radius": {"A": 0.05}}}
        elif kind == "upright":
            out["tilt"] = {"upright": {"types": ["A"], "max_angle_deg": 120}}
        else:
            box = {"min": [-3.0, -3.0, -3.0], "max": [3.0, 3.0, 3.0], "geometry": True}
            out["inside"] = {"inside_box": {"types": list(OBSERVED), **box}}
    return out


def make_spec(pick: Pick, extras: bool = False, rare: bool = False) -> dict[str, Any]:
    """A grammar as a YAML-ready dict; `pick(what, options)` makes every choice.  `extras`:
    also an `observation` section (maybe) and pose constraints on the observed types; `rare`:
    the rarer corners of the language (module docstring)."""
    n_latent = pick("latent", (1, 2, 3))
    latent = [f"L{i}" for i in range(n_latent)]
    types: dict[str, Any] = {name: {"observed": True} for name in OBSERVED}
    entered: set[str] = set()  # types a rule goes back to: each closes a cycle
    for i, name in enumerate(latent):
        back = latent[1 : i + 1] if rare else []  # never the root: no rule may produce it
        body = latent_type(pick, latent[i + 1 :] + list(OBSERVED) + back, rare)
        entered |= {r["child"] for r in rules_of(body) if r["child"] in back}
        types[name] = body
    for name in sorted(entered):
        types[name] = {"max_nesting": pick("max_nesting", (1, 2, 3)), **types[name]}
    spec = {"grammar": "generated", "root": latent[0], "types": types}
    if extras:
        types["A"]["geometry"] = {"sphere": {"radius": 0.02}}
        types["B"]["geometry"] = pick(
            "geometry_b",
            (
                {"cylinder": {"radius": 0.02, "length": 0.03}},
                {"tray": {"size": [0.06, 0.05, 0.03], "wall": 0.005}},  # an open box
            ),
        )
        spec["constraints"] = constraints(pick)
        seen = observation(pick)
        if seen is not None:
            spec["observation"] = seen
    return spec


def latent_type(pick: Pick, reachable: list[str], rare: bool) -> dict[str, Any]:
    """One `L` type: its kind and rules to `reachable` types; `rare`: maybe observed, with
    `or` weights that may be 0 or absent, `independent` p = 0 and counts with zeros."""
    kind = pick("kind", KINDS)
    n_rules = 1 if kind == "repeat" else pick("rules", (1, 2))
    rules = [rule(pick, kind, reachable, rare) for _ in range(n_rules)]
    if kind == "or" and rare and pick("weights", ("p", "none")) == "none":
        rules = [{k: v for k, v in r.items() if k != "p"} for r in rules]
    elif kind == "or" and all(r["p"] == 0 for r in rules):
        rules[0]["p"] = 1.0  # the weights must not all be zero
    body: dict[str, Any] = {"observed": True} if rare and pick("observed", (False, True)) else {}
    if kind == "repeat":
        counts = COUNTS + RARE_COUNTS if rare else COUNTS
        body["repeat"] = {"count": pick("count", counts), "rule": rules[0]}
    else:
        body[kind] = rules
    return body


def rule(pick: Pick, kind: str, reachable: list[str], rare: bool) -> dict[str, Any]:
    """One rule of a type of `kind`: its child, translation, rotation and `p`."""
    out: dict[str, Any] = {"child": pick("child", reachable)}
    out["translation"] = translation(pick("translation", TRANSLATIONS), pick, rare)
    out["rotation"] = rotation(pick("rotation", ROTATIONS), pick)
    if kind == "or":
        out["p"] = pick("weight", (1.0, 2.0, 3.0, 0.0) if rare else (1.0, 2.0, 3.0))
    elif kind == "independent":
        out["p"] = pick("p", (0.3, 0.6, 1.0, 0.0) if rare else (0.3, 0.6, 1.0))
    return out


def kind_of(body: dict[str, Any]) -> str | None:
    """A type's kind key (None for a terminal)."""
    return next((k for k in body if k in KINDS), None)


def rules_of(body: dict[str, Any]) -> list[dict[str, Any]]:
    """A type's rules (one for a `repeat`, none for a terminal)."""
    kind = kind_of(body)
    if kind is None:
        return []
    return [body[kind]["rule"]] if kind == "repeat" else list(body[kind])


def to_yaml(spec: dict[str, Any]) -> str:
    return yaml.safe_dump(spec, sort_keys=False, default_flow_style=None)


def compile_spec(spec: dict[str, Any]) -> Grammar:
    return compile_text(to_yaml(spec))


def random_spec(rng: np.random.Generator, rare: bool = False) -> dict[str, Any]:
    """A grammar of the family drawn by numpy (the long profile: fast, no shrinking)."""
    return make_spec(lambda what, options: options[int(rng.integers(len(options)))], rare=rare)


def grammars(extras: bool = False, rare: bool = False) -> Any:
    """A hypothesis strategy of grammar specs of the family (`extras`, `rare`: see
    `make_spec`)."""
    from hypothesis import strategies as st

    @st.composite
    def strategy(draw: Any) -> dict[str, Any]:
        return make_spec(
            lambda what, options: draw(st.sampled_from(list(options)), label=what), extras, rare
        )

    return strategy()


def sampled_scenes(
    grammar: Grammar, n: int, seed: int, max_objects: int = MAX_OBJECTS
) -> list[Scene]:
    """Scenes sampled from the grammar, each carrying its tree's score (`scene.score`) and
    at most `max_objects` objects."""
    trees, logp = sample_trees(grammar, n, seed)
    scenes = []
    for i in range(n):
        if not np.isfinite(logp[i]):
            continue
        scene = scene_from_tree(grammar, trees.tree(i), f"s{i}", float(logp[i]))
        if len(scene) <= max_objects:
            scenes.append(scene)
    return scenes


def laws(spec: dict[str, Any]) -> set[str]:
    """The laws and kinds a grammar uses, for statistics by law ("t:world_box", "kind:or")."""
    out: set[str] = set()
    for name, body in spec["types"].items():
        if name in OBSERVED:
            continue
        out.add(f"kind:{kind_of(body)}")
        for one in rules_of(body):
            out.add("t:" + _law_name(one["translation"]))
            r = one["rotation"]
            name = _law_name(r)
            if name == "revolute" and "min" in r["revolute"]:
                name = "bounded_revolute"
            out.add("r:" + name)
    return out


def _law_name(law: Any) -> str:
    return law if isinstance(law, str) else next(iter(law))
