"""constrained: particles under holonomic and velocity constraints, constraint forces as multipliers.

The public names are imported lazily (PEP 562 ``__getattr__``): ``import constrained`` is
cheap, and the module holding a name (CasADi, SciPy, matplotlib behind it) is imported the
first time the name is used.
"""

from __future__ import annotations

import importlib

from . import notebook
from ._version import __version__

#: public name -> the submodule defining it
_LAZY = {
    **dict.fromkeys(("ActionResult", "PathResult", "StationarityResult", "action", "stationarity",
                     "stationary_path"), "analysis.action"),
    **dict.fromkeys(("ConstraintReport", "constraint_report", "degrees_of_freedom"),
                    "manifold.constraint_report"),
    **dict.fromkeys(("Curve", "Custom", "Distance", "Pin", "Plane", "Surface"), "model.constraints"),
    **dict.fromkeys(("KnifeEdge", "Rolling", "Velocity"), "model.velocity"),
    **dict.fromkeys(("Conservation", "check_constant_of_motion", "conservation", "describe",
                     "describe_conserved"), "analysis.derivation"),
    **dict.fromkeys(("EquationCheck", "check_equations"), "analysis.equations"),
    **dict.fromkeys(("check_generalized_forces", "check_lagrangian"), "analysis.candidates"),
    **dict.fromkeys(("Central", "Damping", "Electromagnetic", "Force", "Gravity", "Pairwise",
                     "Potential", "Spring"), "model.effects"),
    **dict.fromkeys(("ConstrainedError", "InconsistentStateError", "InitialStateWarning", "InputError",
                     "RunInterrupted", "SimulationError"), "errors"),
    **dict.fromkeys(("Model", "assemble"), "model.structure"),
    "CrossCheck": "analysis.crosscheck",
    "ReducedModel": "run.reduced",
    "cross_check": "analysis.crosscheck",
    "simulate": "run.simulate",
    **dict.fromkeys(("Ensemble", "simulate_many"), "run.ensemble"),
    **dict.fromkeys(("Event", "EventHit", "Status"), "solvers.base"),
    **dict.fromkeys(("Equilibrium", "constraint_virtual_work_residual", "equilibrium",
                     "generalized_forces", "virtual_work"), "analysis.statics"),
    **dict.fromkeys(("SweepResult", "sweep"), "sweeps.sweep"),
    **dict.fromkeys(("FitSweep", "fit_sweep"), "sweeps.fits"),
    **dict.fromkeys(("Mode", "Modes", "ModesCrossCheck", "modes"), "analysis.modes"),
    "RotatingFrame": "analysis.linearization",
    **dict.fromkeys(("Sensitivities", "sensitivities"), "analysis.fitting.sensitivities"),
    **dict.fromkeys(("FitResult", "fit"), "analysis.fitting.fit"),
    **dict.fromkeys(("Measurements", "read_measurements"), "analysis.fitting.measurements"),
    **dict.fromkeys(("SymmetryReport", "charge_drift", "euler_lagrange", "is_symmetry",
                     "is_symmetry_reduced", "noether_charge", "noether_charge_reduced",
                     "with_total_derivative"), "analysis.symmetry"),
    **dict.fromkeys(("RigidSymmetry", "rigid_symmetries"), "analysis.conservation.rigid_motions"),
    **dict.fromkeys(("Particle", "System"), "model.system"),
    "Trajectory": "run.trajectory",
    **dict.fromkeys(("Scene", "RunResult"), "scene.load"),
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'constrained' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


def load_scene(path, overrides=None):
    """Load a TOML scene: a Scene with ``.system``, ``.settings``, ``.outputs`` (and ``.run()``).

    ``overrides`` are ``"KEY=VALUE"`` strings as the command line's ``--set``. A scene that
    cannot be used raises an InputError naming the file, the key and what is wrong. Example::

        import constrained as C

        scene = C.load_scene("scenarios/double_pendulum.toml", ["simulate.t_end=2"])
        run = scene.run()                  # the scene's own [simulate] settings
        print(run.ok, run.report())        # its [expect] checks
        traj = run.trajectory              # t, x, v, multipliers, constraint forces, energy ...
        print(traj.success, traj["x"].shape)
        df = traj.to_pandas()              # columns x_p1, y_p1, ..., lambda[...] (needs pandas)

    The same scene without a file: ``C.System`` (see ``help(C.System)``).
    """
    from .scene.load import load_scene as _load

    return _load(path, overrides)


def _inline_viewer(trajectory, *, system=None, title: str = "") -> str:
    """The interactive viewer of a trajectory inside a notebook cell (constrained.output.viewer)."""
    from .output.viewer import inline_viewer

    return inline_viewer(trajectory, system=system, title=title)


notebook.register("viewer", _inline_viewer)


__all__ = [
    "ActionResult", "PathResult", "StationarityResult", "stationarity", "stationary_path",
    "Central", "ConstrainedError", "ConstraintReport", "Curve", "Custom", "Damping", "Distance",
    "Electromagnetic", "Force", "Gravity", "InconsistentStateError", "InitialStateWarning", "InputError",
    "Model",
    "Pairwise", "Particle", "Pin", "Plane", "Potential", "RunInterrupted", "SimulationError", "Spring",
    "Surface", "System", "KnifeEdge", "Rolling", "Velocity",
    "Trajectory", "assemble", "constraint_report", "degrees_of_freedom", "load_scene", "simulate",
    "Conservation", "CrossCheck", "EquationCheck", "ReducedModel", "check_equations", "conservation",
    "cross_check", "describe", "check_lagrangian", "check_generalized_forces", "check_constant_of_motion",
    "describe_conserved",
    "SymmetryReport", "charge_drift", "euler_lagrange", "is_symmetry", "is_symmetry_reduced",
    "noether_charge", "noether_charge_reduced", "with_total_derivative", "RigidSymmetry", "rigid_symmetries",
    "Equilibrium", "constraint_virtual_work_residual", "equilibrium", "generalized_forces",
    "virtual_work",
    "SweepResult", "sweep", "action", "Scene", "RunResult", "__version__",
    "Mode", "Modes", "ModesCrossCheck", "RotatingFrame", "modes",
    "Sensitivities", "sensitivities", "FitResult", "fit", "Measurements", "read_measurements",
    "FitSweep", "fit_sweep",
]
