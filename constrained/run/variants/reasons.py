"""Why a variant of ``simulate_many`` did not finish, in the words its own ``simulate`` uses
(session 15: batched runs and sweep rows used to say only "inconsistent start", "non-finite",
"projection failed" — a rod of length 0 and a rod of negative length read alike).

- The start: each variant's size is its own ``System.size()`` (the largest |x_i| and
  |x_i − x_j| of its start), as ``simulate`` takes it; the batched start was judged against the
  size of the system's *default* parameter values, floored at 1 m, so a 1 mm pendulum 0.3 mm off
  its rod was projected where its own run refuses it, and a 100 m one 5 cm off was refused where
  its own run projects it. A variant the mapped start refuses goes through ``consistent_start``,
  the single run's start: accepted there, it runs from that start; refused, its status carries
  that refusal's sentence (the constraint, how far off, or the undefined gradient).
- A stop: the last good state (x, v, t) of the frozen column and the model for that variant's
  parameters give the single run's diagnosis (``nonfinite_cause``, ``likely_cause``).
"""

from __future__ import annotations

import numpy as np

from ...errors import InconsistentStateError
from ...manifold import diagnostics
from ...model.structure import Model
from ...model.system import length_scale

#: Failed variants diagnosed in full (each costs a model view and an SVD or two); the others
#: of a run with more failures get the short sentence with their time.
DIAGNOSED_MAX = 64

SHORT = {
    "non-finite": "the solution became non-finite (NaN or inf)",
    "inconsistent start": "inconsistent start: the initial positions miss the constraints by more than "
                          "max_initial_correction × the system's size",
    "projection failed": "the projection onto the constraints no longer converged (a singular "
                         "configuration?); reduce rtol or give other parameter values",
    "step limit": "the step limit was reached before t_end; raise max_steps",
    "step size collapsed": "the step size collapsed (stiff or singular motion)",
    "non-positive mass": "a particle's mass (a formula of the parameters) is not a finite positive number "
                         "for these parameter values; give values that make every mass positive",
}


def start_sizes(x0: np.ndarray) -> np.ndarray:
    """``System.size()`` of every variant's start x0 (N, 3n) (``system.length_scale``)."""
    return length_scale(x0.reshape(x0.shape[0], -1, 3))


def particle_moves(x0: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The start's correction of every variant: max_i |x_i − x0_i| (m), as ``consistent_start``."""
    n = x0.shape[0]
    return np.max(np.linalg.norm((x - x0).reshape(n, -1, 3), axis=2), axis=1)


def variant_model(model: Model, p: np.ndarray) -> Model:
    """The Model for one row of the parameter matrix (the parameters first, then the plain numbers)."""
    return model.with_parameters({name: float(p[i]) for i, name in enumerate(model.parameter_names)})


def single_start(model: Model, p: np.ndarray, x0: np.ndarray, v0: np.ndarray, t0: float,
                 max_correction: float, size: float):
    """``consistent_start`` for one variant: (x, v, correction, None) or (None, None, nan, reason)."""
    from ..start import consistent_start

    try:
        start = consistent_start(variant_model(model, p), x0, v0, t0, max_correction=max_correction,
                                 size=size)
    except InconsistentStateError as error:
        return None, None, np.nan, f"inconsistent start: {error}"
    except Exception as error:  # a diagnosis must never hide the refusal itself
        return None, None, np.nan, f"inconsistent start: {SHORT['inconsistent start']} ({error})"
    return start.x, start.v, float(start.correction["position"]), None


def mass_reason(model: Model, p: np.ndarray) -> str:
    """Which particle's mass formula is not a finite positive number for this variant."""
    try:
        masses = np.asarray(model.parametric("masses")(p), float).ravel()
        bad = int(np.argmax(~(np.isfinite(masses) & (masses > 0))))
        return (f"particle '{model.particle_names[bad]}' has mass {masses[bad]:.6g} kg for these parameter "
                "values: a mass must be a finite positive number; give values that make every mass positive")
    except Exception:
        return SHORT["non-positive mass"]


def stiffness_reason(m: Model, x: np.ndarray, t: float, t0: float, t_end: float, steps: int) -> str | None:
    """The stiffness watch's sentence for a variant whose mean step (t − t0)/steps is held below
    the period of its fastest spring (or HELD relaxation times m/c of a damper) — the advice its
    own run's ``StiffnessWatch`` gives, for a variant stopped by its step budget or a collapse
    (one that would take too long is stopped before, by ``watch.MemberWatch``) — else None."""
    from ...solvers.stiffness import StiffnessWatch

    if not steps or not t > t0:
        return None
    watch = StiffnessWatch(m, x, t0, t_end, method="dopri")
    mean = (t - t0) / steps
    element = watch.fastest(x, t)
    if element is not None and mean <= element.period:
        return watch.describe(element, t, steps)
    damper = watch.held_damper(t, steps)
    return watch.describe_damper(damper, t, steps) if damper is not None else None


def stop_reason(model: Model, status: str, p: np.ndarray, x: np.ndarray, v: np.ndarray, t: float,
                h: float, max_steps: int, t_end: float, diagnose: bool = True, t0: float = 0.0,
                steps: int = 0) -> str:
    """The sentence of a run stopped at its last good state (x, v, t) with ``status``; a step
    limit or a collapse held down by a stiff spring or damper carries the stiffness watch's advice."""
    if status == "step limit":
        limit = (f"more than max_steps = {max_steps} steps before t = {t_end:.6g} s (at t = {t:.6g} s); "
                 "raise max_steps for a longer run")
        try:
            stiff = stiffness_reason(variant_model(model, p), x, t, t0, t_end, steps) if diagnose else None
        except Exception:  # a diagnosis must never hide the stop itself
            stiff = None
        return f"{limit}; {stiff}" if stiff else limit
    if not diagnose:
        return f"{SHORT.get(status, status)} (at t = {t:.6g} s)"
    try:
        m = variant_model(model, p)
        stiff = stiffness_reason(m, x, t, t0, t_end, steps) if status == "step size collapsed" else None
        if stiff:
            return f"the step size collapsed at t = {t:.6g} s (h = {h:.3g} s); {stiff}"
        if status == "non-finite":
            return f"non-finite state after t = {t:.6g} s; {diagnostics.nonfinite_cause(m, x, v, t)}"
        cause = diagnostics.likely_cause(m, x, v, t)
    except Exception:  # a diagnosis must never hide the stop itself
        return f"{SHORT.get(status, status)} (at t = {t:.6g} s)"
    if status == "projection failed":
        return f"the state could not be kept on the constraints near t = {t:.6g} s: reduce rtol; {cause}"
    if status == "step size collapsed":
        return f"the step size collapsed at t = {t:.6g} s (h = {h:.3g} s); {cause}"
    return f"{SHORT.get(status, status)} (at t = {t:.6g} s); {cause}"
