"""The constraint manifold: THE mass-scaled KKT/Schur solve and the projections onto
``f(x, t) = 0`` and ``J v + f_t = 0``, in NumPy and as CasADi graphs.

Every method, statics, the action module and the diagnostics solve their linear systems
here; no other module factors ``J M⁻¹ Jᵀ``.

The KKT system ``[[M, Jᵀ], [J, 0]] [a; −λ] = [F; −γ]`` is solved through its Schur
complement ``A = J M⁻¹ Jᵀ``:

    A λ = −γ − J M⁻¹ F,        a = M⁻¹ (F + Jᵀ λ).

``A`` carries the spread of the masses (a 1e6 kg bob beside a 1e-6 kg one puts 1e12 between
its diagonal entries), so every dense solve first scales it symmetrically, ``D A D`` with
``D = diag(A)^(-1/2)``: the rows of the mass-weighted Jacobian ``Ĵ = D J M^(-1/2)`` then have
unit length and ``D A D = Ĵ Ĵᵀ``. A Cholesky factorization of ``D A D`` is accepted when its
pivots are well above round-off; otherwise (redundant rows, a singular configuration) the
minimum-norm least-squares solution is taken from the SVD of ``Ĵ`` itself — never of ``A``,
whose singular values are squares — with one relative cut-off (``RankPolicy``). Rows that
are merely heavy are therefore never cut as if they were dependent, and identical rows share
their load equally (two identical rods each carry half).

The projections are the mass-weighted nearest points:

    x ← x − M⁻¹ Jᵀ A⁻¹ f        (Newton on f(x, t) = 0)
    v ← v − M⁻¹ Jᵀ A⁻¹ (J v + f_t)

A ``Manifold`` is one run's view of a Model: the row set it solves with (all rows, or an
independent subset when rows are redundant, decided once at the start), the rank policy,
and the run's counters. The Model itself stays immutable and can serve many runs at once.
"""

from __future__ import annotations

import enum
import threading
import weakref
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .fast_call import FastCall
from .model import Model
from .rank_policy import RANK, RankPolicy
from .sparse_rank import as_dense, as_scipy, independent_rows_sparse
from .sparse_rows import row_max
from .sparse_schur import sparse_schur_solve


class ProjectionStatus(enum.Enum):
    """How a position projection ended."""

    CONVERGED = "converged"
    STALLED = "stalled"  # Newton stopped reducing |f| (incompatible constraints, or too far off)
    MAX_ITERATIONS = "max_iterations"
    NON_FINITE = "non_finite"

    @property
    def message(self) -> str:
        return {
            ProjectionStatus.CONVERGED: "the state was brought onto the constraints",
            ProjectionStatus.STALLED: "Newton's iteration stopped reducing the constraint violation",
            ProjectionStatus.MAX_ITERATIONS: "Newton's iteration ran out of iterations",
            ProjectionStatus.NON_FINITE: "the constraint functions became non-finite",
        }[self]


@dataclass(frozen=True)
class ProjectionResult:
    """A position projection: the new ``x``, its ``status``, Newton ``iterations`` and the
    ``residual`` max |f| left (in the constraints' units)."""

    x: np.ndarray
    status: ProjectionStatus
    iterations: int
    residual: float

    @property
    def converged(self) -> bool:
        return self.status is ProjectionStatus.CONVERGED


@dataclass
class Counters:
    """Work done by one run, incremented where it happens: right-hand sides (``nfev``),
    Jacobian evaluations (``njev``), factorizations (``nlu``), ``projections``."""

    nfev: int = 0
    njev: int = 0
    nlu: int = 0
    projections: int = 0

    def as_dict(self) -> dict:
        return {"nfev": self.nfev, "njev": self.njev, "nlu": self.nlu, "projections": self.projections}


# --- the dense solve ----------------------------------------------------------------------------
def schur_matrix(J: np.ndarray, inverse_masses: np.ndarray) -> np.ndarray:
    """A = J M⁻¹ Jᵀ for a (C, 3N) Jacobian and the flat inverse masses (3N,)."""
    return (J * inverse_masses) @ J.T


