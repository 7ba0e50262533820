"""What is built once per model or per structure and shared by every run: a dict kept beside the
Model (not on it, which stays immutable), and ``ParametricView``, the Model with its parameters a
symbol, on which step loops are built once per structure."""

from __future__ import annotations

import threading
import weakref

import casadi as ca

from .structure import Model

_built: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_lock = threading.Lock()


def per_model_cache(model: Model) -> dict:
    """A dict kept beside ``model`` (not on it) for what solvers build once per model and
    reuse across runs, e.g. a compiled step loop. It goes when the model goes."""
    with _lock:
        return _built.setdefault(model, {})


def built_once(model: Model, key, build):
    """``build()`` the first time ``key`` is asked for on ``model``, the kept value after that
    (two threads asking at once may both build; either result serves)."""
    cache = per_model_cache(model)
    if key not in cache:
        cache[key] = build()
    return cache[key]


class ParametricView:
    """``model`` with its parameters a CasADi symbol ``P``: the attributes the graph builders
    read (``dynamics(x, v, t)``, ``jacobian``, ``velocity_terms``, ``constraint``, sizes,
    masses), calling the parametric Functions with P. A step loop built on it takes p as an
    input and serves every Model of the structure (``structure_cache``). ``differentiable``:
    for a graph that takes their derivatives (``Structure.function``)."""

    def __init__(self, model: Model, P, *, differentiable: bool = False):
        self.P = P
        self._model = model
        self._differentiable = differentiable
        for name in ("n_coordinates", "n_constraints", "n_position_rows", "n_particles", "masses",
                     "inverse_masses", "rheonomic", "constraint_labels", "parameter_vector"):
            setattr(self, name, getattr(model, name))
        if model.masses_follow_parameters:  # masses as entries or formulas of P in the graphs
            entries = getattr(model.structure, "mass_entries", None)
            self.masses = (ca.vec(P[entries.tolist()]) if entries is not None
                           else model.parametric("masses")(P))
            self.inverse_masses = 1 / self.masses

    def _call(self, name: str, *args):
        return self._model.parametric(name, differentiable=self._differentiable)(*args, self.P)

    def constraint(self, X, T):
        return self._call("constraint", X, T)

    def jacobian(self, X, T):
        return self._call("jacobian", X, T)

    def velocity_terms(self, X, T):
        return self._call("velocity_terms", X, T)

    def dynamics(self, X, V, T):
        return self._call("dynamics", X, V, T)

    def energy(self, X, V, T):
        return self._call("energy", X, V, T)

    def forces_and_potential(self, X, V, T):
        """(F, W): the forces and the energy less the kinetic, W = h − ½ vᵀMv, from one pass."""
        return self._call("forces_and_potential", X, V, T)


def structure_cache(model: Model) -> tuple[dict, tuple]:
    """(cache, key prefix) for what is built with the parameters as inputs (``ParametricView``):
    kept beside the model's structure, so every Model of the structure (other parameter
    values, masses included) shares it; the row set held (constrained.held) is in the key."""
    return per_model_cache(model.structure), (getattr(model, "rows", None),)
