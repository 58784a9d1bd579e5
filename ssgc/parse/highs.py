"""The HiGHS implementation of a parse `Session` (`ssgc.parse.milp`)."""

from __future__ import annotations

import ctypes
import functools
import os
import sys
import time
from typing import Any

import highspy
import numpy as np
from numpy.typing import NDArray

from ssgc.parse.milp import FloatArray, Milp, Solution

INF = highspy.kHighsInf


def quiet_highs() -> Any:
    """A `highspy.Highs` that writes nothing.  highspy 1.16 prints its banner ("Running HiGHS
    ...") to the process's standard output while the object is built, before `output_flag` can
    be set, and `ssg parse` and `ssg explain --json` write their JSON there: so standard output
    is pointed at the null device for that moment, at the file-descriptor level (the banner is
    written by C code, which `sys.stdout` does not reach), and C's own buffer is flushed before
    it is pointed back, so that nothing buffered surfaces later."""
    sys.stdout.flush()
    _flush_c_stdio()  # what was written before goes where it was meant to
    try:
        saved = os.dup(1)
    except OSError:  # no standard output to protect
        h = highspy.Highs()
    else:
        try:
            with open(os.devnull, "wb") as null:
                os.dup2(null.fileno(), 1)
                try:
                    h = highspy.Highs()
                finally:
                    _flush_c_stdio()
                    os.dup2(saved, 1)
        finally:
            os.close(saved)
    h.setOptionValue("output_flag", False)
    return h


def _flush_c_stdio() -> None:
    libc = _libc()
    if libc is not None:
        libc.fflush(None)


@functools.cache
def _libc() -> Any:
    try:
        return ctypes.CDLL(None)
    except (OSError, TypeError):  # no C library to ask (Windows)
        return None


class HighsSession:
    """One HiGHS model, solved repeatedly with cuts added in between (for top-N)."""

    def __init__(self, milp: Milp, time_limit: float | None = None) -> None:
        self.milp = milp
        self.h = quiet_highs()
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
