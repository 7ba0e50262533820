"""Derived quantities along a trajectory: multipliers, constraint forces, energy, residuals.

Only what a run asks for (``wanted``) is computed. The action, which needs the Lagrangian
along the path, is added by the caller (constrained.action).
"""

from __future__ import annotations

import numpy as np

from . import residual
from .manifold import constraint_forces_along, multipliers_along
from .model import Model
from .trajectory import QUANTITIES, Trajectory

#: Output names accepted by ``outputs`` (``positions``/``velocities`` are always computed).
OUTPUT_NAMES = frozenset({"positions", "velocities", *QUANTITIES})


def trajectory_from(model: Model, t, X, V, wanted, stats=None) -> Trajectory:
    """Build a Trajectory with the derived quantities in ``wanted`` evaluated at each sample."""
    t = np.asarray(t, float)
    n = len(t)
    N = model.n_particles
    traj = Trajectory(
        t=t,
        x=X.reshape(n, N, 3),
        v=V.reshape(n, N, 3),
        particle_names=list(model.particle_names),
        constraint_labels=list(model.constraint_labels),
        stats=dict(stats or {}),
    )
    if n == 0:
        return traj
    if "multipliers" in wanted or "constraint_forces" in wanted:
        lam = multipliers_along(model, X, V, t)
        if "multipliers" in wanted:
            traj.multipliers = lam
        if "constraint_forces" in wanted:
            traj.constraint_forces = constraint_forces_along(model, X, t, lam)
    if "energy" in wanted:
        traj.energy = model.evaluate(model.energy, X, V, t)[0].ravel()
    if "constraint_residual" in wanted:  # in metres, whatever the scale of the formulas
        traj.constraint_residual = residual.position_residual_along(model, X, t)
    if "velocity_residual" in wanted:  # in m/s
        traj.velocity_residual = residual.velocity_residual_along(model, X, V.reshape(n, -1), t)
    return traj
