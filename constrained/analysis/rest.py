"""Velocity constraints at rest (model/velocity.py): whether rest is allowed, and what their
multipliers say at an equilibrium.

At rest (v = 0) a velocity row a·v + b = 0 reads b(x, t) = 0; it lasts while ∂b/∂t = 0 too
(its acceleration-level row A x'' + γ_v = 0 has γ_v = ∂b/∂t at v = 0). Where rest is
allowed, d'Alembert's principle asks F·δx = 0 for the virtual displacements with J δx = 0
and A δx = 0, i.e. F + Jᵀλ + Aᵀμ = 0: the velocity rows' forces Aᵀμ do no work at rest
(their power is μ·(A v) = −μ·b = 0), but they can hold a system that the holonomic
constraints alone would let go — a skate standing across a slope is held by its blade
(μ = its weight's component down the slope). Such equilibria come in families (the skate
rests anywhere on the slope, turned across it), and the energy method decides their
stability only where μ = 0 and V has a strict minimum on the configuration space.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..model.structure import Model

#: A velocity row's force counts as zero below this fraction of the forces at the equilibrium.
FORCE_RTOL = 1e-9


def require_rest(model: Model, x: np.ndarray, t: float, size: float) -> None:
    """Refuse a configuration where rest breaks a velocity row: b(x, t) ≠ 0 (rest not
    allowed) or ∂b/∂t ≠ 0 (it would not last), within round-off of the row's scale."""
    C_f, C = model.n_position_rows, model.n_constraints
    if C_f == C:
        return
    zero = np.zeros_like(x)
    _, b = model.velocity_terms(x, t)
    _, G, gamma = model.dynamics(x, zero, t)
    G = np.asarray(G, float).reshape(C, -1)
    b, gamma = np.asarray(b, float).ravel(), np.asarray(gamma, float).ravel()
    for k in range(C_f, C):
        scale = float(np.max(np.linalg.norm(G[k].reshape(-1, 3), axis=1), initial=0.0)) or 1.0
        what = ("b ≠ 0 at v = 0: it prescribes a velocity" if abs(b[k]) > 1e-12 * scale * size else
                "∂b/∂t ≠ 0 at v = 0: rest would not last" if abs(gamma[k]) > 1e-12 * scale * size else None)
        if what:
            raise InputError(f"no static equilibrium: the velocity constraint '{model.constraint_labels[k]}' "
                             f"does not allow rest ({what})")


def velocity_forces_note(model: Model, G: np.ndarray, multipliers: np.ndarray,
                         force_scale: float) -> tuple[str, bool]:
    """(the report's sentence on the velocity rows at an equilibrium, whether they carry a
    force there); ('', False) without velocity rows."""
    C_f = model.n_position_rows
    if C_f == model.n_constraints:
        return "", False
    force = G[C_f:].T @ multipliers[C_f:]
    if np.max(np.abs(force), initial=0.0) <= FORCE_RTOL * force_scale:
        return ("velocity constraints: no force at this equilibrium (μ = 0: the holonomic constraints "
                "balance the applied forces); at rest they do no work", False)
    return ("velocity constraints: they hold the system at rest here (μ ≠ 0, as a skate's blade holds it "
            "across a slope) and do no work (power −μ·b = 0); such equilibria form families, and the "
            "energy method does not decide their stability", True)
