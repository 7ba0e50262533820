"""Statics with one-sided constraints: which of their rows hold at an equilibrium.

The active set of a static problem (constrained.analysis.statics): the one-sided rows held are
solved as equalities (``held_system``), then a held row whose force has the forbidden sign is
dropped, or a slack row whose gap is violated is added (``statics_active_set``), until neither
remains.
"""

from __future__ import annotations

import numpy as np

from ...model.structure import Model
from ...run.unilateral import gaps, one_sided, scales


def held_system(system, model: Model, held) -> tuple[object, np.ndarray]:
    """The System whose constraints are the two-sided ones and the one-sided rows ``held``
    (a one-sided plane or surface on several particles is split into one constraint per
    particle, so each row is held or slack on its own), and for each of its rows the row of
    ``model`` it is (``row_map``)."""
    import copy

    from ...model.system import System

    info = one_sided(model)
    owner = model.constraint_owner
    constraints, row_map = [], []
    for i, c in enumerate(system.constraints):
        rows = [k for k in range(model.n_constraints) if owner[k] == i]
        if not c.unilateral:
            constraints.append(c)
            row_map += rows
            continue
        particles = getattr(c, "particles", None)
        for j, k in enumerate(rows):
            if k not in held or k not in info.rows:
                continue
            if particles is not None and len(particles) > 1:
                part = copy.copy(c)
                part.particles = [particles[j]]
                constraints.append(part)
            else:
                constraints.append(c)
            row_map.append(k)
    sub = System(system.particles, constraints, system.effects, system.parameters, system.name)
    return sub, np.array(row_map, dtype=int)


def statics_active_set(model: Model, x, t, multipliers_full, held, size: float):
    """One step of the statics active set at an equilibrium x of the held rows: the row to
    drop (a held one-sided row with a force of the forbidden sign, the most negative) or to
    add (a slack row whose gap is violated there, the most violated), as ("drop"|"add", row),
    or None when the held set is consistent."""
    info = one_sided(model)
    s = scales(model, x, t)
    mu = info.side * np.asarray(multipliers_full, float) * s
    bad = [(mu[k], k) for k in info.rows if k in held and mu[k] < -1e-9 * max(1.0, np.max(np.abs(mu)))]
    if bad:
        return "drop", min(bad)[1]
    g = gaps(model, x, t) / s
    violated = [(g[k], k) for k in info.rows if k not in held and g[k] < -1e-9 * size]
    if violated:
        return "add", min(violated)[1]
    return None
