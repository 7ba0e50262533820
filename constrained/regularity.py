"""Which constraints and effects are undefined at a state: a value or a gradient not finite.

A rod whose particle sits on its anchor (the gradient (x − p)/|x − p| is 0/0) or a 1/r
potential at r = 0 cannot be simulated from there. The test stacks every item's value g_k
(constraint rows; effect terms) into one vector g and evaluates g, ∂g/∂x and (effects) ∂g/∂v
as sparse matrices in one call: O(nnz) for the whole system, whatever its size. An item is
undefined when one of its entries of g, or of its rows' stored entries of the two Jacobians,
is not finite.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .errors import InputError
from .symbols import Symbols
from .system import System


def _item_values(obj, section: str, s: Symbols, built=None) -> list | None:
    """The item's values as a list of SX columns (a constraint's rows as ``rows(s)`` gives
    them, scalars in the usual case: no CasADi call per item; an effect's term) from
    ``built`` or built here; None when it cannot be built (reported by the scene's formula
    checks instead)."""
    try:
        if built is None:
            built = obj.rows(s) if section == "constraints" else obj.term(s)
        values = [row for row, _ in built] if section == "constraints" else [built]
        return [v if isinstance(v, ca.SX) and v.is_column() else ca.vec(ca.SX(v)) for v in values]
    except (InputError, RuntimeError, TypeError, ZeroDivisionError):
        return None


def _bad_rows(matrix: ca.DM) -> np.ndarray:
    """Rows of a sparse DM holding a stored entry that is not finite."""
    values = np.asarray(matrix.nonzeros(), float)
    if np.all(np.isfinite(values)):
        return np.zeros(0, dtype=int)
    rows, _ = matrix.sparsity().get_triplet()
    return np.asarray(rows, dtype=int)[~np.isfinite(values)]


def undefined_items(system: System, t0: float,
                    built: tuple[Symbols, dict] | None = None) -> list[tuple[str, int, object]]:
    """(section, index, item) of each constraint ("constraints") and effect ("effects") whose
    value or gradient is not finite at the system's initial state (positions, velocities) and
    time t0, in scene order. ``built``: the Symbols and {(section, index): rows or term}
    already made for this system (the scene's formula check), reused instead of built again."""
    s, done = built if built is not None else (Symbols(system), {})
    items, constraint_values, effect_values = [], [], []
    owner_c, owner_e = [], []  # row of the stacked vector -> index into items
    for section, objs in (("constraints", system.constraints), ("effects", system.effects)):
        values, owner = (constraint_values, owner_c) if section == "constraints" else (effect_values, owner_e)
        for i, obj in enumerate(objs):
            parts = _item_values(obj, section, s, done.get((section, i)))
            if parts is None:
                continue
            owner.extend([len(items)] * sum(part.numel() for part in parts))
            items.append((section, i, obj))
            values.extend(parts)
    if not items:
        return []
    gc, ge = ca.vertcat(*constraint_values, ca.SX(0, 1)), ca.vertcat(*effect_values, ca.SX(0, 1))
    function = ca.Function("start", [s.x, s.v, s.t],
                           [gc, ca.jacobian(gc, s.x), ge, ca.jacobian(ge, s.x), ca.jacobian(ge, s.v)])
    x0 = np.asarray(system.positions, float).reshape(-1)
    v0 = np.asarray(system.velocities, float).reshape(-1)
    with np.errstate(all="ignore"):
        vc, jc, ve, jex, jev = function(x0, v0, t0)
    owner_c, owner_e = np.asarray(owner_c, dtype=int), np.asarray(owner_e, dtype=int)
    bad = set(owner_c[_bad_rows(vc)]) | set(owner_c[_bad_rows(jc)])
    bad |= set(owner_e[_bad_rows(ve)]) | set(owner_e[_bad_rows(jex)]) | set(owner_e[_bad_rows(jev)])
    return [items[k] for k in sorted(int(k) for k in bad)]
