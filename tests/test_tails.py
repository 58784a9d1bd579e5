"""The physical tails of `ssg explain` belong to their constraint (`non_penetration`'s `tail:`,
`inside_box`'s `floating:` and `outside:`), explain reads them, and `ssg fit` measures them
(ssgc/tails.py, ssgc/fit/tails.py; docs/explain.md, docs/fitting.md)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_support import BIN, FLIP, UP, tub_scene
from typer.testing import CliRunner

from ssgc.cli.app import app
from ssgc.compile import compile_text
from ssgc.explain import blocks, match_objects, overlap_reasons, support_reasons
from ssgc.fit.em import FitJournal, FitOptions, GrammarSource, fit_grammar, fit_header
from ssgc.fit.tails import Measured, tail_updates
from ssgc.fit.writeback import apply_updates
from ssgc.overlaps import overlaps
from ssgc.parse.parser import Parser
from ssgc.support import findings
from ssgc.tails import FLOATING, OUTSIDE, OVERLAP, TOLERANCE, Tail

pytest.importorskip("fcl")
runner = CliRunner()

# tests/test_support.py's tub (plates on its floor, mugs on the plates), with a comment that a
# fit must keep.
TUB = BIN.lstrip("\n").replace("  apart:\n", "  apart:\n    # plates and mugs keep apart\n")
TAIL = "    non_penetration: {types: [Plate, Mug]}\n"
BOX = "      geometry: true\n"


def with_tails(overlap: str = "", floating: str = "", outside: str = "") -> str:
    text = TUB
    if overlap:
        text = text.replace(TAIL, TAIL.replace("]}", f"], tail: {overlap}}}"))
    extra = (f"      floating: {floating}\n" if floating else "") + (
        f"      outside: {outside}\n" if outside else ""
    )
    return text.replace(BOX, BOX + extra)


def constraint(g, name: str):
    return next(c for c in g.constraints if c.name == name)


# ------------------------------------------------------------------ the language ---


def test_absent_tails_are_the_sink_defaults() -> None:
    g = compile_text(TUB, "tub.yaml")
    assert constraint(g, "apart").tail == OVERLAP
    box = constraint(g, "in_tub")
    assert (box.floating, box.outside) == (FLOATING, OUTSIDE)
    assert OVERLAP == Tail(34 / 169, 0.0113) and FLOATING.rate == 15 / 169


def test_tails_are_read_from_their_constraints() -> None:
    text = with_tails("{rate: 0.5, mean: 0.02}", "{rate: 0.25, mean: 0.03}", "{rate: 1, mean: 1}")
    g = compile_text(text, "tub.yaml")
    assert constraint(g, "apart").tail == Tail(0.5, 0.02)
    assert constraint(g, "in_tub").floating == Tail(0.25, 0.03)
    assert constraint(g, "in_tub").outside == Tail(1.0, 1.0)


@pytest.mark.parametrize(
    "text, line, says",
    [
        (with_tails(overlap="{rate: 0, mean: 0.01}"), 29, "greater than 0"),
        (with_tails(overlap="{rate: 1.5, mean: 0.01}"), 29, "less than or equal to 1"),
        (with_tails(overlap="{rate: 0.5, mean: -1}"), 29, "greater than 0"),
        (with_tails(overlap="{rate: 0.5, mean: .inf}"), 29, "finite"),
        (with_tails(overlap="{rate: .nan, mean: 0.01}"), 29, "finite"),
        (with_tails(overlap="{rate: 0.5}"), 29, "mean"),
        (with_tails(overlap="{rate: 0.5, mean: 0.01, median: 1}"), 29, "unknown key 'median'"),
        (with_tails(overlap='{rate: "0.5", mean: 0.01}'), 29, "rate"),
        (with_tails(floating="{rate: 0.1, mean: 0}"), 37, "greater than 0"),
        (with_tails(outside="{rate: 2, mean: 0.01}"), 37, "less than or equal to 1"),
        (
            with_tails(floating="{rate: 0.1, mean: 0.01}").replace(BOX, ""),
            36,
            "`floating` calibrates the floor and walls that only `geometry: true` declares",
        ),
        (
            with_tails(outside="{rate: 0.1, mean: 0.01}").replace(BOX, ""),
            36,
            "`outside` calibrates",
        ),
    ],
    ids=lambda v: v if isinstance(v, str) and len(v) < 60 else "",
)
def test_bad_tails_are_located_messages(tmp_path: Path, text: str, line: int, says: str) -> None:
    path = tmp_path / "g.yaml"
    path.write_text(text)
    result = runner.invoke(app, ["validate", str(path)])
    assert result.exit_code != 0
    assert says in result.output
    assert f"{path}:{line}:" in result.output and "Traceback" not in result.output


# ------------------------------------------------------------------ explain reads them ---


def parsed(g, scene):
    tree = Parser(g).parse(scene, top=1).parses[0].tree
    return tree, match_objects(g, scene, tree)


def test_overlap_nats_follow_the_constraints_tail() -> None:
    a, b = Tail(0.5, 0.02), Tail(0.05, 0.005)
    ga = compile_text(with_tails(overlap="{rate: 0.5, mean: 0.02}"), "a.yaml")
    gb = compile_text(with_tails(overlap="{rate: 0.05, mean: 0.005}"), "b.yaml")
    scene = tub_scene(ga, {2: ([-0.22, 0, 0], UP)})  # plate 2 slid into plate 1
    tree, obj_of = parsed(ga, scene)
    depth = sum(v.depth for v in overlaps(ga, scene, tree, blocks(ga, tree), obj_of) if v.a == 1)
    assert depth > 0.05
    na, nb = overlap_reasons(ga, scene, tree, obj_of), overlap_reasons(gb, scene, tree, obj_of)
    assert na[1][0] == pytest.approx(-np.log(a.rate) + depth / a.mean)
    assert nb[1][0] == pytest.approx(-np.log(b.rate) + depth / b.mean)
    assert sum(r.excess for r in nb[1][1]) == pytest.approx(nb[1][0])


def test_support_nats_follow_the_constraints_tails() -> None:
    text = with_tails(floating="{rate: 0.5, mean: 0.05}", outside="{rate: 0.2, mean: 0.1}")
    g, base = compile_text(text, "a.yaml"), compile_text(TUB, "b.yaml")
    moves = {3: ([0.0, 0.2, 0.0], UP), 2: ([0.1, 0, 0], UP)}  # mug floats 2 cm, plate in a wall
    scene = tub_scene(g, moves)
    tree, obj_of = parsed(g, scene)
    mine, sink = support_reasons(g, scene, tree, obj_of), support_reasons(base, scene, tree, obj_of)
    assert mine[3][0] == pytest.approx(-np.log(0.5) + (0.02 - TOLERANCE) / 0.05, abs=1e-6)
    assert mine[2][0] == pytest.approx(-np.log(0.2) + (0.05 - TOLERANCE) / 0.1, abs=1e-6)
    assert sink[3][0] == pytest.approx(FLOATING.nats(0.02 - TOLERANCE), abs=1e-6)
    assert sink[2][0] == pytest.approx(OUTSIDE.nats(0.05 - TOLERANCE), abs=1e-6)


# ------------------------------------------------------------------ fit measures them ---

MOVES = [
    {},
    {3: ([0.0, 0.2, 0.0], UP)},  # the mug floats 2 cm
    {2: ([0.1, 0, 0], UP)},  # a plate 5 cm into a wall
    {2: ([-0.22, 0, 0], UP)},  # plate 2 slid into plate 1 (and its mug)
    {2: ([0, 0, 0], FLIP), 3: ([0.0, 0.2, 0.0], UP)},  # turned over; the mug floats
]


def fit_tub(tmp_path: Path, text: str):
    tmp_path.mkdir(exist_ok=True)
    g = compile_text(text, "tub.yaml")
    scenes = [tub_scene(g, m) for m in MOVES]
    opts = FitOptions(iterations=1, top=1)
    header = fit_header(text, tmp_path, scenes, opts)
    with FitJournal(tmp_path / "fit.partial.jsonl", header, resume=False) as journal:
        return g, scenes, fit_grammar(text, GrammarSource("tub.yaml"), scenes, opts, journal)


def direct(g, scenes) -> dict[str, Tail]:
    """The estimator of ssgc/fit/tails.py, counted by hand on each scene's best parse."""
    n = found_o = found_f = found_x = 0
    depths: list[float] = []
    floats: list[float] = []
    outs: list[float] = []
    for scene in scenes:
        tree, obj_of = parsed(g, scene)
        n += 3  # two plates and a mug, all in the tub
        depth = np.zeros(len(scene))
        for v in overlaps(g, scene, tree, blocks(g, tree), obj_of):
            depth[[v.a, v.b]] += v.depth
        found_o += int(np.sum(depth > 0))
        depths += list(depth[depth > 0])
        fs = findings(g, scene, tree, obj_of)
        found_f += len({f.obj for f in fs if f.kind == "floats"})
        found_x += len({f.obj for f in fs if f.kind != "floats"})
        floats += [f.distance - TOLERANCE for f in fs if f.kind == "floats"]
        outs += [f.distance - TOLERANCE for f in fs if f.kind != "floats"]

    def tail(found: int, sizes: list[float]) -> Tail:
        typical = float(np.median(sizes)) / np.log(2) if sizes else 0.0
        return Tail(max(found, 1) / n, max(typical, TOLERANCE))

    return {
        "tail": tail(found_o, depths),
        "floating": tail(found_f, floats),
        "outside": tail(found_x, outs),
    }


