"""Baumgarte stabilization: the acceleration-level constraint with feedback.

Instead of ``J a + γ = 0`` the method imposes
``J a + γ + 2α (J v + f_t) + β² f = 0``, so a constraint violation obeys the damped
oscillator ``f'' + 2α f' + β² f = 0`` and decays instead of drifting. The ODE is then
integrated by SciPy's DOP853 (the projection module's step loop, composed: a Projection
with this right-hand side and its projections off).
Defaults α = β = 10 s⁻¹ (decay time 0.1 s); the drift left is of the order of the
integrator's local error times 1/α — small, not zero (tests/test_solvers.py measures it:
on the double pendulum at rtol 1e-6 it is 65× below the unstabilized ODE's).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..errors import InputError
from ..manifold.graph import acceleration_graph
from .base import DRIVER_OPTIONS, Advance
from .driver import Stepper
from .projection import EXPLICIT, Projection


class Baumgarte(Stepper):
    """The stabilized acceleration (the manifold's ``acceleration_graph(feedback=...)``) stepped
    by projection's SciPy loop, composed with projections turned off."""

    name = "baumgarte"
    OPTIONS = ("base", "alpha", "beta", *DRIVER_OPTIONS)
    BASES = ("DOP853", "RK45", "Radau")

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, alpha: float = 10.0,
                 beta: float = 10.0, base: str = "DOP853", **options):
        if isinstance(base, str) and base.startswith("CVODES"):
            # the CVODES route integrates projection's equations, not the stabilized ones
            raise InputError(f"method 'baumgarte' steps in SciPy: base must be DOP853, RK45 or "
                             f"Radau, got {base!r} (for CVODES use method 'projection')")
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        for key, value in (("alpha", alpha), ("beta", beta)):
            if not (isinstance(value, int | float) and np.isfinite(value) and value >= 0):
                raise InputError(f"{key} must be a non-negative number (1/s), got {value!r}")
        self.alpha, self.beta = float(alpha), float(beta)
        m = self.model
        n3 = m.n_coordinates
        X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
        # the acceleration level with feedback: γ → γ + 2α (J v + f_t) + β² f, over the
        # independent rows (a redundant row's feedback is implied by the others)
        acc, _ = acceleration_graph(m, X, V, T, rows=self.manifold.rows, linsol="qr",
                                    feedback=(self.alpha, self.beta))
        self._rhs = ca.Function("baumgarte_rhs", [T, ca.vertcat(X, V)], [ca.vertcat(V, acc)])
        self._loop = Projection(self.manifold, rtol=rtol, atol=atol, dt=dt, base=base,
                                right_hand_side=self.derivative, project=False)
        self._loop.name = self.name  # its diagnoses speak of this method
        self._loop.stats = self.stats  # one set of counters
        self.order = self._loop.order
        self.lands = self._loop.lands
        self.refines_events = self._loop.refines_events
        self.explicit = base in EXPLICIT

    def derivative(self, t, y):
        """(x', v') with the stabilized acceleration."""
        self.manifold.counters.nfev += 1
        self.manifold.counters.nlu += 1
        return self._rhs(t, y).full().ravel()

    def init(self, x0, v0, t0, t_end, first_step=None):
        return self._loop.init(x0, v0, t0, t_end, first_step)

    def step(self, state, t_stop) -> Advance:
        return self._loop.step(state, t_stop)

    def stiffness_advice(self) -> tuple[str, str]:
        return f"baumgarte's explicit base {self._loop.base}", 'use base = "Radau"'
