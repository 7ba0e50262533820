"""Index-1 ODE with coordinate projection after every accepted step.

The state (x, v) follows x' = v, v' = a(x, v, t) with a from the KKT system. After each
accepted step of an embedded Runge–Kutta method (SciPy's DOP853 by default, error
controlled by rtol/atol) the state is projected, mass-weighted, onto f(x, t) = 0 (Newton)
and then onto J v + f_t = 0 (linear). Output times inside a step are taken from the
step's dense output and projected the same way, so every sample lies on both manifolds.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import DOP853, RK45, Radau

from .. import compiled as compiled_evaluation
from ..errors import InputError
from .base import Solution, Solver

BASES = {"DOP853": DOP853, "RK45": RK45, "Radau": Radau, "CVODES": None}
#: With compiled="auto", the model's per-call functions are compiled from this many coordinates.
COMPILE_FROM_COORDINATES = 90


class _NonFinite(Exception):
    pass


class Projection(Solver):
    name = "projection"
    #: Whether accepted steps and outputs are projected onto the constraint manifolds.
    projecting = True

    def __init__(self, model, *, rtol=1e-8, atol=1e-10, dt=None, base: str = "DOP853", **options):
        super().__init__(model, rtol=rtol, atol=atol, dt=dt, **options)
        if base not in BASES:
            raise InputError(f"unknown base integrator {base!r} (choose from {', '.join(BASES)})")
        self.base = base
        # Per-call functions gain from machine code only when the model is large enough that
        # evaluation, not CasADi's Python call overhead, dominates (docs/performance.md).
        want = self.compiled_setting is True or (
            self.compiled_setting == "auto" and model.n_coordinates >= COMPILE_FROM_COORDINATES
        )
        if want and compiled_evaluation.enabled(self.compiled_setting):
            model.compile()

    def derivative(self, t, y):
        """(x', v') = (v, a(x, v, t)) with a from the KKT system."""
        n = self.model.n_coordinates
        a, _ = self.model.accelerations(y[:n], y[n:], t)
        return np.concatenate([y[n:], a])

    def project(self, x, v, t):
        if not self.projecting:
            return x, v
        m = self.model
        x, err, _ = m.project_positions(x, t, tol=self.position_tol)
        v = m.project_velocities(x, v, t)
        self.stats["projections"] += 1
        return x, v

    def run(self, x0, v0, t0, t_end, t_eval=None) -> Solution:
        if self.base == "CVODES":
            return self._run_cvodes(x0, v0, t0, t_end, t_eval)
        m = self.model
        n = m.n_coordinates
        scale = max(float(np.max(np.abs(x0), initial=0.0)), 1.0)
        self.position_tol = 1e-14 * scale

        def rhs(t, y):
            dy = self.derivative(t, y)
            self.stats["nfev"] += 1
            if not np.all(np.isfinite(dy)):
                raise _NonFinite(t)
            return dy

        y0 = np.concatenate([x0, v0])
        integ = BASES[self.base](
            rhs, t0, y0, t_end, rtol=self.rtol, atol=self.atol, first_step=self.dt
        )
        ts, ys = [t0], [y0]
        pending = None if t_eval is None else list(np.asarray(t_eval, float))
        if pending is not None:
            ts, ys = [], []
            while pending and pending[0] <= t0:
                pending.pop(0)
                ts.append(t0)
                ys.append(y0)
        failure = None
        while integ.status == "running":
            try:
                message = integ.step()
            except _NonFinite as exc:
                failure = f"non-finite accelerations at t = {exc.args[0]:.6g} s"
                break
            except KeyboardInterrupt:
                failure = f"interrupted at t = {integ.t:.6g} s"
                break
            if integ.status == "failed":
                failure = f"the step size collapsed at t = {integ.t:.6g} s ({message})"
                break
            self.stats["steps"] += 1
            if pending is not None and pending and pending[0] <= integ.t:
                dense = integ.dense_output()
                while pending and pending[0] <= integ.t:
                    tk = pending.pop(0)
                    yk = dense(tk)
                    xk, vk = self.project(yk[:n], yk[n:], tk)
                    ts.append(tk)
                    ys.append(np.concatenate([xk, vk]))
            y = integ.y
            if self.projecting:
                x, v = self.project(integ.y[:n], integ.y[n:], integ.t)
                y = np.concatenate([x, v])
                if not np.all(np.isfinite(y)):
                    failure = f"non-finite state after projection at t = {integ.t:.6g} s"
                    break
                integ.y = y
                if hasattr(integ, "f"):  # keep first-same-as-last consistent with the new state
                    integ.f = rhs(integ.t, y)
            if pending is None:
                ts.append(integ.t)
                ys.append(y)
        for key in ("njev", "nlu"):
            self.stats[key] = max(self.stats[key], m.counters[key])
        self.stats["evaluation"] = m.evaluation
        Y = np.array(ys).reshape(-1, 2 * n)
        return Solution(np.array(ts), Y[:, :n], Y[:, n:], dict(self.stats), failure)

    # --- CVODES base: CasADi integrates between projection points --------------------------
    #: Without t_eval, the state is projected this many times over the run.
    CVODES_SEGMENTS = 100

    def _run_cvodes(self, x0, v0, t0, t_end, t_eval) -> Solution:
        """Integrate with CasADi's CVODES (Adams, no Python per evaluation) from one output
        time to the next, projecting onto both manifolds at each of them."""
        import casadi as ca

        m = self.model
        n = m.n_coordinates
        scale = max(float(np.max(np.abs(x0), initial=0.0)), 1.0)
        self.position_tol = 1e-14 * scale
        grid = (np.asarray(t_eval, float) if t_eval is not None
                else np.linspace(t0, t_end, self.CVODES_SEGMENTS + 1))
        # one integrator for every segment: τ ∈ [0, 1], t = t_a + Δ τ, d/dτ = Δ d/dt
        y, tau, p = ca.MX.sym("y", 2 * n), ca.MX.sym("tau"), ca.MX.sym("p", 2)
        a, _ = m._acceleration(y[:n], y[n:], p[0] + p[1] * tau)
        ode = p[1] * ca.vertcat(y[n:], a)
        integ = ca.integrator("segment", "cvodes", {"x": y, "p": p, "t": tau, "ode": ode}, 0.0, 1.0, {
            "abstol": self.atol, "reltol": self.rtol, "max_num_steps": 10_000_000,
            "linear_multistep_method": "adams", "nonlinear_solver_iteration": "functional",
        })
        ts, xs, vs = [], [], []
        if grid[0] <= t0:
            ts.append(t0)
            xs.append(x0)
            vs.append(v0)
            grid = grid[1:]
        state, t_a, failure = np.concatenate([x0, v0]), t0, None
        for t_b in grid:
            try:
                out = integ(x0=state, p=[t_a, t_b - t_a])
            except RuntimeError as exc:
                failure = f"CVODES stopped after t = {t_a:.6g} s ({str(exc).splitlines()[-1][:200]})"
                break
            except KeyboardInterrupt:
                failure = f"interrupted at t = {t_a:.6g} s"
                break
            stats = integ.stats()
            self.stats["steps"] += int(stats.get("nsteps", 0))
            self.stats["nfev"] += int(stats.get("nfevals", 0))
            yb = out["xf"].full().ravel()
            x, v = self.project(yb[:n], yb[n:], t_b)
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
                failure = f"non-finite state at t = {t_b:.6g} s"
                break
            ts.append(t_b)
            xs.append(x)
            vs.append(v)
            state, t_a = np.concatenate([x, v]), t_b
        self.stats["evaluation"] = m.evaluation
        return Solution(np.array(ts), np.array(xs).reshape(-1, n), np.array(vs).reshape(-1, n),
                        dict(self.stats), failure)
