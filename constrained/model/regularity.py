"""Which constraints and effects are undefined at a state: a value or a gradient not finite.

A rod whose particle sits on its anchor (the gradient (x − p)/|x − p| is 0/0) or a 1/r
potential at r = 0 cannot be simulated from there. The test stacks every item's value g_k
(constraint rows; effect terms) into one vector g and evaluates g, ∂g/∂x and (effects) ∂g/∂v
as sparse matrices in one call: O(nnz) for the whole system, whatever its size. An item is
undefined when one of its entries of g, or of its rows' stored entries of the two Jacobians,
is not finite.

With the system's Model (``model``: constrained.model) the same vector is made of
the Structure's rows and effect terms, as a Function of (x, v, t, p) built once per
structure: reading a scene again with other numbers (a sweep, a fresh call) evaluates it and
builds nothing.
"""

from __future__ import annotations

import itertools
import operator

import casadi as ca
import numpy as np

from ..errors import InputError
from .cache import built_once
from .constraints import Distance
from .structure import Model, Structure
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


def undefined_items(system: System, t0: float, built: tuple[Symbols, dict] | None = None, *,
                    model: Model | None = None, jacobian=None,
                    effects_finite: bool = False) -> list[tuple[str, int, object]]:
    """(section, index, item) of each constraint ("constraints") and effect ("effects") whose
    value or gradient is not finite at the system's initial state (positions, velocities) and
    time t0, in scene order. ``built``: the Symbols and {(section, index): rows or term}
    already made for this system (the scene's formula check), reused instead of built again;
    ``model``: the system's Model, whose Structure's expressions are used instead (nothing built
    per call), at its parameter vector; ``jacobian``:
    ``(x, t) -> (f, J)`` of the constraint rows to use instead of the Structure's (a large
    model's vectorized build); ``effects_finite``: the effects' values and gradients are known
    to be finite there (a large model's potentials, ``manifold.potential_forces_finite``), so
    they are not checked one by one."""
    if model is not None:
        return _undefined_in(system, t0, model.structure, model.parameter_vector, jacobian, effects_finite)
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


def _start_check(structure: Structure) -> tuple[ca.Function, np.ndarray]:
    """``(x, v, t, p) -> (g_e, ∂g_e/∂x, ∂g_e/∂v)`` of the Structure's effect terms and the item
    of each row of g_e (once per structure); the rows are the Structure's ``jacobian``."""
    def build():
        e = structure.expressions
        terms = [term if isinstance(term, ca.SX) and term.is_column() else ca.vec(ca.SX(term))
                 for term in e.terms]  # (an SX column as it is: a copy of each costs 0.1 ms)
        ge = ca.vertcat(*terms, ca.SX(0, 1))
        owner = np.repeat(np.arange(len(terms)), [term.numel() for term in terms]).astype(int)
        function = ca.Function("start", [e.x, e.v, e.t, e.p],
                               [ge, ca.jacobian(ge, e.x), ca.jacobian(ge, e.v)])
        return function, owner

    return built_once(structure, "start check", build)


def _undefined_in(system: System, t0: float, structure: Structure, p: np.ndarray, jacobian=None,
                  effects_finite: bool = False) -> list:
    """``undefined_items`` by the Structure's Functions at the Model's parameter vector ``p``
    (the parameters, the plain numbers, a pair potential's neighbour list)."""
    x0 = np.asarray(system.positions, float).reshape(-1)
    v0 = np.asarray(system.velocities, float).reshape(-1)
    effects, owner_e = (None, np.zeros(0, int)) if effects_finite else _start_check(structure)
    with np.errstate(all="ignore"):
        bad = set()
        if structure.n_constraints:  # f and J, then the velocity level [J; A], [f_t; b]
            owner_c = np.asarray(structure.constraint_owner, dtype=int)
            if jacobian is not None:  # (no velocity rows: a large model's own f and J)
                vc, jc = jacobian(x0, t0)
                matrices = (ca.DM(np.asarray(vc, float).reshape(-1, 1)), jc)
            else:
                matrices = (*structure.function("jacobian")(x0, t0, p),
                            *structure.function("velocity_terms")(x0, t0, p))
            rows = [_bad_rows(m) for m in matrices]
            bad |= {("constraints", int(k)) for k in owner_c[np.concatenate(rows)]}
        if owner_e.size:
            ve, jex, jev = effects(x0, v0, t0, p[:structure.expressions.p.numel()])  # (no neighbour list)
            rows = np.concatenate([_bad_rows(ve), _bad_rows(jex), _bad_rows(jev)])
            bad |= {("effects", int(k)) for k in owner_e[rows]}
        values = structure.pair_potentials.values(x0, t0, p)
        for (V, F), owner in zip(values, structure.pair_owner, strict=True):
            if not (np.isfinite(V) and np.all(np.isfinite(F))):  # a pair at r = 0 under 1/r, say
                bad.add(("effects", owner))
    items = {"constraints": system.constraints, "effects": system.effects}
    return [(section, k, items[section][k]) for section, k in sorted(bad)]


