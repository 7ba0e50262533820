"""Index-1 ODE with coordinate projection after every accepted step.

The state (x, v) follows x' = v, v' = a(x, v, t) with a from the KKT system. After each
accepted step of an embedded Runge–Kutta method (SciPy's DOP853 by default, error
controlled by rtol/atol) the state is projected, mass-weighted, onto f(x, t) = 0 (Newton)
and then onto J v + f_t = 0 (linear). Output times inside a step are taken from the
step's dense output and projected the same way, so every sample lies on both manifolds.
"""

from __future__ import annotations

import numpy as np

from .. import interrupt
from ..codegen import compiled as compiled_evaluation
from ..codegen.fast_call import FastCall
from ..errors import InputError
from ..manifold import residual
from ..manifold.graph import acceleration_graph
from ..manifold.manifold import Manifold
from ..model.cache import per_model_cache
from .base import DRIVER_OPTIONS, Advance, Status
from .driver import Stepper
from .sundials.messages import quiet

#: "CVODES" is Adams with functional iteration (non-stiff, cheapest per step); "CVODES_BDF"
#: is BDF with Newton iteration, for stiff scenes (springs with k/m = 1e8 beside constraints).
#: The bases: SciPy's integrators by class name (imported when a run uses one), or CVODES.
BASES = {"DOP853": "DOP853", "RK45": "RK45", "Radau": "Radau", "CVODES": None, "CVODES_BDF": None}
#: Explicit bases, whose accepted steps are watched for stiffness (StiffnessWarning).
EXPLICIT = ("DOP853", "RK45")
#: A projection that leaves |f| above this (× system size) means Newton failed: the run stops.
PROJECTION_FAIL = 1e-8
#: This many accepted steps in a row below 1e-14 of the run stop it (a collapsed step size).
COLLAPSED_STEPS = 100


class _NonFinite(Exception):
    pass


class _ProjectionFailed(Exception):
    pass


