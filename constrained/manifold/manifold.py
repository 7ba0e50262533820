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
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..codegen.fast_call import FastCall
from ..model.cache import ParametricView, built_once, per_model_cache, structure_cache
from ..model.structure import Model
from .algebra import LinearAlgebra, algebra_for
from .dense import independent_rows_after
from .graph import acceleration_graph, no_velocity_correction, position_step_graph, velocity_correction_graph
from .rank_policy import RANK, RankPolicy
from .vectorized import at_point
from .vectorized import graphs as vectorized


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


def dense_jacobian(model: Model):
    """``(x, t) -> [G]`` dense (column-major, flat) through a FunctionBuffer, with the model's
    parameter values: the matrix of every row at the velocity level, J (= ∂f/∂x) and then
    the velocity rows' A, (C, 3N); the Function (p an input) is built once per structure."""
    def build(view, X, T, P):
        return ca.Function("dense_jacobian", [X, T, P], [ca.densify(view.velocity_terms(X, T)[0])])

    return structural_call(model, "dense_jacobian", build, "x", "t")


def constraint_values(model: Model):
    """``(x, t) -> [f]`` (dense, a FunctionBuffer call), the Function built once per structure
    (for a large model after its first calls, which are answered on numbers: ``numeric_first``)."""
    def build(view, X, T, P):
        return ca.Function("constraint_dense", [X, T, P], [ca.densify(view.constraint(X, T))])

    if vectorized.applies(model):
        return at_point.numeric_first(model, "constraint", ("f",),
                                      lambda: structural_call(model, "constraint", build, "x", "t"))
    return structural_call(model, "constraint", build, "x", "t")


def structural_call(model: Model, key, build, *inputs: str):
    """A fast call ``(*inputs) -> [outputs]`` of the Function ``build(view, *symbols, P)``
    (SX symbols for ``inputs``, each "x"/"v" of 3N, "lam" of C, "t" a scalar; ``view`` the model's
    ``ParametricView`` with P), built once per structure and called with the model's p."""
    cache, prefix = structure_cache(model)
    full_key = (*prefix, "structural", key)
    fast = cache.get(full_key)
    if fast is None:
        n3 = model.n_coordinates
        # MX where pair potentials are mapped kernels (in SX they would be one term per pair) or
        # for a large model on the vectorized build (an SX graph of every row would be built)
        large = vectorized.applies(model)
        pairs = bool(getattr(model.structure, "pairs", ()))
        kind = ca.MX if large or pairs else ca.SX
        View = vectorized.VectorizedView if large else ParametricView
        sizes = {"x": n3, "v": n3, "lam": model.n_constraints}
        symbols = [kind.sym(name, sizes.get(name, 1)) for name in inputs]
        P = kind.sym("p", len(model.parameter_vector))
        fast = cache[full_key] = FastCall(build(View(model, P), *symbols, P))
    p = model.parameter_vector
    potentials = getattr(model.structure, "pair_potentials", None)
    if "x" not in inputs or potentials is None or not any(term.size for term in potentials.terms):
        return lambda *args: fast(*args, p)
    at = inputs.index("x")

    def call(*args):  # a pair potential's neighbour list rebuilt where the particles have moved far
        fresh = potentials.refreshed(p, args[at])
        return fast(*args, p if fresh is None else fresh)

    return call


def sparse_jacobian(model: Model):
    """``(x, t) -> G`` (a sparse CasADi DM, C × 3N: J, then the velocity rows' A) with the model's
    parameter values: the Model's ``velocity_terms``, or for a large model (no velocity rows) one
    call of the vectorized build (``at_point.JacobianAt``), given again for the same x, t and p."""
    if not vectorized.applies(model):
        return lambda x, t: model.velocity_terms(x, t)[0]

    def build(view, X, T, P):
        return ca.Function("jacobian_nonzeros", [X, T, P], [ca.densify(view.jacobian(X, T)[1].nz[:])])

    nonzeros = at_point.numeric_first(model, "jacobian_nonzeros", ("f", "J"),
                                      lambda: structural_call(model, "jacobian_nonzeros", build, "x", "t"))
    b = vectorized.vectorized_build(model.structure)
    cache, prefix = structure_cache(model)
    p = model.parameter_vector

    def call(x, t):
        # kept beside the structure, given again for the same x, t and p: a start asks at x0 three
        # times (scene.build's regular_start, the start's undefined gradient and its redundancy)
        x = np.asarray(x, float).ravel()
        key = (x.tobytes(), np.float64(t).tobytes(), p.tobytes())
        kept = cache.get((*prefix, "jacobian at"))
        if kept is not None and kept[0] == key:
            return kept[1]
        J = at_point.JacobianAt(b, nonzeros(x, t)[0])
        cache[(*prefix, "jacobian at")] = (key, J)
        return J

    return call


