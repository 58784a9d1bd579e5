"""The Python API, for notebooks and scripts (docs/api.md): grammars, scenes, trees, parses.

A thin facade: every call is one of the functions the `ssg` commands call —
`ssgc.compile` to load, `ssgc.sample.run.draw_scenes` to sample (forward or under
constraints), `ssgc.parse.parser.Parser` to parse, `ssgc.explain` to explain, `ssgc.fit.em` to
fit, `ssgc.io.scene` for the JSON documents and `ssgc.render` for pictures.  The objects here
only carry the grammar along, so that a scene can say its types' names, write its JSON and
draw itself.  `.to_json()` gives the same document the command line writes (a scene file of
`ssg sample`, one scene of `ssg parse`'s output), and `.render(path)` draws what `ssg render`
draws from that document.

Heavy parts (the parser, the fitter, matplotlib) are imported when first used.
"""

from __future__ import annotations

import copy
import inspect
import json
import math
import reprlib
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ssgc import ir
from ssgc.compile import compile_text, read_grammar_text
from ssgc.errors import SceneError, SsgError
from ssgc.io import scene as scene_io
from ssgc.tree import Trees

if TYPE_CHECKING:
    from ssgc.explain import Explanation
    from ssgc.fit.em import FitJournal, FitOptions, GrammarSource
    from ssgc.fit.em import FitResult as FitReport
    from ssgc.parse.parser import Parser, SceneParses

__all__ = [
    "FitResult",
    "FitRun",
    "Grammar",
    "Parse",
    "ParseResult",
    "Scene",
    "Tree",
    "explain",
    "fit",
    "fit_defaults",
    "fit_options",
    "load_grammar",
    "load_scenes",
    "open_fit",
    "parse",
]


def load_grammar(path: str | Path, allow_outside: bool = False) -> Grammar:
    """Read and compile a grammar file; a mistake raises `ssgc.errors.GrammarError`, whose
    message lists every problem as FILE:LINE:COL (as `ssg validate` prints them).  Mesh and
    model files must lie in the grammar's directory unless `allow_outside`.  The grammar
    keeps its file's absolute path: after a change of directory (a notebook's `%cd`) its mesh
    files, a pickled copy and `Scene.save`'s refusal to overwrite it still find that file."""
    if not isinstance(path, str | Path):
        raise TypeError(f"path must be a str or Path of a grammar file, got {type(path).__name__}")
    if not isinstance(allow_outside, bool):
        raise TypeError(f"allow_outside must be True or False, got {_shown(allow_outside)}")
    path = Path(path)
    text = read_grammar_text(path)
    compiled = compile_text(text, str(path), base_dir=path.parent, allow_outside=allow_outside)
    return Grammar(compiled, text, path.absolute(), allow_outside)


def _compiled_again(text: str, path: str | None, allow_outside: bool) -> Grammar:
    """A pickled `Grammar` (`Grammar.__reduce__`)."""
    if path is None:
        return Grammar(compile_text(text), text, None, allow_outside)
    file = Path(path)
    compiled = compile_text(text, path, base_dir=file.parent, allow_outside=allow_outside)
    return Grammar(compiled, text, file, allow_outside)


def load_scenes(path: str | Path, grammar: Grammar) -> list[Scene]:
    """Scenes from a JSON scene file, a directory of them, or a sink-format YAML dataset.  A
    scene `ssg sample` wrote keeps its seed and index (`Scene.run`), so that saving it again
    writes a file `ssg sample --resume` still accepts."""
    if not isinstance(path, str | Path):
        raise TypeError(
            f"path must be a str or Path of scenes (load_scenes(path, grammar)), "
            f"got {type(path).__name__}"
        )
    _checked(grammar)
    return [Scene(grammar, s, run=s.run) for s in scene_io.load_scenes(path, grammar.ir)]


def parse(
    grammar: Grammar,
    scene: Scene,
    top: int = 1,
    method: str = "auto",
    time_limit: float | None = None,
) -> ParseResult:
    """The `top` most probable distinct parse trees of `scene` (as `ssg parse`): `method` is
    auto, ip or micp (docs/parsing.md), `time_limit` in seconds.  A scene the grammar cannot
    produce is not an exception: the result's `status` says `infeasible` (proven) or
    `no_parse` (none found, not proven)."""
    from ssgc.scene_reports import parse_document

    data = _scene_data(_checked(grammar), scene)
    top, time_limit = _count("top", top, 1), _time_limit(time_limit)
    parser = grammar.parser(method)
    result = parser.parse(data, top=top, time_limit=time_limit)
    document = parse_document(parser, data, result, top, time_limit=time_limit)
    return ParseResult(grammar, result, document)


