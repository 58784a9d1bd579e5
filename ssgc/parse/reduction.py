"""A parse reduction: (scene, candidate poses) → a solver-neutral MILP and its inverse.

Each formulation of parsing is a `Reduction` (the shape of CVXPY's reductions): `accepts` says
whether it can take a request — its kind (latent poses or not, with or without the bound's
assignments) and its size, counted before anything is built; `apply` builds the `Milp` and the
inverse data that maps a solution back (`Problem`); `invert` does that mapping.  The parser
holds them as a chain and uses the first that accepts (`choose`); a new formulation is one more
link, and a solver is a `Session` (`ssgc.parse.milp`) that never sees the reduction.

Completeness.  A reduction whose model holds *every* tree of the grammar for the scene at its
exact score sets a class attribute `complete = True`: the parser then takes its infeasibility
(an `UnparseableScene` from `apply`, or HiGHS's `infeasible`) as a proof (status `infeasible`)
and its optimum within the gap tolerance as a certificate (status `optimal`).  Without it, for
grammars with latent poses, the parser claims neither (`no_parse`, `feasible`); models of
grammars without latent poses are complete by construction (`Parser.complete`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from ssgc.errors import SsgError
from ssgc.io.scene import Scene
from ssgc.ir import Grammar
from ssgc.parse.milp import Milp
from ssgc.parse.proposals import Candidates
from ssgc.parse.supertree import Supertree
from ssgc.tree import Trees


class ModelTooLarge(SsgError):
    """The parse model of a scene would not fit the stated limits."""


class Problem(Protocol):
    """A reduced scene: its MILP, and the inverse data that reads a tree off a solution."""

    milp: Milp
    structural: NDArray[np.int64]  # the binaries that determine the tree (no-good cuts)
    build_s: float

    def invert(self, x: NDArray[np.float64]) -> Trees: ...


@dataclass(frozen=True)
class Request:
    """What a reduction is asked to reduce: a scene, with the candidate poses of every set and,
    for latent grammars parsed with the bound, each latent set's assignments (`bounds`)."""

    grammar: Grammar
    supertree: Supertree
    scene: Scene
    cand: Candidates
    latent: bool  # the grammar has sets without observed poses
    bounds: dict | None = None  # ssgc.parse.bound.SetBound per latent set
    deadline: float | None = None
    best_only: bool = False  # only the best tree is wanted (`--top 1`): see reduce_posed


class Reduction(Protocol):
    def accepts(self, request: Request) -> bool:
        """Whether `apply` can take the request (its kind and its size)."""
        ...

    def refusal(self, request: Request) -> str | None:
        """Why a request of this reduction's kind is refused (too large), None when it is
        not of its kind or is accepted."""
        ...

    def apply(self, request: Request) -> tuple[Milp, Problem]: ...

    def invert(self, problem: Problem, x: NDArray[np.float64]) -> Trees: ...


def choose(chain: tuple[Reduction, ...], request: Request) -> Reduction:
    """The first reduction of the chain that accepts the request; when none does, the reason
    given by the last one whose kind it was."""
    reasons = []
    for reduction in chain:
        if reduction.accepts(request):
            return reduction
        reasons.append(reduction.refusal(request))
    reason = next((r for r in reversed(reasons) if r), "no parse formulation takes this scene")
    raise ModelTooLarge.single(reason)