def forces_and_energy(model: Model):
    """``(x, v, t) -> (F, E)``: the applied forces (3N,) and the energy, through a FunctionBuffer
    (a few µs a call); the Function takes the parameters as an input and is built once per
    structure (``structural_call`` "forces_and_energy": the start check of a large scene and
    the run's check of a finite start share it)."""
    def build(view, x, v, t, p):
        return ca.Function("forces_and_energy", [x, v, t, p],
                           [ca.densify(view.dynamics(x, v, t)[0]), view.energy(x, v, t)])

    if vectorized.applies(model):  # (its first calls on numbers, without the Function)
        return at_point.forces_first(model, lambda: structural_call(model, "forces_and_energy", build,
                                                                    "x", "v", "t"))
    return structural_call(model, "forces_and_energy", build, "x", "v", "t")


def potential_forces_finite(model: Model):
    """``(x, v, t) -> bool`` for a large model (the vectorized build) whose effects are
    potentials alone: whether F = −∂V/∂x and the energy T + V are finite there. Every term's
    value and gradient then are (a sum of numbers is finite only when each is: an infinity
    stays one, or meets its opposite in a NaN), so the per-effect check need not be built."""
    values = forces_and_energy(model)

    def finite(x, v, t) -> bool:
        with np.errstate(all="ignore"):
            F, E = (np.asarray(out, float) for out in values(np.asarray(x, float).ravel(),
                                                             np.asarray(v, float).ravel(), t))
        return bool(np.all(np.isfinite(F)) and np.all(np.isfinite(E)))

    return finite


def dynamics_values(model: Model):
    """``(x, v, t) -> (F, J, γ)`` (F and γ flat NumPy, J a sparse CasADi DM) with the model's
    parameter values: the Model's ``dynamics``, or for a large model the vectorized build."""
    if not vectorized.applies(model):
        def call(x, v, t):
            F, J, gamma = model.dynamics(x, v, t)
            return np.asarray(F, float).ravel(), J, np.asarray(gamma, float).ravel()
        return call

    def build(view, X, V, T, P):
        F, J, gamma = view.dynamics(X, V, T)
        return ca.Function("dynamics_nonzeros", [X, V, T, P], [ca.densify(F), ca.densify(J.nz[:]),
                                                                ca.densify(gamma)])

    values = structural_call(model, "dynamics_nonzeros", build, "x", "v", "t")
    sparsity = vectorized.vectorized_build(model.structure).jacobian_sparsity

    def call(x, v, t):
        F, nz, gamma = values(np.asarray(x, float).ravel(), np.asarray(v, float).ravel(), t)
        return F, ca.DM(sparsity, nz), gamma
    return call


def redundant_rows(model: Model, x, t: float, policy: RankPolicy = RANK) -> tuple[int, ...] | None:
    """None when the rows of J(x, t) (and of the velocity rows' A) are independent; otherwise
    the independent subset to solve with (the others are implied by it), holding an
    independent set of the rows of f (velocity rows join where independent of those, so the
    position projection keeps rows enough). This is the run's redundancy, a value: the last
    one asked of ``model`` is kept, and given again for the same x, t and policy (a run's
    post-processing asks at the start state the run decided it at: 0.03 s on a 10,000-link chain)."""
    if model.n_constraints == 0:
        return None
    x = np.asarray(x, float).ravel()
    key = (x.tobytes(), np.float64(t).tobytes(), policy, algebra_for(model.n_constraints).name)
    kept = per_model_cache(model).get("redundant rows")
    if kept is not None and kept[0] == key:
        return kept[1]
    rows = _redundant_rows(model, x, t, policy)
    per_model_cache(model)["redundant rows"] = (key, rows)
    return rows


def _redundant_rows(model: Model, x: np.ndarray, t: float, policy: RankPolicy) -> tuple[int, ...] | None:
    algebra = algebra_for(model.n_constraints)
    if algebra.name == "sparse":
        J = sparse_jacobian(model)(x, t)  # CasADi-sparse (J, then A): the O(N) factorization
    else:
        J = dense_jacobian(model)(x, t)[0].reshape(model.n_coordinates, model.n_constraints).T
    if algebra.full_row_rank(J, model.inverse_masses, policy):
        return None
    C_f = model.n_position_rows
    if C_f < model.n_constraints:  # velocity rows: those of f first
        lead = algebra.independent_rows(J[:C_f, :], model.inverse_masses, policy) if C_f else None
        rows = independent_rows_after(J, C_f, model.inverse_masses, policy, lead)
    else:
        rows = algebra.independent_rows(J, model.inverse_masses, policy)
    return None if rows.size == model.n_constraints else tuple(int(k) for k in rows)


# --- the per-model functions, built once and shared by every run --------------------------------
_lock = threading.Lock()


class _FastPaths:
    """The acceleration, Newton step and velocity correction (``vectorized.FAST_PATHS``) as
    FastCalls: all given at once, or each built by ``build(name)`` when first asked for (a
    large model's: a start at rest on its constraints needs neither projection's Function)."""

    def __init__(self, evaluation: str, functions: list | None = None, build=None):
        self.evaluation = evaluation
        self._calls = {} if functions is None else dict(zip(vectorized.FAST_PATHS, map(FastCall, functions),
                                                            strict=True))
        self._build = build
        self._lock = threading.Lock()

    def built(self, name: str) -> bool:
        return name in self._calls

    def _call(self, name: str) -> FastCall:
        call = self._calls.get(name)
        if call is None:
            with self._lock:
                call = self._calls.get(name)
                if call is None:
                    call = self._calls[name] = FastCall(self._build(name))
        return call

    @property
    def acceleration(self) -> FastCall:
        return self._call("acceleration")

    @property
    def newton_step(self) -> FastCall:
        return self._call("newton_step")

    @property
    def velocity_correction(self) -> FastCall:
        return self._call("velocity_correction")


