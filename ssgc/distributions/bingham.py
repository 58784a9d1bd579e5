r"""Bingham distribution on unit quaternions (the 3-sphere S³).

Conventions
-----------
* Quaternions are ``wxyz`` (scalar first) float64 arrays of shape ``(..., 4)``.
* The density is taken with respect to the ordinary surface measure ``dS`` on
  S³ (total area ``2π²``)::

      p(q) = exp(qᵀ M diag(Z) Mᵀ q) / F(Z),
      F(Z) = ∫_{S³} exp(Σ_i Z_i x_i²) dS(x),        F(0) = 2π².

  ``M`` is a 4×4 orthogonal matrix whose columns are the principal axes and
  ``Z`` is a 4-vector.  Adding a constant ``c`` to every ``Z_i`` multiplies
  ``F`` by ``e^c`` and leaves the density unchanged, so :class:`Bingham`
  stores ``Z`` shifted such that ``max(Z) == 0``; the column of ``M`` with
  ``Z_i == 0`` is the mode.  Concentrations are ``c_i = -Z_i >= 0``.
  The density is antipodally symmetric, ``p(q) == p(-q)``, as it must be for
  a distribution over rotations.

Normalising constant
--------------------
With Hopf-type coordinates ``x1 = cosθ cosφ1``, ``x2 = cosθ sinφ1``,
``x3 = sinθ cosφ2``, ``x4 = sinθ sinφ2`` (θ ∈ [0, π/2], φ1, φ2 ∈ [0, 2π)) the
surface element is ``dS = cosθ sinθ dθ dφ1 dφ2``.  Substituting
``t = cos²θ`` (so ``cosθ sinθ dθ = dt/2``) and using
``∫₀^{2π} exp(a cos 2φ) dφ = 2π I0(a)`` gives the exact one-dimensional form::

    F(Z) = 2π² ∫₀¹ exp(t (z1+z2)/2 + (1-t)(z3+z4)/2)
                    · I0(t (z1-z2)/2) · I0((1-t)(z3-z4)/2) dt.

Internally ``Z`` is sorted in decreasing order and shifted so ``z1 = 0`` (the
two largest values form the first pair); with
exponentially scaled Bessel functions (``i0e(x) = e^{-|x|} I0(x)``) the
integrand becomes ``exp(-(1-t)·|z3|) · i0e(t (z1-z2)/2) · i0e((1-t)(z3-z4)/2)``,
which is bounded by 1, so nothing overflows.  Its only sharp features sit at
the end points ``t = 0`` and ``t = 1`` on length scales ``1/|z|``.  The interval
is split at ``t = 1/2`` and the upper half is integrated in ``u = 1 - t`` (so
both small variables are exact near their end point).  Each half is cut into
panels that halve toward its end point, down to 1/16 of the shortest length
scale, and each panel gets a 16-point Gauss–Legendre rule: every factor is
smooth on a panel relative to the panel's length, and all four moments and
``F`` come from one vectorised evaluation of about 16 · 2 · log2(16 |z|)
points.  Against 30-digit reference values (mpmath, `tests/test_bingham.py`)
``log F`` is exact to 2e-15 for concentrations from 0 to 1e10, and the moments
to 1e-14 relative up to concentrations of 1e4 (beyond, the smallest moments
lose digits to the cancellation in ``i0e - i1e``).  The adaptive Gauss–Kronrod
rule of QUADPACK used before agreed to 4e-15 in ``log F`` and 2e-16 in the
moments on 604 random ``Z``, at 16 times the CPU time (3.4 ms against 0.21 ms
for ``log F`` with its moments).

The second moments ``E[x_i²] = ∂ log F / ∂z_i`` follow from the same
integral with the conditional expectations (given t)
``E[x1² | t] = (t/2)(1 + I1(a)/I0(a))``, ``E[x2² | t] = (t/2)(1 - I1(a)/I0(a))``
with ``a = t (z1-z2)/2``, and the analogous ``(1-t)`` expressions for x3, x4.

References
----------
* C. Bingham (1974). "An antipodally symmetric distribution on the sphere."
  Annals of Statistics 2(6), 1201–1225.
* K. V. Mardia and P. E. Jupp (2000). *Directional Statistics*. Wiley.
  (Exponential-family maximum likelihood for the Bingham distribution.)
* J. T. Kent, A. M. Ganeiber and K. V. Mardia (2013). "A new method to simulate
  the Bingham and related distributions in directional data analysis with
  applications." arXiv:1310.8110; published as "A new unified approach for
  the simulation of a wide class of directional distributions", Journal of
  Computational and Graphical Statistics 27(2), 2018.  (Exact rejection
  sampler with an angular central Gaussian envelope.)
* D. E. Tyler (1987). "Statistical analysis for the angular central Gaussian
  distribution on the sphere." Biometrika 74(3), 579–589.
"""

