"""The reduced route as a method: Lagrange's equations in generalized coordinates q.

``simulate(system, t_end, method="reduced", reduced_model=ReducedModel(...))`` integrates
``M(q, t) q̈ = rhs`` (constrained.reduced) instead of the Cartesian DAE. The consistent
Cartesian start (x0, v0) is carried into q by Gauss–Newton on ``x(q, t0) = x0`` from the
model's own initial values, and ``q̇0 = (∂x/∂q)⁺ (v0 − ∂x/∂t)``; the result is mapped back
to x and v, so it is a Trajectory like any other method's.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .base import DRIVER_OPTIONS, Advance, Status
from .driver import Stepper


class Reduced(Stepper):
    name = "reduced"
    order = 8  # SciPy's DOP853 on Lagrange's equations
    OPTIONS = ("reduced_model", *DRIVER_OPTIONS)
    lands = False  # outputs from the dense output, mapped to x and v
    refines_events = False  # SciPy's interpolant is the method's solution between steps

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, reduced_model=None, **options):
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        model = self.model
        if reduced_model is None:
            raise InputError(
                "method 'reduced' needs generalized coordinates: pass reduced_model="
                "ReducedModel(system, coordinates, map) (from a scene: ReducedModel.from_scene(scene))"
            )
        if reduced_model.model.n_coordinates != model.n_coordinates:
            raise InputError("the reduced model maps a different system (particle count differs)")
        self.reduced_model = reduced_model

    def coordinates_of(self, x0, v0, t0: float):
        """(q, q̇) with x(q, t0) = x0 and ẋ(q, q̇, t0) = v0, or an InputError."""
        rm = self.reduced_model
        q = np.array(rm.initial, dtype=float)
        for _ in range(50):
            r = np.asarray(rm.position(q, t0)).ravel() - x0
            if np.max(np.abs(r)) < 1e-14 * max(1.0, np.max(np.abs(x0))):
                break
            Jq = np.asarray(rm.map_jacobian(q, t0))
            q = q - np.linalg.lstsq(Jq, r, rcond=None)[0]
        miss = float(np.max(np.abs(np.asarray(rm.position(q, t0)).ravel() - x0)))
        if miss > 1e-9 * max(1.0, np.max(np.abs(x0))):
            raise InputError(
                f"the start is not reached by the map x(q, t): the nearest mapped point is {miss:.3g} m "
                "away; check the map and the [reduced] initial values"
            )
        Jq = np.asarray(rm.map_jacobian(q, t0))
        dxdt = np.asarray(rm.velocity(q, np.zeros(rm.n), t0)).ravel()
        qd = np.linalg.lstsq(Jq, v0 - dxdt, rcond=None)[0]
        return q, qd

    def init(self, x0, v0, t0, t_end, first_step=None):
        q0, qd0 = self.coordinates_of(np.asarray(x0, float), np.asarray(v0, float), t0)
        ode = self.reduced_model._ode

        def fun(t, y):
            self.stats["nfev"] += 1
            return np.asarray(ode(y, t)).ravel()

        from scipy.integrate import DOP853  # (0.1 s of imports, for this method only)

        return DOP853(fun, t0, np.concatenate([q0, qd0]), t_end, rtol=self.rtol, atol=self.atol,
                      first_step=first_step)

    def _cartesian(self, y, t):
        rm = self.reduced_model
        q, qd = y[:rm.n], y[rm.n:]
        return (np.asarray(rm.position(q, t)).ravel(), np.asarray(rm.velocity(q, qd, t)).ravel())

    def step(self, integ, t_stop) -> Advance:
        n = self.model.n_coordinates
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            message = integ.step()
        if integ.status == "failed":
            return Advance(integ, np.zeros(0), np.zeros((0, n)), np.zeros((0, n)),
                           status=Status.STEP_SIZE_COLLAPSED,
                           message=f"the step size collapsed at t = {integ.t:.6g} s ({message})")
        self.stats["steps"] += 1
        dense = []  # built on first use, before the next step

        def interpolant(t):
            if not dense:
                dense.append(integ.dense_output())
            return self._cartesian(dense[0](t), t)

        x, v = self._cartesian(integ.y, integ.t)
        return Advance(integ, np.array([integ.t]), x[None], v[None], interpolant=interpolant,
                       h=integ.step_size)
