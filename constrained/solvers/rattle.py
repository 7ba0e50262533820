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

from .. import compiled as compiled_evaluation
from .. import diagnostics, residual
from ..errors import InputError
from ..manifold import schur_solve_graph, velocity_correction_graph
from .base import Failure, Solution, Solver, Status

#: Under compiled="auto", RATTLE's folded steps are compiled for models up to this size.
AUTO_COMPILE_COORDINATES = 90

#: Largest number of output samples when the caller gives no output grid.
DEFAULT_SAMPLES = 2000
#: Coordinate-steps per chained call (see ``run``): 16384 steps of a 6-coordinate model.
CHUNK_WORK = 6 << 14


class Rattle(Solver):
    name = "rattle"
    adaptive = False
    order = 2
    OPTIONS = ("newton_tol", "newton_iterations")

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
        self._chunks: dict[int, ca.Function] = {}

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

    def _chunk(self, step: ca.Function, k: int, *, compile_it: bool = False) -> ca.Function:
        chunk = self._chunks.get(k)
        if chunk is None:
            chunk = step.fold(k) if k > 1 else step
            if compile_it:
                chunk = compiled_evaluation.compile_function(chunk)
            self._chunks[k] = chunk
        return chunk

    def run(self, x0, v0, t0, t_end, t_eval=None) -> Solution:
        m = self.model
        n3, C = m.n_coordinates, len(self.rows)
        n_steps = max(1, math.ceil((t_end - t0) / self.dt - 1e-9))
        self.scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
        h = (t_end - t0) / n_steps  # the step is shortened slightly to land on t_end
        if t_eval is None:
            every = max(1, n_steps // DEFAULT_SAMPLES)
            sample_steps = list(range(0, n_steps + 1, every))
            if sample_steps[-1] != n_steps:
                sample_steps.append(n_steps)
        else:
            k = (np.asarray(t_eval) - t0) / h
            sample_steps = np.rint(k).astype(int).tolist()
            if np.max(np.abs(k - np.rint(k)), initial=0.0) > 1e-6:
                raise InputError(
                    f"method 'rattle' outputs at multiples of its step ({h:.6g} s); "
                    "give t_eval on that grid or omit it"
                )
        self.row_scales = residual.row_scales(m, x0, t0) if C else np.zeros(0)
        step = self._step(h)
        lam0 = self.manifold.accelerations(x0, v0, t0)[1][self.rows] if C else np.zeros(0)
        state = np.concatenate([x0, v0, [t0], lam0, [0.0]])
        ts, xs, vs = [], [], []
        done = 0
        failure = None
        gaps = np.diff([0, *sample_steps])
        # the regular gap between samples is one chunk, compiled once; other gaps are split
        # into powers of two (at most a few distinct folds)
        regular = int(np.bincount(gaps[gaps > 0]).argmax()) if np.any(gaps > 0) else 1
        # a chunk is one call into CasADi, where Ctrl-C waits for its end: chunks of about
        # CHUNK_WORK coordinate-steps keep each call near 0.1 s at most (checked in between)
        regular = min(regular, 1 << 14, 1 << max(3, int(math.log2(max(CHUNK_WORK // n3, 1)))))
        self.watch_stiffness(x0, t0, t_end)
        for target in sample_steps:
            while done < target:
                if self.stop_requested():
                    failure = self.interrupted_at(state[2 * n3])
                    break
                failure = self.too_stiff(state[2 * n3], done, state[:n3])
                if failure:
                    break
                left = target - done
                k = regular if left >= regular else 1 << (left.bit_length() - 1)
                chunk = self._chunk(step, k, compile_it=self.compiled and k == regular and k >= 8)
                try:
                    new = chunk(state).full().ravel()
                except KeyboardInterrupt:
                    failure = self.interrupted_at(state[2 * n3])
                    break
                if not np.all(np.isfinite(new)):
                    failure = Failure(Status.NON_FINITE,
                        (f"non-finite state between t = {state[2 * n3]:.6g} s and "
                               f"{t0 + (done + k) * h:.6g} s; "
                               + diagnostics.nonfinite_cause(m, state[:n3], state[n3:2 * n3], state[2 * n3])))
                    break
                if new[-1] > self.newton_tol * self.scale:
                    failure = Failure(Status.PROJECTION_FAILED, (
                        f"Newton for the position multipliers did not converge between t = "
                        f"{state[2 * n3]:.6g} s and {new[2 * n3]:.6g} s (|f| = {new[-1]:.3g} m after "
                        f"{self.newton_iterations} iterations): reduce dt"
                    ))
                    break
                state = new
                done += k
                self.report(state[2 * n3])
            if failure:
                # the state reached (the last good one) between two samples is kept
                if t_eval is None and done > (sample_steps[len(ts) - 1] if ts else -1):
                    ts.append(t0 + done * h)
                    xs.append(state[:n3])
                    vs.append(state[n3:2 * n3])
                break
            ts.append(t0 + done * h)
            xs.append(state[:n3])
            vs.append(state[n3:2 * n3])
        self.stats.update({"steps": done, "nfev": 2 * done, "dt": h,
                           "evaluation": "compiled" if self.compiled else "virtual machine"})
        return Solution(np.array(ts), np.array(xs).reshape(-1, n3), np.array(vs).reshape(-1, n3),
                        self.counted(), failure)
