"""A mixed-integer linear program in matrix form, and solving it with HiGHS.

The parser lowers (supertree, scene) to a `Milp` — objective, sparse constraint matrix, bounds,
integrality — plus its own inverse data; nothing downstream looks at solver variables by name.
`HighsSession` keeps one HiGHS model alive so that top-N parsing adds a no-good cut and
re-solves without rebuilding anything.

Why not a Pyomo model: Pyomo builds and translates models expression by expression.  Measured
on this machine for a 20k-column, 15k-row binary program: 0.32 s to build the Pyomo model from
`LinearExpression` rows and 1.4 s for `appsi_highs` to translate and solve it, while the same
matrices are built with numpy in milliseconds; Pyomo's `MatrixConstraint` is not accepted by its
HiGHS interfaces.  Parses must take ~0.1 s, so the matrices go to HiGHS directly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import highspy
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
INF = highspy.kHighsInf


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


class HighsSession:
    """One HiGHS model, solved repeatedly with cuts added in between (for top-N)."""

    def __init__(self, milp: Milp, time_limit: float | None = None) -> None:
        self.milp = milp
        self.h = highspy.Highs()
        self.h.setOptionValue("output_flag", False)
        self.h.setOptionValue("mip_rel_gap", 0.0)  # rankings must be exact
        self.h.setOptionValue("mip_abs_gap", 1e-9)
        self.h.setOptionValue("threads", 1)
        if time_limit is not None:
            self.h.setOptionValue("time_limit", float(max(time_limit, 1e-3)))
        lp = highspy.HighsLp()
        n, m = milp.cost.shape[0], milp.A.shape[0]
        lp.num_col_, lp.num_row_ = n, m
        lp.col_cost_ = milp.cost
        lp.col_lower_ = milp.col_lo
        lp.col_upper_ = milp.col_hi
        lp.row_lower_ = np.where(np.isfinite(milp.row_lo), milp.row_lo, -INF)
        lp.row_upper_ = np.where(np.isfinite(milp.row_hi), milp.row_hi, INF)
        lp.sense_ = highspy.ObjSense.kMaximize
        lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
        lp.a_matrix_.start_ = milp.A.indptr.astype(np.int32)
        lp.a_matrix_.index_ = milp.A.indices.astype(np.int32)
        lp.a_matrix_.value_ = milp.A.data.astype(float)
        lp.integrality_ = [
            highspy.HighsVarType.kInteger if f else highspy.HighsVarType.kContinuous
            for f in milp.integer
        ]
        status = self.h.passModel(lp)
        if status == highspy.HighsStatus.kError:
            raise RuntimeError("HiGHS refused the model")

    def set_time_limit(self, seconds: float) -> None:
        self.h.setOptionValue("time_limit", float(max(seconds, 1e-3)))

    def solve(self) -> Solution:
        t0 = time.perf_counter()
        run = self.h.run()
        solve_s = time.perf_counter() - t0
        model_status = self.h.getModelStatus()
        info = self.h.getInfo()
        status = _status_name(model_status, run)
        x = None
        objective = bound = float("nan")
        gap = float("inf")
        if status in ("optimal", "time_limit") and info.primal_solution_status >= 2:
            x = np.asarray(self.h.getSolution().col_value, float)
            objective = float(info.objective_function_value)
            bound = float(info.mip_dual_bound)
            gap = (
                _gap(objective, bound)
                if status == "time_limit"
                else max(0.0, _gap(objective, bound))
            )
        elif status == "time_limit":
            status = "time_limit"
        message = self.h.modelStatusToString(model_status)
        return Solution(status, x, objective, bound, gap, solve_s, message)

    def add_cut(self, cols: NDArray[np.int64], coefs: FloatArray, lo: float, hi: float) -> None:
        self.h.addRow(
            lo if np.isfinite(lo) else -INF,
            hi if np.isfinite(hi) else INF,
            len(cols),
            cols.astype(np.int32),
            coefs.astype(float),
        )


def _status_name(model_status: highspy.HighsModelStatus, run: highspy.HighsStatus) -> str:
    S = highspy.HighsModelStatus
    if model_status == S.kOptimal:
        return "optimal"
    if model_status in (S.kInfeasible, S.kUnboundedOrInfeasible):
        return "infeasible"
    if model_status in (S.kTimeLimit, S.kInterrupt, S.kIterationLimit, S.kSolutionLimit):
        return "time_limit"
    return "error"


def _gap(objective: float, bound: float) -> float:
    """Relative gap |bound - objective| / max(1, |objective|) (reported with every parse)."""
    if not (np.isfinite(objective) and np.isfinite(bound)):
        return float("inf")
    return abs(bound - objective) / max(1.0, abs(objective))