def _row_scale(J: np.ndarray, inverse_masses: np.ndarray) -> np.ndarray:
    """D = diag(J M⁻¹ Jᵀ)^(-1/2), rows of zero weight left unscaled."""
    d = np.sqrt(np.einsum("ij,ij,j->i", J, J, inverse_masses))
    return np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)


def schur_solve(J: np.ndarray, inverse_masses: np.ndarray, b: np.ndarray, *,
                policy: RankPolicy = RANK, full_rank: bool = True) -> np.ndarray:
    """Solve (J M⁻¹ Jᵀ) y = b; the minimum-norm least-squares y (in the scaled norm |D⁻¹y|)
    when rows are dependent.

    ``full_rank=False`` skips the Cholesky attempt (the caller knows rows are redundant).
    ``b`` may be a vector (C,) or a matrix (C, k). A sparse J (SciPy or CasADi) of more than
    SPARSE_FROM rows: the same solution without a dense J (constrained.sparse_schur).
    """
    if not isinstance(J, np.ndarray) and J.shape[0] > SPARSE_FROM:
        y = sparse_schur_solve(J, inverse_masses, b, policy=policy)
        if y is not None:
            return y
        J = as_dense(J)
    b = np.asarray(b, float)
    if J.shape[0] == 0:
        return np.zeros(b.shape)
    s = _row_scale(J, inverse_masses)
    sb = s * b if b.ndim == 1 else s[:, None] * b
    if full_rank:
        A = s[:, None] * schur_matrix(J, inverse_masses) * s[None, :]
        try:
            import scipy.linalg as sla  # (imported on first use: 0.1 s)

            L, lower = sla.cho_factor(A, lower=True, check_finite=False)
            d = np.abs(np.diag(L))
            if d.size and d.min() > policy.cholesky_rtol * d.max():
                z = sla.cho_solve((L, lower), sb, check_finite=False)
                return s * z if z.ndim == 1 else s[:, None] * z
        except (np.linalg.LinAlgError, ValueError):
            pass
    # SVD of Ĵ = D J M^(-1/2): A's scaled form is Ĵ Ĵᵀ = U Σ² Uᵀ, so z = U Σ⁻² Uᵀ (D b)
    Jhat = s[:, None] * J * np.sqrt(inverse_masses)[None, :]
    U, sv, _ = np.linalg.svd(Jhat, full_matrices=False)
    keep = sv > policy.dependent_rtol * sv[0] if sv.size and sv[0] > 0 else np.zeros(sv.shape, bool)
    Uk, w = U[:, keep], 1.0 / sv[keep] ** 2
    z = Uk @ (w * (Uk.T @ sb)) if sb.ndim == 1 else Uk @ (w[:, None] * (Uk.T @ sb))
    return s * z if z.ndim == 1 else s[:, None] * z