def explain(grammar: Grammar, scene: Scene, time_limit: float | None = None) -> Explanation:
    """Why `scene` scores what it scores (as `ssg explain`): its best parse's −log p split over
    objects and rules, most unusual object first.  `.text()` says it in words, `.to_json()`
    is `ssg explain --json`'s entry.  Raises `ssgc.explain.UnexplainedScene`, an
    `ssgc.errors.SsgError`, when the scene has no parse: `status` infeasible (no tree of the
    grammar contains it; `diagnosis` names the objects to blame) or no_parse (none found,
    e.g. within `time_limit`)."""
    from ssgc.explain import best_parse, explain_tree, reparse_budget

    data = _scene_data(_checked(grammar), scene)
    parser = grammar.parser("auto")
    t0 = time.perf_counter()
    limit = _time_limit(time_limit)
    tree, status, gap = best_parse(grammar.ir, data, parser, time_limit=limit)
    budget = reparse_budget(time_limit, time.perf_counter() - t0)
    explanation = explain_tree(grammar.ir, data, tree, parser, budget)
    explanation.status, explanation.gap = status, gap
    return explanation


def fit(
    grammar: Grammar,
    dataset: Sequence[Scene] | str | Path,
    iterations: int = 10,
    top: int = 10,
    method: str = "auto",
    seed: int = 0,
    tol: float = 1e-4,
    estep: str = "topn",
    samples: int | None = None,
    pseudocount: float = 0.01,
    min_variance: float = 1e-6,
    max_concentration: float = 1e4,
    jobs: int = 1,
    time_limit: float | None = None,
) -> FitResult:
    """Fit the grammar's parameters to a dataset by approximate EM (as `ssg fit`, whose flags
    these are, with these defaults; docs/fitting.md).  `dataset` is a list of scenes or a path
    `load_scenes` reads.  The grammar itself is not changed: the result holds the fitted
    grammar, its YAML text (the original with only the fitted numbers changed) and one report
    per iteration."""
    _checked(grammar)
    if isinstance(dataset, str | Path):
        where, scenes = Path(dataset), load_scenes(dataset, grammar)
    else:
        where, scenes = Path("<scenes>"), _fit_scenes(grammar, dataset, "dataset", api_only=True)
    options = fit_options(
        iterations=iterations,
        top=top,
        method=method,
        seed=seed,
        tol=tol,
        estep=estep,
        samples=samples,
        pseudocount=pseudocount,
        min_variance=min_variance,
        max_concentration=max_concentration,
        jobs=jobs,
    )
    time_limit = _time_limit(time_limit)
    with open_fit(grammar, scenes, where, options) as run:
        result = run.fit(time_limit)
    fitted = run.fitted(result)
    return FitResult(fitted, result.iterations, result.status, result.message, result.tails)


def _whole(value: Any) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _read_only(array: NDArray[Any]) -> NDArray[Any]:
    view = array.view()
    view.flags.writeable = False
    return view


def _count(name: str, value: Any, least: int | None = None) -> int:
    """A whole-number argument (numpy's too) as an int; 2.5 iterations ran 3, and a numpy
    integer reached the journal's JSON.  Without `least`, the range is left to the caller
    (`FitOptions` says it as `ssg fit` does)."""
    if not _whole(value) or (least is not None and value < least):
        wanted = "a whole number" + ("" if least is None else f" >= {least}")
        raise ValueError(f"{name} must be {wanted}, got {_shown(value)}")
    return int(value)


def _seed(value: Any) -> int:
    if not _whole(value) or not 0 <= value < 2**63:
        raise ValueError(
            f"seed must be a whole number in [0, 2**63) as for ssg, got {_shown(value)}"
        )
    return int(value)


def _shown(value: Any) -> str:
    """An argument as a message quotes it: 10**400 or a long string cut short."""
    return reprlib.repr(value)


