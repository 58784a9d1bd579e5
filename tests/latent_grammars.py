"""Small random grammars over the whole placement language, for parse property tests.

`random_grammar(seed)` writes the YAML text of a grammar of one to three latent levels: a root
with one or two children, latent `and` / `or` / `repeat` nodes whose children are deeper latent
nodes or observed leaves, each rule's translation and rotation drawn from every law the
language has.  Small on purpose: a sampled scene has a handful of objects.
"""

from __future__ import annotations

import random

TRANSLATIONS = (
    "same",
    "{offset: [0.2, 0.1, 0.0]}",
    "{world_normal: {mean: [0.1, 0.0, 0.2], variance: 0.01}}",
    "{world_normal: {mean: [0.0, 0.3, 0.0], variance: [0.02, 0.01, 0.04]}}",
    "{world_normal_offset: {mean: [0.3, 0.0, 0.0], variance: 0.01}}",
    "{parent_normal_offset: {mean: [0.0, 0.3, 0.0], variance: 0.01}}",
    "{parent_normal_offset: {mean: [0.2, 0.0, 0.1], variance: [0.01, 0.02, 0.01]}}",
    "{world_box: {min: [0, 0, 0], max: [1, 1, 1]}}",
    "{world_box_offset: {min: [-0.5, -0.5, -0.5], max: [0.5, 0.5, 0.5]}}",
)
ROTATIONS = (
    "same",
    "uniform",
    "{revolute: {axis: [0, 0, 1]}}",
    "{revolute: {axis: [0, 0, 1], min: -0.5, max: 0.5}}",
    "{world_bingham: {concentration: [20, 20, 20]}}",
    "{parent_bingham: {concentration: 20.0}}",
    "{offset: {rpy_deg: [0, 0, 90]}}",
)
LEAVES = ("X", "Y")


def _rule(rng: random.Random, child: str, indent: str) -> str:
    return (
        f"{indent}child: {child}\n"
        f"{indent}translation: {rng.choice(TRANSLATIONS)}\n"
        f"{indent}rotation: {rng.choice(ROTATIONS)}\n"
    )


def _node(rng: random.Random, name: str, children: list[str]) -> str:
    kind = (
        rng.choice(("and", "or", "repeat")) if len(children) > 1 else rng.choice(("and", "repeat"))
    )
    if kind == "repeat":
        rule = _rule(rng, children[0], "        ")
        return (
            f"  {name}:\n    repeat:\n      count: {{probs: [0.3, 0.4, 0.3]}}\n      rule:\n{rule}"
        )
    out = f"  {name}:\n    {kind}:\n"
    for c in children:
        rule = _rule(rng, c, "        ")
        out += "      - " + rule.lstrip()
        if kind == "or":
            out += f"        p: {1.0 / len(children):.6f}\n"
    return out


def random_grammar(seed: int) -> str:
    """The YAML text of a random grammar with one to three latent levels."""
    rng = random.Random(seed)
    depth = rng.randint(1, 3)
    names = [f"L{i}" for i in range(depth)]
    body = ""
    for i, name in enumerate(names):
        below = names[i + 1 : i + 2]
        leaves = rng.sample(LEAVES, rng.randint(1, 2))
        kids = below + leaves if below else leaves
        rng.shuffle(kids)
        body += _node(rng, name, kids)
    root_kids = [names[0]] + ([rng.choice(LEAVES)] if rng.random() < 0.3 else [])
    root = "  R:\n    and:\n" + "".join(
        "      - " + _rule(rng, c, "        ").lstrip() for c in root_kids
    )
    leaves = "".join(f"  {x}: {{observed: true}}\n" for x in LEAVES)
    return f"grammar: random_{seed}\nroot: {{type: R}}\ntypes:\n{root}{body}{leaves}"
