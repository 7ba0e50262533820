"""DAE methods through CasADi's IDAS (SUNDIALS' variable-order BDF for DAEs).

``idas``: the index-1 form, differential x, v and algebraic λ:

    x' = v,   v' = M⁻¹ (F + Jᵀλ),   0 = J M⁻¹ (F + Jᵀλ) + γ

Position and velocity constraints are only implied, so they drift slowly; by default the
state is projected onto both manifolds at every output time (``project_outputs``) and the
integration continues from the projected state.

``ggl``: the Gear–Gupta–Leimkuhler stabilized index-2 form, with a second multiplier μ:

    x' = v + M⁻¹Jᵀμ,   v' = M⁻¹ (F + Jᵀλ),   0 = f(x, t),   0 = J v + f_t

Both constraint levels hold exactly along the solution (μ = 0 there), so there is no
drift. The algebraic variables are left out of the error test, as index-2 problems need.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..errors import InputError
from .base import Solution, Solver


class _IdasBase(Solver):
    adaptive = True
    OPTIONS = ("max_step",)
    project_outputs = False
    #: First step as a fraction of the run when no dt is given (None: IDAS chooses).
    first_step_fraction: float | None = None

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, max_step: float | None = None,
                 **options):
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        # redundant rows: the DAE takes the independent subset (its algebraic equations would
        # be singular with all of them); the run's multipliers are the minimum-norm ones
        if self.model.n_constraints == 0:
            raise InputError(f"method '{self.name}' is for constrained systems; this one has none")
        self.max_step = max_step

    def dae(self):
        raise NotImplementedError

    def algebraic_guess(self, x, v, t):
        raise NotImplementedError

    def run(self, x0, v0, t0, t_end, t_eval=None) -> Solution:
        m = self.model
        n3 = m.n_coordinates
        dae, nz = self.dae()
        grid = np.asarray(t_eval, float) if t_eval is not None else np.linspace(t0, t_end, 201)
        grid = grid[grid > t0]
        opts = {"abstol": self.atol, "reltol": self.rtol, "max_num_steps": 1_000_000,
                "calc_ic": True, "print_stats": False}
        step0 = self.dt or (self.first_step_fraction * (t_end - t0) if self.first_step_fraction else None)
        if step0:
            opts["step0"] = step0
        if self.max_step:
            opts["max_step_size"] = self.max_step
        opts.update(self.extra_options())
        ts, xs, vs = [], [], []
        if t_eval is None or (len(t_eval) and t_eval[0] == t0):
            ts.append(t0)
            xs.append(x0)
            vs.append(v0)
        state = np.concatenate([x0, v0])
        z = self.algebraic_guess(x0, v0, t0)
        failure = None
        t_prev = t0
        segments = [grid] if not self.project_outputs else [[tk] for tk in grid]
        for seg in segments:
            a_prev, _ = self.manifold.accelerations(state[:n3], state[n3:], t_prev)
            opts["init_xdot"] = np.concatenate([state[n3:], a_prev]).tolist()
            integ = ca.integrator("dae", "idas", dae, t_prev, list(seg), opts)
            try:
                res = integ(x0=state, z0=z)
            except RuntimeError as exc:
                failure = f"IDAS stopped after t = {t_prev:.6g} s ({str(exc).splitlines()[-1][:200]})"
                break
            except KeyboardInterrupt:
                failure = f"interrupted at t = {t_prev:.6g} s"
                break
            stats = integ.stats()
            for key, skey in (("steps", "nsteps"), ("nfev", "nfevals"), ("nlu", "nlinsetups"),
                              ("rejected", "netfails")):
                self.stats[key] = self.stats.get(key, 0) + int(stats.get(skey, 0))
            X = res["xf"].full()
            Z = res["zf"].full()
            for k, tk in enumerate(seg):
                x, v = X[:n3, k], X[n3:, k]
                if self.project_outputs:
                    x = self.manifold.project_positions(x, tk, tol=1e-14 * max(1.0, np.max(np.abs(x)))).x
                    v = self.manifold.project_velocities(x, v, tk)
                    self.manifold.counters.projections += 1
                ts.append(tk)
                xs.append(x)
                vs.append(v)
            self.report(seg[-1])
            state = np.concatenate([xs[-1], vs[-1]])
            z = Z[:, -1] if not self.project_outputs else self.algebraic_guess(xs[-1], vs[-1], seg[-1])
            t_prev = seg[-1]
        return Solution(np.array(ts), np.array(xs).reshape(-1, n3), np.array(vs).reshape(-1, n3),
                        self.counted(), failure)

    def extra_options(self) -> dict:
        return {}


class Idas(_IdasBase):
    name = "idas"
    OPTIONS = ("max_step", "project_outputs")
    project_outputs = True

    def __init__(self, manifold, *, project_outputs: bool = True, **kwargs):
        super().__init__(manifold, **kwargs)
        self.project_outputs = bool(project_outputs)

    def dae(self):
        m = self.model
        n3, C = m.n_coordinates, len(self.rows)
        x, v, t = ca.SX.sym("x", n3), ca.SX.sym("v", n3), ca.SX.sym("t")
        lam = ca.SX.sym("lam", C)
        minv = ca.DM(m.inverse_masses)
        F, J, gamma = m.dynamics(x, v, t)
        J, gamma = J[self.rows, :], gamma[self.rows]
        a = minv * (F + ca.mtimes(J.T, lam))
        dae = {"x": ca.vertcat(x, v), "z": lam, "t": t, "ode": ca.vertcat(v, a),
               "alg": ca.mtimes(J, a) + gamma}
        return dae, C

    def algebraic_guess(self, x, v, t):
        return self.manifold.accelerations(x, v, t)[1][self.rows]


class GGL(_IdasBase):
    name = "ggl"
    #: IDAS picks a first step from the tolerances; at tight ones it is so small that the
    #: index-2 Newton matrix (conditioned like 1/h²) defeats the corrector at t = 0
    #: (atol < 1e-10 failed on the double pendulum). A first step of 1e-5 of the run avoids it.
    first_step_fraction = 1e-5

    def dae(self):
        m = self.model
        n3, C = m.n_coordinates, len(self.rows)
        x, v, t = ca.SX.sym("x", n3), ca.SX.sym("v", n3), ca.SX.sym("t")
        lam, mu = ca.SX.sym("lam", C), ca.SX.sym("mu", C)
        minv = ca.DM(m.inverse_masses)
        F, J, _ = m.dynamics(x, v, t)
        _, f_t = m.velocity_terms(x, t)
        f = m.constraint(x, t)
        J, f_t, f = J[self.rows, :], f_t[self.rows], f[self.rows]
        dae = {"x": ca.vertcat(x, v), "z": ca.vertcat(lam, mu), "t": t,
               "ode": ca.vertcat(v + minv * ca.mtimes(J.T, mu), minv * (F + ca.mtimes(J.T, lam))),
               "alg": ca.vertcat(f, ca.mtimes(J, v) + f_t)}
        return dae, 2 * C

    def algebraic_guess(self, x, v, t):
        return np.concatenate([self.manifold.accelerations(x, v, t)[1][self.rows], np.zeros(len(self.rows))])

    def extra_options(self) -> dict:
        return {"suppress_algebraic": True, "calc_ic": False}
