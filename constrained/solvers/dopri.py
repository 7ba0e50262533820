"""Dormand–Prince embedded Runge–Kutta stepped inside CasADi, with projection after each step.

The same index-1 ODE as ``projection`` — x' = v, v' = a(x, v, t) from the KKT system — but
the whole step loop runs in one CasADi Function, compiled to machine code for small models:
no Python per step. One attempted step from (x, v, a, t) with step h:

    K_0 = (v, a),  K_i = f(t + c_i h, y + h Σ_j A_ij K_j)    (i = 1 … s−1)
    y_new = y + h Σ b_i K_i,  then projected: two mass-weighted Newton steps
            x ← x − M⁻¹Jᵀ (J M⁻¹ Jᵀ)⁻¹ f, and v ← v − M⁻¹Jᵀ (J M⁻¹ Jᵀ)⁻¹ (J v + f_t)
    K_s = f(t + h, y_new)   (first-same-as-last: the next step's K_0)
    err = the tableau's error norm (SciPy's, scaled by atol + rtol·max(|y|, |y_new|))

accepted when err ≤ 1; h ← h · clip(0.9 err^(−1/(p+1)), 0.2, 10) as in SciPy (no growth
right after a rejection). Steps are clipped to land exactly on each output time; an
attempt at the output time is skipped (a short-circuit branch, nearly free), so ``mapaccum``
can chain a fixed number of attempts per call and Python only picks how many.

Compiled, from ``mapped.MAPPED_FROM`` coordinates the loop is built on the mapped Functions
(constrained.mapped: each kind of repeated row or term one kernel applied with CasADi ``map``),
so the generated C code, and the compiler's time, does not grow with the model.

``base`` picks the tableau (solvers/tableaus/): "DOP853" (8th order, error estimator of
orders 5 and 3, 12 evaluations per step; the default), "DOPRI5" (5th order with a 4th-order
estimate, 6 per step) — the same pairs as SciPy's DOP853 and RK45, whose coefficients are
used — or "Tsit5" (Tsitouras' 5(4) pair, 6 per step).
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from ..codegen import compiled as compiled_evaluation
from ..codegen.combination import combination
from ..codegen.fast_call import FastCall
from ..errors import InputError
from ..manifold import diagnostics, mapped, residual
from ..manifold.graph import projection_graph
from ..manifold.manifold import acceleration_function
from ..manifold.vectorized import graphs as vectorized
from ..model.cache import ParametricView, structure_cache
from .base import DRIVER_OPTIONS, Advance, Status
from .dense import hermite
from .driver import Stepper
from .tableaus import TABLEAUS

#: Under compiled="auto", the step loop is compiled for models up to this many coordinates
#: (the one-time C compile takes a few seconds there and is cached; beyond, it grows steeply).
AUTO_COMPILE_COORDINATES = 200
#: Attempts chained per CasADi call; Python picks the shortest chain expected to reach the
#: stop (attempts past it are skipped), else the longest, but none above one whose call took
#: longer than CHUNK_SECONDS (Ctrl-C waits for a call).
CHUNKS = (1, 8, 64)
CHUNK_SECONDS = 0.1
#: A chain of k attempts is built only when k × coordinates is at most this: an attempt costs
#: ~1.3 µs per coordinate, so longer chains would exceed CHUNK_SECONDS anyway, and building
#: the 64-chain of a 10,000-particle chain took 0.6 s and 350 MB.
CHUNK_COORDINATE_ATTEMPTS = 80_000
#: Up to this many constraint rows the whole step is one SX expression (the KKT solves
#: written out symbolically): ~2.7x faster than calling the sparse linear solver.
SYMBOLIC_MAX_CONSTRAINTS = 8
#: Projection residual |f| (× system size) before the last Newton step that stops the run:
#: Newton converges quadratically, so this leaves |f| ≈ 1e-12 after it.
PROJECTION_FAIL = 1e-6
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0
#: The ``rejected`` flag of an attempt refused because it came out non-finite (1: too large an error).
NOT_FINITE = 2
#: A run with at most this many output times ends a step at each; with more, and a model of
#: DENSE_FROM coordinates or more, they come from the dense output (``Dopri.prepare``).
LANDED_OUTPUTS = 16
#: Below this many coordinates every output time ends a step: a step is cheap there, and a
#: landed sample is exact where an interpolated one carries up to about twice the step's
#: error (conservation checks at tight tolerances notice).
DENSE_FROM = 300
#: The scalars after [x, v, a] in the state a step works on, in order.
SCALARS = ("t", "h", "rejected", "n_acc", "n_rej", "res", "t_target", "rtol", "atol")


def combined(y, terms: list, shape: tuple):
    """y + Σ c_j K_j (y None: Σ c_j K_j; no terms: y, or zeros of ``shape``) for ``terms``
    [(c_j, K_j)] of MX columns: one pass of C (``codegen.combination``) where the columns are
    dense and compiled code can be had, else one product and one sum per term, the scalars
    c_j first (no pass over the sum to scale it)."""
    if terms and all(Kj.nnz() == Kj.numel() for _, Kj in terms):
        f = combination(terms[0][1].numel(), len(terms), with_y=y is not None)
        if f is not None:
            c = ca.vertcat(*[ca.MX(cj) if not isinstance(cj, ca.MX) else cj for cj, _ in terms])
            return f(*([y] if y is not None else []), *[Kj for _, Kj in terms], c)
    for c, Kj in terms:
        y = c * Kj if y is None else y + c * Kj
    return ca.MX.zeros(shape) if y is None else y


def skipping(name: str, S, done, attempt: ca.Function, direct: bool = False) -> ca.Function:
    """S -> S where ``done`` (an MX of S), else attempt(S): a short circuit, nothing of the
    attempt evaluated when done. ``direct``: CasADi's Switch built here, the same as
    ``ca.if_else``'s short circuit but without its search for the symbols of both branches
    (their 90,000 entries on a 100 x 100 cloth: 11 ms); the compiled step loops keep the
    latter, whose generated code the compile cache holds."""
    if direct:
        switch = ca.Function.if_else(f"{name}_switch", ca.Function("skipped", [S], [S]), attempt)
        return ca.Function(name, [S], [switch(done, S)])
    return ca.Function(name, [S], [ca.if_else(done, S, attempt(S), True)])


def _slot(n: int, name: str) -> int:
    """Index of the scalar ``name`` in the state of a model with n coordinates."""
    return 3 * n + SCALARS.index(name)


#: The tableaus (``base``): solvers/tableau.py and one module per pair in solvers/tableaus/.
BASES = TABLEAUS


class Dopri(Stepper):
    name = "dopri"
    OPTIONS = ("base", *DRIVER_OPTIONS)
    explicit = True
    BASES = tuple(BASES)

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, base: str = "DOP853", **options):
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        model = self.model
        if base not in BASES:
            elsewhere = ("; it is a base of method 'projection': pass method=\"projection\""
                         if base in ("RK45", "Radau", "CVODES", "CVODES_BDF") else "")
            raise InputError(f"unknown base tableau {base!r} for method 'dopri' "
                             f"(choose from {', '.join(BASES)}){elsewhere}")
        #: The tableau's order: the global error falls like h^order.
        self.order = BASES[base].order
        self.tableau = BASES[base]
        # (pair potentials compile at any size: their O(N²) work is one kernel of fixed code)
        self.compiled = compiled_evaluation.enabled(self.compiled_setting) and (
            self.compiled_setting is True or model.n_coordinates <= AUTO_COMPILE_COORDINATES
            or bool(model.structure.pairs)
        )
        self._chunks = self._functions()  # the one-time cost, outside the run's wall time
        self._longest = max(self._chunks)
        self._scale = None
        self._smallest_scale = None
        n = model.n_coordinates
        self._slots = tuple(_slot(n, k) for k in ("t", "h", "n_acc", "n_rej", "res", "t_target"))

    # --- the step as a CasADi graph -------------------------------------------------------
    def _state_size(self) -> int:
        return 3 * self.model.n_coordinates + len(SCALARS) + len(self.model.parameter_vector)

    def _step_function(self, stale_stops: bool = True) -> ca.Function:
        with vectorized.shared_nodes():  # (what the accelerations of a step share, built once)
            return self._step_graph(stale_stops)

    def _step_graph(self, stale_stops: bool) -> ca.Function:
        """One attempted step on the state [x, v, a, *SCALARS, *p]: the parameters are part of
        the state (carried along unchanged), so one step loop serves every parameter value.
        ``stale_stops``: an attempt is skipped where a pair potential's neighbour list in p has
        gone stale, for ``step`` to refresh it (else the step sums every pair there: exact)."""
        tab = self.tableau
        n = self.model.n_coordinates
        S = ca.MX.sym("state", self._state_size())
        x, v, a = S[:n], S[n:2 * n], S[2 * n:3 * n]
        scalars = S[3 * n:3 * n + len(SCALARS)]
        P = S[3 * n + len(SCALARS):]
        t, h, rejected, n_acc, n_rej, res, t_target, rtol, atol = ca.vertsplit(scalars, 1)
        rows = self.manifold.rows
        # (pair potentials are mapped kernels: written out as SX they would be one term per pair)
        symbolic = len(self.rows) <= SYMBOLIC_MAX_CONSTRAINTS and not self.model.structure.pairs
        # compiled and large: repeated rows and terms as mapped kernels (constrained.mapped),
        # so the generated code, and the compile time, does not grow with the model
        # in the virtual machine and large: the vectorized build (whole columns of instances)
        vector = not self.compiled and not symbolic and vectorized.applies(self.model, rows)
        if self.compiled and not symbolic and mapped.applies(self.model):
            m, with_p = mapped.MappedView(self.model, P), mapped.acceleration_function(self.model, rows)
        elif vector:  # m⁻¹ (and forces of p alone) once per step, shared by its accelerations
            m = ParametricView(self.model, P)
            minv, forces = vectorized.statics(m)
        else:
            m = ParametricView(self.model, P)
            with_p = acceleration_function(self.model, rows, symbolic=symbolic, parametric=True)

        def accel(X, V, T):
            if vector:  # written into the step's graph (no copies in and out of a call), where
                # what depends on p alone is built once (``shared_nodes``: _step_function)
                return vectorized.acceleration_graph(m, X, V, T, minv=minv, forces=forces)
            return with_p(X, V, T, P)

        linsol = "symbolicqr" if symbolic else "ldl"
        done = t >= t_target  # (then the attempt is skipped: see the end)
        remaining = t_target - t
        clipped = h >= remaining
        hh = ca.if_else(done, h, ca.fmin(h, remaining))  # a valid step even when discarded
        reach = self.model.structure.pair_potentials.step_limit(v, P)
        if reach is not None:  # the stages stay where the neighbour lists hold (no O(N²) sums)
            clipped = ca.logic_and(clipped, remaining <= reach)
            hh = ca.if_else(done, h, ca.fmin(hh, reach))
        # stages as columns: one matrix-vector product per combination keeps the graph small
        Kx, Kv = [v], [a]

        def combine(K, w):
            if vector:  # Σ w_j K_j over the nonzero weights, column by column (no copies of K)
                return combined(None, [(float(wj), Kj) for wj, Kj in zip(w, K, strict=False) if wj != 0],
                                K[0].shape)
            return ca.mtimes(ca.horzcat(*K), ca.DM(np.asarray(w, float)))

        def advanced(y, K, w):
            """y + hh Σ w_j K_j; vectorized: ``combined`` with the scalars hh w_j."""
            if not vector:
                return y + hh * combine(K, w)
            return combined(y, [(hh * float(wj), Kj) for wj, Kj in zip(w, K, strict=False) if wj != 0],
                            y.shape)

        for i in range(1, tab.stages):
            xi = advanced(x, Kx, tab.A[i, :i])
            vi = advanced(v, Kv, tab.A[i, :i])
            ai, _ = accel(xi, vi, t + tab.C[i] * hh)
            Kx.append(vi)
            Kv.append(ai)
        x1 = advanced(x, Kx, tab.B)
        v1 = advanced(v, Kv, tab.B)
        t1 = ca.if_else(clipped, t_target, t + hh)
        if m.n_constraints and vector:
            x1, v1, residual = vectorized.projection_graph(m, x1, v1, t1, minv=minv)
        elif m.n_constraints:
            x1, v1, residual = projection_graph(m, x1, v1, t1, rows=rows, linsol=linsol)
        else:
            residual = ca.MX(0)
        a1, _ = accel(x1, v1, t1)
        Kx.append(v1)
        Kv.append(a1)
        scale_x = atol + rtol * ca.fmax(ca.fabs(x), ca.fabs(x1))
        scale_v = atol + rtol * ca.fmax(ca.fabs(v), ca.fabs(v1))

        def weighted(E):
            return ca.sumsqr(combine(Kx, E) / scale_x) + ca.sumsqr(combine(Kv, E) / scale_v)

        if len(tab.E) == 2:  # DOP853: Hairer's blend of the 5th- and 3rd-order estimates
            e5, e3 = weighted(tab.E[0]), weighted(tab.E[1])
            denom = e5 + 0.01 * e3
            err = ca.if_else(denom > 0, hh * e5 / ca.sqrt(ca.fmax(denom, 1e-300) * 2 * n), 0)
        else:
            err = hh * ca.sqrt(weighted(tab.E[0]) / (2 * n))
        # a trial step that left the finite numbers (a stage far off the manifold: a rod's
        # beads on top of each other, a singular KKT solve, a Newton step that diverged) is
        # rejected and shrunk, never accepted (NaN compares false: the blend above made its
        # error 0); its ``rejected`` flag is NOT_FINITE, so a step that collapses on such
        # trials is reported as non-finite
        total = ca.sum1(x1) + ca.sum1(v1) + ca.sum1(a1) + residual + err
        finite = ca.logic_and(total < ca.inf, total > -ca.inf)  # (NaN compares false)
        err = ca.if_else(finite, err, ca.inf)
        accept = err <= 1.0
        grow = ca.if_else(err == 0, MAX_FACTOR,
                          ca.fmin(MAX_FACTOR, SAFETY * ca.power(ca.fmax(err, 1e-300), tab.exponent)))
        grow = ca.if_else(rejected, ca.fmin(1.0, grow), grow)
        shrink = ca.fmax(MIN_FACTOR, SAFETY * ca.power(ca.fmax(err, 1e-300), tab.exponent))
        shrink = ca.if_else(finite, shrink, MIN_FACTOR)
        # after a step clipped to an output time, keep the proposal that step had
        h_accept = ca.if_else(clipped, ca.fmax(h, hh * grow), hh * grow)
        accepted = ca.vertcat(x1, v1, a1, t1, h_accept, 0, n_acc + 1, n_rej, ca.fmax(res, residual),
                              t_target, rtol, atol, P)
        flag = ca.if_else(finite, 1, NOT_FINITE)
        refused = ca.vertcat(x, v, a, t, hh * shrink, flag, n_acc, n_rej + 1, res, t_target, rtol, atol, P)
        name = f"dopri_{tab.name.lower()}"
        attempt = ca.Function(f"{name}_attempt", [S], [ca.if_else(accept, accepted, refused)])
        if symbolic:  # one SX graph, common subexpressions merged (≈ 9 % fewer operations)
            attempt = attempt.expand(attempt.name(), {"cse": True})
        # at the output time the attempt is skipped (short-circuit), so no-ops in a chain are free
        S2 = ca.MX.sym("state", S.numel())
        done = S2[_slot(n, "t")] >= S2[_slot(n, "t_target")]
        if stale_stops and self.model.structure.pairs:  # a stale neighbour list: stop, ``step`` refreshes it
            stale = self.model.structure.pair_potentials.stale(S2[:n], S2[3 * n + len(SCALARS):])
            done = ca.logic_or(done, stale)
        return skipping(f"{name}_step", S2, done, attempt, direct=vector)

    def _functions(self) -> dict[int, FastCall]:
        """The chained-step Functions, built (and compiled) once per model and kept there."""
        cache, prefix = structure_cache(self.model)  # shared by every parameter value
        key = (*prefix, self.name, self.tableau.name, self.compiled, self.manifold.rows)
        cached = cache.get(key)
        if cached is None:
            cached = self._build_functions()
            if not (self.compiled and compiled_evaluation.cut_short()):  # (cut by Ctrl-C: not kept)
                cache[key] = cached
        self.stats["evaluation"] = cached[0]
        return cached[1]

    def _build_functions(self) -> tuple[str, dict[int, FastCall]]:
        step = self._step_function()
        evaluation = "virtual machine"
        n = self.model.n_coordinates
        chunks = {k: (step if k == 1 else step.mapaccum(f"{step.name()}_{k}", k)) for k in CHUNKS
                  if k == 1 or k * n <= CHUNK_COORDINATE_ATTEMPTS}
        if self.compiled:
            compiled = compiled_evaluation.compile_functions(list(chunks.values()))
            if all(f.class_name() == "External" for f in compiled):
                chunks = dict(zip(chunks, compiled, strict=True))
                evaluation = "compiled"
        return evaluation, {k: FastCall(f) for k, f in chunks.items()}

    # --- the stepper -----------------------------------------------------------------------
    def prepare(self, t0, t_end, t_eval) -> None:
        """Output times end a step each (exact step ends), except more than LANDED_OUTPUTS of
        them for a model of DENSE_FROM coordinates or more: those are taken from the dense
        output between steps (``between``) and projected (``output``), so a fine grid costs
        no steps where steps are expensive."""
        self.lands = (t_eval is None or len(t_eval) <= LANDED_OUTPUTS
                      or self.model.n_coordinates < DENSE_FROM)

    def start_acceleration(self, state):
        n = self.model.n_coordinates
        return np.array(state[2 * n:3 * n])

    def between(self, t0, x0, v0, a0, t1, x1, v1, a1):
        """The quintic Hermite interpolant of the step's ends corrected by the acceleration at
        its midpoint (``dense.hermite``: O(h⁷), one more acceleration per step with outputs)."""
        def acceleration(t, x, v):
            return self.manifold.accelerations(x, v, t)[0]

        return hermite(t0, x0, v0, a0, t1, x1, v1, a1, acceleration)

    def output(self, t, x, v):
        """A dense-output sample, projected onto both manifolds as a step's end is."""
        m = self.manifold
        if not self.model.n_constraints:
            return x, v
        if self._smallest_scale is None:  # the rows' scale (metres), from the first output
            self._smallest_scale = residual.smallest_scale(self.model, x, t)
        scale = self._scale or 1.0
        projected = m.project_positions(x, t, tol=1e-14 * scale * self._smallest_scale)
        if not projected.residual <= PROJECTION_FAIL * scale * self._smallest_scale:  # NaN too
            return np.full_like(x, np.nan), np.full_like(v, np.nan)
        m.counters.projections += 1
        return projected.x, m.project_velocities(projected.x, v, t)

    def _initial_step(self, x0, v0, a0, t0, t_end) -> float:
        """Hairer's starting step (as SciPy's select_initial_step), from two evaluations."""
        if self.dt is not None:
            return min(float(self.dt), t_end - t0)
        m = self.manifold
        y0, f0 = np.concatenate([x0, v0]), np.concatenate([v0, a0])
        scale = self.atol + np.abs(y0) * self.rtol
        d0, d1 = np.linalg.norm(y0 / scale), np.linalg.norm(f0 / scale)
        h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
        h0 = min(h0, t_end - t0)
        x1, v1 = x0 + h0 * v0, v0 + h0 * a0
        a1, _ = m.accelerations(x1, v1, t0 + h0)
        d2 = np.linalg.norm((np.concatenate([v1, a1]) - f0) / scale) / h0
        order = self.tableau.order
        if d1 <= 1e-15 and d2 <= 1e-15:
            h1 = max(1e-6, h0 * 1e-3)
        else:
            h1 = (0.01 / max(d1, d2)) ** (1 / (order + 1))
        return min(100 * h0, h1, t_end - t0)

    def init(self, x0, v0, t0, t_end, first_step=None):
        a0, _ = self.manifold.accelerations(x0, v0, t0)
        h = first_step if first_step else self._initial_step(x0, v0, a0, t0, t_end)
        if self._scale is None:  # the run's scale, from its start (not a restart's)
            self._scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
        start = {"t": t0, "h": h, "t_target": t0, "rtol": self.rtol, "atol": self.atol,
                 "n_acc": self.stats["steps"], "n_rej": self.stats.get("rejected", 0)}
        return np.concatenate([x0, v0, a0, [start.get(k, 0.0) for k in SCALARS], self.model.parameter_vector])

    def step(self, state, t_stop) -> Advance:
        """One call of the chained steps (CHUNKS) towards t_stop: its accepted columns."""
        n = self.model.n_coordinates
        T, H, N_ACC, N_REJ, RES, TARGET = self._slots
        state = state.copy()
        state[TARGET] = t_stop
        if self.model.structure.pairs:  # neighbour lists rebuilt where particles moved far
            p = self.model.structure.pair_potentials.refreshed(state[3 * n + len(SCALARS):], state[:n])
            if p is not None:
                state[3 * n + len(SCALARS):] = p
        expected = (t_stop - state[T]) / max(state[H], 1e-300) + 1
        # the shortest chain that should reach t_stop (attempts past it are skipped, nearly
        # free), else the longest allowed: fewer calls, each with its Python overhead
        fits = [c for c in self._chunks if c <= self._longest]
        k = next((c for c in fits if c >= expected), fits[-1])
        called = time.perf_counter()
        (out,) = self._chunks[k](state)
        if k > 1 and time.perf_counter() - called > CHUNK_SECONDS:
            # Ctrl-C waits for the call: keep calls short on slow (large) models
            self._longest = max(c for c in self._chunks if c < k)
        cols = out.reshape(k, -1)
        finite = bool(np.isfinite(out).all())
        good = cols if finite else cols[:np.argmin(np.isfinite(cols).all(axis=1))]
        # a rejected attempt (or one skipped at t_stop) leaves t as it was: the accepted
        # columns are those whose t moved on
        t = good[:, T]
        moved = np.empty(len(t), bool)
        if len(t):
            moved[0] = t[0] > state[T]
            moved[1:] = t[1:] > t[:-1]
        taken = good[moved]
        new = good[-1] if len(good) else state
        self.stats.update(steps=int(new[N_ACC]), rejected=int(new[N_REJ]))
        samples = dict(t=taken[:, T], x=taken[:, :n], v=taken[:, n:2 * n], a=taken[:, 2 * n:3 * n],
                       h=float(new[H]))
        if not finite:
            return Advance(new, **samples, status=Status.NON_FINITE,
                           message=f"non-finite state after t = {new[T]:.6g} s; "
                           + diagnostics.nonfinite_cause(self.model, new[:n], new[n:2 * n], new[T]))
        if new[RES] > PROJECTION_FAIL * self._scale:
            # RES is a running maximum: the attempts before the first above the limit are good
            # (kept, so the last good state, and its diagnosis, is the one next to the failure)
            bad = int(np.argmax(cols[:, RES] > PROJECTION_FAIL * self._scale))
            before = cols[:bad][moved[:bad]]
            samples = dict(t=before[:, T], x=before[:, :n], v=before[:, n:2 * n], a=before[:, 2 * n:3 * n],
                           h=float(new[H]))
            last = cols[bad - 1] if bad else state
            return Advance(last, **samples, status=Status.PROJECTION_FAILED, message=(
                f"the state could not be kept on the constraints near t = {cols[bad, T]:.6g} s (residual "
                f"{cols[bad, RES]:.3g} m before the last Newton step): reduce rtol"))
        if new[T] < t_stop and new[H] < 1e-14 * max(1.0, abs(new[T])):
            if new[_slot(n, "rejected")] == NOT_FINITE:  # every trial came out non-finite
                return Advance(new, **samples, status=Status.NON_FINITE,
                               message=f"non-finite state after t = {new[T]:.6g} s; "
                               + diagnostics.nonfinite_cause(self.model, new[:n], new[n:2 * n], new[T]))
            held = self.model.structure.pair_potentials.step_held(  # (a list's skin, not the forces)
                new[n:2 * n], new[3 * n + len(SCALARS):], new[H], self.model.particle_names)
            return Advance(new, **samples, status=Status.STEP_SIZE_COLLAPSED,
                           message=(f"the step size collapsed at t = {new[T]:.6g} s (h = {new[H]:.3g} s); "
                                    + (f"likely cause: {held}" if held
                                       else self.diagnose(new[:n], new[n:2 * n], new[T]))))
        return Advance(new, **samples)

    def stiffness_advice(self) -> tuple[str, str]:
        return (f"dopri's explicit {self.tableau.name}",
                'use method = "rodas" (linearly implicit, steps set by accuracy), or method = "projection" '
                'with base = "Radau" or base = "CVODES_BDF"')

    def finish(self) -> None:
        accepted, rejected = self.stats["steps"], self.stats.get("rejected", 0)
        evals = self.tableau.stages  # per attempt: s − 1 stages plus the projected last one
        self.stats.update({
            "nfev": 2 + evals * (accepted + rejected), "njev": 2 * (accepted + rejected),
            "nlu": (evals + 2) * (accepted + rejected), "projections": accepted,
            "tableau": self.tableau.name,
        })
