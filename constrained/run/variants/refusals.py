"""Members of ``simulate_many`` refused before they run, as their own ``simulate`` refuses them.

- A mass that is not a finite positive number for the member's parameter values (``mass = "m"``
  with m = 0): status "non-positive mass". It used to be reported as an "inconsistent start"
  (or to run with a negative mass), which named the wrong cause.
- A damping coefficient given by a formula of the parameters and t (``coefficient = "b"``)
  that is negative or not finite at any instant of [t_start, t_end]: status "negative
  damping", with the sentence of ``Damping.refusal``, the one its own run raises. Such a
  member used to run as an energy source and be reported as an ordinary row.

The damping check costs nothing without a damper whose coefficient is a formula (0.1 ms for
1000 members). Otherwise members with the same values of the parameters the formula names
(directly or through the definitions it uses) share one check: 1000 members with one value of
``b`` and 1000 rod lengths, 2 ms in all. Each distinct value set costs its own run's check: about
0.05 ms for a formula without t (``"b"``: 1000 values, 53 ms) and 3 ms for one of t (an interval
search over the span; ``"b + 0.15*sin(20*t)"`` over 2 s: 1000 values, 3 s, the time the batch of
1000 pendulums takes to run).
"""

from __future__ import annotations

import numpy as np

from ...model import expressions
from ...model.effects import damping_formulas
from ...model.parameters import values as evaluated
from ...model.structure import Model
from .reasons import mass_reason


def before_running(model: Model, system, P: np.ndarray, t0: float, t_end: float) -> dict[int, tuple]:
    """{member: (status, message)} of the members of the parameter matrix ``P`` (a row per
    member: the parameters in ``model.parameter_names`` order, then the plain numbers) refused
    before running: a non-positive mass first (as ``simulate`` checks it first), then a
    negative damping coefficient over [t0, t_end]."""
    out = {int(k): ("non-positive mass", mass_reason(model, P[k])) for k in invalid_masses(model, P)}
    for k, why in damping_refusals(model, system, P, t0, t_end, skip=out).items():
        out[k] = ("negative damping", why)
    return out


def invalid_masses(model: Model, P: np.ndarray) -> np.ndarray:
    """The members whose parameter values give a particle a mass that is not a finite positive
    number (``simulate`` refuses such a mass by name)."""
    if not model.masses_follow_parameters:
        return np.zeros(0, int)
    entries = getattr(model.structure, "mass_entries", None)
    if entries is not None:
        masses = P[:, np.asarray(entries, int)]
    else:
        masses = np.asarray(model.parametric("masses").map(P.shape[0])(P.T), float).T
    with np.errstate(invalid="ignore"):
        return np.flatnonzero(~np.all(np.isfinite(masses) & (masses > 0), axis=1))


def damping_refusals(model: Model, system, P: np.ndarray, t0: float, t_end: float,
                     skip=()) -> dict[int, str]:
    """{member: the text of the InputError its own ``simulate`` raises} for the members (not in
    ``skip``) whose damping coefficient, a formula of the parameters and t, is negative or not
    finite somewhere on [t0, t_end] (``Damping.refusal``, the check ``refuse_negative_damping``
    makes): one check per distinct set of values of the parameters the formulas name."""
    dampers = damping_formulas(system.effects)
    if not dampers:
        return {}
    base = model.system
    used = named(base, [e.coefficient for e in dampers])
    definitions = {d: base.definitions[d] for d in base.definitions if d in used}
    columns = [i for i, name in enumerate(model.parameter_names) if name in used]
    groups: dict[tuple, list[int]] = {}
    for k in range(P.shape[0]):
        if k not in skip:
            groups.setdefault(tuple(P[k, columns].tolist()), []).append(k)
    out = {}
    for key, members in groups.items():
        member = {model.parameter_names[i]: v for i, v in zip(columns, key, strict=True)}
        try:  # the values simulate parses the formula with (System.parameter_values), for the names used
            values = evaluated({**base.parameters, **member}, definitions)
        except Exception:  # (a definition its own run cannot evaluate: refused there, not here)
            continue
        for effect in dampers:
            error = effect.refusal(values, t0, t_end)
            if error is not None:
                out.update((k, str(error)) for k in members)
                break
    return out


def named(system, formulas) -> set[str]:
    """The parameters and definitions the ``formulas`` name, directly or through definitions."""
    seen: set[str] = set()
    todo = [name for text in formulas for name in expressions.free_names(text)]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        formula = system.definitions.get(name)
        if isinstance(formula, str):
            todo += expressions.free_names(formula)
    return seen & (set(system.parameters) | set(system.definitions))
