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

from collections import deque

import casadi as ca
import numpy as np

from .. import interrupt, residual
from ..errors import InputError
from .base import Failure, Solution, Solver, Status

#: Output times integrated per IDAS call by pantelides: every restart builds an integrator and
#: takes tiny first steps again (2.4x slower at 10 than in one call), while Ctrl-C reaches inside
#: a call anyway (``interrupt.external``); 100 keeps a long run stoppable between calls too.
SEGMENT_OUTPUTS = 100
#: Steps one IDAS call may take; a call that needs more is split into SPLIT parts.
STEPS_PER_CALL = 20_000
SPLIT = 10
#: Factors on the first step tried when a restarted call fails at once (see ``run``).
RESTART_STEPS = (1e-2, 1e2, 1e-4)
#: IDAS failures that a stiff spring explains.
STIFF_FAILURES = ("TOO_MUCH_WORK", "CONV_FAIL", "ERR_FAIL", "TOO_CLOSE")


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
        # constraint rows divided by their scale at the start (constrained.residual), so IDAS
        # sees the same equations and multipliers (in N) whatever scale a formula is written in
        self.row_scales = residual.row_scales(m, x0, t0)
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
        # one IDAS call per output time (idas, projecting there) or per group of them (ggl):
        # Ctrl-C is honoured between calls, and inside one it loses only that call's part.
        # A call that runs out of steps (STEPS_PER_CALL) is split at intermediate times (not
        # outputs), so wall time is watched between calls and a stiff spring is named.
        # ggl's index-2 corrector restarts badly at tight tolerances (a tiny first step, a
        # 1/h² Newton matrix): one call for the whole grid, split only by the pace watch below
        per_call = 1 if self.project_outputs else max(len(grid), 1)
        queue = deque([(tk, True) for tk in grid[k:k + per_call]] for k in range(0, len(grid), per_call))
        opts["max_num_steps"] = STEPS_PER_CALL
        self.watch_stiffness(x0, t0, t_end)
        scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
        # projection tolerances in metres (constrained.residual): |f| ≤ tol × smallest row scale
        tol_f = 1e-14 * residual.smallest_scale(m, x0, t0)
        retries, pace = list(RESTART_STEPS), 0.0
        while queue:
            seg = queue.popleft()
            if self.stop_requested():
                failure = self.interrupted_at(t_prev)
                break
            failure = self.too_stiff(t_prev, self.stats["steps"], state[:n3])
            if failure:
                break
            times = [tk for tk, _ in seg]
            pieces = int(np.ceil(pace * (times[-1] - t_prev) / (STEPS_PER_CALL // 2)))
            if pieces > 1:  # at the pace so far this call would run out of steps: split it first
                inner = [(tk, False) for tk in np.linspace(t_prev, times[0], pieces + 1)[1:-1]]
                if inner:
                    queue.extendleft(reversed([[item] for item in inner] + [seg]))
                    continue
            a_prev, _ = self.manifold.accelerations(state[:n3], state[n3:], t_prev)
            opts["init_xdot"] = np.concatenate([state[n3:], a_prev]).tolist()
            integ = ca.integrator("dae", "idas", dae, t_prev, times, opts)
            try:
                with interrupt.external():
                    res = integ(x0=state, z0=z)
            except KeyboardInterrupt:
                failure = self.interrupted_at(t_prev)
                break
            except RuntimeError as exc:
                if self.stop_requested():
                    failure = self.interrupted_at(t_prev)
                    break
                reason = str(exc).splitlines()[-1][:200]
                span = times[0] - t_prev
                if step0 and t_prev > t0 and "CONV_FAIL" in reason and retries:
                    # ggl's index-2 corrector can fail on a restart's first step: the next
                    # first step in RESTART_STEPS usually passes
                    opts["step0"] = step0 * retries.pop(0)
                    queue.appendleft(seg)
                    continue
                if "TOO_MUCH_WORK" in reason and span > 1e-9 * max(abs(t_end - t0), 1e-300):
                    inner = [(tk, False) for tk in np.linspace(t_prev, times[0], SPLIT + 1)[1:-1]]
                    queue.extendleft(reversed([[item] for item in inner] + [seg]))
                    continue
                failure = Failure(Status.SOLVER_FAILED, f"IDAS stopped after t = {t_prev:.6g} s ({reason})")
                element = self._stiffness.fastest(state[:n3], t_prev) if self._stiffness else None
                if element is not None and any(k in reason for k in STIFF_FAILURES):
                    failure += "; " + self._stiffness.describe(element, t_prev, self.stats["steps"])
                break
            if step0:
                opts["step0"], retries = step0, list(RESTART_STEPS)
            stats = integ.stats()
            pace = int(stats.get("nsteps", 0)) / max(times[-1] - t_prev, 1e-300)  # steps per second
            for key, skey in (("steps", "nsteps"), ("nfev", "nfevals"), ("nlu", "nlinsetups"),
                              ("rejected", "netfails")):
                self.stats[key] = self.stats.get(key, 0) + int(stats.get(skey, 0))
            X = res["xf"].full()
            for k, (tk, output) in enumerate(seg):
                x, v = X[:n3, k], X[n3:, k]
                if self.project_outputs:
                    x = self.manifold.project_positions(x, tk, tol=tol_f * max(scale, np.max(np.abs(x)))).x
                    v = self.manifold.project_velocities(x, v, tk)
                    self.manifold.counters.projections += 1
                if output:
                    ts.append(tk)
                    xs.append(x)
                    vs.append(v)
            t_prev = times[-1]
            self.report(t_prev)
            if not self.project_outputs and queue:
                # the next call restarts IDAS, whose index-2 corrector (ggl) needs a start on
                # both constraint levels to round-off: the restart point is projected
                x = self.manifold.project_positions(x, t_prev, tol=tol_f * max(scale, np.max(np.abs(x)))).x
                v = self.manifold.project_velocities(x, v, t_prev)
            state = np.concatenate([x, v])
            z = self.algebraic_guess(x, v, t_prev)
        if failure and t_eval is None and t_prev > (ts[-1] if ts else -np.inf):
            ts.append(t_prev)  # the state reached between two outputs is kept
            xs.append(state[:n3])
            vs.append(state[n3:])
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
        w = ca.DM(1.0 / self.row_scales[self.rows])
        J, gamma = ca.mtimes(ca.diag(w), J[self.rows, :]), w * gamma[self.rows]  # rows in metres
        a = minv * (F + ca.mtimes(J.T, lam))
        dae = {"x": ca.vertcat(x, v), "z": lam, "t": t, "ode": ca.vertcat(v, a),
               "alg": ca.mtimes(J, a) + gamma}
        return dae, C

    def algebraic_guess(self, x, v, t):
        return (self.manifold.accelerations(x, v, t)[1] * self.row_scales)[self.rows]


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
        w = ca.DM(1.0 / self.row_scales[self.rows])  # rows in metres (see run)
        J, f_t, f = ca.mtimes(ca.diag(w), J[self.rows, :]), w * f_t[self.rows], w * f[self.rows]
        dae = {"x": ca.vertcat(x, v), "z": ca.vertcat(lam, mu), "t": t,
               "ode": ca.vertcat(v + minv * ca.mtimes(J.T, mu), minv * (F + ca.mtimes(J.T, lam))),
               "alg": ca.vertcat(f, ca.mtimes(J, v) + f_t)}
        return dae, 2 * C

    def algebraic_guess(self, x, v, t):
        return np.concatenate([(self.manifold.accelerations(x, v, t)[1] * self.row_scales)[self.rows],
                               np.zeros(len(self.rows))])

    def extra_options(self) -> dict:
        return {"suppress_algebraic": True, "calc_ic": False}
