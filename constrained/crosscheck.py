"""The cross-check: the Cartesian route and the reduced route from the same start, compared.

The Cartesian run goes through the one map of settings (``run_options``), like ``run`` and
sweeps; the reduced run integrates Lagrange's equations in the scene's ``[reduced]``
coordinates on the Cartesian run's time grid.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .reduced import CrossCheck, ReducedModel, _number
from .run_options import from_settings
from .simulate import simulate

#: Output samples when the scene gives no grid (output_dt, samples) and no t_eval is passed.
DEFAULT_SAMPLES = 201


def cross_check(scene, t_end: float | None = None, **settings) -> CrossCheck:
    """Run the Cartesian route (``simulate``) and the reduced route of ``scene.reduced`` from
    the same start (the reduced ``initial``/``rates`` mapped to x, v) on one time grid.

    ``settings`` override the scene's ``[simulate]`` ones: ``method``, ``rtol``, ``atol``,
    ``t_start``, ``t_eval``, ``samples``, ``output_dt``, a method's own options (``base`` …),
    ``parameters`` (extra names for the map); ``progress`` and ``model`` go to ``simulate``.
    """
    base = dict(getattr(scene, "settings", None) or {})
    extra_parameters = settings.pop("parameters", None)
    passthrough = {k: settings.pop(k) for k in ("progress", "model") if k in settings}
    t_end = (settings.pop("t_end", None) or base.get("t_end")) if t_end is None else t_end
    if t_end is None:
        raise InputError("no end time: give t_end, or t_end in the scene's [simulate]",
                         where="simulate.t_end")
    t_end = _number(t_end, "t_end")
    base.setdefault("rtol", 1e-10)
    base.setdefault("atol", 1e-10)
    if all(settings.get(k) is None and base.get(k) is None for k in ("t_eval", "samples", "output_dt")):
        base["samples"] = DEFAULT_SAMPLES
    options = from_settings(base, scene=scene, t_end=t_end, **settings)
    t_start, rtol, atol = options.t_start, options.rtol, options.atol
    rm = ReducedModel.from_scene(scene, parameters=extra_parameters, t0=t_start)
    x0, v0 = rm.state(rm.initial, rm.rates, t_start)
    system = scene.system.with_state(x0, v0)
    kwargs = options.simulate_kwargs()
    cart = simulate(system, t_end, **kwargs, **passthrough)
    red = rm.solve(t_end, t_start=t_start, rtol=rtol, atol=atol, t_eval=cart.t)
    dx = np.max(np.linalg.norm(cart.x - red.x, axis=2), axis=1)
    dv = np.max(np.linalg.norm(cart.v - red.v, axis=2), axis=1)
    de = None
    if cart.energy is not None and red.energy is not None:
        de = float(np.max(np.abs(cart.energy - red.energy)))
    dF = None
    if cart.constraint_forces is not None and red.constraint_forces is not None and rm.model.n_constraints:
        dF = float(np.max(np.linalg.norm(cart.constraint_forces - red.constraint_forces, axis=2)))
    return CrossCheck(
        cartesian=cart,
        reduced=red,
        reduced_model=rm,
        t=cart.t,
        position_difference=dx,
        velocity_difference=dv,
        max_position_difference=float(np.max(dx)),
        max_velocity_difference=float(np.max(dv)),
        max_energy_difference=de,
        max_constraint_force_difference=dF,
        settings={"t_end": t_end, **{k: v for k, v in kwargs.items() if k != "t_eval"}},
    )
