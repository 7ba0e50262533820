"""constrained: particles under holonomic constraints, constraint forces as Lagrange multipliers."""

from .action import (  # the action of a run: constrained.action.action (the module keeps its name)
    ActionResult,
    PathResult,
    StationarityResult,
    stationarity,
    stationary_path,
)
from .analysis import ConstraintReport, constraint_report, degrees_of_freedom
from .constraints import Curve, Custom, Distance, Pin, Plane, Surface
from .crosscheck import cross_check
from .derivation import (
    Conservation,
    EquationCheck,
    check_equations,
    check_generalized_forces,
    check_lagrangian,
    conservation,
    describe,
)
from .effects import Central, Damping, Electromagnetic, Force, Gravity, Pairwise, Potential, Spring
from .errors import ConstrainedError, InconsistentStateError, InputError, RunInterrupted, SimulationError
from .model import Model, assemble
from .reduced import CrossCheck, ReducedModel
from .simulate import simulate
from .statics import (
    Equilibrium,
    constraint_virtual_work_residual,
    equilibrium,
    generalized_forces,
    virtual_work,
)
from .sweep import SweepResult  # the function: constrained.sweep.sweep (the module keeps its name)
from .symmetry import (
    SymmetryReport,
    charge_drift,
    euler_lagrange,
    is_symmetry,
    is_symmetry_reduced,
    noether_charge,
    noether_charge_reduced,
    with_total_derivative,
)
from .system import Particle, System
from .trajectory import Trajectory


def load_scene(path, overrides=None):
    """Load a TOML scene: a Scene with ``.system``, ``.settings``, ``.outputs``."""
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
    "SweepResult",
]
