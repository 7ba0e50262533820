"""RATTLE: the fixed-step constrained symplectic integrator (SHAKE for positions, RATTLE
for velocities), for long runs with bounded energy error and no secular drift.

One step of size h from (x_n, v_n, t_n):

    v½      = v_n + h/2 · M⁻¹ (F(x_n, v_n, t_n) + J(x_n)ᵀ λ)
    x_{n+1} = x_n + h v½,           with f(x_{n+1}, t_{n+1}) = 0   (Newton in λ)
    v_{n+1} = v½ + h/2 · M⁻¹ (F(x_{n+1}, v½, t_{n+1}) + J(x_{n+1})ᵀ μ),
              with J(x_{n+1}) v_{n+1} + f_t = 0                    (linear in μ)

It is symplectic and time-reversible for conservative forces F(x). Velocity-dependent forces
(damping, magnetic) are taken at v_n and v½: the method stays consistent (first order in
those terms) but is no longer symplectic. The whole step, Newton included, is one CasADi
Function; ``fold`` chains many steps per call so no Python runs per step.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ..errors import InputError
from .base import Solution, Solver

#: Largest number of output samples when the caller gives no output grid.
DEFAULT_SAMPLES = 2000


class Rattle(Solver):
    name = "rattle"
    adaptive = False

    def __init__(self, model, *, rtol=1e-8, atol=1e-10, dt=None, newton_tol: float = 1e-13,
                 **options):
        super().__init__(model, rtol=rtol, atol=atol, dt=dt, **options)
        if dt is None:
            raise InputError("method 'rattle' takes fixed steps: give dt (seconds), e.g. dt = 1e-3")
        self.require_independent_constraints("its Newton matrix is singular")
        self.newton_tol = newton_tol
        self._chunks: dict[int, ca.Function] = {}

    def _step(self, h: float) -> ca.Function:
        m = self.model
        n3, C = m.n_coordinates, m.n_constraints
        x, v, t = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
        lam = ca.MX.sym("lam", C)
        minv = ca.DM(m.inverse_masses)
        F0, J0, _ = m.dynamics(x, v, t)
        t1 = t + h
        if C:
            x1_of = x + h * v + 0.5 * h * h * minv * (F0 + ca.mtimes(J0.T, lam))
            g = ca.Function("g", [lam, ca.vertcat(x, v, t)], [m.constraint(x1_of, t1)])
            newton = ca.rootfinder("shake", "newton", g, {
                "abstol": self.newton_tol, "max_iter": 30, "error_on_fail": False,
            })
            lam_guess = ca.MX.sym("lam_guess", C)
            lam_n = newton(lam_guess, ca.vertcat(x, v, t))
            v_half = v + 0.5 * h * minv * (F0 + ca.mtimes(J0.T, lam_n))
            x1 = x + h * v_half
            F1, J1, _ = m.dynamics(x1, v_half, t1)
            _, f_t1 = m.velocity_terms(x1, t1)
            v_pred = v_half + 0.5 * h * minv * F1
            A = ca.mtimes(ca.mtimes(J1, ca.diag(minv)), J1.T)
            mu_term = ca.solve(A, ca.mtimes(J1, v_pred) + f_t1, "qr")
            v1 = v_pred - minv * ca.mtimes(J1.T, mu_term)
            state = ca.vertcat(x, v, t, lam_guess)
            out = ca.vertcat(x1, v1, t1, lam_n)
        else:
            v_half = v + 0.5 * h * minv * F0
            x1 = x + h * v_half
            F1, _, _ = m.dynamics(x1, v_half, t1)
            state = ca.vertcat(x, v, t)
            out = ca.vertcat(x1, v_half + 0.5 * h * minv * F1, t1)
        if C:
            return ca.Function("rattle_step", [state], [out])
        return ca.Function("verlet_step", [state], [out])

    def run(self, x0, v0, t0, t_end, t_eval=None) -> Solution:
        m = self.model
        n3, C = m.n_coordinates, m.n_constraints
        n_steps = max(1, math.ceil((t_end - t0) / self.dt - 1e-9))
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
        step = self._step(h)
        state = np.concatenate([x0, v0, [t0], np.zeros(C)])
        ts, xs, vs = [], [], []
        done = 0
        failure = None
        for target in sample_steps:
            while done < target:
                k = min(target - done, 1 << max(0, (target - done).bit_length() - 1))
                chunk = self._chunks.get(k)
                if chunk is None:
                    chunk = self._chunks[k] = step.fold(k) if k > 1 else step
                try:
                    new = chunk(state).full().ravel()
                except KeyboardInterrupt:
                    failure = f"interrupted at t = {state[2 * n3]:.6g} s"
                    break
                if not np.all(np.isfinite(new)):
                    failure = f"non-finite state between t = {state[2 * n3]:.6g} s and {new[2 * n3]:.6g} s"
                    break
                state = new
                done += k
            if failure:
                break
            ts.append(t0 + done * h)
            xs.append(state[:n3])
            vs.append(state[n3:2 * n3])
        self.stats.update({"steps": done, "nfev": 2 * done, "dt": h})
        return Solution(np.array(ts), np.array(xs).reshape(-1, n3), np.array(vs).reshape(-1, n3),
                        dict(self.stats), failure)