from __future__ import annotations

import functools
import math
import operator
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy import optimize, special

from ssgc.distributions.arrays import frozen
from ssgc.geometry import quat_multiply

__all__ = [
    "SPHERE_AREA",
    "Bingham",
    "fit_bingham",
    "log_normalizer",
    "moments",
]

#: Surface area of the unit 3-sphere, ``F(0)``.
SPHERE_AREA = 2.0 * math.pi**2
_LOG_SPHERE_AREA = math.log(SPHERE_AREA)

#: Dimension of the ambient space of the quaternion sphere.
_DIM = 4

#: Maximum deviation of ``MᵀM`` from the identity accepted by :class:`Bingham`.
ORTHOGONALITY_TOL = 1e-6

#: Gauss–Legendre rule of each panel of the normaliser's quadrature (:func:`_nodes`).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)

ArrayLike = npt.ArrayLike


# ---------------------------------------------------------------------------
# Normalising constant and moments
# ---------------------------------------------------------------------------


def _as_z(z: ArrayLike) -> np.ndarray:
    arr = np.asarray(z, dtype=np.float64)
    if arr.shape != (_DIM,):
        raise ValueError(f"Z must be a 4-vector, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"Z must be finite, got {arr.tolist()}")
    return arr


def _canonical_key(z: np.ndarray) -> tuple[float, np.ndarray, tuple[float, ...]]:
    """Shift ``z`` so its maximum is 0 and sort it in decreasing order.

    Returns the shift, the permutation ``order`` with ``z[order]`` decreasing,
    and the shifted, sorted values as a hashable tuple.
    """
    shift = float(np.max(z))
    order = np.argsort(-z, kind="stable")
    zs = z[order] - shift
    zs[0] = 0.0
    return shift, order, tuple(float(v) for v in zs)


def _pair_parameters(zs: tuple[float, ...]) -> tuple[float, float, float]:
    """Parameters of the scaled integrand for sorted, shifted ``zs``.

    With ``zs = (0, z2, z3, z4)`` decreasing, the integrand of ``F / 2π²`` is
    ``exp(-(1-t)·c) · i0e(t·d1) · i0e((1-t)·d2)`` with ``d1 = (0 - z2)/2``,
    ``c = -z3`` and ``d2 = (z3 - z4)/2`` (all non-negative).
    """
    d1 = 0.5 * (zs[0] - zs[1])
    c = -zs[2]
    d2 = 0.5 * (zs[2] - zs[3])
    return d1, c, d2


def _halvings(scales: Sequence[float]) -> int:
    """How many halving panels :func:`_nodes` needs to reach 1/(16 · largest scale)."""
    return max(3, math.ceil(math.log2(16.0 * max(4.0, *scales))) - 1)


@functools.lru_cache(maxsize=128)
def _nodes(halvings: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes and weights on [0, 1/2]: panels [2⁻ᵏ⁻¹, 2⁻ᵏ], k = 1 ... halvings,
    and the panel from 0 to the last edge.  A factor varying on a length ``1/scale`` next to 0
    (``i0e(x · scale)``, a power of x on the scale's far side; ``exp(-x · scale)``) is smooth
    on every panel relative to the panel's own length, so a fixed rule per panel converges."""
    edges = np.append(0.5 ** np.arange(1, halvings + 2), 0.0)  # 1/2, 1/4, ..., 0
    lo, hi = edges[1:, None], edges[:-1, None]
    x = (0.5 * (hi - lo) * (_GL_X + 1.0) + lo).ravel()
    w = (0.5 * (hi - lo) * _GL_W).ravel()
    return x, w


def _numerators(d1: float, c: float, d2: float) -> np.ndarray:
    """``∫₀¹ nᵢ(t) dt`` for the four numerators of the moments (module docstring): with ``u =
    1 - t``, ``n1,2 = (t/2) e^{-uc} (i0e(t d1) ± i1e(t d1)) i0e(u d2)`` and ``n3,4`` the same
    with the roles of ``(t, d1)`` and ``(u, d2)`` exchanged.  Their sum is the integrand of
    ``F / 2π²``.  The interval is split at 1/2 and the upper half is integrated in ``u``, so
    both small variables are exact near their end point, each half on the geometric panels of
    :func:`_nodes` at the scales of the factors that vary there."""
    xt, wt = _nodes(_halvings((d1,)))
    xu, wu = _nodes(_halvings((c, d2)))
    t = np.concatenate([xt, 1.0 - xu])
    u = np.concatenate([1.0 - xt, xu])
    args = np.concatenate([t * d1, u * d2])
    i0, i1 = special.i0e(args), special.i1e(args)
    n = t.size
    i0a, i1a, i0b, i1b = i0[:n], i1[:n], i0[n:], i1[n:]
    weight = 0.5 * np.exp(-u * c) * np.concatenate([wt, wu])
    ta, ub = weight * t * i0b, weight * u * i0a
    return np.array([ta @ (i0a + i1a), ta @ (i0a - i1a), ub @ (i0b + i1b), ub @ (i0b - i1b)])


@functools.lru_cache(maxsize=4096)
def _numerators_sorted(zs: tuple[float, ...]) -> tuple[float, float, float, float]:
    """:func:`_numerators` for decreasing ``zs`` with ``zs[0] == 0`` (cached: the fit asks
    for ``log F`` and the moments at the same ``z``)."""
    return tuple(float(v) for v in _numerators(*_pair_parameters(zs)))  # type: ignore[return-value]


def _log_normalizer_sorted(zs: tuple[float, ...]) -> float:
    """log F for decreasing ``zs`` with ``zs[0] == 0``."""
    if zs == (0.0, 0.0, 0.0, 0.0):
        return _LOG_SPHERE_AREA
    return _LOG_SPHERE_AREA + math.log(math.fsum(_numerators_sorted(zs)))


def _moments_sorted(zs: tuple[float, ...]) -> tuple[float, float, float, float]:
    """``E[x_i²]`` for decreasing ``zs`` with ``zs[0] == 0``.

    Conditional on t, ``E[x1²|t] ∝ (t/2)(I0(a) + I1(a))`` and ``E[x2²|t] ∝ (t/2)(I0(a) -
    I1(a))`` with ``a = t·d1``, and likewise with ``u = 1 - t`` and ``b = u·d2`` for x3, x4;
    the numerators are written with scaled Bessel functions, so nothing is divided by I0.
    Normalising by their sum (the integral of ``F / 2π²``) makes the moments sum to one."""
    parts = _numerators_sorted(zs)
    total = math.fsum(parts)
    return tuple(p / total for p in parts)  # type: ignore[return-value]


def log_normalizer(z: ArrayLike) -> float:
    """Return ``log F(Z)``, the log normalising constant of the Bingham density.

    ``F(Z) = ∫_{S³} exp(Σ z_i x_i²) dS(x)`` with respect to the surface measure
    on the unit 3-sphere, so ``F(0) = 2π²``.  Computed by adaptive quadrature of
    an exact one-dimensional integral (see the module docstring); the relative
    error of ``F`` is below about 1e-12 for concentrations from 0 up to at least
    1e10 and any ordering of ``z``.  ``log F(z + s) == s + log F(z)`` for a scalar ``s``.
    Results are cached on the canonical (shifted, sorted) tuple of ``z``.
    """
    arr = _as_z(z)
    shift, _order, key = _canonical_key(arr)
    return shift + _log_normalizer_sorted(key)


def moments(z: ArrayLike) -> np.ndarray:
    """Return ``E[x_i²]`` (i = 1..4) under the Bingham density with ``M = I``.

    These are the partial derivatives ``∂ log F / ∂z_i``; they are non-negative
    and sum to one.  For a general ``M`` the second-moment matrix is
    ``E[q qᵀ] = M diag(moments(Z)) Mᵀ``.
    """
    arr = _as_z(z)
    _shift, order, key = _canonical_key(arr)
    out = np.empty(_DIM)
    out[order] = _moments_sorted(key)
    return out


# ---------------------------------------------------------------------------
# Quaternion helpers
# ---------------------------------------------------------------------------


def _canonical_sign(q: np.ndarray) -> np.ndarray:
    """Flip ``q`` so its first non-negligible component is positive."""
    q = np.array(q, dtype=np.float64)
    idx = int(np.argmax(np.abs(q) > 1e-12))
    if q[idx] < 0:
        q = -q
    return q


def _as_unit_quaternions(q: ArrayLike, name: str = "q") -> np.ndarray:
    arr = np.asarray(q, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != _DIM:
        raise ValueError(f"{name} must have shape (..., 4), got {arr.shape}")
    norms = np.linalg.norm(arr, axis=-1, keepdims=True)
    if not np.all(np.isfinite(norms)) or np.any(norms == 0.0):
        raise ValueError(f"{name} must contain finite, non-zero quaternions")
    return arr / norms


def _acg_parameter(lam: np.ndarray) -> float:
    """Root ``b`` in [1, 4] of ``Σ_i 1/(b + 2λ_i) = 1`` (Kent et al., 2013).

    ``lam`` are the eigenvalues of ``A = -M diag(Z) Mᵀ``; at least one is 0 for a
    canonicalised ``Z``, so the left-hand side is >= 1 at ``b = 1`` and <= 1 at
    ``b = 4`` (equality iff all ``λ_i = 0``).
    """

    def g(b: float) -> float:
        return float(np.sum(1.0 / (b + 2.0 * lam))) - 1.0

    hi = float(_DIM)
    if g(hi) >= 0.0:
        return hi
    lo = 1.0
    if g(lo) <= 0.0:  # only in the limit of infinite concentrations
        return lo
    return float(optimize.brentq(g, lo, hi, xtol=1e-14, rtol=1e-14))


# ---------------------------------------------------------------------------
# The distribution
# ---------------------------------------------------------------------------


class Bingham:
    """Bingham distribution on unit quaternions (``wxyz``), antipodally symmetric.

    ``p(q) = exp(qᵀ M diag(Z) Mᵀ q) / F(Z)`` with respect to the surface measure
    on S³ (see the module docstring).

    Parameters
    ----------
    M:
        4×4 orthogonal matrix; column ``i`` is the axis with parameter ``Z[i]``.
        ``MᵀM`` must equal the identity within 1e-6 (max-abs); ``M`` is then
        re-orthonormalised to machine precision (nearest orthogonal matrix).
    Z:
        Finite 4-vector.  It is stored shifted so that ``max(Z) == 0``.

    Attributes ``M``, ``Z``, ``concentration`` and ``mode`` are read-only
    arrays; instances are immutable.
    """

    __slots__ = ("_M", "_Z", "_acg_b", "_log_norm")

    def __init__(self, M: ArrayLike, Z: ArrayLike) -> None:
        m = np.asarray(M, dtype=np.float64)
        if m.shape != (_DIM, _DIM):
            raise ValueError(f"M must be a 4x4 matrix, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise ValueError("M must be finite")
        deviation = float(np.max(np.abs(m.T @ m - np.eye(_DIM))))
        if deviation > ORTHOGONALITY_TOL:
            raise ValueError(
                f"M must be orthogonal: max |MᵀM - I| = {deviation:.3g} "
                f"exceeds {ORTHOGONALITY_TOL:g}"
            )
        u, _s, vt = np.linalg.svd(m)
        m = u @ vt
        z = _as_z(Z)
        z = z - np.max(z)
        self._M = frozen(m)
        self._Z = frozen(z)
        self._log_norm = log_normalizer(z)
        self._acg_b = _acg_parameter(-z)

    # -- constructors -------------------------------------------------------

    @classmethod
    def from_mode(cls, q_mode: ArrayLike, concentration: float | ArrayLike) -> Bingham:
        """Bingham concentrated about the rotation ``q_mode`` (``wxyz``).

        ``concentration`` is a scalar or a 3-vector ``(c_x, c_y, c_z) >= 0``
        about the three axes of the mode's own (body) frame: the columns of
        ``M`` are ``q_mode ⊗ (0, e_x)``, ``q_mode ⊗ (0, e_y)``, ``q_mode ⊗ (0, e_z)``
        and ``q_mode`` (Hamilton product), and ``Z = (-c_x, -c_y, -c_z, 0)``.

        For a small rotation ``δ`` about body axis ``i``,
        ``q = q_mode ⊗ (cos(δ/2), sin(δ/2) e_i)``, the log density falls by
        ``c_i sin²(δ/2) ≈ c_i δ²/4``, i.e. the rotation angle about that axis
        has an angular standard deviation of about ``sqrt(2 / c_i)`` radians
        (for large ``c_i``).
        """
        qm = _as_unit_quaternions(q_mode, "q_mode")
        if qm.shape != (_DIM,):
            raise ValueError(f"q_mode must be a single quaternion, got shape {qm.shape}")
        c = np.asarray(concentration, dtype=np.float64)
        if c.ndim == 0:
            c = np.full(3, float(c))
        if c.shape != (3,):
            raise ValueError(f"concentration must be a scalar or a 3-vector, got shape {c.shape}")
        if not np.all(np.isfinite(c)) or np.any(c < 0):
            raise ValueError(f"concentration must be finite and >= 0, got {c.tolist()}")
        pure = np.zeros((3, _DIM))
        pure[:, 1:] = np.eye(3)
        axes = quat_multiply(qm[None, :], pure)  # (3, 4): q_mode ⊗ (0, e_i)
        m = np.column_stack([axes[0], axes[1], axes[2], qm])
        return cls(m, np.concatenate([-c, [0.0]]))

    @classmethod
    def fit(
        cls,
        q: ArrayLike,
        weights: ArrayLike | None = None,
        max_concentration: float = 1e4,
    ) -> Bingham:
        """Weighted maximum-likelihood fit to quaternion samples ``q`` of shape (n, 4).

        ``S = Σ w q qᵀ / Σ w`` is the weighted scatter matrix (samples are first
        normalised to unit length; the sign of each sample is irrelevant).  The
        MLE of ``M`` is the eigenvector matrix of ``S``, sorted by increasing
        eigenvalue so that the last column (largest eigenvalue) is the mode.  With
        ``λ`` the eigenvalues, ``Z`` maximises the concave log likelihood
        ``Σ_i z_i λ_i - log F(z)`` with ``z_mode = 0`` and the other
        ``z_i ∈ [-max_concentration, 0]``; at the optimum ``moments(Z) = λ`` unless a
        bound is active.  The result is polished with a few Newton steps so it is
        accurate to about 1e-10 relative.

        Degenerate inputs: an empty sample, non-finite or zero-norm samples,
        negative or non-finite weights, or a zero total weight raise
        ``ValueError``.  When the samples span fewer than four dimensions (fewer
        than four linearly independent samples, e.g. a single sample) some
        eigenvalues of ``S`` vanish and the corresponding concentrations hit
        ``max_concentration``; a single sample gives the mode at that sample with
        all three concentrations equal to ``max_concentration``.  Equal weights
        give the same fit as unweighted data, and integer weights the same fit
        as duplicating samples.
        """
        arr = np.asarray(q, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != _DIM:
            raise ValueError(f"q must have shape (n, 4), got {arr.shape}")
        if arr.shape[0] == 0:
            raise ValueError("cannot fit a Bingham distribution to an empty sample")
        arr = _as_unit_quaternions(arr)
        if weights is None:
            w = np.ones(arr.shape[0])
        else:
            w = np.asarray(weights, dtype=np.float64)
            if w.shape != (arr.shape[0],):
                raise ValueError(
                    f"weights must have shape ({arr.shape[0]},) to match q, got {w.shape}"
                )
            if not np.all(np.isfinite(w)) or np.any(w < 0):
                raise ValueError("weights must be finite and non-negative")
        total = float(np.sum(w))
        if not total > 0.0:
            raise ValueError("the total weight is zero; cannot fit a Bingham distribution")
        if not (np.isfinite(max_concentration) and max_concentration > 0):
            raise ValueError("max_concentration must be finite and positive")

        scatter = (arr * (w / total)[:, None]).T @ arr
        scatter = 0.5 * (scatter + scatter.T)
        evals, evecs = np.linalg.eigh(scatter)  # ascending: last column is the mode
        lam = np.clip(evals, 0.0, None)
        lam = lam / lam.sum()
        z = _fit_concentrations(lam, float(max_concentration))
        return cls(evecs, z)

    @classmethod
    def fit_about_mode(
        cls,
        q: ArrayLike,
        weights: ArrayLike,
        start_mode: ArrayLike,
        isotropic: bool,
        max_concentration: float = 1e4,
        rounds: int = 100,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Weighted MLE within the :meth:`from_mode` family: ``(mode, concentrations)``.

        The family fixes the axes to the mode's body axes, so the raw-``M`` fit of :meth:`fit`
        does not apply.  With ``m_i = mode ⊗ (0, e_i)`` the log likelihood is
        ``Σ_i z_i m_iᵀ S m_i - log F(z)``: concave in ``z`` for a fixed mode, and for a fixed
        ``z`` a quadratic form ``modeᵀ A mode`` with ``A = Σ_i z_i R_iᵀ S R_i`` (``R_i`` the
        right multiplication by ``(0, e_i)``), maximised by A's top eigenvector.  Alternating
        the two exact steps from ``start_mode`` never lowers the likelihood, but from a start
        a half turn about a body axis away from the data it stalls at a free turn about that
        axis (its concentration 0: the data lie on the circle of modes); so it also starts from
        the top eigenvector of ``S`` and keeps the likelier end.  ``isotropic`` ties the three
        concentrations (one scalar), for which the top eigenvector of ``S`` is the exact mode
        and one round suffices.
        """
        arr = _as_unit_quaternions(np.asarray(q, dtype=np.float64))
        w = np.asarray(weights, dtype=np.float64)
        scatter = (arr * (w / w.sum())[:, None]).T @ arr
        scatter = 0.5 * (scatter + scatter.T)
        if isotropic:
            mode = np.linalg.eigh(scatter)[1][:, -1]
            lam_mode = float(mode @ scatter @ mode)
            lam = np.append(np.full(3, (1.0 - lam_mode) / 3.0), lam_mode)
            z = _fit_concentrations(np.clip(lam, 0.0, None), max_concentration)
            return _canonical_sign(mode), np.full(3, -float(np.mean(z[:3])))
        starts = (
            _as_unit_quaternions(np.asarray(start_mode, dtype=np.float64)),
            np.linalg.eigh(scatter)[1][:, -1],
        )
        fits = [_alternate(scatter, s, max_concentration, rounds) for s in starts]
        mode, z, _ = max(fits, key=lambda f: f[2])
        return _canonical_sign(mode), -z[:3]

    # -- properties ---------------------------------------------------------

    @property
    def M(self) -> np.ndarray:
        """Orthogonal 4×4 matrix of principal axes (columns), read-only."""
        return self._M

    @property
    def Z(self) -> np.ndarray:
        """Canonical parameters (``max(Z) == 0``), aligned with the columns of ``M``."""
        return self._Z

    @property
    def concentration(self) -> np.ndarray:
        """Concentrations ``-Z >= 0`` aligned with the columns of ``M`` (4-vector).

        For :meth:`from_mode` distributions this is ``(c_x, c_y, c_z, 0)``.
        """
        return frozen(-self._Z)

    @property
    def mode(self) -> np.ndarray:
        """The mode, a unit quaternion (``wxyz``); ``-mode`` is equally a mode.

        Returned with its first non-zero component (normally ``w``) positive.  If
        several ``Z_i`` equal 0 the mode is not unique and the first such
        column of ``M`` is returned.
        """
        return frozen(_canonical_sign(self._M[:, int(np.argmax(self._Z))]))

    @property
    def log_normalizer(self) -> float:
        """``log F(Z)`` for the canonical ``Z``."""
        return self._log_norm

    def second_moment(self) -> np.ndarray:
        """``E[q qᵀ] = M diag(moments(Z)) Mᵀ`` (4×4)."""
        return (self._M * moments(self._Z)) @ self._M.T

    def __repr__(self) -> str:
        return f"Bingham(mode={self.mode.tolist()}, Z={self._Z.tolist()})"

    # -- density ------------------------------------------------------------

    def log_prob(self, q: ArrayLike) -> np.ndarray:
        """Log density at ``q`` (shape ``(..., 4)``) w.r.t. the surface measure on S³.

        Inputs are normalised to unit length first; ``log_prob(q) == log_prob(-q)``.
        Returns an array of shape ``q.shape[:-1]`` (a 0-d array for one quaternion).
        """
        x = _as_unit_quaternions(q)
        proj = x @ self._M
        return np.einsum("...i,i->...", proj * proj, self._Z) - self._log_norm

    def prob(self, q: ArrayLike) -> np.ndarray:
        """Density at ``q`` w.r.t. the surface measure on S³ (see :meth:`log_prob`)."""
        return np.exp(self.log_prob(q))

    # -- sampling -----------------------------------------------------------

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Draw ``n`` exact samples (shape ``(n, 4)``, unit ``wxyz`` quaternions).

        Rejection sampling with an angular central Gaussian (ACG) envelope
        (Kent, Ganeiber & Mardia, 2013).  With ``A = -M diag(Z) Mᵀ`` (positive
        semi-definite, eigenvalues ``λ_i = -Z_i``), ``Ω = I + 2A/b`` where ``b``
        solves ``Σ_i 1/(b + 2λ_i) = 1``, proposals are ``x = y/|y|`` with
        ``y ~ N(0, Ω⁻¹)``, accepted with probability
        ``exp(-xᵀAx) (xᵀΩx)² / M*`` where ``M* = exp(-(4-b)/2) (4/b)²`` bounds
        ``exp(-xᵀAx)(xᵀΩx)²`` on the sphere.  Proposals are drawn in vectorised
        batches sized by the exact expected acceptance rate.  The output is a
        deterministic function of the generator state; signs are random.
        """
        n = operator.index(n)
        if n < 0:
            raise ValueError(f"n must be non-negative, got {n}")
        out = np.empty((n, _DIM))
        if n == 0:
            return out
        lam = -self._Z
        b = self._acg_b
        omega_diag = 1.0 + 2.0 * lam / b
        scale = 1.0 / np.sqrt(omega_diag)
        half_dim = 0.5 * _DIM
        log_m_star = -0.5 * (_DIM - b) + half_dim * math.log(_DIM / b)
        # Acceptance rate = ∫ exp(-xᵀAx) dS / (M* ∫ (xᵀΩx)^(-2) dS)
        #                 = F(Z) |Ω|^(1/2) / (2π² M*).
        log_rate = (
            self._log_norm + 0.5 * float(np.sum(np.log(omega_diag))) - _LOG_SPHERE_AREA - log_m_star
        )
        rate = min(max(math.exp(log_rate), 1e-3), 1.0)

        filled = 0
        while filled < n:
            need = n - filled
            batch = min(int(need / rate * 1.05) + 32, 1 << 20)
            # Work in the eigenbasis of A: y = diag(Ω)^(-1/2) u with u ~ N(0, I).
            y = rng.standard_normal((batch, _DIM)) * scale
            x = y / np.linalg.norm(y, axis=1, keepdims=True)
            quad_a = (x * x) @ lam  # xᵀAx
            log_accept = -quad_a + half_dim * np.log1p(2.0 * quad_a / b) - log_m_star
            accepted = x[np.log(rng.random(batch)) < log_accept]
            take = min(need, accepted.shape[0])
            out[filled : filled + take] = accepted[:take] @ self._M.T
            filled += take
        return out


def _right_multipliers() -> np.ndarray:
    """(3, 4, 4): R_i with R_i q = q ⊗ (0, e_i), the body axes of a mode q."""
    pure = np.zeros((3, _DIM))
    pure[:, 1:] = np.eye(3)
    basis = np.eye(_DIM)
    return np.stack([quat_multiply(basis, np.broadcast_to(e, (_DIM, _DIM))).T for e in pure])


def fit_bingham(
    q: ArrayLike,
    weights: ArrayLike | None = None,
    max_concentration: float = 1e4,
) -> Bingham:
    """Weighted maximum-likelihood Bingham fit; same as :meth:`Bingham.fit`."""
    return Bingham.fit(q, weights=weights, max_concentration=max_concentration)


def _alternate(
    scatter: np.ndarray, mode: np.ndarray, max_concentration: float, rounds: int
) -> tuple[np.ndarray, np.ndarray, float]:
    """`Bingham.fit_about_mode`'s alternation from one start: (mode, z, log-likelihood per
    unit weight, Σ z_i λ_i - log F(z))."""
    right = _right_multipliers()
    z, lam = np.zeros(4), np.zeros(4)
    for _ in range(rounds):
        axes = right @ mode  # (3, 4): mode ⊗ (0, e_i)
        lam = np.append(np.einsum("ij,jk,ik->i", axes, scatter, axes), mode @ scatter @ mode)
        z = _fit_concentrations(np.clip(lam, 0.0, None), max_concentration)
        a = np.einsum("i,ikj,kl,ilm->jm", z[:3], right, scatter, right)
        new = np.linalg.eigh(0.5 * (a + a.T))[1][:, -1]
        if abs(float(new @ mode)) > 1.0 - 1e-15:
            break
        mode = new
    return mode, z, float(z @ lam - log_normalizer(z))


def _fit_concentrations(lam: Sequence[float], max_concentration: float) -> np.ndarray:
    """Solve the Bingham MLE for ``Z`` given scatter eigenvalues ``lam`` (ascending).

    Maximises ``Σ z_i λ_i - log F(z)`` over ``z = (z1, z2, z3, 0)`` with
    ``z_i ∈ [-max_concentration, 0]``.  The problem is concave; it is solved by
    L-BFGS-B with the analytic gradient ``λ - moments(z)`` in the rescaled
    variables ``y_i = z_i / s_i`` with ``s_i ≈ 1/(2 λ_i)`` (the large-concentration
    estimate of ``-z_i``), which makes the Hessian roughly scale-free.
    """
    lam = np.asarray(lam, dtype=np.float64)
    free = lam[:3]
    with np.errstate(divide="ignore", invalid="ignore"):  # λ = 0: ∞, or ∞ - ∞ (no mass on
        guess = 0.5 / free - 0.5 / lam[3]  # the mode, in `fit_about_mode`) guesses 0 below
    guess = np.clip(np.nan_to_num(guess, posinf=max_concentration), 0.0, max_concentration)
    with np.errstate(divide="ignore"):
        s = np.clip(np.nan_to_num(0.5 / free, posinf=max_concentration), 1.0, max_concentration)

    def objective(y: np.ndarray) -> tuple[float, np.ndarray]:
        z = np.append(s * y, 0.0)
        value = log_normalizer(z) - float(np.dot(z, lam))
        grad = (moments(z)[:3] - free) * s
        return value, grad

    y0 = -guess / s
    bounds = [(-max_concentration / si, 0.0) for si in s]
    res = optimize.minimize(
        objective,
        y0,
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"maxiter": 1000, "ftol": 1e-15, "gtol": 1e-12},
    )
    z = np.clip(s * res.x, -max_concentration, 0.0)
    z = _newton_polish(z, free, max_concentration)
    return np.append(z, 0.0)


def _newton_polish(
    z: np.ndarray, free: np.ndarray, max_concentration: float, max_iter: int = 6
) -> np.ndarray:
    """Refine the L-BFGS-B solution with projected Newton steps.

    The gradient of ``log F(z) - z·λ`` in the free coordinates is
    ``moments(z) - λ``; its Jacobian (the covariance of the ``x_i²``, positive
    definite) is obtained by central differences of :func:`moments`.  Variables
    sitting on a bound with the gradient pointing outwards are held fixed.  A
    step is kept only if it reduces the gradient, so this never makes the fit
    worse; it removes the residual ~1e-8 relative error of the quasi-Newton
    stopping rule, e.g. so that equivalent weightings give identical fits.
    """

    def gradient(zz: np.ndarray) -> np.ndarray:
        return moments(np.append(zz, 0.0))[:3] - free

    def projected(zz: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        at_lower = (zz <= -max_concentration) & (g > 0)
        at_upper = (zz >= 0.0) & (g < 0)
        active = at_lower | at_upper
        return ~active, np.where(active, 0.0, g)

    g = gradient(z)
    inside, pg = projected(z, g)
    for _ in range(max_iter):
        gnorm = float(np.max(np.abs(pg)))
        if gnorm == 0.0 or not np.any(inside):
            break
        idx = np.flatnonzero(inside)
        jac = np.empty((idx.size, idx.size))
        for col, j in enumerate(idx):
            h = 1e-6 * max(1.0, abs(z[j]))
            zp, zm = z.copy(), z.copy()
            zp[j] += h
            zm[j] -= h
            jac[:, col] = (gradient(zp)[idx] - gradient(zm)[idx]) / (2.0 * h)
        jac = 0.5 * (jac + jac.T)
        try:
            step = np.linalg.solve(jac, -g[idx])
        except np.linalg.LinAlgError:
            break
        z_new = z.copy()
        z_new[idx] = np.clip(z[idx] + step, -max_concentration, 0.0)
        g_new = gradient(z_new)
        inside_new, pg_new = projected(z_new, g_new)
        if not float(np.max(np.abs(pg_new))) < gnorm:
            break
        z, g, inside, pg = z_new, g_new, inside_new, pg_new
    return z
