"""The scene format's keys and defaults: the top-level tables, ``[simulate]``'s defaults and
limits, ``[outputs]``'s choices, ``[expect]``'s keys and each constraint's and effect's keys
(docs/scene-format.md). Validation (constrained.scene_build) reads them; so do the CLI and
the sweeps."""

from __future__ import annotations

from typing import Any

from ..defaults import DEFAULT_METHOD
from ..run.trajectory import QUANTITIES

TOP_LEVEL_TABLES = (
    "scene",
    "particles",
    "constraints",
    "effects",
    "parameters",
    "definitions",
    "simulate",
    "outputs",
    "reduced",
    "expect",
    "events",
)

SIMULATE_DEFAULTS: dict[str, Any] = {
    "t_end": None,
    "t_start": 0.0,
    "method": DEFAULT_METHOD,
    "rtol": 1e-8,
    "atol": 1e-10,
    "dt": None,
    "output_dt": None,
    "samples": None,
    "base": "DOP853",
    "max_initial_correction": 1e-3,
    "compiled": "auto",
    "rest_speed": None,  # one-sided constraints: rebounds slower than this (m/s) settle; None: 1000 × atol
    "max_steps": None,  # the step limit; None: the driver's default (solvers/driver.py)
}

#: Limits of [simulate]: output samples a run may store, fixed steps it may take (dt), and
#: the largest |time| (beyond it a float cannot resolve a step).
MAX_SAMPLES = 1_000_000
MAX_STEPS = 1e10
MAX_TIME = 1e12

OUTPUT_QUANTITIES = ("positions", "velocities", *QUANTITIES)
OUTPUT_PLOTS = (
    "trajectory",
    "energy",
    "constraint_residual",
    "constraint_forces",
    "multipliers",
    "phase",
    "action",
    "animation",
    "viewer",
)
OUTPUT_FORMATS = ("npz", "csv")
OUTPUT_DEFAULTS: dict[str, list[str]] = {
    "quantities": ["multipliers", "constraint_forces", "energy", "constraint_residual"],
    "plots": [],
    "formats": ["npz"],
}

#: Keys of the [expect] table (see docs/scene-format.md, "[expect]").
EXPECT_KEYS = (
    "energy_drift",
    "constraint_residual",
    "velocity_residual",
    "final",
    "closed_form",
    "bounds",
    "reaches",
    "conserved",
    "period",
)
# Keys of one [expect.conserved.NAME] entry.
_CONSERVED_KEYS = ("axis", "point", "translation", "tol")

# Scene keys of each constraint / effect type: (required, optional), besides type and name.
CONSTRAINT_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "distance": (("a", "length"), ("b", "point")),
    "pin": (("a", "point"), ()),
    "plane": (("particles", "normal"), ("offset",)),
    "surface": (("particles", "expr"), ()),
    "curve": (("particles", "expr"), ()),
    "custom": (("expr",), ()),
    "velocity": (("expr",), ()),
    "knife_edge": (("particle",), ("across", "along", "normal")),
    "rolling": (("particle", "normal"), ("radius", "a", "b")),
}
EFFECT_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "gravity": (("g",), ("particles",)),
    "spring": (("a", "k"), ("b", "point", "rest")),
    "potential": (("expr",), ()),
    "central": (("a", "expr"), ("b", "point")),
    "pairwise": (("expr",), ("particles",)),
    "damping": (("coefficient",), ("particles", "a", "b")),
    "force": (("particle", "expr"), ()),
    "electromagnetic": (("charges",), ("phi", "A")),
}
#: Optional keys every constraint type takes: one-sided (see docs/scene-format.md).
ONE_SIDED_KEYS = ("unilateral", "restitution")
#: Keys of one [[events]] entry: (required, optional).
EVENT_KEYS = (("name", "expr"), ("direction", "stop"))
