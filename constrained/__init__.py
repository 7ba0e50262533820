"""constrained: particles under holonomic constraints, constraint forces as Lagrange multipliers.

The public names are imported lazily (PEP 562 ``__getattr__``): ``import constrained`` is
cheap, and the module holding a name (CasADi, SciPy, matplotlib behind it) is imported the
first time the name is used.
"""

from __future__ import annotations

import importlib
import sys
import types

from ._version import __version__

#: public name -> the submodule defining it
_LAZY = {
    # the action of a run: constrained.action.action (the module keeps its name)
    **dict.fromkeys(("ActionResult", "PathResult", "StationarityResult", "stationarity",
                     "stationary_path"), "action"),
    **dict.fromkeys(("ConstraintReport", "constraint_report", "degrees_of_freedom"), "analysis"),
    **dict.fromkeys(("Curve", "Custom", "Distance", "Pin", "Plane", "Surface"), "constraints"),
    **dict.fromkeys(("Conservation", "EquationCheck", "check_equations", "check_generalized_forces",
                     "check_lagrangian", "conservation", "describe"), "derivation"),
    **dict.fromkeys(("Central", "Damping", "Electromagnetic", "Force", "Gravity", "Pairwise",
                     "Potential", "Spring"), "effects"),
    **dict.fromkeys(("ConstrainedError", "InconsistentStateError", "InputError", "RunInterrupted",
                     "SimulationError"), "errors"),
    **dict.fromkeys(("Model", "assemble"), "model"),
    **dict.fromkeys(("CrossCheck", "ReducedModel"), "reduced"),
    "cross_check": "crosscheck",
    "simulate": "simulate",
    **dict.fromkeys(("Ensemble", "simulate_many"), "ensemble"),
    **dict.fromkeys(("Event", "EventHit", "Status"), "solvers.base"),
    **dict.fromkeys(("Equilibrium", "constraint_virtual_work_residual", "equilibrium",
                     "generalized_forces", "virtual_work"), "statics"),
    # the function: constrained.sweep.sweep (the module keeps its name)
    "SweepResult": "sweep",
    **dict.fromkeys(("SymmetryReport", "charge_drift", "euler_lagrange", "is_symmetry",
                     "is_symmetry_reduced", "noether_charge", "noether_charge_reduced",
                     "with_total_derivative"), "symmetry"),
    **dict.fromkeys(("Particle", "System"), "system"),
    "Trajectory": "trajectory",
    **dict.fromkeys(("Scene", "RunResult"), "scene"),
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'constrained' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


class _Package(types.ModuleType):
    """The package's module type: ``constrained.simulate`` is the function, even after the
    submodule of the same name has been imported (the import system would otherwise set the
    module object as the package attribute)."""

    @property
    def simulate(self):
        from .simulate import simulate

        return simulate

    @simulate.setter
    def simulate(self, value):  # the import system setting the submodule: the function wins
        pass


sys.modules[__name__].__class__ = _Package


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


def load_scene(path, overrides=None):
    """Load a TOML scene: a Scene with ``.system``, ``.settings``, ``.outputs`` (and ``.run()``)."""
    from .scene import load_scene as _load

    return _load(path, overrides)


__all__ = [
    "ActionResult", "PathResult", "StationarityResult", "stationarity", "stationary_path",
    "Central", "ConstrainedError", "ConstraintReport", "Curve", "Custom", "Damping", "Distance",
    "Electromagnetic", "Force", "Gravity", "InconsistentStateError", "InputError", "Model",
    "Pairwise", "Particle", "Pin", "Plane", "Potential", "RunInterrupted", "SimulationError", "Spring",
    "Surface", "System",
    "Trajectory", "assemble", "constraint_report", "degrees_of_freedom", "load_scene", "simulate",
    "Conservation", "CrossCheck", "EquationCheck", "ReducedModel", "check_equations", "conservation",
    "cross_check", "describe", "check_lagrangian", "check_generalized_forces",
    "SymmetryReport", "charge_drift", "euler_lagrange", "is_symmetry", "is_symmetry_reduced",
    "noether_charge", "noether_charge_reduced", "with_total_derivative",
    "Equilibrium", "constraint_virtual_work_residual", "equilibrium", "generalized_forces",
    "virtual_work",
    "SweepResult", "Scene", "RunResult", "__version__",
]
