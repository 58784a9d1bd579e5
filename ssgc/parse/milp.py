"""A mixed-integer linear program in matrix form, solver-neutral, and what a solver offers.

The parser lowers (supertree, scene) to a `Milp` — objective, sparse constraint matrix, bounds,
integrality — plus its own inverse data (`ssgc.parse.reduction`); nothing downstream looks at
solver variables by name.  A solver is a `Session` over one `Milp`: it keeps its model alive so
that top-N parsing adds a no-good cut and re-solves without rebuilding anything.  HiGHS is the
one implementation (`ssgc.parse.highs`).

Why not a Pyomo model: Pyomo builds and translates models expression by expression.  Measured
on this machine for a 20k-column, 15k-row binary program: 0.32 s to build the Pyomo model from
`LinearExpression` rows and 1.4 s for `appsi_highs` to translate and solve it, while the same
matrices are built with numpy in milliseconds; Pyomo's `MatrixConstraint` is not accepted by its
HiGHS interfaces.  Parses must take ~0.1 s, so the matrices go to HiGHS directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class ColumnBuilder:
    """Allocates columns (variables) in blocks: bounds, integrality and objective per column."""

    def __init__(self) -> None:
        self.lo: list[FloatArray] = []
        self.hi: list[FloatArray] = []
        self.cost: list[FloatArray] = []
        self.integer: list[NDArray[np.bool_]] = []
        self.extra: list[tuple[NDArray[np.int64], FloatArray]] = []
        self.n = 0

    def add_cost(self, cols: NDArray[np.int64], values: FloatArray) -> None:
        """Add to the objective of existing columns (costs gathered per node after allocation)."""
        self.extra.append((np.asarray(cols, np.int64), np.asarray(values, float)))

    def add(
        self,
        count: int,
        integer: bool,
        lo: float | FloatArray = 0.0,
        hi: float | FloatArray = 1.0,
        cost: float | FloatArray = 0.0,
    ) -> NDArray[np.int64]:
        self.lo.append(np.broadcast_to(np.asarray(lo, float), (count,)))
        self.hi.append(np.broadcast_to(np.asarray(hi, float), (count,)))
        self.cost.append(np.broadcast_to(np.asarray(cost, float), (count,)))
        self.integer.append(np.full(count, integer))
        cols = np.arange(self.n, self.n + count, dtype=np.int64)
        self.n += count
        return cols


class RowBuilder:
    """Collects constraint rows lo <= A x <= hi as COO triplets, a block of rows at a time."""

    def __init__(self) -> None:
        self.rows: list[NDArray[np.int64]] = []
        self.cols: list[NDArray[np.int64]] = []
        self.vals: list[FloatArray] = []
        self.lo: list[FloatArray] = []
        self.hi: list[FloatArray] = []
        self.m = 0

    def add(
        self,
        row: NDArray[np.int64],
        col: NDArray[np.int64],
        val: FloatArray | float,
        n_rows: int,
        lo: float | FloatArray,
        hi: float | FloatArray,
    ) -> None:
        """Rows numbered 0..n_rows-1 locally; `row`, `col`, `val` are their nonzeros."""
        row = np.asarray(row, np.int64)
        self.rows.append(row + self.m)
        self.cols.append(np.asarray(col, np.int64))
        self.vals.append(np.broadcast_to(np.asarray(val, float), row.shape))
        self.lo.append(np.broadcast_to(np.asarray(lo, float), (n_rows,)))
        self.hi.append(np.broadcast_to(np.asarray(hi, float), (n_rows,)))
        self.m += n_rows


def add_leq(rows: RowBuilder, lhs: NDArray[np.int64], rhs: NDArray[np.int64]) -> None:
    """x[lhs[i]] <= x[rhs[i]] for every i (child <= parent, choice <= selection, ...)."""
    k = len(lhs)
    rows.add(
        np.r_[np.arange(k), np.arange(k)],
        np.r_[lhs, rhs],
        np.r_[np.ones(k), -np.ones(k)],
        k,
        -np.inf,
        0.0,
    )


def add_count_law(
    cols: ColumnBuilder,
    rows: RowBuilder,
    parent: int,
    children: NDArray[np.int64],
    probs: FloatArray,
) -> None:
    """A `repeat` node: one count indicator z[c] per possible count c, costing log P(c);
    exactly one is on iff the parent is, and it equals the number of active children."""
    counts = np.flatnonzero(probs[: len(children) + 1] > 0)
    z = cols.add(len(counts), integer=True, cost=np.log(probs[counts]))
    rows.add(
        np.zeros(len(z) + 1, np.int64), np.r_[z, parent], np.r_[np.ones(len(z)), -1.0], 1, 0.0, 0.0
    )
    rows.add(
        np.zeros(len(z) + len(children), np.int64),
        np.r_[z, children],
        np.r_[-counts.astype(float), np.ones(len(children))],
        1,
        0.0,
        0.0,
    )


def add_correspondences(
    rows: RowBuilder,
    b: NDArray[np.int64],
    node: NDArray[np.int64],
    obj: NDArray[np.int64],
    n_obj: int,
    node_cols: NDArray[np.int64],
    observed_nodes: NDArray[np.int64],
) -> None:
    """b[i] = node[i] explains object obj[i]: each object exactly once; an observed node is
    active iff it explains one object."""
    rows.add(obj, b, 1.0, n_obj, 1.0, 1.0)
    local = np.full(int(max(node.max(initial=0), observed_nodes.max(initial=0))) + 1, -1, np.int64)
    local[observed_nodes] = np.arange(len(observed_nodes))
    rows.add(
        np.r_[local[node], local[observed_nodes]],
        np.r_[b, node_cols[observed_nodes]],
        np.r_[np.ones(len(b)), -np.ones(len(observed_nodes))],
        len(observed_nodes),
        0.0,
        0.0,
    )


@dataclass(frozen=True)
class Milp:
    """maximise cost·x subject to row_lo <= A x <= row_hi, col_lo <= x <= col_hi."""

    cost: FloatArray
    A: sp.csc_matrix
    row_lo: FloatArray
    row_hi: FloatArray
    col_lo: FloatArray
    col_hi: FloatArray
    integer: NDArray[np.bool_]

    @staticmethod
    def build(cols: ColumnBuilder, rows: RowBuilder) -> Milp:
        cat = np.concatenate
        empty_i, empty_f = np.zeros(0, np.int64), np.zeros(0)
        A = sp.csc_matrix(
            (
                cat(rows.vals or [empty_f]),
                (cat(rows.rows or [empty_i]), cat(rows.cols or [empty_i])),
            ),
            shape=(rows.m, cols.n),
        )
        A.sum_duplicates()
        cost = cat(cols.cost or [empty_f]).astype(float)
        for idx, values in cols.extra:
            np.add.at(cost, idx, values)
        return Milp(
            cost=cost,
            A=A,
            row_lo=cat(rows.lo or [empty_f]).astype(float),
            row_hi=cat(rows.hi or [empty_f]).astype(float),
            col_lo=cat(cols.lo or [empty_f]).astype(float),
            col_hi=cat(cols.hi or [empty_f]).astype(float),
            integer=cat(cols.integer or [np.zeros(0, bool)]),
        )

    @property
    def shape(self) -> dict[str, int]:
        return {
            "variables": int(self.cost.shape[0]),
            "binaries": int(self.integer.sum()),
            "rows": int(self.A.shape[0]),
            "nonzeros": int(self.A.nnz),
        }


@dataclass
class Solution:
    status: str  # optimal | time_limit | infeasible | error
    x: FloatArray | None
    objective: float
    bound: float
    gap: float
    solve_s: float
    message: str = ""
    extra: dict[str, float] = field(default_factory=dict)


class Session(Protocol):
    """One solver model of a `Milp`, solved repeatedly with cuts added in between."""

    def set_time_limit(self, seconds: float) -> None: ...

    def solve(self) -> Solution: ...

    def add_cut(self, cols: NDArray[np.int64], coefs: FloatArray, lo: float, hi: float) -> None:
        """Add the row lo <= coefs · x[cols] <= hi (infinite bounds allowed)."""
        ...