def _sampling_options(
    constraints: Any, method: Any, max_tries: int | None, time_limit: float | None
) -> None:
    """`Grammar.sample`'s options, checked in the API's words (`plan_sampling` says the same
    in `ssg sample`'s flags, which an API user never typed)."""
    from ssgc.sample.constrained import METHODS

    if constraints is not None and not isinstance(constraints, str):
        raise TypeError(
            f"constraints must be a string, 'all' or 'NAME,NAME', got {_shown(constraints)}"
            + ("; join the names with commas" if isinstance(constraints, list | tuple) else "")
        )
    if not isinstance(method, str) or method not in ("auto", *METHODS):
        raise ValueError(
            f"method must be 'auto' or one of: {', '.join(METHODS)}, got {_shown(method)}"
        )
    if constraints is not None:
        return
    if (max_tries, time_limit) != (None, None):
        raise ValueError(
            "max_tries= and time_limit= bound constrained sampling: they need constraints= "
            "('all', or 'NAME,NAME')"
        )
    if method != "auto":
        raise ValueError(
            "method= chooses how constrained sampling draws: it needs constraints= "
            "('all', or 'NAME,NAME')"
        )


def _time_limit(value: Any) -> float | None:
    """Seconds, > 0 and finite, or None for no limit (nan ran without one; 0 gave no parse)."""
    if value is None:
        return None
    seconds = _as_float(value)
    if seconds is None or not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(
            f"time_limit must be a finite number of seconds > 0 or None, got {_shown(value)}"
        )
    return seconds


def _real(name: str, value: Any) -> float:
    """A real-number argument as a float; its range is left to the caller (`FitOptions` says
    it as `ssg fit` does).  A string or None raised `float()`'s own error, which named no
    argument."""
    number = _as_float(value)
    if number is None:
        raise ValueError(f"{name} must be a number, got {_shown(value)}")
    return number


