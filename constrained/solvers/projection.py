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
from .. import diagnostics, interrupt, residual
from ..errors import InputError
from ..manifold import Manifold, acceleration_graph, per_model_cache
from .base import Failure, Solution, Solver, Status

#: "CVODES" is Adams with functional iteration (non-stiff, cheapest per step); "CVODES_BDF"
#: is BDF with Newton iteration, for stiff scenes (springs with k/m = 1e8 beside constraints).
BASES = {"DOP853": DOP853, "RK45": RK45, "Radau": Radau, "CVODES": None, "CVODES_BDF": None}
#: Explicit bases, whose accepted steps are watched for stiffness (StiffnessWarning).
EXPLICIT = ("DOP853", "RK45")
#: The stiffness check estimates ρ(∂f/∂y) every this many accepted steps (the verdict:
#: diagnostics.stiffness_verdict).
STIFFNESS_EVERY = diagnostics.STIFFNESS_EVERY
#: A projection that leaves |f| above this (× system size) means Newton failed: the run stops.
PROJECTION_FAIL = 1e-8
#: The run stops at a singular configuration when the rank-th singular value of the
#: row-normalized J (rank: at the start) falls below ``singular_tol`` (default below); watched
#: after every accepted step for models up to SINGULAR_WATCH_MAX coordinates.
SINGULAR_TOL = 1e-4
SINGULAR_WATCH_MAX = 300
#: This many accepted steps in a row below 1e-14 of the run stop it (a collapsed step size).
COLLAPSED_STEPS = 100



class _NonFinite(Exception):
    pass


class _ProjectionFailed(Exception):
    pass


