"""What is measured: formulas of the state, the constraint forces and the parameters.

An observable is a formula (the whitelisted parser, constrained.expressions) in

- ``x_P, y_P, z_P`` positions and ``vx_P, vy_P, vz_P`` velocities of particle P,
- ``ax_P, ay_P, az_P`` its acceleration and ``Fx_P, Fy_P, Fz_P`` the constraint force on it,
  ``(Jᵀλ)_P = m_P a_P − F_P`` (the names [expect] uses),
- ``t`` and the scene's [parameters] and [definitions],

so a camera's positions are ``x_bob, y_bob``, an angle ``atan2(x_bob, -y_bob)``, a load cell
``sqrt(Fx_bob**2 + Fy_bob**2)``. ``observables(model, formulas)`` builds one CasADi Function
``(x, v, a, t, p) -> y`` for the whole structure (p: the Model's parameter vector), so
derivatives with respect to the parameters see them wherever they appear.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import casadi as ca

from ...errors import InputError
from ...model import lifting
from ...model.cache import structure_cache
from ...model.structure import Model
from ...model.symbols import Symbols

__all__ = ["Observables", "observables", "position_names"]


@dataclass(frozen=True)
class Observables:
    """``names`` (k,), their ``formulas`` and ``function(x, v, a, t, p) -> y (k,)``."""

    names: tuple[str, ...]
    formulas: tuple[str, ...]
    function: ca.Function


def position_names(model: Model) -> list[str]:
    """``x_P, y_P, z_P`` of every particle, in order: the default observables."""
    return [f"{axis}_{name}" for name in model.particle_names for axis in "xyz"]


def _named(formulas) -> list[tuple[str, str]]:
    """(name, formula) pairs from a list of formulas (each its own name) or a mapping."""
    if isinstance(formulas, str):
        formulas = [formulas]
    if isinstance(formulas, Mapping):
        pairs = [(str(k), v) for k, v in formulas.items()]
    elif isinstance(formulas, Sequence):
        pairs = [(f, f) for f in formulas]
    else:
        raise InputError("observables must be formulas (a list, or a table name -> formula), got "
                         f"{formulas!r}", where="observables")
    if not pairs:
        raise InputError("no observable given", where="observables")
    for name, text in pairs:
        if not isinstance(text, str) or not text.strip():
            raise InputError(f"observable {name!r} must be a formula string, got {text!r}",
                             where="observables")
    names = [n for n, _ in pairs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"observable(s) {', '.join(twice)} named twice", where="observables")
    return pairs


def observables(model: Model, formulas) -> Observables:
    """The Function of the observables ``formulas`` (a list of formulas, each its own name, or
    a table name -> formula), built once per structure and set of formulas."""
    pairs = _named(formulas)
    cache, prefix = structure_cache(model)
    key = (*prefix, "observables", tuple(pairs))
    if key not in cache:
        cache[key] = Observables(tuple(n for n, _ in pairs), tuple(f for _, f in pairs), _build(model, pairs))
    return cache[key]


def _build(model: Model, pairs) -> ca.Function:
    system, numbers = lifting.lift(model.system)
    s = Symbols(system, symbolic_parameters=True, numbers=len(numbers))
    n3 = model.n_coordinates
    a = ca.SX.sym("a", n3)
    F, _, _ = model.parametric("dynamics")(s.x, s.v, s.t, s.p)
    masses = ca.repmat(ca.SX(s.mass_column()).T, 3, 1).reshape((n3, 1))
    constraint_force = masses * a - F
    extra = {}
    for i, name in enumerate(model.particle_names):
        for k, axis in enumerate("xyz"):
            extra[f"a{axis}_{name}"] = a[3 * i + k]
            extra[f"F{axis}_{name}"] = constraint_force[3 * i + k]
    clash = sorted(set(extra) & set(s.state_names))
    if clash:
        raise InputError(f"the name(s) {', '.join(clash)} are taken by the scene (a parameter or "
                         "definition): observables use them for accelerations and constraint forces",
                         where="observables")
    rows = [ca.SX(s.parse(text, f"observables.{name}", velocities=True, extra=extra)) for name, text in pairs]
    return ca.Function("observables", [s.x, s.v, a, s.t, s.p], [ca.vertcat(*rows)],
                       ["x", "v", "a", "t", "p"], ["y"])