def independent_rows(J: np.ndarray, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> np.ndarray:
    """A maximal set of independent rows of J, in scene order (pivoted QR of Ĵᵀ; a row whose
    pivot is below ``dependent_rtol`` of the largest is implied by the others). A sparse J of
    more than SPARSE_FROM rows: the sparse Gram factorization (constrained.sparse_rank)."""
    C = J.shape[0]
    if C == 0:
        return np.zeros(0, dtype=int)
    if C > SPARSE_FROM and not isinstance(J, np.ndarray):  # CasADi/SciPy sparse: constrained.sparse_rank
        rows = independent_rows_sparse(J, np.sqrt(inverse_masses), policy)
        if rows is not None:
            return rows
    J = as_dense(J)
    Jhat = _row_scale(J, inverse_masses)[:, None] * J * np.sqrt(inverse_masses)[None, :]
    import scipy.linalg as sla

    _, R, order = sla.qr(Jhat.T, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    if diag.size == 0 or diag[0] == 0:
        return np.zeros(0, dtype=int)
    rank = int(np.sum(diag > policy.dependent_rtol * diag[0]))
    return np.sort(order[:rank])


def full_row_rank(J, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> bool | None:
    """True when J shows full row rank by a cheap factorization of D A D (dense Cholesky for
    small J, sparse LU for a CasADi-sparse J with many rows: O(N) on a chain); None when it
    cannot tell (a small pivot: use ``independent_rows``)."""
    if isinstance(J, ca.DM) and J.shape[0] > SPARSE_FROM:
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        Js = as_scipy(J)
        A = (Js @ sp.diags(inverse_masses) @ Js.T).tocsc()
        d = A.diagonal()
        if d.size == 0 or np.any(d <= 0):
            return None
        s = sp.diags(1.0 / np.sqrt(d))
        try:
            lu = spla.splu((s @ A @ s).tocsc(), diag_pivot_thresh=0.0)
        except RuntimeError:  # exactly singular
            return None
        u = np.sqrt(np.abs(lu.U.diagonal()))  # pivots of D A D are squares of Ĵ's
        return True if u.min() > policy.cholesky_rtol * u.max() else None
    J = np.asarray(J, float)
    s = _row_scale(J, inverse_masses)
    try:
        L = np.linalg.cholesky(s[:, None] * schur_matrix(J, inverse_masses) * s[None, :])
    except np.linalg.LinAlgError:
        return None
    d = np.abs(np.diag(L))
    return True if d.size and d.min() > policy.cholesky_rtol * d.max() else None


def tangent_basis(J: np.ndarray, n: int | None = None, policy: RankPolicy = RANK) -> np.ndarray:
    """Orthonormal basis (n, d) of null(J), the admissible virtual displacements (SVD of the
    row-normalized J; singular values below ``dependent_rtol`` of the largest count as 0)."""
    J = np.asarray(J, float)
    n = J.shape[1] if n is None else n
    norms = np.linalg.norm(J, axis=1) if J.shape[0] else np.zeros(0)
    Jn = J[norms > 0] / norms[norms > 0, None]
    if Jn.shape[0] == 0:
        return np.eye(n)
    import scipy.linalg as sla

    return sla.null_space(Jn, rcond=policy.dependent_rtol)


#: From this many constraint rows, full rank is first shown by a sparse factorization.
SPARSE_FROM = 100


def jacobian_matrix(J: ca.DM):
    """A CasADi J as NumPy: dense up to SPARSE_FROM rows, SciPy CSR beyond (never C × 3N dense)."""
    return np.asarray(J, float) if J.shape[0] <= SPARSE_FROM else as_scipy(J)


def dense_jacobian(model: Model):
    """``(x, t) -> [J]`` dense (column-major, flat) through a FunctionBuffer, with the model's
    parameter values; the Function (p an input) is built once per structure."""
    def build(view, X, T, P):
        return ca.Function("dense_jacobian", [X, T, P], [ca.densify(view.jacobian(X, T)[1])])

    return structural_call(model, "dense_jacobian", build, "x", "t")


def constraint_values(model: Model):
    """``(x, t) -> [f]`` (dense, a FunctionBuffer call), the Function built once per structure."""
    def build(view, X, T, P):
        return ca.Function("constraint_dense", [X, T, P], [ca.densify(view.constraint(X, T))])

    return structural_call(model, "constraint", build, "x", "t")


def structural_call(model: Model, key, build, *inputs: str):
    """A fast call ``(*inputs) -> [outputs]`` of the Function ``build(view, *symbols, P)``
    (SX symbols for ``inputs``, each "x"/"v" of 3N, "t" a scalar; ``view`` the model's
    ``ParametricView`` with P), built once per structure and called with the model's p."""
    cache, prefix = structure_cache(model)
    full_key = (*prefix, "structural", key)
    fast = cache.get(full_key)
    if fast is None:
        n3 = model.n_coordinates
        symbols = [ca.SX.sym(name, n3 if name in ("x", "v") else 1) for name in inputs]
        P = ca.SX.sym("p", len(model.parameter_vector))
        fast = cache[full_key] = FastCall(build(ParametricView(model, P), *symbols, P))
    p = model.parameter_vector
    return lambda *args: fast(*args, p)


def redundant_rows(model: Model, x, t: float, policy: RankPolicy = RANK) -> tuple[int, ...] | None:
    """None when the rows of J(x, t) are independent; otherwise the independent subset to
    solve with (the others are implied by it). This is the run's redundancy, a value."""
    if model.n_constraints == 0:
        return None
    x = np.asarray(x, float).ravel()
    if model.n_constraints > SPARSE_FROM:
        J = model.jacobian(x, t)[1]  # CasADi-sparse: the O(N) factorization
    else:
        J = dense_jacobian(model)(x, t)[0].reshape(model.n_coordinates, model.n_constraints).T
    if full_row_rank(J, model.inverse_masses, policy):
        return None
    rows = independent_rows(J, model.inverse_masses, policy)
    return None if rows.size == model.n_constraints else tuple(int(k) for k in rows)


# --- the CasADi graph forms ------------------------------------------------------------------
def _casadi(values):
    """Numbers as a DM; a CasADi expression (masses that are formulas of p) as it is."""
    return values if isinstance(values, ca.SX | ca.MX) else ca.DM(values)


def _select(expr, rows):
    return expr if rows is None else expr[list(rows), :]


def symbolic_spd_solve(A, rhs):
    """y with A y = rhs for a symmetric positive definite A, the sparse LDLᵀ factorization
    (AMD ordering, no pivoting: stable for SPD) written out as operations: about 0.6× the
    operations of the symbolic QR in an acceleration (216 against 336 for the double
    pendulum). SX arguments give SX; MX arguments call an SX Function of A's sparsity (it is
    inlined where the graph is expanded)."""
    if isinstance(A, ca.SX):
        D, Lt, p = ca.ldl(A)
        return ca.ldl_solve(rhs, D, Lt, p)
    key = (A.sparsity().serialize(), rhs.shape)
    solve = _SPD_SOLVES.get(key)
    if solve is None:
        As, bs = ca.SX.sym("A", A.sparsity()), ca.SX.sym("b", *rhs.shape)
        D, Lt, p = ca.ldl(As)
        solve = _SPD_SOLVES[key] = ca.Function("spd_solve", [As, bs], [ca.ldl_solve(bs, D, Lt, p)])
    return solve(A, rhs)


#: The SX solves of symbolic_spd_solve for MX graphs, by sparsity and right-hand side shape.
_SPD_SOLVES: dict = {}


def schur_solve_graph(J_left, J_right, inverse_masses, rhs, linsol: str | None = "qr"):
    """y with (J_left M⁻¹ J_rightᵀ) y = rhs, as a CasADi expression (J_left = J_right: the
    Schur complement; RATTLE's Newton step takes J at two states). ``linsol``: a CasADi
    linear solver plugin for MX graphs, None for SX (solved symbolically).

    Numeric linear solvers are scaled like the NumPy solve, D_l A D_r z = D_l rhs, y = D_r z,
    with D = diag(J M⁻¹ Jᵀ)^(-1/2) of each side: CasADi's sparse QR takes pivots below an
    absolute 1e-12 or so for zero, and h² M⁻¹ of a heavy particle is far below that. Symbolic
    solves (SX, "symbolicqr": the factorization written out) and the sparse LDLᵀ (no pivoting,
    so invariant to a symmetric diagonal scaling) are not scaled: there it would only add
    operations to every step of a compiled loop."""
    minv = _casadi(inverse_masses)
    if linsol in (None, "symbolicqr", "ldl"):  # no absolute pivot threshold: unscaled
        A = ca.mtimes(ca.mtimes(J_left, ca.diag(minv)), J_right.T)
        if linsol == "ldl":
            return ca.solve(A, rhs, linsol)
        if J_left is not J_right:  # not symmetric (RATTLE's two states): a symbolic QR
            return ca.solve(A, rhs) if linsol is None else ca.solve(A, rhs, linsol)
        return symbolic_spd_solve(A, rhs)

    def scale(J):
        return 1.0 / ca.sqrt(ca.mtimes(J * J, minv))

    d_left, d_right = scale(J_left), scale(J_right)
    # diagonal matrices (sparse) keep the scaling O(nnz): an outer product d_l d_rᵀ would be C × C
    Dl, Dr = ca.diag(d_left), ca.diag(d_right)
    A = ca.mtimes(ca.mtimes(ca.mtimes(Dl, J_left), ca.diag(minv)), ca.mtimes(Dr, J_right).T)
    b = ca.mtimes(Dl, rhs)
    z = ca.solve(A, b) if linsol is None else ca.solve(A, b, linsol)
    return ca.mtimes(Dr, z)


def acceleration_graph(model: Model, X, V, T, *, rows=None, linsol: str = "ldl", feedback=None):
    """(a, λ) of the KKT system as CasADi expressions in (X, V, T): A λ = −γ − J M⁻¹ F,
    a = M⁻¹ (F + Jᵀ λ), over ``rows`` (all by default; λ holds those rows only).

    ``feedback = (α, β)`` imposes Baumgarte's J a + γ + 2α (J v + f_t) + β² f = 0 instead."""
    minv = _casadi(model.inverse_masses)
    F, J, gamma = model.dynamics(X, V, T)
    if not model.n_constraints:
        return minv * F, (ca.SX if isinstance(X, ca.SX) else ca.MX)(0, 1)
    if feedback is not None:
        alpha, beta = feedback
        _, f_t = model.velocity_terms(X, T)
        gamma = gamma + 2 * alpha * (ca.mtimes(J, V) + f_t) + beta**2 * model.constraint(X, T)
    J, gamma = _select(J, rows), _select(gamma, rows)
    lam = schur_solve_graph(J, J, model.inverse_masses, -gamma - ca.mtimes(J, minv * F), linsol)
    return minv * (F + ca.mtimes(J.T, lam)), lam


def position_step_graph(model: Model, X, T, *, rows=None, linsol: str = "qr"):
    """(f, dx): one mass-weighted Newton step toward f = 0 is x ← x − dx, dx = M⁻¹Jᵀ A⁻¹ f;
    f is over all rows (the residual), the step over ``rows``."""
    f, J = model.jacobian(X, T)
    fs, Js = _select(f, rows), _select(J, rows)
    minv = _casadi(model.inverse_masses)
    return f, minv * ca.mtimes(Js.T, schur_solve_graph(Js, Js, model.inverse_masses, fs, linsol))


def velocity_correction_graph(model: Model, X, V, T, *, rows=None, linsol: str = "qr"):
    """dv with v ← v − dv the mass-weighted nearest velocity satisfying J v + f_t = 0."""
    J, f_t = model.velocity_terms(X, T)
    J, f_t = _select(J, rows), _select(f_t, rows)
    minv = _casadi(model.inverse_masses)
    c = ca.mtimes(J, V) + f_t
    return minv * ca.mtimes(J.T, schur_solve_graph(J, J, model.inverse_masses, c, linsol))


def row_scales_expr(J, n_particles: int):
    """s_i = max_p |∂f_i/∂x_p| as a column (C,) of J's type (SX or MX), 1 where a row's gradient
    vanishes. O(nnz J) operations (constrained.sparse_rows): the squared per-particle norms
    Q = (J∘J) B, with B (3N × N) summing each particle's three columns, then each row's
    largest √Q_ip over its stored entries."""
    C = J.shape[0]
    if C == 0:
        return ca.SX(0, 1)
    B = ca.DM(ca.Sparsity.triplet(3 * n_particles, n_particles, list(range(3 * n_particles)),
                                  [k // 3 for k in range(3 * n_particles)]), 1.0)
    norms = row_max(ca.sqrt(ca.mtimes(J * J, B)))
    return ca.if_else(norms > 0, norms, 1.0)


def projection_graph(model: Model, x, v, t, *, rows=None, linsol: str = "qr"):
    """Two Newton steps onto f = 0, the second sharing its factorization with the velocity
    projection: (x, v, residual before the last step, in metres: max_i |f_i| / s_i with the row
    scales of ``row_scales_expr``, or the view's ``row_scales``). The step loops (dopri) use it."""
    minv = _casadi(model.inverse_masses)
    _, dx = position_step_graph(model, x, t, rows=rows, linsol=linsol)
    x = x - dx
    f, J = model.jacobian(x, t)
    _, f_t = model.velocity_terms(x, t)
    fs, Js, f_ts = _select(f, rows), _select(J, rows), _select(f_t, rows)
    sol = schur_solve_graph(Js, Js, model.inverse_masses, ca.horzcat(fs, ca.mtimes(Js, v) + f_ts), linsol)
    s = model.row_scales(x, t) if hasattr(model, "row_scales") else row_scales_expr(J, model.n_particles)
    return x - minv * ca.mtimes(Js.T, sol[:, 0]), v - minv * ca.mtimes(Js.T, sol[:, 1]), ca.mmax(abs(f) / s)


# --- the per-model functions, built once and shared by every run --------------------------------
_built: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_lock = threading.Lock()


@dataclass(frozen=True)
class _FastPaths:
    acceleration: FastCall
    newton_step: FastCall
    velocity_correction: FastCall
    evaluation: str


def _fast_paths(model: Model, rows, compiled: bool) -> _FastPaths:
    """The acceleration, Newton step and velocity correction as one CasADi call each (sparse
    LDLᵀ of the SPD A for the acceleration, sparse QR for the projections), with the
    parameters p as their last input: built once per structure and row set (every parameter
    value shares them, ``structure_cache``), optionally compiled."""
    cache, prefix = structure_cache(model)
    key = (*prefix, "fast", rows, bool(compiled))
    with _lock:
        cached = cache.get(key)
    if cached is not None:
        return cached
    n3 = model.n_coordinates
    X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
    P = ca.MX.sym("p", len(model.parameter_vector))
    view = ParametricView(model, P)
    d = ca.densify
    if model.n_constraints:
        a, lam = acceleration_graph(view, X, V, T, rows=rows, linsol="ldl")
        f, dx = position_step_graph(view, X, T, rows=rows)
        dv = velocity_correction_graph(view, X, V, T, rows=rows)
    else:
        a, lam = acceleration_graph(view, X, V, T)
        f, dx, dv = ca.MX(0, 1), ca.MX.zeros(n3), ca.MX.zeros(n3)
    funcs = [ca.Function("acceleration", [X, V, T, P], [d(a), d(lam)]),
             ca.Function("newton_step", [X, T, P], [d(f), d(dx)]),
             ca.Function("velocity_correction", [X, V, T, P], [d(dv)])]
    evaluation = "virtual machine"
    if compiled:
        from . import compiled as compiled_evaluation

        machine = compiled_evaluation.compile_functions(funcs)
        if all(f.class_name() == "External" for f in machine):
            funcs, evaluation = machine, "compiled"
    paths = _FastPaths(*(FastCall(f) for f in funcs), evaluation)
    with _lock:
        cache[key] = paths
    return paths


def per_model_cache(model: Model) -> dict:
    """A dict kept beside ``model`` (not on it) for what solvers build once per model and
    reuse across runs, e.g. a compiled step loop. It goes when the model goes."""
    with _lock:
        return _built.setdefault(model, {})


def built_once(model: Model, key, build):
    """``build()`` the first time ``key`` is asked for on ``model``, the kept value after that
    (two threads asking at once may both build; either result serves)."""
    cache = per_model_cache(model)
    if key not in cache:
        cache[key] = build()
    return cache[key]


def acceleration_function(model: Model, rows=None, *, symbolic: bool = False,
                          parametric: bool = False) -> ca.Function:
    """``(x, v, t) -> (a, λ_rows)`` as one Function, built once per model and row set: step
    loops call it as a node of their graphs. MX with a sparse LDLᵀ inside, or (``symbolic``)
    one SX expression with the KKT solve written out: fastest for a few constraint rows, where
    a step loop can expand it into one SX graph; its size grows with the cube of the rows.
    ``parametric``: ``(x, v, t, p) -> (a, λ_rows)``, built once per structure
    (``structure_cache``)."""
    def build():
        n3 = model.n_coordinates
        kind = ca.SX if symbolic else ca.MX
        X, V, T = kind.sym("x", n3), kind.sym("v", n3), kind.sym("t")
        name = "acceleration_sx" if symbolic else "acceleration"
        linsol = None if symbolic else "ldl"
        if not parametric:
            graph = acceleration_graph(model, X, V, T, rows=rows, linsol=linsol)
            return ca.Function(name, [X, V, T], list(graph))
        P = kind.sym("p", len(model.parameter_vector))
        graph = acceleration_graph(ParametricView(model, P), X, V, T, rows=rows, linsol=linsol)
        return ca.Function(name, [X, V, T, P], list(graph))

    if parametric:
        cache, prefix = structure_cache(model)
        key = (*prefix, "acceleration", rows, symbolic)
        if key not in cache:
            cache[key] = build()
        return cache[key]
    return built_once(model, ("acceleration", rows, symbolic), build)


class ParametricView:
    """``model`` with its parameters a CasADi symbol ``P``: the attributes the graph builders
    read (``dynamics(x, v, t)``, ``jacobian``, ``velocity_terms``, ``constraint``, sizes,
    masses), calling the parametric Functions with P. A step loop built on it takes p as an
    input and serves every Model of the structure (``structure_cache``)."""

    def __init__(self, model: Model, P):
        self.P = P
        self._model = model
        for name in ("n_coordinates", "n_constraints", "n_particles", "masses", "inverse_masses",
                     "rheonomic", "constraint_labels", "parameter_vector"):
            setattr(self, name, getattr(model, name))
        if model.masses_follow_parameters:  # masses as entries or formulas of P in the graphs
            entries = getattr(model.structure, "mass_entries", None)
            self.masses = (ca.vec(P[entries.tolist()]) if entries is not None
                           else model.parametric("masses")(P))
            self.inverse_masses = 1 / self.masses

    def _call(self, name: str, *args):
        return self._model.parametric(name)(*args, self.P)

    def constraint(self, X, T):
        return self._call("constraint", X, T)

    def jacobian(self, X, T):
        return self._call("jacobian", X, T)

    def velocity_terms(self, X, T):
        return self._call("velocity_terms", X, T)

    def dynamics(self, X, V, T):
        return self._call("dynamics", X, V, T)

    def energy(self, X, V, T):
        return self._call("energy", X, V, T)


def structure_cache(model: Model) -> tuple[dict, tuple]:
    """(cache, key prefix) for what is built with the parameters as inputs (``ParametricView``):
    kept beside the model's structure, so every Model of the structure (other parameter
    values, masses included) shares it; the row set held (constrained.held) is in the key."""
    return per_model_cache(model.structure), (getattr(model, "rows", None),)


def symbolic_acceleration(model: Model, rows=None) -> ca.Function:
    """``acceleration_function(model, rows, symbolic=True)``."""
    return acceleration_function(model, rows, symbolic=True)


def _fast_or_nan(call: FastCall, sizes, *args) -> list[np.ndarray]:
    """A fast-path call; NaN results when CasADi's solver fails (a singular factorization),
    which sends the caller to the NumPy minimum-norm path."""
    try:
        return call(*args)
    except RuntimeError:
        return [np.full(k, np.nan) for k in sizes]


# --- one run's view of the manifold ------------------------------------------------------------
class Manifold:
    """One run's numeric access to the KKT system and the projections of ``model``.

    ``rows``: None (all rows independent) or the independent subset decided at the start
    (``redundant_rows``); the projections and the step graphs then solve with that subset
    (the others are implied by it), while multipliers are always the minimum-norm ones over
    every row. ``counters`` belong to this run.
    """

    def __init__(self, model: Model, *, rows: tuple[int, ...] | None = None,
                 policy: RankPolicy = RANK, compiled: bool = False):
        self.model = model
        self.rows = rows
        self.policy = policy
        self.counters = Counters()
        self._fast = _fast_paths(model, rows, compiled)
        self._p = model.parameter_vector

    @classmethod
    def at(cls, model: Model, x, t: float, *, policy: RankPolicy = RANK, compiled: bool = False) -> Manifold:
        """The manifold of a run starting at (x, t): redundancy decided there."""
        return cls(model, rows=redundant_rows(model, x, t, policy), policy=policy, compiled=compiled)

    @property
    def redundant(self) -> bool:
        return self.rows is not None

    @property
    def evaluation(self) -> str:
        return self._fast.evaluation

    def schur_solve(self, J: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(J M⁻¹ Jᵀ) y = b, minimum-norm for dependent rows (see ``schur_solve``)."""
        self.counters.nlu += 1
        return schur_solve(J, self.model.inverse_masses, b, policy=self.policy, full_rank=not self.redundant)

    def accelerations(self, x: np.ndarray, v: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Accelerations and multipliers (over every row) at (x, v, t)."""
        m = self.model
        self.counters.nfev += 1
        if not self.redundant:
            a, lam = _fast_or_nan(self._fast.acceleration, (m.n_coordinates, len(m.constraint_labels)),
                                  x, v, t, self._p)
            self.counters.nlu += 1
            if np.all(np.isfinite(a)) and np.all(np.isfinite(lam)):
                return a, lam
        F, J, gamma = m.dynamics(x, v, t)
        F, J, gamma = np.asarray(F, float).ravel(), jacobian_matrix(J), np.asarray(gamma, float).ravel()
        if m.n_constraints == 0:
            return m.inverse_masses * F, np.zeros(0)
        lam = self.schur_solve(J, -gamma - J @ (m.inverse_masses * F))
        return m.inverse_masses * (F + J.T @ lam), lam

    def project_positions(self, x: np.ndarray, t: float, tol: float, max_iter: int = 12) -> ProjectionResult:
        """Mass-weighted nearest point on f(x, t) = 0 by Newton, x ← x − M⁻¹Jᵀ A⁻¹ f, until
        max|f| ≤ tol; stops when an iteration no longer halves the violation. After each step
        f alone is evaluated (``nfev``): the next Jacobian and factorization (``njev``) only
        when it has not converged."""
        x = np.array(x, dtype=float)
        m = self.model
        if m.n_constraints == 0:
            return ProjectionResult(x, ProjectionStatus.CONVERGED, 0, 0.0)
        best = err = np.inf
        for it in range(max_iter + 1):
            if it:  # after a step: f alone says whether it converged (no factorization)
                self.counters.nfev += 1
                err = float(np.max(np.abs(constraint_values(m)(x, t)[0])))
                if err <= tol:
                    return ProjectionResult(x, ProjectionStatus.CONVERGED, it, err)
            self.counters.njev += 1
            f, dx = _fast_or_nan(self._fast.newton_step, (m.n_constraints, m.n_coordinates), x, t, self._p)
            err = float(np.max(np.abs(f)))
            if not np.isfinite(err):  # the fast path failed, or f itself is not finite
                f = np.asarray(m.constraint(x, t), float).ravel()
                err = float(np.max(np.abs(f)))
                if not np.isfinite(err):
                    return ProjectionResult(x, ProjectionStatus.NON_FINITE, it, err)
            if err <= tol:
                return ProjectionResult(x, ProjectionStatus.CONVERGED, it, err)
            if it == max_iter:
                return ProjectionResult(x, ProjectionStatus.MAX_ITERATIONS, it, err)
            if err > 0.5 * best and it > 2:
                return ProjectionResult(x, ProjectionStatus.STALLED, it, err)
            best = min(best, err)
            self.counters.nlu += 1
            if not np.all(np.isfinite(dx)):
                f, J = m.jacobian(x, t)
                J = jacobian_matrix(J)
                dx = m.inverse_masses * (J.T @ self.schur_solve(J, np.asarray(f, float).ravel()))
            x = x - dx
        return ProjectionResult(x, ProjectionStatus.MAX_ITERATIONS, max_iter, err)  # pragma: no cover

    def project_velocities(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """Mass-weighted nearest velocity with J v + f_t = 0 (one linear solve)."""
        m = self.model
        if m.n_constraints == 0:
            return np.array(v, dtype=float)
        self.counters.njev += 1
        self.counters.nlu += 1
        (dv,) = _fast_or_nan(self._fast.velocity_correction, (m.n_coordinates,), x, v, t, self._p)
        if np.all(np.isfinite(dv)):
            return v - dv
        J, f_t = m.velocity_terms(x, t)
        J = jacobian_matrix(J)
        c = J @ v + np.asarray(f_t, float).ravel()
        return v - m.inverse_masses * (J.T @ self.schur_solve(J, c))