class Projection(Solver):
    name = "projection"
    OPTIONS = ("base", "singular_tol")
    BASES = tuple(BASES)
    #: Whether accepted steps and outputs are projected onto the constraint manifolds.
    projecting = True

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, base: str = "DOP853",
                 singular_tol: float | None = SINGULAR_TOL, right_hand_side=None, project: bool = True,
                 **options):
        """``right_hand_side(t, y) -> y'`` replaces the KKT acceleration and ``project=False``
        turns the projections off: how another method (Baumgarte) runs this step loop on its
        own equations (programmatic only, not scene options)."""
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        self._right_hand_side = right_hand_side
        self.projecting = bool(project)
        if singular_tol is not None and not (isinstance(singular_tol, int | float) and 0 <= singular_tol < 1):
            raise InputError(f"singular_tol must be a number in [0, 1) or None, got {singular_tol!r}")
        self.singular_tol = singular_tol
        if base not in BASES:
            raise InputError(f"unknown base integrator {base!r} (choose from {', '.join(BASES)})")
        self.base = base
        self.order = {"DOP853": 8, "RK45": 5, "Radau": 5}.get(base)
        # The per-call functions gain ~1.3x from machine code (docs/performance.md), while the
        # C compiler's time grows steeply with the model (13 s at 200 particles, 98 s at 1000):
        # compiled only when asked for (compiled=True), never under "auto".
        if self.compiled_setting is True and compiled_evaluation.enabled(True):
            self.manifold = Manifold(self.model, rows=self.manifold.rows, policy=self.manifold.policy,
                                     compiled=True)
        # built here, so its cost is setup (stats["setup_time_s"]), not the run
        self._integrator = self._cvodes_integrator() if base.startswith("CVODES") else None

    def derivative(self, t, y):
        """(x', v') = (v, a(x, v, t)) with a from the KKT system."""
        if self._right_hand_side is not None:
            return self._right_hand_side(t, y)
        n = self.model.n_coordinates
        a, _ = self.manifold.accelerations(y[:n], y[n:], t)
        return np.concatenate([y[n:], a])

    def project(self, x, v, t):
        if not self.projecting:
            return x, v
        m = self.manifold
        projected = m.project_positions(x, t, tol=self.position_tol)
        x, err = projected.x, projected.residual
        # err is max |f|; in metres every row |f_i| / s_i ≤ err / s_min (constrained.residual),
        # and where that bound is too coarse the residual is measured in metres
        if np.isfinite(err):
            err = err / self.row_scale
            if err > PROJECTION_FAIL * self.scale:
                err = residual.position_residual(self.model, x, t)
        if not np.isfinite(err) or err > PROJECTION_FAIL * self.scale:
            raise _ProjectionFailed(t, err)
        v = m.project_velocities(x, v, t)
        m.counters.projections += 1
        return x, v

    def _watch_rank(self, x0, t0) -> int:
        """The rank to watch (that of J at the start), or 0 when the watch is off."""
        m = self.model
        if not self.singular_tol or not m.n_constraints or m.n_coordinates > SINGULAR_WATCH_MAX:
            return 0
        return len(self.rows)

    def diagnose(self, x, v, t) -> str:
        """The likely cause of a stop, from the last good state (x, v, t)."""
        return diagnostics.likely_cause(self.model, x, v, t, self.manifold)

    def run(self, x0, v0, t0, t_end, t_eval=None) -> Solution:
        self.scale = max(float(np.max(np.abs(x0), initial=0.0)), 1.0)
        # tolerances are in metres: |f| ≤ tol × (smallest row scale) keeps every row within tol
        self.row_scale = residual.smallest_scale(self.model, x0, t0)
        if self.base.startswith("CVODES"):
            return self._run_cvodes(x0, v0, t0, t_end, t_eval)
        m = self.model
        n = m.n_coordinates
        scale = self.scale
        self.position_tol = 1e-14 * scale * self.row_scale

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
        good = (t0, x0, v0)  # the last accepted, projected state
        watch_rank = self._watch_rank(x0, t0)
        watch = self.base in EXPLICIT
        h_rho, rho_max, tiny = [], 0.0, 0
        self.watch_stiffness(x0, t0, t_end)
        while integ.status == "running":
            if self.stop_requested():
                failure = self.interrupted_at(good[0])
                break
            failure = self.too_stiff(good[0], self.stats["steps"], good[1])
            if failure:
                break
            try:
                message = integ.step()
            except _NonFinite as exc:
                failure = Failure(Status.NON_FINITE, (f"non-finite accelerations at t = {exc.args[0]:.6g} s; "
                           + diagnostics.nonfinite_cause(m, *good[1:], good[0])))
                break
            except KeyboardInterrupt:
                failure = self.interrupted_at(good[0])
                break
            if integ.status == "failed":
                failure = Failure(Status.STEP_SIZE_COLLAPSED,
                    (f"the step size collapsed at t = {integ.t:.6g} s ({message}); "
                           + self.diagnose(*good[1:], good[0])))
                break
            self.stats["steps"] += 1
            self.report(integ.t)
            # SciPy only stops at h < 10 eps |t|, which near t = 0 is no limit at all: steps
            # below 1e-14 of the run, many in a row, are a collapse too
            tiny = tiny + 1 if (integ.step_size or 0.0) < 1e-14 * max(t_end - t0, abs(integ.t)) else 0
            if tiny > COLLAPSED_STEPS:
                failure = Failure(Status.STEP_SIZE_COLLAPSED,
                    (f"the step size collapsed at t = {integ.t:.6g} s (h = {integ.step_size:.3g} s "
                           f"for {tiny} steps); " + diagnostics.nonfinite_cause(m, *good[1:], good[0])))
                break
            if watch and self.stats["steps"] % STIFFNESS_EVERY == 0 and integ.step_size:
                rho = diagnostics.spectral_radius(self.derivative, integ.t, integ.y)
                rho_max = max(rho_max, rho)
                h_rho.append(integ.step_size * rho)
            if pending is not None and pending and pending[0] <= integ.t:
                dense = integ.dense_output()
                while pending and pending[0] <= integ.t:
                    tk = pending.pop(0)
                    yk = dense(tk)
                    try:
                        xk, vk = self.project(yk[:n], yk[n:], tk)
                    except _ProjectionFailed as exc:
                        failure = Failure(Status.PROJECTION_FAILED,
                            (f"the state could not be brought back onto the constraints at "
                                   f"t = {tk:.6g} s (residual {exc.args[1]:.3g} m after Newton); "
                                   + self.diagnose(*good[1:], good[0])))
                        break
                    ts.append(tk)
                    ys.append(np.concatenate([xk, vk]))
                if failure:
                    break
            y = integ.y
            if self.projecting:
                try:
                    x, v = self.project(integ.y[:n], integ.y[n:], integ.t)
                except _ProjectionFailed as exc:
                    failure = Failure(Status.PROJECTION_FAILED,
                        (f"the state could not be brought back onto the constraints at "
                               f"t = {integ.t:.6g} s (residual {exc.args[1]:.3g} m after Newton); "
                               + self.diagnose(*good[1:], good[0])))
                    break
                y = np.concatenate([x, v])
                if not np.all(np.isfinite(y)):
                    failure = Failure(Status.NON_FINITE,
                        (f"non-finite state after projection at t = {integ.t:.6g} s; "
                               + self.diagnose(*good[1:], good[0])))
                    break
                integ.y = y
                if hasattr(integ, "f"):  # keep first-same-as-last consistent with the new state
                    integ.f = rhs(integ.t, y)
            if watch_rank:
                sigma = diagnostics.rank_sigma(m, y[:n], integ.t, watch_rank)
                if sigma < self.singular_tol:
                    failure = Failure(Status.SINGULAR_CONFIGURATION,
                        (f"singular configuration reached at t = {integ.t:.6g} s; likely cause: "
                               + diagnostics.singularity(m, y[:n], integ.t, rank=watch_rank).describe()))
                    if pending is None:
                        ts.append(integ.t)
                        ys.append(y)
                    break
            good = (integ.t, y[:n].copy(), y[n:].copy())
            if pending is None:
                ts.append(integ.t)
                ys.append(y)
        if watch and getattr(failure, "status", None) is not Status.STIFF:  # (that stop says it)
            self._stiffness_verdict(h_rho, rho_max)
        self.stats["evaluation"] = self.manifold.evaluation
        Y = np.array(ys).reshape(-1, 2 * n)
        return Solution(np.array(ts), Y[:, :n], Y[:, n:], self.counted(), failure)

    def _stiffness_verdict(self, h_rho, rho_max) -> None:
        diagnostics.stiffness_verdict(
            self.stats, h_rho, rho_max, what=f"the explicit base {self.base}",
            advice='use base = "Radau" or base = "CVODES_BDF"' + self.stiff_hint())

    # --- CVODES base: CasADi integrates between projection points --------------------------
    #: Without t_eval, the state is projected this many times over the run.
    CVODES_SEGMENTS = 100

    def _cvodes_integrator(self):
        """The CVODES integrator of this model and setting, built once and kept on the model
        (building it forms the right-hand side's Jacobian: seconds for large models)."""
        import casadi as ca

        m = self.model
        n = m.n_coordinates
        # only the latest setting is kept: one integrator can hold hundreds of MB
        settings = (self.base, self.rtol, self.atol, self.manifold.rows)
        cache = per_model_cache(m)
        cached = cache.get("projection_cvodes")
        if cached is not None and cached[0] == settings:
            return cached[1]
        # one integrator for every segment: τ ∈ [0, 1], t = t_a + Δ τ, d/dτ = Δ d/dt
        y, tau, p = ca.MX.sym("y", 2 * n), ca.MX.sym("tau"), ca.MX.sym("p", 2)
        a, _ = acceleration_graph(m, y[:n], y[n:], p[0] + p[1] * tau,
                                  rows=self.manifold.rows)
        ode = p[1] * ca.vertcat(y[n:], a)
        bdf = self.base == "CVODES_BDF"
        options = {
            "abstol": self.atol, "reltol": self.rtol, "max_num_steps": 10_000_000,
            "linear_multistep_method": "bdf" if bdf else "adams",
            "nonlinear_solver_iteration": "newton" if bdf else "functional",
        }
        if not bdf:
            # Functional iteration never solves with the Jacobian, but CasADi still builds one
            # for the default direct scheme (dense here: 3.6 s at 128 links); the Krylov scheme
            # only needs Jacobian-vector products, about half the construction time.
            options["newton_scheme"] = "gmres"
        integ = ca.integrator("segment", "cvodes", {"x": y, "p": p, "t": tau, "ode": ode}, 0.0, 1.0,
                              options)
        cache["projection_cvodes"] = (settings, integ)
        return integ

    def _run_cvodes(self, x0, v0, t0, t_end, t_eval) -> Solution:
        """Integrate with CasADi's CVODES (Adams, or BDF with Newton for base CVODES_BDF; no Python
        per evaluation) from one output time to the next, projecting onto both manifolds at each
        of them."""

        m = self.model
        n = m.n_coordinates
        scale = self.scale
        self.position_tol = 1e-14 * scale * self.row_scale
        grid = (np.asarray(t_eval, float) if t_eval is not None
                else np.linspace(t0, t_end, self.CVODES_SEGMENTS + 1))
        integ = self._integrator
        ts, xs, vs = [], [], []
        if grid[0] <= t0:
            ts.append(t0)
            xs.append(x0)
            vs.append(v0)
            grid = grid[1:]
        state, t_a, failure = np.concatenate([x0, v0]), t0, None
        self.watch_stiffness(x0, t0, t_end)
        for t_b in grid:
            if self.stop_requested():
                failure = self.interrupted_at(t_a)
                break
            failure = self.too_stiff(t_a, self.stats["steps"], state[:n])
            if failure:
                break
            try:
                with interrupt.external():
                    out = integ(x0=state, p=[t_a, t_b - t_a])
            except KeyboardInterrupt:
                failure = self.interrupted_at(t_a)
                break
            except RuntimeError as exc:
                if self.stop_requested():  # Ctrl-C inside CVODES: its right-hand side "failed"
                    failure = self.interrupted_at(t_a)
                    break
                failure = Failure(Status.SOLVER_FAILED,
                    (f"CVODES stopped after t = {t_a:.6g} s ({str(exc).splitlines()[-1][:200]}); "
                           + self.diagnose(state[:n], state[n:], t_a)))
                break
            stats = integ.stats()
            self.stats["steps"] += int(stats.get("nsteps", 0))
            self.stats["nfev"] += int(stats.get("nfevals", 0))
            yb = out["xf"].full().ravel()
            try:
                x, v = self.project(yb[:n], yb[n:], t_b)
            except _ProjectionFailed as exc:
                failure = Failure(Status.PROJECTION_FAILED,
                    (f"the state could not be brought back onto the constraints at t = {t_b:.6g} s "
                           f"(residual {exc.args[1]:.3g}); " + self.diagnose(state[:n], state[n:], t_a)))
                break
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
                failure = Failure(Status.NON_FINITE,
                    f"non-finite state at t = {t_b:.6g} s; " + self.diagnose(state[:n], state[n:], t_a))
                break
            ts.append(t_b)
            xs.append(x)
            vs.append(v)
            state, t_a = np.concatenate([x, v]), t_b
            self.report(t_b)
        self.stats["evaluation"] = self.manifold.evaluation
        return Solution(np.array(ts), np.array(xs).reshape(-1, n), np.array(vs).reshape(-1, n),
                        self.counted(), failure)