def _as_float(value: Any) -> float | None:
    """A number (numpy's too, not a bool) as a float, inf when too large for one (10**400
    raised OverflowError); None for anything else."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        return None
    try:
        return float(value)
    except OverflowError:
        return math.inf


def _checked(grammar: Any) -> Grammar:
    """The grammar, or a TypeError that says what is wanted (not an AttributeError deep in).
    The compiled grammar (`Grammar.ir`) is a class named Grammar too: said so, or the message
    would read "expected a Grammar, got Grammar"."""
    if isinstance(grammar, ir.Grammar):
        raise TypeError(
            "expected a Grammar (ssgc.load_grammar) as grammar, got the compiled grammar "
            "(ssgc.ir.Grammar, a Grammar's .ir): pass the Grammar itself"
        )
    if not isinstance(grammar, Grammar):
        raise TypeError(
            f"expected a Grammar (ssgc.load_grammar) as grammar, got {type(grammar).__name__}"
        )
    return grammar


def _scene_data(grammar: Grammar, scene: Any) -> scene_io.Scene:
    """The scene as the library reads it, in `grammar`'s type numbers.  A scene of another
    grammar (sampled from `sink.yaml`, parsed with `sink_detailed.yaml`) is read again by its
    types' names, checked as a scene file is: its numbers are the other grammar's."""
    if not isinstance(scene, Scene):
        raise TypeError(f"expected a Scene (of ssgc.api), got {_kind(scene)}")
    if scene.grammar.ir is grammar.ir:
        return scene.data
    objects = zip(scene.types, scene.xyz.tolist(), scene.quat.tolist(), strict=True)
    return grammar.scene(objects, scene.name).data


# `fit`'s samples per scene chain of the posterior E-step when none are given (the fitter's
# own default, `FitOptions.samples`: tests/test_api.py checks they agree)
POSTERIOR_SAMPLES = 100


def fit_defaults() -> dict[str, Any]:
    """The defaults of `fit`'s options by name: `ssg fit`'s flags take theirs from here, so the
    command and the API cannot drift apart."""
    return {
        name: p.default
        for name, p in inspect.signature(fit).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


def fit_options(
    *,
    iterations: int,
    top: int,
    method: str,
    seed: int,
    tol: float,
    estep: str,
    samples: int | None,
    pseudocount: float,
    min_variance: float,
    max_concentration: float,
    jobs: int,
) -> FitOptions:
    """`fit`'s options (and `ssg fit`'s flags) as the fitter (`ssgc.fit.em`) takes them,
    each checked in the argument's name: numpy's numbers are taken, a fraction of an
    iteration or a string is not (open_fit's run used them as they came).  `samples` is for
    the posterior E-step only: None is its default, and a number given with the top-N E-step
    is refused (it was accepted and ignored)."""
    from ssgc.fit.em import FitOptions
    from ssgc.fit.mstep import FitSettings

    if samples is not None and estep != "mcmc":
        raise SsgError.single(
            "samples (ssg fit --samples) needs the posterior E-step, estep 'mcmc' "
            "(--estep mcmc): the top-N E-step draws none"
        )
    return FitOptions(
        iterations=_count("iterations", iterations),
        top=_count("top", top),
        method=method,
        seed=_seed(seed),
        tol=_real("tol", tol),
        jobs=_count("jobs", jobs),
        estep=estep,
        samples=POSTERIOR_SAMPLES if samples is None else _count("samples", samples),
        settings=FitSettings(
            pseudocount=_real("pseudocount", pseudocount),
            min_variance=_real("min_variance", min_variance),
            max_concentration=_real("max_concentration", max_concentration),
        ),
    )


@contextmanager
def open_fit(
    grammar: Grammar,
    scenes: Iterable[Scene | scene_io.Scene],
    dataset: str | Path,
    options: FitOptions,
    journal_next_to: Path | None = None,
    resume: bool = False,
) -> Iterator[FitRun]:
    """A fit of `grammar` to `scenes` (read from `dataset`), with its journal open: what `fit`
    and `ssg fit` share.  `scenes` are the API's (`load_scenes`, `Grammar.sample`) or the
    library's read with `grammar.ir` (`ssgc.io.scene`, as `ssg fit` has them); `dataset`
    names where they came from, for the journal and messages; `options` come from
    `fit_options`.  The journal lies next to `journal_next_to` (the fitted grammar's file,
    so that `resume` finds it), or in a temporary directory removed at the end; the caller
    decides when to delete a finished run's journal, after writing its results."""
    from ssgc.fit.em import FitJournal, FitOptions, fit_header, fit_journal_file

    data = _fit_scenes(_checked(grammar), scenes, "scenes")
    if not isinstance(dataset, str | Path):
        raise TypeError(f"dataset must be a str or Path, got {type(dataset).__name__}")
    if not isinstance(options, FitOptions):
        raise TypeError(
            f"options must come from ssgc.api.fit_options, got {type(options).__name__}"
        )
    if not data:
        raise SsgError.single("the dataset has no scenes", str(dataset))
    source = grammar.source(str(dataset))
    header = fit_header(grammar.text, Path(dataset), data, options)
    with fit_journal_file(journal_next_to) as path, FitJournal(path, header, resume) as journal:
        yield FitRun(grammar, data, options, source, journal)


def _fit_scenes(
    grammar: Grammar, scenes: Any, name: str, api_only: bool = False
) -> list[scene_io.Scene]:
    """The scenes to fit (the argument `name`), as the fitter reads them: the API's in
    `grammar`'s type numbers (`_scene_data`), the library's (`ssg fit` reads its files with
    `grammar.ir`) as they are, once their type numbers are checked; `fit` takes the API's
    only.  A path here is a mistake (`fit` reads one before; `open_fit` wants scenes), as is
    anything that is not a scene: they raised AttributeError from the fitter."""
    if isinstance(scenes, str | bytes | Path) or not isinstance(scenes, Iterable):
        raise TypeError(
            f"{name} must be a list of scenes (ssgc.load_scenes, Grammar.sample), "
            f"got {type(scenes).__name__}"
        )
    data = []
    for k, scene in enumerate(scenes):
        if isinstance(scene, scene_io.Scene) and not api_only:
            data.append(_library_scene(grammar, scene, f"{name}[{k}]"))
        elif isinstance(scene, Scene):
            data.append(_scene_data(grammar, scene))
        else:
            raise TypeError(f"{name}[{k}] must be a Scene, got {_kind(scene)}")
    return data


def _library_scene(grammar: Grammar, scene: scene_io.Scene, name: str) -> scene_io.Scene:
    """A library scene, whose type numbers carry no grammar: numbers beyond `grammar`'s types
    or of types it does not observe are another grammar's (they broke the parser's arrays)."""
    table = grammar.ir.tables.type_observed
    types = scene.types
    if types.size and (types.min() < 0 or types.max() >= len(table) or not table[types].all()):
        raise SceneError.single(
            f"{name} holds type numbers that are not observed types of grammar "
            f"'{grammar.name}': a scene read with another grammar (read it with this one: "
            "ssgc.load_scenes, Grammar.scene)",
            scene.name,
        )
    return scene


def _kind(value: Any) -> str:
    """What was passed, as a message says it: the library's Scene (`Scene.data`) has the
    API's class name, so "must be a Scene, got Scene" would name neither."""
    if isinstance(value, scene_io.Scene):
        return "the library's scene (ssgc.io.scene.Scene, a Scene's .data): pass the Scene"
    return type(value).__name__


@dataclass(frozen=True, eq=False)
class FitRun:
    """One EM run with its journal open (`open_fit`): `fit()` runs it, from where the journal
    stopped; `fitted()` compiles the grammar it returns."""

    grammar: Grammar
    scenes: list[scene_io.Scene]
    options: FitOptions
    source: GrammarSource
    journal: FitJournal

    def __repr__(self) -> str:
        """One line, as every API object's: the dataclass's own printed every scene's arrays
        (120,000 characters for the sink dataset)."""
        return f"<FitRun of '{self.grammar.name}': {len(self.scenes)} scenes>"

    def fit(
        self,
        time_limit: float | None = None,
        on_scene: Callable[[], None] | None = None,
        on_iteration: Callable[[dict[str, Any]], None] | None = None,
        on_tails: Callable[[], None] | None = None,
    ) -> FitReport:
        """Run EM (`ssgc.fit.em.fit_grammar`): `on_scene` after each parsed scene,
        `on_iteration` with each iteration's report, `on_tails` when the EM is over and the
        physical tails are measured."""
        from ssgc.fit.em import fit_grammar

        return fit_grammar(
            self.grammar.text,
            self.source,
            self.scenes,
            self.options,
            self.journal,
            time_limit=_time_limit(time_limit),
            on_scene=on_scene,
            on_iteration=on_iteration,
            on_tails=on_tails,
        )

    def fitted(self, result: FitReport) -> Grammar:
        """The fitted grammar, compiled as the original was (same file, directory, files)."""
        g, s = self.grammar, self.source
        compiled = compile_text(result.text, s.file, s.base_dir, s.allow_outside)
        return Grammar(compiled, result.text, g.path, g.allow_outside)


class Grammar:
    """A compiled grammar (`ir`, an `ssgc.ir.Grammar`) with the text and file it came from."""

    def __init__(
        self, compiled: ir.Grammar, text: str, path: Path | None = None, allow_outside: bool = False
    ) -> None:
        self.ir = compiled
        self.text = text
        self.path = path
        self.allow_outside = allow_outside
        self._parsers: dict[str, Parser] = {}

    @property
    def name(self) -> str:
        return self.ir.name

    @property
    def types(self) -> list[str]:
        """Node type names, in file order."""
        return [t.name for t in self.ir.types]

    def __repr__(self) -> str:
        return f"<Grammar '{self.name}': {len(self.ir.types)} types, {len(self.ir.rules)} rules>"

    def __reduce__(self) -> tuple[Any, tuple[str, str | None, bool]]:
        """Pickled (and deep-copied) as its text, compiled again where it is read: the compiled
        grammar holds collision shapes of python-fcl, which cannot be pickled (scenes, trees
        and parses of such grammars could not go to another process)."""
        where = None if self.path is None else str(self.path)
        return _compiled_again, (self.text, where, self.allow_outside)

    def sample(
        self,
        n: int = 1,
        seed: int = 0,
        constraints: str | None = None,
        method: str = "auto",
        max_tries: int | None = None,
        time_limit: float | None = None,
    ) -> list[Scene]:
        """Draw `n` scenes, each with its tree and log-probability: exactly the scenes
        `ssg sample -n N --seed SEED` writes (scene i depends only on the seed and i).  With
        `constraints` (`all`, or `NAME,NAME`) they follow the grammar conditioned on them
        (docs/constraints.md); `max_tries` and `time_limit` bound that search, and when they
        run out first `ssgc.sample.constrained.Unmet` is raised.  Mistakes name these
        arguments, never the flags of `ssg sample`."""
        from ssgc.sample.constrained import ARGUMENTS
        from ssgc.sample.run import draw_scenes, plan_sampling

        n, seed, time_limit = _count("n", n, 0), _seed(seed), _time_limit(time_limit)
        max_tries = None if max_tries is None else _count("max_tries", max_tries, 1)
        _sampling_options(constraints, method, max_tries, time_limit)
        plan = plan_sampling(
            self.ir, constraints, method, max_tries, time_limit, spelling=ARGUMENTS
        )
        drawn = draw_scenes(self.ir, n, seed, plan)
        return [Scene(self, d.scene, d.metadata or {}, (seed, d.index)) for d in drawn]

    def scene(self, objects: Iterable[Sequence[Any]], name: str = "scene") -> Scene:
        """A scene from Python data: `(type, xyz)` or `(type, xyz, quat_wxyz)` per object,
        checked as a scene file is (types the grammar observes, finite poses, unit
        quaternions); a mistake raises `ssgc.errors.SceneError`."""
        if not isinstance(objects, Iterable):  # None gave "object is not iterable"
            raise SceneError.single(
                f"objects must be a list of (type, xyz) or (type, xyz, quat_wxyz), "
                f"got {type(objects).__name__}",
                "<python>",
            )
        _scene_name(name)
        objs = []
        for k, o in enumerate(objects):
            if not isinstance(o, Sequence) or isinstance(o, str | bytes) or len(o) not in (2, 3):
                raise SceneError.single(
                    f"object {k} must be (type, xyz) or (type, xyz, quat_wxyz), got {o!r}",
                    "<python>",
                )
            pose: dict[str, Any] = {"xyz": _numbers(o[1])}
            if len(o) > 2:
                pose["quat_wxyz"] = _numbers(o[2])
            objs.append({"type": o[0], "pose": pose})
        doc = {"format": scene_io.FORMAT, "name": name, "objects": objs}
        try:
            text = json.dumps(doc, default=repr)  # a Decimal or a complex: the check refuses it
        except ValueError:  # an int of more than 4,300 digits (Python's own limit)
            raise SceneError.single("a number has too many digits for a pose", "<python>") from None
        return Scene(self, scene_io.parse_scene_text(text, "<python>", self.ir, name))

    def parse(
        self, scene: Scene, top: int = 1, method: str = "auto", time_limit: float | None = None
    ) -> ParseResult:
        """`ssgc.parse(self, scene, ...)`."""
        return parse(self, scene, top, method, time_limit)

    def explain(self, scene: Scene, time_limit: float | None = None) -> Explanation:
        """`ssgc.explain(self, scene, ...)`."""
        return explain(self, scene, time_limit)

    def fit(self, dataset: Sequence[Scene] | str | Path, *args: Any, **options: Any) -> FitResult:
        """`ssgc.fit(self, dataset, ...)`, its options in the same order."""
        return fit(self, dataset, *args, **options)

    def parser(self, method: str = "auto") -> Parser:
        """The grammar's parser for `method`, built once (its supertree is reused)."""
        from ssgc.parse.parser import Parser

        if method not in self._parsers:
            self._parsers[method] = Parser(self.ir, method=method)
        return self._parsers[method]

    def source(self, dataset: str = "<dataset>") -> GrammarSource:
        """Where the text came from, so that a fit compiles each iteration like the original."""
        from ssgc.fit.em import GrammarSource

        file = self.ir.file  # the path as given, for messages; the directory is absolute
        base = self.path.parent if self.path is not None else None
        return GrammarSource(file, base, self.allow_outside, dataset)


@dataclass(frozen=True, eq=False)
class Tree:
    """One scene tree: its nodes (latent and observed) with types, parents, rules and poses."""

    grammar: Grammar
    trees: Trees  # a batch of one tree

    def __len__(self) -> int:
        return len(self.trees)

    def __repr__(self) -> str:
        return f"<Tree: {len(self)} nodes>"

    @property
    def types(self) -> list[str]:
        return [self.grammar.ir.types[t].name for t in self.trees.type]

    @property
    def parent(self) -> NDArray[np.int64]:
        """Each node's parent (-1 for the root), read-only: the tree's own array."""
        return _read_only(self.trees.parent)

    @property
    def log_prob(self) -> float:
        """log p(tree) under the grammar (thesis Eq. 2.1), as the scorer computes it: the
        poses of latent nodes with nothing observed below them integrated out
        (docs/conventions.md, "Unseen nodes"), as every score ssgc reports."""
        from ssgc.score import score_trees

        return float(score_trees(self.grammar.ir, self.trees)[0])

    def scene(self, name: str = "scene") -> Scene:
        """The tree's observed nodes as a scene (which keeps the tree)."""
        _scene_name(name)
        data = scene_io.scene_from_tree(self.grammar.ir, self.trees, name, self.log_prob)
        return Scene(self.grammar, data)

    def to_json(self) -> dict[str, Any]:
        """{"nodes": [...]}, the `tree` of a scene file: parents first."""
        return scene_io.tree_to_json(self.grammar.ir, self.trees)

    def render(self, path: str | Path) -> Path:
        """Draw the tree (3-D and from above) into a .png or .svg file."""
        return _render(self.scene("tree").to_json(), path, self.grammar)

    def same_as(self, other: Tree) -> bool:
        """The same tree up to the order of siblings (the test `ssg bench parse` uses).  Trees
        of two grammars with the same types and rules (the file loaded twice, or fitted)
        compare; trees of grammars that differ in them cannot, and raise ValueError."""
        from ssgc.parse.parser import tree_signature

        if not isinstance(other, Tree):
            raise TypeError(f"other must be a Tree, got {type(other).__name__}")
        mine, theirs = self.grammar.ir, other.grammar.ir
        if mine is not theirs and _structure(mine) != _structure(theirs):
            raise ValueError(
                f"other is a tree of grammar '{theirs.name}', whose types and rules are not "
                f"those of '{mine.name}': trees of different grammars cannot be compared"
            )
        return tree_signature(mine, self.trees) == tree_signature(theirs, other.trees)


def _scene_name(name: Any) -> None:
    """A scene's name is one line of text (None made a scene named None, written as null)."""
    if not isinstance(name, str):
        raise ValueError(f"a name is text (got {name!r})")
    if problem := scene_io.name_problem(name):
        raise ValueError(problem)


def _structure(grammar: ir.Grammar) -> tuple[list[str], list[str]]:
    """A grammar's type and rule names in id order: the numbers a tree is written in."""
    rules = [grammar.rule_name(r) for r in range(len(grammar.rules))]
    return [t.name for t in grammar.types], rules


@dataclass(frozen=True, eq=False)
class Scene:
    """Observed objects (types and poses); a sampled scene also has its tree and log-prob."""

    grammar: Grammar
    data: scene_io.Scene
    # the scene file's `metadata` (constrained sampling adds its method and margins); {} for
    # none.  What it holds when the scene is saved is what its file's `metadata` holds.
    metadata: dict[str, Any] = field(default_factory=dict)
    run: tuple[int, int] | None = None  # a sampled scene's seed and index, as its file has

    def __post_init__(self) -> None:
        """`metadata` is the file's (`data.extra`, what a loaded scene was read with) with the
        given one added: a loaded scene showed None while its `to_json()` held the file's
        record.  A copy, so that editing it changes neither the caller's dict nor the data."""
        merged = copy.deepcopy({**self.data.extra, **(self.metadata or {})})
        object.__setattr__(self, "metadata", merged)

    def __len__(self) -> int:
        return len(self.data)

    def __repr__(self) -> str:
        tree = "" if self.data.tree is None else f", a tree of {len(self.data.tree)} nodes"
        return f"<Scene '{self.name}': {len(self)} objects{tree}>"

    @property
    def name(self) -> str:
        return self.data.name

    @property
    def types(self) -> list[str]:
        return [self.grammar.ir.types[t].name for t in self.data.types]

    @property
    def xyz(self) -> NDArray[np.float64]:
        """Positions (m), one row per object; read-only (the scene's own array: an edit in
        place moved the scene past every check).  `.copy()` it to change it."""
        return _read_only(self.data.xyz)

    @property
    def quat(self) -> NDArray[np.float64]:
        """Rotations as unit quaternions, w first (docs/conventions.md); read-only."""
        return _read_only(self.data.quat)

    @property
    def log_prob(self) -> float | None:
        return self.data.log_prob

    @property
    def tree(self) -> Tree | None:
        return None if self.data.tree is None else Tree(self.grammar, self.data.tree)

    def to_json(self) -> dict[str, Any]:
        """The scene file's document: for a sampled scene, what `ssg sample` writes, its seed
        and index included (a file saved without them was refused by `--resume`)."""
        seed, index = self.run if self.run is not None else (None, None)
        # `metadata` alone, not merged with the data's: a key deleted from it stays deleted
        data = replace(self.data, extra={})
        return scene_io.scene_to_json(
            self.grammar.ir, data, seed=seed, index=index, metadata=self.metadata
        )

    def save(self, path: str | Path) -> Path:
        """Write the scene as a JSON file every `ssg` command reads, replacing a file already
        at `path` (atomically, as `ssg sample -o` does), but never the grammar's own file: a
        stray `save(g.path)` replaced the grammar with a scene.  Metadata JSON cannot hold
        (NaN, a set) is refused: the file would be one no command reads."""
        from ssgc.io.outputs import check_output, write_output_text

        grammar_file = () if self.grammar.path is None else (self.grammar.path,)
        out = check_output(path, "scene file", inputs=grammar_file)
        text = _json_text(self.to_json(), str(path))
        write_output_text(out, text)
        return Path(path)

    def render(self, path: str | Path) -> Path:
        """Draw the scene (with its tree, when it has one) into a .png or .svg file."""
        return _render(self.to_json(), path, self.grammar)


@dataclass(frozen=True, eq=False)
class Parse:
    """One parse tree of a scene, with its score (log p) and certificate."""

    tree: Tree
    score: float
    status: str  # optimal, or time_limit (nothing certain)
    gap: float  # latent poses (micp): score bound − score; NaN when there is no bound

    def __repr__(self) -> str:
        return f"<Parse: log p {self.score:.4f}, {self.status}, {len(self.tree)} nodes>"


@dataclass(frozen=True, eq=False)
class ParseResult:
    """A scene's parses, best first, and how the search ended (as in `ssg parse`'s output)."""

    grammar: Grammar
    result: SceneParses
    document: dict[str, Any]  # the scene's entry of `ssg parse`'s output

    def __repr__(self) -> str:
        return (
            f"<ParseResult '{self.result.name}': {self.status}, {len(self.result.parses)} parse(s)>"
        )

    @property
    def status(self) -> str:
        """optimal (certified), feasible (a tree, not proven best), infeasible (proven: no tree
        of the grammar contains the scene), no_parse (none found, not proven) or error
        (docs/parsing.md "Statuses")."""
        return self.result.status

    @property
    def message(self) -> str:
        return self.result.message

    @property
    def parses(self) -> list[Parse]:
        return [
            Parse(Tree(self.grammar, p.tree), p.score, p.status, p.gap) for p in self.result.parses
        ]

    @property
    def best(self) -> Parse | None:
        parses = self.parses
        return parses[0] if parses else None

    def to_json(self) -> dict[str, Any]:
        """This scene's entry of `ssg parse`'s output (`scenes[i]`): with the diagnosis of a
        scene proven infeasible and the objects left to clutter, as the command writes it."""
        return copy.deepcopy(self.document)

    def render(self, path: str | Path) -> Path:
        """Draw the best parse, its edges coloured by their rule's log-probability."""
        doc = {"grammar": self.grammar.name, "scenes": [self.to_json()]}
        return _render(doc, path, self.grammar)


@dataclass
class FitResult:
    """What `ssgc.fit` returns: the fitted grammar and how the fit went."""

    grammar: Grammar  # the fitted grammar (its `.text` is the YAML `ssg fit -o` would write)
    iterations: list[dict[str, Any]] = field(default_factory=list)  # one report each
    status: str = ""  # converged, iterations (the limit was reached) or time_limit
    message: str = ""
    # the physical tails of `ssg explain` measured and written (docs/fitting.md, section 4.4)
    tails: list[dict[str, Any]] = field(default_factory=list)

    def __repr__(self) -> str:
        return f"<FitResult: {self.status}, {len(self.iterations)} iteration(s)>"

    @property
    def log_evidence(self) -> list[float]:
        """Per iteration: the log-evidence estimate of the grammar it started from."""
        return [float(r["log_evidence"]) for r in self.iterations]


def _numbers(values: Iterable[Any]) -> list[Any]:
    """Numbers as JSON holds them (numpy's as Python's); what they are is checked as in a file."""
    if isinstance(values, np.ndarray):  # a wrong shape stays one, for the check to name
        values = values.tolist()
    if not isinstance(values, list | tuple):
        try:
            values = list(values)  # a generator, a zip
        except TypeError:
            return values  # a number or None where a list belongs: the check says so
    return [v.item() if isinstance(v, np.generic) else v for v in values]


def _json_text(doc: dict[str, Any], file: str) -> str:
    """A scene's document as its file's text, or a SceneError when its metadata holds what
    JSON cannot (NaN or infinity, which the reader refuses; a set; a huge integer)."""
    try:
        json.dumps(doc, allow_nan=False)
        _text_keys(doc)
    except (ValueError, TypeError) as exc:
        raise SceneError.single(
            "the scene's metadata must hold only what JSON holds (finite numbers, text, "
            f"lists, dicts with text keys): {exc}",
            file,
        ) from None
    return scene_io.dumps_json(doc)


def _text_keys(value: Any) -> None:
    """JSON's keys are text: `json.dumps` wrote {1: 2} as {"1": 2}, another dict read back."""
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise TypeError(f"the key {key!r} is not text")
            _text_keys(item)
    elif isinstance(value, list | tuple):
        for item in value:
            _text_keys(item)


def _render(doc: dict[str, Any], path: str | Path, grammar: Grammar) -> Path:
    from ssgc.render.scene import render_document

    if not isinstance(path, str | Path):
        raise TypeError(f"the picture's path must be a str or Path, got {type(path).__name__}")
    with np.errstate(all="ignore"):  # as in `ssg`: matplotlib's 3-D projection overflows harmlessly
        render_document(doc, path, grammar.ir)
    return Path(path)
