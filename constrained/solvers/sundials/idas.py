"""DAE methods through CasADi's IDAS (SUNDIALS' variable-order BDF for DAEs).

``idas``: the index-1 form, differential x, v and algebraic λ:

    x' = v,   v' = M⁻¹ (F + Jᵀλ),   0 = J M⁻¹ (F + Jᵀλ) + γ

Position and velocity constraints are only implied, so they drift slowly; by default every
output is projected onto both manifolds (``project_outputs``), and each IDAS call continues
from its projected end. A call covers more output times while the state it ends in stays
within atol of the constraints, fewer when it drifts further.

``ggl``: the Gear–Gupta–Leimkuhler stabilized index-2 form, with a second multiplier μ:

    x' = v + M⁻¹Jᵀμ,   v' = M⁻¹ (F + Jᵀλ),   0 = f(x, t),   0 = J v + f_t

Both constraint levels hold exactly along the solution (μ = 0 there), so there is no
drift. The algebraic variables are left out of the error test, as index-2 problems need, and
out of the corrector's convergence test, where their round-off grows like 1/h (``GGL``).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

import casadi as ca
import numpy as np

from ... import interrupt
from ...errors import InputError
from ...manifold import residual
from ...manifold.manifold import constraint_values
from ...model.cache import ParametricView, structure_cache
from ..base import DRIVER_OPTIONS, Advance, Status
from ..driver import Stepper
from .messages import quiet, tolerance_cause

#: One SUNDIALS call covers this many output times at first (ggl, pantelides: every restart
#: builds an integrator and takes tiny first steps again, 2.4x slower at 10 outputs a call than
#: at 100; a default grid of 201 is one call), growing 4x while calls take under 1/16 of
#: CALL_SECONDS (2x under 1/4) and halving above it, so that progress, the watches and the
#: step limit are honoured between calls of a long run; Ctrl-C reaches inside a call
#: (``interrupt.external``); a failing call is retried in halves (it loses one interval).
FIRST_CALL_OUTPUTS = 200
CALL_SECONDS = 0.25
#: IDAS steps a call should take at least, where the steps are counted (``CallSize.took``).
CALL_STEPS = 200
#: idas, projecting its outputs, starts with calls of this many (growing while the state a call
#: ends in stays within atol of the constraints: ``CallSize.took``).
FIRST_PROJECTED_CALL_OUTPUTS = 1
#: Steps one IDAS call may take; a call that needs more is split into SPLIT parts.
STEPS_PER_CALL = 20_000
SPLIT = 10
#: Factors on the first step tried when a restarted call fails at once (see ``run``).
RESTART_STEPS = (1e-2, 1e2, 1e-4)
#: IDAS integrators kept per structure, method and row set (one per output grid and options).
INTEGRATORS_KEPT = 8
#: ggl's absolute tolerance on its multipliers: so large that their weight 1/atol leaves them
#: out of IDAS's corrector test (``GGL.absolute_tolerances``); finite, so that no weight is 0.
UNTESTED = 1e100
#: ggl's corrector stops when rate/(1 - rate) × its last correction of x and u (weighted) is below
#: this (IDAS's default 0.33). With the multipliers out of the test, 0.33 let x and u stop a
#: little short, and IDAS's error and order estimates, built from them, took 1.5-2x the steps for
#: up to 6x the error (the bead on a turning hoop, the double pendulum); at 0.01 the steps are
#: within 20 % of those before and the errors as small, at about 2 iterations a step as before.
CORRECTOR_TEST = 0.01
_lock = threading.Lock()


def _inverse_masses(m):
    """M⁻¹ of a model view: numbers, or formulas of its parameters (ParametricView)."""
    inverse = m.inverse_masses
    return inverse if isinstance(inverse, ca.SX | ca.MX) else ca.DM(inverse)


def _canonical(grid: tuple) -> tuple:
    """A call's output times in τ ∈ (0, 1]; equally spaced ones (to round-off) as the one tuple
    k/n, k = 1…n, so that calls over equal intervals share their integrator (building one
    takes about 0.6 s on a 1,000-bead rope)."""
    even = tuple(np.arange(1, len(grid) + 1) / len(grid))
    return even if np.max(np.abs(np.subtract(grid, even))) <= 1e-13 else grid


def _steps_taken(integ) -> int | None:
    """The steps an IDAS integrator took in its last call (None when it has no statistics)."""
    try:
        return int(integ.stats()["nsteps"])
    except (AttributeError, KeyError, RuntimeError, TypeError, ValueError):
        return None


class CallSize:
    """How many output times the next SUNDIALS call covers (see FIRST_CALL_OUTPUTS)."""

    def __init__(self, fixed: int | None = None, first: int = FIRST_CALL_OUTPUTS):
        self.fixed, self.size = fixed, fixed or first

    def took(self, seconds: float, steps: int | None = None, drifted: bool = False) -> None:
        """After a call that took ``seconds`` and (where counted) ``steps``. Every call restarts
        IDAS at order 1 with small steps (about a dozen on a rope), so a call should take
        CALL_STEPS steps or more: the size grows eightfold while it takes fewer and falls eightfold
        above 8 CALL_STEPS (the watches and the progress meter act between calls), or when the
        state the call ended in left the constraints (index 1, where f = 0 is only implied) by
        more than the run's atol (``drifted``). Decided by counts, never by the clock, so a run
        takes the same steps on a loaded machine. Without ``steps``: by its seconds."""
        if self.fixed:
            return
        if steps is not None:  # (sizes 1, 8, 64, …: each size's integrator is built once)
            if drifted or steps > 8 * CALL_STEPS:
                self.size = max(1, self.size // 8)
            elif steps < CALL_STEPS:
                self.size *= 8
        elif seconds < CALL_SECONDS / 16:
            self.size *= 4
        elif seconds < CALL_SECONDS / 4:
            self.size *= 2
        elif seconds > CALL_SECONDS:
            self.size = max(1, self.size // 2)

    def retry_smaller(self, covered: int, seconds: float, by_steps: bool = False) -> bool:
        """After a failed call over ``covered`` times that took ``seconds``: whether to retry
        it in halves (not when failing took long: a stiff run would pay that again).
        ``by_steps`` (calls sized by their steps, ``took``): in eighths, whatever the clock, so
        that a failure near a singularity keeps the same outputs on any machine (at most three
        retries from 64 times: each covers an eighth of the one before)."""
        if covered <= 1 or (not by_steps and seconds > 4 * CALL_SECONDS):
            return False
        self.size = max(1, covered // (8 if by_steps else 2))
        return True


class _IdasBase(Stepper):
    adaptive = True
    OPTIONS = ("max_step", *DRIVER_OPTIONS)
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

    def dae(self, m, w, t) -> dict:
        """The DAE {x, z, ode, alg} in real time ``t`` (an expression) of the model view ``m``
        (its parameters symbols), the held rows multiplied by the weights ``w``."""
        raise NotImplementedError

    def algebraic_guess(self, x, v, t):
        raise NotImplementedError

    def prepare(self, t0, t_end, t_eval) -> None:
        self._grid = np.asarray(t_eval, float) if t_eval is not None else self.default_grid(t0, t_end)

    def default_grid(self, t0, t_end):
        return np.linspace(t0, t_end, 201)

    def init(self, x0, v0, t0, t_end, first_step=None):
        m = self.model
        if not hasattr(self, "row_scales"):  # the run's scales, from its start
            # constraint rows divided by their scale at the start (constrained.residual), so IDAS
            # sees the same equations and multipliers (in N) whatever scale a formula is written in
            self.row_scales = residual.row_scales(m, x0, t0)
            self._weights = 1.0 / self.row_scales[self.rows]
            self._step0 = self.dt or (self.first_step_fraction * (t_end - t0) if self.first_step_fraction
                                      else None)
            self._scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
            # projection tolerances in metres (constrained.residual): |f| ≤ tol × smallest row scale
            self._tol_f = 1e-14 * residual.smallest_scale(m, x0, t0)
            self._retries, self._pace, self._t0 = list(RESTART_STEPS), 0.0, t0
        times = tuple(float(tk) for tk in self._grid if t0 < tk < t_end) + (float(t_end),)
        # one IDAS call per group of output times (CallSize): Ctrl-C is honoured between calls,
        # and inside one it loses only that call's part. A call that runs out of steps
        # (STEPS_PER_CALL) is split at intermediate times. Every call restarts IDAS at order 1
        # with small steps, so idas does not restart at every output it projects (on a
        # 1,000-bead rope that made 20x the steps): the next call starts from the projected end
        first = FIRST_PROJECTED_CALL_OUTPUTS if self.project_outputs else FIRST_CALL_OUTPUTS
        self._calls = CallSize(first=first)
        return (float(t0), np.concatenate([x0, v0]), self.algebraic_guess(x0, v0, t0), times)

    def step(self, state, t_stop) -> Advance:
        """One IDAS call over the next group of times (landing on each)."""
        m = self.model
        n3 = m.n_coordinates
        t_prev, y, z, times = state
        size = self._calls.size
        if self.project_outputs and len(times) < size:  # (the sizes' integrators, not one more)
            size = 8 ** int(np.log(len(times)) / np.log(8) + 1e-9)
        seg, rest = times[:size], times[size:]
        pieces = int(np.ceil(self._pace * (seg[-1] - t_prev) / (STEPS_PER_CALL // 2)))
        if pieces > 1 and len(seg) > 1:  # at the pace so far: fewer times in this call
            self._calls.size = max(1, len(seg) // pieces)
            return Advance.empty(state, n3)
        if pieces > 1:  # one output interval too long for a call: split it at inner times
            inner = tuple(float(tk) for tk in np.linspace(t_prev, seg[0], pieces + 1)[1:-1])
            if inner:
                return Advance.empty((t_prev, y, z, inner + times), n3)
        span = seg[-1] - t_prev
        grid = _canonical(tuple((np.asarray(seg) - t_prev) / span))
        p = np.concatenate([[t_prev, span], self._weights, m.parameter_vector])
        called = time.perf_counter()
        integ = None
        try:
            res = None
            if not self.needs_derivatives:
                try:  # the integrator built once for these options (see _integrator)
                    integ = self._integrator(grid, span)
                    with interrupt.external(), quiet():
                        res = integ(x0=self.call_state(y, span), z0=self.call_algebraic(z, span), p=p)
                except RuntimeError:
                    if self.stop_requested():
                        raise
            if res is None:  # a call of its own, given the derivatives at its start
                a_prev, _ = self.manifold.accelerations(y[:n3], y[n3:], t_prev)
                integ = self._integrator(grid, span, init_xdot=self.call_rates(y[n3:], a_prev, span))
                with interrupt.external(), quiet():
                    res = integ(x0=self.call_state(y, span), z0=self.call_algebraic(z, span), p=p)
        except RuntimeError as exc:
            if self.stop_requested():
                raise KeyboardInterrupt from None
            reason = str(exc).splitlines()[-1][:200]
            if self._step0 and t_prev > self._t0 and "CONV_FAIL" in reason:
                if self._retries and _steps_taken(integ) == 0:
                    # ggl's index-2 corrector can fail on a restart's first step: the next
                    # first step in RESTART_STEPS usually passes
                    self._step0_next = self._step0 * self._retries.pop(0)
                    return Advance.empty(state, n3)
                # a failure further on (near a singular configuration), or at every first step
                # tried: a smaller call (below), from the first step the last good call gave
                self._step0_next = self._step0_after
            if "TOO_MUCH_WORK" in reason and span > 1e-9 * max(abs(seg[-1]), 1e-300):
                # more than STEPS_PER_CALL steps for this span: the pace is at least SPLIT times
                # that, and the next call is cut to fit it (``pieces`` above: fewer output times,
                # or inner times in one interval). Decided by step counts, never by the clock, so
                # a run does not fail on a loaded machine where it passes on an idle one
                self._pace = max(self._pace, SPLIT * STEPS_PER_CALL / span)
                return Advance.empty(state, n3)
            failed_after = time.perf_counter() - called
            if self._calls.retry_smaller(len(seg), failed_after, by_steps=True):
                return Advance.empty(state, n3)
            return Advance.empty(state, n3, Status.SOLVER_FAILED,
                                 f"IDAS stopped after t = {t_prev:.6g} s ({reason})"
                                 + tolerance_cause(self.rtol, self.atol, self._scale))
        took = time.perf_counter() - called
        stats = integ.stats()
        if self._step0:
            # the next call restarts at order 1: a tenth of the last step taken (RESTART_STEPS
            # retries other first steps should the corrector fail there); IDAS steps in τ
            last = float(stats.get("hlast", 0.0)) * span
            self._step0_next = 0.1 * last if np.isfinite(last) and last > 0 else self._step0
            self._step0_after, self._retries = self._step0_next, list(RESTART_STEPS)
        self._pace = int(stats.get("nsteps", 0)) / max(span, 1e-300)  # steps per second
        for key, skey in (("steps", "nsteps"), ("nfev", "nfevals"), ("nlu", "nlinsetups"),
                          ("rejected", "netfails")):
            self.stats[key] = self.stats.get(key, 0) + int(stats.get(skey, 0))
        X = self.real_states(res["xf"].full(), span)
        # calls sized by their steps (idas: and the drift at their end), never by the clock: ggl's
        # were sized by their seconds, so on a loaded machine a run took other calls, other steps,
        # and a collapse's predicted instant moved by 3e-3 s
        self._calls.took(took, int(stats.get("nsteps", 0)),
                         drifted=self.project_outputs and bool(rest)
                         and self._drift(X[:n3, -1], seg[-1]) > self.atol)
        xs, vs = [], []
        for k, tk in enumerate(seg):
            x, v = X[:n3, k], X[n3:, k]
            if self.project_outputs or (k == len(seg) - 1 and rest):
                # idas projects its outputs; ggl's next call restarts IDAS, whose index-2
                # corrector needs a start on both constraint levels to round-off
                tol = self._tol_f * max(self._scale, np.max(np.abs(x)))
                x = self.manifold.project_positions(x, tk, tol=tol).x
                v = self.manifold.project_velocities(x, v, tk)
                self.manifold.counters.projections += 1
            xs.append(x)
            vs.append(v)
        t_new = seg[-1]
        new = (t_new, np.concatenate([xs[-1], vs[-1]]), self.algebraic_guess(xs[-1], vs[-1], t_new), rest)
        return Advance(new, np.array(seg), np.array(xs), np.array(vs))

    def _drift(self, x: np.ndarray, t: float) -> float:
        """max_i |f_i(x, t)| / s_i, the drift of the state a call ended in from the position
        manifold in metres (s_i the rows' scales at the start)."""
        m = self.model
        if m.n_position_rows == 0:
            return 0.0
        f = np.asarray(constraint_values(m)(x, t)[0], float).ravel()
        return float(np.max(np.abs(f) / self.row_scales[:m.n_position_rows]))

    def extra_options(self) -> dict:
        return {}

    # IDAS's variables in a call: (x, v) and the algebraic ones as ``dae`` has them, unless a
    # method integrates in the call's own unit of time (GGL.tau_dae)
    def call_state(self, y, span):
        return y

    def call_algebraic(self, z, span):
        return z

    def call_rates(self, v, a, span):
        """d/dτ of the call's state at its start, from the velocities and accelerations."""
        return span * np.concatenate([v, a])

    def real_states(self, Y, span):
        """The call's (x, v) columns from IDAS's states."""
        return Y

    def absolute_tolerances(self, span) -> dict:
        return {"abstol": self.atol}

    #: Whether every call needs the derivatives at its start (``init_xdot``: IDAS computes no
    #: consistent initial condition), so that no integrator is shared between calls; else a
    #: shared one is tried first and a call of its own, given them, where its solve fails.
    needs_derivatives = False
    _step0_next: float | None = None
    _step0_after: float | None = None  # the first step after the last good call

    def _integrator(self, grid: tuple, span: float, init_xdot=None):
        """IDAS over τ ∈ [0, 1] with output times ``grid`` in τ, on the DAE in τ (``_scaled_dae``):
        built once per structure, method, row set, grid and options and kept with the
        structure's cache (building an integrator costs about as much as a call integrates);
        a call with ``init_xdot`` (dy/dτ at its start) is built for that call alone."""
        opts = {**self.absolute_tolerances(span), "reltol": self.rtol, "max_num_steps": STEPS_PER_CALL,
                "calc_ic": True, "print_stats": False, **self.extra_options()}
        step0 = self._step0_next if self._step0_next is not None else self._step0
        if step0:
            opts["step0"] = step0 / span
        if self.max_step:
            opts["max_step_size"] = self.max_step / span
        if init_xdot is not None or self._step0_next is not None:  # this call's own
            if init_xdot is not None:
                opts["init_xdot"] = np.asarray(init_xdot, float).tolist()
            return ca.integrator(f"{self.name}_call", "idas", self._scaled_dae(), 0.0, list(grid), opts)
        cache, prefix = structure_cache(self.model)
        kept = cache.setdefault((*prefix, self.name, "integrators", tuple(self.rows)), OrderedDict())
        key = (grid, tuple(sorted(opts.items())))
        integ = kept.get(key)
        if integ is None:
            integ = ca.integrator(self.name, "idas", self._scaled_dae(), 0.0, list(grid), opts)
            with _lock:
                kept[key] = integ
                while len(kept) > INTEGRATORS_KEPT:
                    kept.popitem(last=False)
        return integ

    def _scaled_dae(self) -> dict:
        """The method's DAE (``dae``) in τ ∈ [0, 1], t = t_a + Δ τ (d/dτ = Δ d/dt), with the
        parameters p = [t_a, Δ, w, model parameters]: w the rows' weights (1 / their scale at
        the start), so one DAE serves every run, start and parameter value of the structure."""
        cache, prefix = structure_cache(self.model)
        key = (*prefix, self.name, "scaled dae", tuple(self.rows))
        if key not in cache:
            m = self.model
            kind = ca.MX if getattr(m.structure, "pairs", ()) else ca.SX  # (mapped pair kernels: MX)
            P = kind.sym("p", len(m.parameter_vector))
            W = kind.sym("w", len(self._weights))
            span = kind.sym("span", 2)
            tau = kind.sym("tau")
            # (differentiable: IDAS takes its Jacobian)
            dae = self.tau_dae(ParametricView(m, P, differentiable=True), W, span[0], span[1], tau)
            cache[key] = {**dae, "p": ca.vertcat(span, W, P), "t": tau}
        return cache[key]

    def tau_dae(self, m, w, t_a, span, tau) -> dict:
        """The DAE {x, z, ode, alg} in τ: ``dae`` at t = t_a + Δ τ with its rates times Δ."""
        dae = self.dae(m, w, t_a + span * tau)
        return {"x": dae["x"], "z": dae["z"], "ode": span * dae["ode"], "alg": dae["alg"]}


class Idas(_IdasBase):
    name = "idas"
    OPTIONS = ("max_step", "project_outputs", *DRIVER_OPTIONS)
    project_outputs = True

    def __init__(self, manifold, *, project_outputs: bool = True, **kwargs):
        super().__init__(manifold, **kwargs)
        self.project_outputs = bool(project_outputs)

    def dae(self, m, w, t) -> dict:
        n3, C = m.n_coordinates, len(self.rows)
        kind = type(m.P)  # (MX where pair potentials are mapped kernels)
        x, v = kind.sym("x", n3), kind.sym("v", n3)
        lam = kind.sym("lam", C)
        F, J, gamma = m.dynamics(x, v, t)
        J, gamma = w * J[self.rows, :], w * gamma[self.rows]  # rows in metres
        a = _inverse_masses(m) * (F + ca.mtimes(J.T, lam))
        return {"x": ca.vertcat(x, v), "z": lam, "ode": ca.vertcat(v, a), "alg": ca.mtimes(J, a) + gamma}

    def algebraic_guess(self, x, v, t):
        return (self.manifold.accelerations(x, v, t)[1] * self.row_scales)[self.rows]


class GGL(_IdasBase):
    """Each call integrates in its own unit of time, the call's span Δ: τ = (t − t_a)/Δ, with
    u = Δ v (metres per unit τ) and the multipliers taken as Δ²λ and Δμ:

        x' = u + M⁻¹Jᵀ(Δμ),   u' = Δ² M⁻¹F(x, u/Δ, t) + M⁻¹Jᵀ(Δ²λ),   0 = f,   0 = J u + Δ f_t

    the same motion and the same tolerances (atol on u is Δ atol), but a Newton matrix that does
    not depend on the span. Written in seconds, its rows mixed α/h with 1 and its constraint
    block shrank like h: on a 1 ns run (h ~ 1e-14 s) the corrector did not converge with
    CasADi's sparse LU (a dense LU did), and IDAS stopped at t = 0 with IDA_CONV_FAIL
    (docs/hard-cases.md, section 18)."""

    name = "ggl"
    #: IDAS picks a first step from the tolerances; at tight ones it is so small that the
    #: index-2 Newton matrix (conditioned like 1/h²) defeats the corrector at t = 0
    #: (atol < 1e-10 failed on the double pendulum). A first step of 1e-5 of the run avoids it.
    first_step_fraction = 1e-5

    def tau_dae(self, m, w, t_a, span, tau) -> dict:
        """Velocity rows (model/velocity.py) are held at the velocity level only: μ is one per
        row of f (``_position``), and x' = u + M⁻¹Jᵀμ takes those rows of J."""
        n3, C = m.n_coordinates, len(self.rows)
        kind = type(m.P)  # (MX where pair potentials are mapped kernels)
        x, u = kind.sym("x", n3), kind.sym("u", n3)
        t = t_a + span * tau
        pos = self._position()
        impulse, mu = kind.sym("span2_lam", C), kind.sym("span_mu", len(pos))
        minv = _inverse_masses(m)
        F, J, _ = m.dynamics(x, u / span, t)
        _, f_t = m.velocity_terms(x, t)
        f = m.constraint(x, t)
        Jf, f = ((w[pos] * J[self.rows, :][pos, :], w[pos] * f[[self.rows[k] for k in pos]]) if pos
                 else (kind(0, n3), kind(0, 1)))
        J, f_t = w * J[self.rows, :], w * f_t[self.rows]  # rows in metres
        return {"x": ca.vertcat(x, u), "z": ca.vertcat(impulse, mu),
                "ode": ca.vertcat(u + minv * ca.mtimes(Jf.T, mu),
                                  minv * (span**2 * F + ca.mtimes(J.T, impulse))),
                "alg": ca.vertcat(f, ca.mtimes(J, u) + span * f_t)}

    def _position(self) -> list[int]:
        """Indices into ``rows`` of the rows of f."""
        return [k for k, row in enumerate(self.rows) if row < self.model.n_position_rows]

    def algebraic_guess(self, x, v, t):
        return np.concatenate([(self.manifold.accelerations(x, v, t)[1] * self.row_scales)[self.rows],
                               np.zeros(len(self._position()))])

    def call_state(self, y, span):
        n3 = self.model.n_coordinates
        return np.concatenate([y[:n3], span * y[n3:]])

    def call_algebraic(self, z, span):
        C = len(self.rows)
        return np.concatenate([span**2 * z[:C], span * z[C:]])

    def call_rates(self, v, a, span):
        return np.concatenate([span * v, span**2 * a])

    def real_states(self, Y, span):
        n3 = self.model.n_coordinates
        return np.concatenate([Y[:n3], Y[n3:] / span])

    def absolute_tolerances(self, span) -> dict:
        """atol on x, atol Δ on u = Δ v; the multipliers Δ²λ and Δμ out of the corrector's test
        (UNTESTED), as they are out of the error test (``suppress_algebraic``).

        IDAS's corrector stops when its last correction, weighted by 1/(rtol |y| + atol), is
        small. For index-2 multipliers that correction does not shrink: a residual ε of f (round-off
        of coordinates of size |x|) gives δμ = (α/h)(J M⁻¹ Jᵀ)⁻¹ ε, up to (α/h) m ε / σ² along a
        chain's longest mode (σ ≈ 1.1/N, of the row-normalized J), whatever the iteration. With μ
        tested at atol Δ, a chain of N 10 g beads on 1 cm rods at rest put the largest δμ at 1 to 6
        times its tolerance at the first step (N = 100 to 400): IDAS took the corrector for
        diverging (rate ≈ 1), cut h, which makes δμ larger, and stopped at t = 0 with IDA_CONV_FAIL
        at N = 100, 200, 1000, 2000 (not 400: the round-off's luck). Λ = Δ²λ likewise on a chain
        moving across itself. The corrections of x and u, which the multipliers move, stay in the
        test; those of the multipliers carry the round-off they amplify, nothing more."""
        n3, algebraic = self.model.n_coordinates, len(self.rows) + len(self._position())
        return {"abstolv": [self.atol] * n3 + [self.atol * span] * n3 + [UNTESTED] * algebraic}

    needs_derivatives = True  # IDAS's initial-condition solve is for index-1 DAEs

    def extra_options(self) -> dict:
        return {"suppress_algebraic": True, "calc_ic": False, "nonlin_conv_coeff": CORRECTOR_TEST}