#: A rod shorter than this fraction of the system's size (its largest start coordinate) is not
#: resolved: the start is accepted within 1e-8 of the size, positions are resolved to 2.2e-16 of
#: it, and the rod's direction — its constraint force — is then noise of its own size, or 0/0
#: where the two ends round to one point (a rod of length 0 is refused outright).
UNRESOLVED_FRACTION = 1e-12
#: Below this no rod can be computed at all: |x_a − x_b| is the root of a sum of squares, and the
#: squares of a smaller difference are subnormal (below 2.2e-308) or zero.
SMALLEST_LENGTH = 1e-150


def unresolved_rods(system: System) -> list[tuple[int, Distance, float, float]]:
    """(index, rod, length, smallest resolved length) of each ``distance`` constraint with a
    plain length too short for the coordinates of the system at its start (a subnormal 1e-320,
    or 1e-20 m among coordinates of metres): such a rod either holds its two ends on one point,
    where its direction is undefined (0/0, a run of NaN), or on a direction that is round-off.
    O(N) in the constraints: one pass over the rods' lengths, and an item-by-item look only at
    those below the bound of the positions alone and at rods to a point (whose point counts)."""
    positions = np.asarray(system.positions, float).reshape(-1)
    size = float(np.max(np.abs(positions), initial=0.0))
    constraints = system.constraints
    rods = list(itertools.compress(itertools.count(), map(operator.is_, map(type, constraints),
                                                          itertools.repeat(Distance))))
    items = list(map(constraints.__getitem__, rods))
    given = list(map(operator.attrgetter("length"), items))
    # (floats alone, a cloth's 19,800: as they are, in one pass; else each by _plain_length)
    lengths = np.array(given if _FLOAT.issuperset(map(type, given)) else list(map(_plain_length, given)),
                       dtype=float).reshape(-1)
    to_points = np.fromiter(map(operator.is_, map(operator.attrgetter("b"), items), itertools.repeat(None)),
                            bool, len(items))
    floor = max(UNRESOLVED_FRACTION * size, SMALLEST_LENGTH)  # (a rod to a point: its point's too)
    found = []
    for k in np.flatnonzero((lengths < floor) | to_points):  # (nan, a formula: never below)
        i = rods[k]
        c = constraints[i]
        anchor = np.asarray(c.point, float) if c.b is None and not any(
            isinstance(coordinate, str) for coordinate in c.point) else np.zeros(1)
        smallest = max(UNRESOLVED_FRACTION * max(size, float(np.max(np.abs(anchor)))), SMALLEST_LENGTH)
        if 0 < lengths[k] < smallest:
            found.append((i, c, float(lengths[k]), smallest))
    return found


_FLOAT = frozenset((float,))


def _plain_length(length) -> float:
    """A rod's length as a number, NaN for a formula (or a bool)."""
    return float(length) if isinstance(length, int | float) and not isinstance(length, bool) else np.nan


def unresolved_reason(rod: Distance, length: float, smallest: float) -> str:
    """Why a rod of ``unresolved_rods`` cannot be simulated, and what to do."""
    ends = f"'{rod.a}' and '{rod.b}'" if rod.b is not None else f"'{rod.a}' and its point"
    return (f"a rod of length {length:.3g} m is shorter than the positions of this scene resolve "
            f"({smallest:.3g} m: {UNRESOLVED_FRACTION:g} of the largest start coordinate, and never "
            f"below {SMALLEST_LENGTH:g} m, where |x_a - x_b| is computed from squares that underflow): "
            f"it would hold {ends} on one point, where its direction and its force are undefined "
            "(0/0); merge the two into one particle, or give the rod a length the positions resolve")