def test_fit_writes_the_tails_it_measures(tmp_path: Path) -> None:
    g, scenes, result = fit_tub(tmp_path, TUB)
    want = direct(g, scenes)
    assert want["floating"].rate == 2 / 15 and want["outside"].rate == 2 / 15
    fitted = compile_text(result.text, "tub.yaml")
    for got in (constraint(fitted, "apart").tail, Tail(**_yaml_tail(result.text, "tail"))):
        assert got.rate == pytest.approx(want["tail"].rate, rel=1e-7)
        assert got.mean == pytest.approx(want["tail"].mean, rel=1e-7)
    box = constraint(fitted, "in_tub")
    for got, key in ((box.floating, "floating"), (box.outside, "outside")):
        assert got.rate == pytest.approx(want[key].rate, rel=1e-7)
        assert got.mean == pytest.approx(want[key].mean, rel=1e-7)
    assert "# plates and mugs keep apart" in result.text  # comments survive
    assert {m["key"] for m in result.tails} == {"tail", "floating", "outside"}


def test_the_tails_change_no_fitted_law(tmp_path: Path) -> None:
    """Fitting from a grammar with other tails written gives the same laws; only the tails
    differ from the fit without them, and those are measured again."""
    _, _, plain = fit_tub(tmp_path / "a", TUB)
    other = with_tails("{rate: 0.9, mean: 0.5}", "{rate: 0.9, mean: 0.5}", "{rate: 0.9, mean: 0.5}")
    _, _, tailed = fit_tub(tmp_path / "b", other)
    assert tailed.text == plain.text  # the tails written over, the same everywhere else
    last = json.loads((tmp_path / "a" / "fit.partial.jsonl").read_text().splitlines()[-1])
    stripped = re.sub(r", tail: \{[^}]*\}", "", plain.text)
    stripped = "".join(
        line
        for line in stripped.splitlines(True)
        if not line.lstrip().startswith(("floating:", "outside:"))
    )  # the last M-step's grammar and the output differ only by the tails
    assert stripped == last["grammar"] != plain.text
    assert [r["log_evidence"] for r in tailed.iterations] == [
        r["log_evidence"] for r in plain.iterations
    ]