def _graph_fast_paths(model: Model, rows) -> list[ca.Function]:
    """The fast paths' Functions on the model's own (SX) Functions."""
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
    return [ca.Function("acceleration", [X, V, T, P], [d(a), d(lam)]),
            ca.Function("newton_step", [X, T, P], [d(f), d(dx)]),
            ca.Function("velocity_correction", [X, V, T, P], [d(dv)])]


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
    # large: the vectorized build (whole columns of instances, J's products by index data)
    vector = vectorized.applies(model, rows) and not compiled
    if vector:  # each built when first called
        paths = _FastPaths("virtual machine", build=lambda name: vectorized.fast_path_function(model, name))
        with _lock:
            return cache.setdefault(key, paths)
    funcs = _graph_fast_paths(model, rows)
    evaluation = "virtual machine"
    if compiled:
        from ..codegen import compiled as compiled_evaluation

        machine = compiled_evaluation.compile_functions(funcs)
        if all(f.class_name() == "External" for f in machine):
            funcs, evaluation = machine, "compiled"
    paths = _FastPaths(evaluation, funcs)
    if compiled and compiled_evaluation.cut_short():  # a compile cut by Ctrl-C: not kept
        return paths
    with _lock:
        cache[key] = paths
    return paths


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
        self.algebra: LinearAlgebra = algebra_for(model.n_constraints)
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
        return self.algebra.schur_solve(J, self.model.inverse_masses, b, policy=self.policy,
                                        full_rank=not self.redundant)

    def accelerations(self, x: np.ndarray, v: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Accelerations and multipliers (over every row) at (x, v, t)."""
        m = self.model
        self.counters.nfev += 1
        if m.structure.pairs:  # pair potentials' neighbour lists, rebuilt where particles moved far
            p = m.structure.pair_potentials.refreshed(self._p, x)
            self._p = self._p if p is None else p
        if not self.redundant:
            a, lam = _fast_or_nan(self._fast.acceleration, (m.n_coordinates, len(m.constraint_labels)),
                                  x, v, t, self._p)
            self.counters.nlu += 1
            if np.all(np.isfinite(a)) and np.all(np.isfinite(lam)):
                return a, lam
        F, J, gamma = m.dynamics(x, v, t)
        F, J, gamma = np.asarray(F, float).ravel(), self.algebra.matrix(J), np.asarray(gamma, float).ravel()
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
        if m.n_position_rows == 0:  # no f (none, or velocity rows only)
            return ProjectionResult(x, ProjectionStatus.CONVERGED, 0, 0.0)
        best = err = np.inf
        for it in range(max_iter + 1):
            if it:  # after a step: f alone says whether it converged (no factorization)
                self.counters.nfev += 1
                err = float(np.max(np.abs(constraint_values(m)(x, t)[0])))
                if err <= tol:
                    return ProjectionResult(x, ProjectionStatus.CONVERGED, it, err)
            elif not self._fast.built("newton_step"):  # f alone (a start's: on numbers) for a
                # start on f = 0, without building the Newton step's Function (the same f)
                err = float(np.max(np.abs(constraint_values(m)(x, t)[0])))
                if err <= tol:
                    self.counters.njev += 1
                    return ProjectionResult(x, ProjectionStatus.CONVERGED, it, err)
            self.counters.njev += 1
            f, dx = _fast_or_nan(self._fast.newton_step, (m.n_position_rows, m.n_coordinates), x, t, self._p)
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
                J = self.algebra.matrix(J)
                dx = m.inverse_masses * (J.T @ self.schur_solve(J, np.asarray(f, float).ravel()))
            x = x - dx
        return ProjectionResult(x, ProjectionStatus.MAX_ITERATIONS, max_iter, err)  # pragma: no cover

    def project_velocities(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """Mass-weighted nearest velocity with J v + f_t = 0 and A v + b = 0 (one linear solve)."""
        m = self.model
        if m.n_constraints == 0:
            return np.array(v, dtype=float)
        self.counters.njev += 1
        self.counters.nlu += 1
        if no_velocity_correction(m, v):  # (at rest: v − dv is v)
            return np.array(v, dtype=float)
        (dv,) = _fast_or_nan(self._fast.velocity_correction, (m.n_coordinates,), x, v, t, self._p)
        if np.all(np.isfinite(dv)):
            return v - dv
        J, f_t = m.velocity_terms(x, t)
        J = self.algebra.matrix(J)
        c = J @ v + np.asarray(f_t, float).ravel()
        return v - m.inverse_masses * (J.T @ self.schur_solve(J, c))