class Projection(Stepper):
    name = "projection"
    OPTIONS = ("base", *DRIVER_OPTIONS)
    BASES = tuple(BASES)
    #: Whether accepted steps and outputs are projected onto the constraint manifolds.
    projecting = True
    lands = False  # SciPy's integrators stop at their t_bound only: outputs are dense
    refines_events = False  # SciPy's interpolant is the method's solution between steps

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, base: str = "DOP853",
                 right_hand_side=None, project: bool = True, **options):
        """``right_hand_side(t, y) -> y'`` replaces the KKT acceleration and ``project=False``
        turns the projections off: how another method (Baumgarte) runs this step loop on its
        own equations (programmatic only, not scene options)."""
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        self._right_hand_side = right_hand_side
        self.projecting = bool(project)
        if base not in BASES:
            raise InputError(f"unknown base integrator {base!r} (choose from {', '.join(BASES)})")
        self.base = base
        self.order = {"DOP853": 8, "RK45": 5, "Radau": 5}.get(base)
        self.explicit = base in EXPLICIT
        # The per-call functions gain ~1.3x from machine code (docs/performance.md), while the
        # C compiler's time grows steeply with the model (13 s at 200 particles, 98 s at 1000):
        # compiled only when asked for (compiled=True), never under "auto".
        if self.compiled_setting is True and compiled_evaluation.enabled(True):
            self.manifold = Manifold(self.model, rows=self.manifold.rows, policy=self.manifold.policy,
                                     compiled=True)
        # built here, so its cost is setup (stats["setup_time_s"]), not the run
        self._integrator = self._cvodes_integrator() if base.startswith("CVODES") else None
        if self._integrator is not None:
            self.lands = self.refines_events = True
        self.scale = None

    def derivative(self, t, y):
        """(x', v') = (v, a(x, v, t)) with a from the KKT system."""
        if self._right_hand_side is not None:
            return self._right_hand_side(t, y)
        return super().derivative(t, y)

    def stiffness_advice(self) -> tuple[str, str]:
        return f"the explicit base {self.base}", 'use base = "Radau" or base = "CVODES_BDF"'

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

    def output(self, t, x, v):
        """A dense-output sample, projected onto both manifolds like the steps."""
        try:
            return self.project(x, v, t)
        except _ProjectionFailed:
            return np.full_like(x, np.nan), np.full_like(v, np.nan)

    def default_grid(self, t0, t_end):
        if self._integrator is not None:  # CVODES: projected at these times
            return np.linspace(t0, t_end, self.CVODES_SEGMENTS + 1)
        return None

    def _rhs(self, t, y):
        dy = self.derivative(t, y)
        self.stats["nfev"] += 1
        if not np.all(np.isfinite(dy)):
            raise _NonFinite(t)
        return dy

    def init(self, x0, v0, t0, t_end, first_step=None):
        if self.scale is None:  # the run's scales, from its start (not a restart's)
            self.scale = max(float(np.max(np.abs(x0), initial=0.0)), 1.0)
            # tolerances are in metres: |f| ≤ tol × (smallest row scale) keeps every row within tol
            self.row_scale = residual.smallest_scale(self.model, x0, t0)
            self.position_tol = 1e-14 * self.scale * self.row_scale
        y0 = np.concatenate([x0, v0])
        if self._integrator is not None:
            return (float(t0), y0)
        self._tiny = 0
        self._span = t_end - t0
        first_step = first_step or self.dt
        import scipy.integrate  # (0.1 s of imports, for this method only)

        integrator = getattr(scipy.integrate, BASES[self.base])
        return integrator(self._rhs, t0, y0, t_end, rtol=self.rtol, atol=self.atol,
                          first_step=min(first_step, t_end - t0) if first_step else None)

    def _stopped(self, integ, status, text, t_good, y_good) -> Advance:
        """The failed call's Advance: ``text`` and the likely cause from the last good state."""
        n = self.model.n_coordinates
        return Advance.empty(integ, n, status, text + self.diagnose(y_good[:n], y_good[n:], t_good))

    def step(self, integ, t_stop) -> Advance:
        if self._integrator is not None:
            return self._cvodes_step(integ, t_stop)
        n = self.model.n_coordinates
        t_good, y_good = integ.t, integ.y.copy()
        try:
            message = integ.step()
        except _NonFinite as exc:
            return self._stopped(integ, Status.NON_FINITE,
                                 f"non-finite accelerations at t = {exc.args[0]:.6g} s; ", t_good, y_good)
        if integ.status == "failed":
            why = f"the step size collapsed at t = {integ.t:.6g} s ({message}); "
            return self._stopped(integ, Status.STEP_SIZE_COLLAPSED, why, t_good, y_good)
        self.stats["steps"] += 1
        # SciPy only stops at h < 10 eps |t|, which near t = 0 is no limit at all: steps
        # below 1e-14 of the run, many in a row, are a collapse too
        small = (integ.step_size or 0.0) < 1e-14 * max(self._span, abs(integ.t))
        self._tiny = self._tiny + 1 if small else 0
        if self._tiny > COLLAPSED_STEPS:
            why = (f"the step size collapsed at t = {integ.t:.6g} s (h = {integ.step_size:.3g} s "
                   f"for {self._tiny} steps); ")
            return self._stopped(integ, Status.STEP_SIZE_COLLAPSED, why, t_good, y_good)
        dense = []  # built on first use (DOP853's costs three more evaluations), before the next step

        def interpolant(t):
            if not dense:
                dense.append(integ.dense_output())
            y = dense[0](t)
            return y[:n], y[n:]

        y = integ.y
        if self.projecting:
            try:
                x, v = self.project(y[:n], y[n:], integ.t)
            except _ProjectionFailed as exc:
                return self._stopped(integ, Status.PROJECTION_FAILED,
                                     f"the state could not be brought back onto the constraints at "
                                     f"t = {integ.t:.6g} s (residual {exc.args[1]:.3g} m after Newton); ",
                                     t_good, y_good)
            y = np.concatenate([x, v])
            if not np.all(np.isfinite(y)):
                return self._stopped(integ, Status.NON_FINITE,
                                     f"non-finite state after projection at t = {integ.t:.6g} s; ",
                                     t_good, y_good)
            integ.y = y
            if hasattr(integ, "f"):  # keep first-same-as-last consistent with the new state
                integ.f = self._rhs(integ.t, y)
        return Advance(integ, np.array([integ.t]), y[None, :n].copy(), y[None, n:].copy(),
                       interpolant=interpolant, h=integ.step_size)

    def finish(self) -> None:
        self.stats["evaluation"] = self.manifold.evaluation

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
        cache["projection_cvodes"] = (settings, (integ, FastCall(integ), integ.name_in()))
        return cache["projection_cvodes"][1]

    def _cvodes_step(self, state, t_b) -> Advance:
        """One CVODES call (Adams, or BDF with Newton for base CVODES_BDF; no Python per
        evaluation) from the last output time to the next, projected there onto both manifolds."""
        n = self.model.n_coordinates
        t_a, y = state
        integ, call, names = self._integrator
        inputs = {"x0": y, "p": (t_a, t_b - t_a)}
        try:
            with interrupt.external(), quiet():
                yb = call(*(inputs.get(name, ()) for name in names))[0]
        except KeyboardInterrupt:
            raise
        except RuntimeError as exc:
            if self.stop_requested():  # Ctrl-C inside CVODES: its right-hand side "failed"
                raise KeyboardInterrupt from None
            why = f"CVODES stopped after t = {t_a:.6g} s ({str(exc).splitlines()[-1][:200]}); "
            return self._stopped(state, Status.SOLVER_FAILED, why, t_a, y)
        stats = call.stats()
        self.stats["steps"] += int(stats.get("nsteps", 0))
        self.stats["nfev"] += int(stats.get("nfevals", 0))
        try:
            x, v = self.project(yb[:n], yb[n:], t_b)
        except _ProjectionFailed as exc:
            why = (f"the state could not be brought back onto the constraints at t = {t_b:.6g} s "
                   f"(residual {exc.args[1]:.3g}); ")
            return self._stopped(state, Status.PROJECTION_FAILED, why, t_a, y)
        return Advance((t_b, np.concatenate([x, v])), np.array([t_b]), x[None], v[None])