def test_resume_gives_the_same_tails(tmp_path: Path) -> None:
    """The tails are a function of the journal: a finished fit resumed writes them again."""
    _, scenes, first = fit_tub(tmp_path, TUB)
    opts = FitOptions(iterations=1, top=1)
    header = fit_header(TUB, tmp_path, scenes, opts)
    with FitJournal(tmp_path / "fit.partial.jsonl", header, resume=True) as journal:
        again = fit_grammar(TUB, GrammarSource("tub.yaml"), scenes, opts, journal)
    assert again.text == first.text and again.tails == first.tails
    assert "tail: {rate:" in again.text


def test_a_tail_shared_by_two_constraints_is_not_written_twice(tmp_path: Path) -> None:
    """Two constraints whose `tail:` is one YAML node (an anchor and its alias) measure
    different tails, which one node cannot hold: none is written, the result says why, and
    the laws are fitted as ever."""
    text = with_tails(overlap="&t {rate: 0.5, mean: 0.02}").replace(
        "  in_tub:\n", "  mugs:\n    non_penetration: {types: [Mug], tail: *t}\n  in_tub:\n", 1
    )
    g = compile_text(text, "tub.yaml")
    scenes = [tub_scene(g, m) for m in MOVES]
    opts = FitOptions(iterations=1, top=1)
    with FitJournal(tmp_path / "j.jsonl", fit_header(text, tmp_path, scenes, opts), False) as j:
        result = fit_grammar(text, GrammarSource("tub.yaml"), scenes, opts, j)
    tails = {m["constraint"]: (m["rate"], m["mean"]) for m in result.tails if m["key"] == "tail"}
    assert tails["apart"] != tails["mugs"]
    assert "were not written" in result.message and "one YAML node" not in result.text
    assert "tail: &t {rate: 0.5, mean: 0.02}" in result.text and "floating" not in result.text


def test_a_grammar_without_such_constraints_gets_nothing_written(tmp_path: Path) -> None:
    text = TUB[: TUB.index("constraints:")]
    _, _, result = fit_tub(tmp_path, text)
    assert "tail" not in result.text and "floating" not in result.text
    assert result.tails == []


def _yaml_tail(text: str, key: str) -> dict[str, float]:
    from ruamel.yaml import YAML

    doc = YAML(typ="safe").load(text)
    return doc["constraints"]["apart"]["non_penetration"][key]


@settings(max_examples=30, deadline=None)
@given(
    rate=st.floats(1e-9, 1.0),
    mean=st.floats(1e-9, 1e3),
    key=st.sampled_from(["tail", "floating", "outside"]),
    written=st.booleans(),
)
def test_written_tails_load_and_validate(rate: float, mean: float, key: str, written: bool) -> None:
    """Whatever the fit measures, the grammar it writes compiles and holds those numbers
    (to the 8 digits it writes); a tail already written is edited in place."""
    text = with_tails("{rate: 0.5, mean: 0.02}", "{rate: 0.5, mean: 0.02}") if written else TUB
    g = compile_text(text, "tub.yaml")
    name = "apart" if key == "tail" else "in_tub"
    m = Measured(name, key, objects=1, found=1)
    update = tail_updates(g, [m])[0]
    update.values[key] = {"rate": rate, "mean": mean}
    out = compile_text(apply_updates(text, [update], "tub.yaml"), "tub.yaml")
    c = constraint(out, name)
    got = c.tail if key == "tail" else getattr(c, key)
    assert got.rate == pytest.approx(rate, rel=1e-7) and got.mean == pytest.approx(mean, rel=1e-7)
