"""RATTLE: the fixed-step constrained symplectic integrator (SHAKE for positions, RATTLE
for velocities), for long runs with bounded energy error and no secular drift.

One step of size h from (x_n, v_n, t_n):

    v½      = v_n + h/2 · M⁻¹ (F(x_n, v_n, t_n) + J(x_n)ᵀ λ)
    x_{n+1} = x_n + h v½,           with f(x_{n+1}, t_{n+1}) = 0   (Newton in λ)
    v_{n+1} = v½ + h/2 · M⁻¹ (F(x_{n+1}, v½, t_{n+1}) + J(x_{n+1})ᵀ μ),
              with J(x_{n+1}) v_{n+1} + f_t = 0                    (linear in μ)

It is symplectic and time-reversible for conservative forces F(x). Velocity-dependent forces
(damping, magnetic) are taken at v_n and v½: the method stays consistent (first order in
those terms) but is no longer symplectic.

The whole step is one CasADi Function: Newton for λ is unrolled (``newton_iterations``
iterations from the previous step's λ, which converge quadratically), and the last
iteration's residual |f(x_{n+1})| is carried in the state as a running maximum, checked
after every chunk. ``fold`` chains many steps per call, so no Python runs per step, and
the chained steps can be compiled to machine code (``compiled``; see constrained.compiled).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ..codegen import compiled as compiled_evaluation
from ..codegen.fast_call import FastCall
from ..errors import InputError
from ..manifold import diagnostics, residual
from ..manifold.graph import schur_solve_graph, velocity_correction_graph
from .base import DRIVER_OPTIONS, Advance, Status
from .driver import Stepper

#: Under compiled="auto", RATTLE's folded steps are compiled for models up to this size.
AUTO_COMPILE_COORDINATES = 90

#: Largest number of output samples when the caller gives no output grid.
DEFAULT_SAMPLES = 2000
#: Coordinate-steps per chained call (see ``run``): 16384 steps of a 6-coordinate model.
CHUNK_WORK = 6 << 14


class Rattle(Stepper):
    name = "rattle"
    adaptive = False
    order = 2
    OPTIONS = ("newton_tol", "newton_iterations", *DRIVER_OPTIONS)
    refines_events = False  # its step is fixed: events are located on the dense output
    refuses_velocity_rows = ("its step keeps f = 0 by a Newton iteration in the multipliers, and a "
                             "velocity row has no f (a discrete non-holonomic integrator is another method)")

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, newton_tol: float = 1e-12,
                 newton_iterations: int = 4, **options):
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        model = self.model
        if not (isinstance(newton_iterations, int) and 1 <= newton_iterations <= 50):
            raise InputError(
                f"newton_iterations must be a whole number from 1 to 50, got {newton_iterations!r}"
            )
        self.newton_iterations = newton_iterations
        # "auto" compiles the folded steps of models up to AUTO_COMPILE_COORDINATES coordinates:
        # there the one-time C compile takes seconds and the chunks run ~2.7x faster; beyond,
        # the compiler's time grows steeply, so only compiled=True asks for it.
        self.compiled = compiled_evaluation.enabled(self.compiled_setting) and (
            self.compiled_setting is True or model.n_coordinates <= AUTO_COMPILE_COORDINATES
        )
        if dt is None:
            raise InputError("method 'rattle' takes fixed steps: give dt (seconds), e.g. dt = 1e-3")
        self.newton_tol = newton_tol
        self._chunks: dict[int, FastCall] = {}

    def _step(self, h: float) -> ca.Function:
        """One RATTLE step on the state (x, v, t, λ, err) — err: running max of |f| after Newton."""
        m = self.model
        rows = self.manifold.rows
        n3, C = m.n_coordinates, len(self.rows)
        x, v, t, err = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t"), ca.MX.sym("err")
        lam = ca.MX.sym("lam", C)
        minv = ca.DM(m.inverse_masses)
        F0, J0, _ = m.dynamics(x, v, t)
        t1 = t + h
        if C:
            J0 = J0 if rows is None else J0[list(rows), :]
            kick = 0.5 * h * h * minv
            base = x + h * v + kick * F0
            lam_k = lam
            for _ in range(self.newton_iterations):
                f1, J1 = m.jacobian(base + kick * ca.mtimes(J0.T, lam_k), t1)
                if rows is not None:
                    f1, J1 = f1[list(rows)], J1[list(rows), :]
                # d f(x1(λ)) / dλ = J(x1) · h²/2 M⁻¹ J(x_n)ᵀ
                lam_k = lam_k - schur_solve_graph(J1, J0, 0.5 * h * h * m.inverse_masses, f1)
            v_half = v + 0.5 * h * minv * (F0 + ca.mtimes(J0.T, lam_k))
            x1 = x + h * v_half
            # in metres: each row over its scale at the start (constrained.residual)
            residual = ca.mmax(ca.fabs(m.constraint(x1, t1)) / ca.DM(self.row_scales))
            F1, _, _ = m.dynamics(x1, v_half, t1)
            v_pred = v_half + 0.5 * h * minv * F1
            v1 = v_pred - velocity_correction_graph(m, x1, v_pred, t1, rows=rows)
            state = ca.vertcat(x, v, t, lam, err)
            out = ca.vertcat(x1, v1, t1, lam_k, ca.fmax(err, residual))
            return ca.Function("rattle_step", [state], [out])
        v_half = v + 0.5 * h * minv * F0
        x1 = x + h * v_half
        F1, _, _ = m.dynamics(x1, v_half, t1)
        state = ca.vertcat(x, v, t, err)
        return ca.Function("verlet_step", [state], [ca.vertcat(x1, v_half + 0.5 * h * minv * F1, t1, err)])

    def _chunk(self, step: ca.Function, k: int, *, compile_it: bool = False) -> FastCall:
        """k steps folded into one call (compiled when asked), called through its buffer."""
        chunk = self._chunks.get(k)
        if chunk is None:
            function = step.fold(k) if k > 1 else step
            if compile_it:
                function = compiled_evaluation.compile_function(function)
            chunk = self._chunks[k] = FastCall(function)
        return chunk

    def prepare(self, t0, t_end, t_eval) -> None:
        """The fixed step: dt shortened slightly to land on t_end; t_eval must lie on its grid."""
        self._t0 = t0
        self._n_steps = max(1, math.ceil((t_end - t0) / self.dt - 1e-9))
        self.h = (t_end - t0) / self._n_steps
        if t_eval is not None:
            k = (np.asarray(t_eval) - t0) / self.h
            if np.max(np.abs(k - np.rint(k)), initial=0.0) > 1e-6:
                raise InputError(
                    f"method 'rattle' outputs at multiples of its step ({self.h:.6g} s); "
                    "give t_eval on that grid or omit it"
                )
        grid = np.asarray(t_eval, float) if t_eval is not None else self.default_grid(t0, t_end)
        gaps = np.diff(np.rint((grid - t0) / self.h).astype(int))
        # the regular gap between samples is one chunk, compiled once; other gaps are split
        # into powers of two (at most a few distinct folds)
        self._gap = int(np.bincount(gaps[gaps > 0]).argmax()) if np.any(gaps > 0) else 1

    def default_grid(self, t0, t_end):
        every = max(1, self._n_steps // DEFAULT_SAMPLES)
        steps = list(range(0, self._n_steps + 1, every))
        if steps[-1] != self._n_steps:
            steps.append(self._n_steps)
        return t0 + self.h * np.array(steps, float)

    def init(self, x0, v0, t0, t_end, first_step=None):
        m = self.model
        n3, C = m.n_coordinates, len(self.rows)
        if not hasattr(self, "row_scales"):  # the run's scales, from its start
            self.scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
            self.row_scales = residual.row_scales(m, x0, t0) if C else np.zeros(0)
            self._step_function = self._step(self.h)
            # one call into CasADi (Ctrl-C waits for its end) covers about CHUNK_WORK
            # coordinate-steps: each call is near 0.1 s at most
            self._regular = min(self._gap, 1 << 14, 1 << max(3, int(math.log2(max(CHUNK_WORK // n3, 1)))))
        lam0 = self.manifold.accelerations(x0, v0, t0)[1][self.rows] if C else np.zeros(0)
        return (round((t0 - self._t0) / self.h), np.concatenate([x0, v0, [t0], lam0, [0.0]]))

    def step(self, state, t_stop) -> Advance:
        """One chained call of up to ``_regular`` steps (powers of two for the rest) to t_stop."""
        m = self.model
        n3 = m.n_coordinates
        done, y = state
        left = max(1, round((t_stop - self._t0) / self.h) - done)
        k = self._regular if left >= self._regular else 1 << (left.bit_length() - 1)
        compile_it = self.compiled and k == self._regular and k >= 8
        chunk = self._chunk(self._step_function, k, compile_it=compile_it)
        (new,) = chunk(y)
        t_new = self._t0 + (done + k) * self.h
        if abs(t_new - t_stop) <= 1e-9 * self.h:
            t_new = t_stop
        if not np.all(np.isfinite(new)):
            cause = diagnostics.nonfinite_cause(m, y[:n3], y[n3:2 * n3], y[2 * n3])
            return Advance.empty(state, n3, Status.NON_FINITE,
                                 f"non-finite state between t = {y[2 * n3]:.6g} s and {t_new:.6g} s; {cause}")
        if new[-1] > self.newton_tol * self.scale:
            return Advance.empty(state, n3, Status.PROJECTION_FAILED, (
                               f"Newton for the position multipliers did not converge between t = "
                               f"{y[2 * n3]:.6g} s and {t_new:.6g} s (|f| = {new[-1]:.3g} m after "
                               f"{self.newton_iterations} iterations): reduce dt"))
        self.stats["steps"] = done + k
        return Advance((done + k, new), np.array([t_new]), new[None, :n3], new[None, n3:2 * n3], h=self.h)

    def finish(self) -> None:
        done = self.stats["steps"]
        self.stats.update({"nfev": 2 * done, "dt": self.h,
                           "evaluation": "compiled" if self.compiled else "virtual machine"})
