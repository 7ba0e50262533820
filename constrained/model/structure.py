"""Assembly: System -> Model, the CasADi functions every solver and analysis uses.

Equations (DESIGN.md): ``M x'' = F(x, x', t) + Jᵀ λ`` with ``f(x, t) = 0``. Differentiating
the constraints twice gives ``J x'' + γ = 0``, ``γ = d/dt(J v + f_t) − J x''``, which CasADi
forms by AD as ``γ = ∂c/∂x · v + ∂c/∂t`` for ``c = J v + f_t``. Velocity constraints
(model/velocity.py) add rows ``A v + b = 0`` after f's at the velocity and acceleration levels
(``G = [J; A]``, multipliers [λ; μ]). Only the terms the system needs are built: ``active_terms``.
"""

from __future__ import annotations

import collections
import functools
import threading
from collections.abc import Mapping
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..bulk import collector_paused
from ..errors import InputError
from . import expressions, lifting, velocity
from .constraints import stacked_rows
from .effects import effect_terms, forces
from .pairs.potentials import OUTPUTS as _PAIR_OUTPUTS
from .pairs.potentials import PairPotentials
from .symbols import Symbols
from .system import require_system

#: Functions bound to parameter values that a Structure keeps (the most recent), so that
#: Models with equal values share them.
BOUND_FUNCTIONS_KEPT = 64


class Structure:
    """What the structure of a System decides, built once: which particles, constraints and
    effects, which formulas. Its Functions take the parameter vector ``p`` as their last input
    (``dynamics(x, v, t, p)``, ...); the numbers of a scene are values of ``p``, never
    constants, so Models for other parameter values share one Structure
    (``Model.with_parameters``) and nothing is parsed or differentiated again.

    ``p`` is the named parameters (``parameter_names``, in order) followed by the system's
    ``n_numbers`` nonzero plain numbers (masses, lengths, ``k``, ``g`` entries …: the hidden
    parameters of constrained.lifting), so a system that differs only in such a number has
    this Structure too (``lift=False`` keeps them as constants: a reference for tests).
    ``functions`` / ``function(name)``: the parametric Functions.
    """

    #: Structures built in this process (each one parses and differentiates the system).
    builds = 0
    #: (numbers as bytes, the labels filled with them): the most recent Model's (constraint_labels).
    filled_labels: tuple | None = None

    def __init__(self, system, *, lift: bool = True, walked: tuple | None = None):
        # (walked: the fingerprint's walk of the system, constrained.lifting.lift)
        system, numbers = lifting.lift(system, walked) if lift else (system, np.zeros(0))
        with expressions.shown(numbers):  # a refusal names the scene's numbers, never their tokens
            self._assemble(system, numbers)

    def _assemble(self, system, numbers: np.ndarray) -> None:
        s = Symbols(system, symbolic_parameters=True, numbers=len(numbers))
        x, v, t, p = s.x, s.v, s.t, s.p
        n3 = 3 * system.n_particles
        self.parameter_names: tuple[str, ...] = tuple(system.parameters)
        #: How many plain numbers of the system are hidden parameters (constrained.lifting):
        #: p is the named parameters' values, then these.
        self.n_numbers = len(numbers)
        self.n_particles = system.n_particles
        self.n_coordinates = n3
        self.particle_names = tuple(q.name for q in system.particles)
        active = set()

        # rows of f (runs of rods, a plane's rows: SX columns kept whole), the velocity rows
        rows, velocity_rows, labels, owners, first_row, batches = stacked_rows(system.constraints, s)
        #: The rows' labels (position rows, then velocity rows), a plain number written as a
        #: token (``expressions.fill`` puts a Model's values in).
        self.constraint_labels: list[str] = labels
        self.constraint_owner = owners
        #: Rows of f (position level); the velocity rows (model/velocity.py) follow them.
        self.n_position_rows = len(rows)
        self.n_constraints = len(rows) + len(velocity_rows)
        f = functools.cache(rows.column)  # (its columns made into SX nodes when a Function asks)
        self.rheonomic = bool(rows) and rows.may_depend_on(t)  # (≡ ca.depends_on(f, t): f is a stack)
        if rows:
            active.add("constraints")
        if self.rheonomic:
            active.add("rheonomic")

        @functools.cache
        def kinematics() -> tuple:
            """(J, G, c₀, γ), differentiated when a Function that needs them is first made (a
            large model's runs use the vectorized build's instead: constrained.manifold)."""
            J = ca.jacobian(f(), x)
            if self.rheonomic:
                f_t = ca.jacobian(f(), t)
                c = ca.mtimes(J, v) + f_t
                gamma = ca.jtimes(c, x, v) + ca.jacobian(c, t)
            else:
                f_t = ca.SX(self.n_position_rows, 1)  # structurally zero: no f_t terms
                gamma = ca.jtimes(ca.mtimes(J, v), x, v)
            # the velocity level, J v + f_t = 0 then A v + b = 0 (G = [J; A]), and its derivative
            return (J, *velocity.velocity_level(system, velocity_rows, J, f_t, gamma, x, v, t))

        if velocity_rows:
            kinematics()  # now: its refusals name the scene's items (and its numbers, not tokens)
            active.add("velocity_constraints")

        slots = {"potential": [], "generalized_potential": [], "dissipation": [], "applied_force": []}
        #: Pair potentials built as one mapped kernel each (constrained.model.pairs), apart from
        #: the SX graph: ``pairs`` (PairTerms), from the effects ``pair_owner``; p is the
        #: ``n_physical`` parameters and numbers, then their neighbour lists (``n_p`` in all).
        self.pair_potentials = PairPotentials(system, s, n3)
        self.pairs, self.pair_owner = self.pair_potentials.terms, self.pair_potentials.owners
        self.n_physical, self.n_p = self.pair_potentials.n_physical, self.pair_potentials.n_p
        terms, term_batches = effect_terms(system.effects, s, skip=self.pair_owner)  # (a pair kernel's: 0)
        slot = np.array([e.slot for e in system.effects], dtype=object)
        own = np.ones(len(slot), bool)  # (not a pair kernel's)
        own[list(self.pair_owner)] = False
        potential = own & (slot == "potential")
        in_slot = np.where(potential, np.cumsum(potential) - 1, -1)  # each potential's place in its slot
        slots["potential"] = terms.select(potential)  # (a Stacked: the springs' columns kept whole)
        for k in np.flatnonzero(own & ~potential):
            slots[slot[k]].append(terms[k])
        F, V, U, dU_dv, forcing = forces(slots, x, v, t, deferred=True)  # F(), V(): built when first asked
        active |= forcing
        #: Whether the applied forces depend on v (damping, magnetism, a force of v; pairs never).
        # (with potentials alone, F = −∂V/∂x: free of v when V is, which is the smaller graph to ask)
        potentials_only = not any(slots[k] for k in ("generalized_potential", "dissipation", "applied_force"))
        may = not potentials_only or (slots["potential"].may_depend_on(v) and ca.depends_on(V(), v))
        self.forces_depend_on_velocity = bool(may and ca.depends_on(F(), v))
        if self.pairs:
            active |= {"potential", *(["time_dependent_forces"] * self.pair_potentials.time_dependent)}
        self.active_terms = frozenset(active)
        #: The expressions the Functions are made of: the constraint rows (in order) and the
        #: effects' terms by slot (constrained.mapped cuts them into repeated kernels).
        self.expressions = Expressions(x, v, t, p, rows, slots, terms,
                                       tuple(b.placed(first_row) for b in batches),
                                       tuple(b.placed(in_slot) for b in term_batches))

        #: Whether the masses are symbols of p (plain numbers and formulas are): step graphs
        #: then take them from p, not from a Model's numbers.
        self.masses_symbolic = s.mass_entries is not None or any(isinstance(m, ca.SX) for m in s.masses)
        #: When every mass is an entry of p (a plain number, or a parameter's name): the entry
        #: of each coordinate's mass (3N indices), so that step graphs gather them (index
        #: data) instead of calling the "masses" Function (3N operations of generated code).
        self.mass_entries = None
        if self.masses_symbolic:
            m = s.mass_column()
            entries = s.mass_entries if s.mass_entries is not None else s.entries_of(s.masses)
            if entries is not None:
                self.mass_entries = np.repeat(np.asarray(entries, dtype=np.int64), 3)
        else:
            m = np.repeat(np.asarray(s.masses, float), 3)

        @functools.cache
        def energy_parts() -> tuple:
            """(the 3N masses, T, h − T, h), built when a Function that needs them is first made
            (a large model's runs use the vectorized build's energy: 0.02 s at 10⁴ particles)."""
            # each mass three times, in place
            m3 = ca.reshape(ca.repmat(m.T, 3, 1), n3, 1) if self.masses_symbolic else ca.DM(m)
            T = 0.5 * ca.dot(m3 * v, v)
            potential_part = V() + U - ca.dot(v, dU_dv)  # h − T: what a step adds to ½ vᵀMv for h
            return m3, T, potential_part, T + potential_part
        # The Functions are made when first asked for (making one sorts its whole graph).
        self._p = p
        # every Function takes the whole p, the neighbour lists' entries after the physical ones
        # (those of the pair outputs read them; the others ignore them)
        self._p_input = p if self.n_p == self.n_physical else ca.vertcat(
            p, ca.SX.sym("lists", self.n_p - self.n_physical))
        self._parts: dict[str, tuple] = {}
        self._functions: dict[str, ca.Function] = {}
        self._fixed: dict[str, ca.Function | None] = {}
        self._used: dict[str, np.ndarray] = {}
        self._bound: collections.OrderedDict[tuple, ca.Function] = collections.OrderedDict()
        self._lock = threading.Lock()

        def function(name, inputs, in_names, outputs, out_names):
            self._parts[name] = (inputs, in_names, outputs, out_names)

        function("constraint", [x, t], ["x", "t"], lambda: [f()], ["f"])
        function("jacobian", [x, t], ["x", "t"], lambda: [f(), kinematics()[0]], ["f", "J"])
        function("velocity_terms", [x, t], ["x", "t"], lambda: list(kinematics()[1:3]), ["J", "f_t"])
        function("dynamics", [x, v, t], ["x", "v", "t"], lambda: [F(), kinematics()[1], kinematics()[3]],
                 ["F", "J", "gamma"])
        function("energy", [x, v, t], ["x", "v", "t"], lambda: [energy_parts()[3]], ["E"])
        function("forces_and_potential", [x, v, t], ["x", "v", "t"], lambda: [F(), energy_parts()[2]],
                 ["F", "W"])
        function("potential", [x, t], ["x", "t"], lambda: [V()], ["V"])
        function("kinetic", [v], ["v"], lambda: [energy_parts()[1]], ["T"])
        # (3N,): formulas of p, or numbers
        function("masses", [], [], lambda: [ca.SX(energy_parts()[0])], ["m"])
        Structure.builds += 1

    def function(self, name: str, *, lists: bool = True, differentiable: bool = False) -> ca.Function:
        """The parametric Function ``name``: the Model's inputs, then ``p``. ``lists`` False: the
        pair potentials summed over every pair, their neighbour lists unused (what a Model binds:
        a list fixed in it would be stale wherever the particles move; SX symbols write it out).
        ``differentiable``: for a graph that takes derivatives of it (the forces through a
        neighbour list are then the mapped kernel's, not the fused C loop's, which has none)."""
        pairs = bool(self.pairs) and name in _PAIR_OUTPUTS
        key = name if not pairs else (name, lists, lists and differentiable)
        if key not in self._functions:
            inputs, in_names, outputs, out_names = self._parts[name]
            outputs = outputs() if callable(outputs) else outputs
            function = ca.Function(name, [*inputs, self._p_input], outputs, [*in_names, "p"], out_names)
            self._functions[key] = (self.pair_potentials.with_pairs(name, function, lists=lists,
                                                                    differentiable=differentiable)
                                    if pairs else function)
        return self._functions[key]

    @property
    def functions(self) -> dict[str, ca.Function]:
        """name -> parametric Function (``constraint(x, t, p)``, ``dynamics(x, v, t, p)``, …)."""
        return {name: self.function(name) for name in self._parts}

    def fixed(self, name: str) -> ca.Function | None:
        """The Function ``name`` without ``p`` when its outputs do not depend on p (the same
        for every parameter value, shared by all Models of this structure), else None."""
        if name not in self._fixed:
            inputs, in_names, outputs, out_names = self._parts[name]
            outputs = outputs() if callable(outputs) else outputs
            p = self._p
            free = not p.numel() or not any(o.numel() and ca.depends_on(o, p) for o in outputs)
            free = free and not (self.pairs and name in _PAIR_OUTPUTS)  # (those: MX of the full p)
            self._fixed[name] = ca.Function(name, inputs, outputs, in_names, out_names) if free else None
        return self._fixed[name]

    def _uses(self, name: str) -> np.ndarray:
        """Indices of the entries of p that the outputs of Function ``name`` depend on."""
        uses = self._used
        if name not in uses:
            inputs, _, outputs, _ = self._parts[name]  # (the SX graph's; the pairs' below)
            outputs = outputs() if callable(outputs) else outputs
            fun = ca.Function(name, [*inputs, self._p], outputs)
            last = fun.n_in() - 1
            used = {int(c) for i in range(fun.n_out()) if fun.nnz_out(i) and fun.nnz_in(last)
                    for c in fun.jac_sparsity(i, last, True).get_col()}  # sparsity only: O(nnz)
            if self.pairs and name in _PAIR_OUTPUTS and self.pair_potentials.parametric:
                used |= set(range(self.n_physical))  # (bound: every pair, no neighbour list)
            uses[name] = np.array(sorted(used), dtype=np.int64)
        return uses[name]

    def bind(self, name: str, values: np.ndarray) -> ca.Function:
        """The Function ``name`` without its last input ``p``: p fixed at ``values`` (an SX
        Function of the same inputs and outputs as the Model's public ones)."""
        fixed = self.fixed(name)
        if fixed is not None:
            return fixed
        # keyed by the entries of p the Function uses: Models differing elsewhere share it
        key = (name, np.asarray(values, float)[self._uses(name)].tobytes())
        bound = self._bound.get(key)
        if bound is None:  # Models with equal values share the Function objects
            fun = self.function(name, lists=False)
            kind = ca.MX if fun.is_a("MXFunction") else ca.SX
            inputs = [kind.sym(fun.name_in(i), fun.sparsity_in(i)) for i in range(fun.n_in() - 1)]
            outputs = fun.call([*inputs, ca.DM(values)])
            bound = ca.Function(name, inputs, outputs, fun.name_in()[:-1], fun.name_out())
            with self._lock:
                self._bound[key] = bound
                while len(self._bound) > BOUND_FUNCTIONS_KEPT:
                    self._bound.popitem(last=False)
        return bound


@dataclass(frozen=True)
class Expressions:
    """A Structure's symbols and the SX expressions it is built from: ``rows`` (f's rows, in
    order), ``slots`` (slot name -> the effects' terms, constrained.effects) and ``terms``
    (each effect's term, in the system's order)."""

    x: ca.SX
    v: ca.SX
    t: ca.SX
    p: ca.SX
    rows: list
    slots: dict
    terms: list
    #: Rows built by one formula (Batches: ``items`` their constraint's first row in ``rows``).
    row_batches: tuple = ()
    #: Potential terms built so (``items`` the term's place in slots["potential"], ``offsets`` its summand).
    term_batches: tuple = ()


class Model:
    """An assembled system: CasADi Functions in (x, v, t) for the system's parameter values.
    Immutable once built: runs keep their counters and redundancy in their own ``Manifold``
    (constrained.manifold), which also holds the KKT solve.

    Functions (all with flat 3N vectors; p at ``parameter_vector``: the parameters'
    ``parameter_values``, then the plain ``numbers``):
      ``constraint(x, t) -> f``                (C_f,)
      ``jacobian(x, t) -> (f, J)``              J = ∂f/∂x, (C_f, 3N), C_f = n_position_rows
      ``velocity_terms(x, t) -> (G, c₀)``       G v + c₀ = 0: J, f_t, then velocity rows' A, b
      ``dynamics(x, v, t) -> (F, G, γ)``        what the acceleration-level KKT needs (all rows)
      ``energy(x, v, t) -> h``                 h = T + V + U − v·∂U/∂v (the energy function)
      ``potential(x, t) -> V``
      ``kinetic(v) -> T``

    The parameters are inputs, not constants: ``structure.functions`` holds the same Functions
    with ``p`` (values in the order of ``parameter_names``) as their last input, and
    ``with_parameters({"m1": 1.2})`` gives the Model for other values without building
    anything again (the ``structure`` is shared).
    """

    def __init__(self, system, *, structure: Structure | None = None, numbers: np.ndarray | None = None):
        structure = structure if structure is not None else Structure(system)
        if tuple(system.parameters) != structure.parameter_names:
            raise InputError(
                f"the system's parameters ({', '.join(system.parameters) or 'none'}) are not "
                f"those of the structure ({', '.join(structure.parameter_names) or 'none'}); "
                "use Model.with_parameters on a Model of this system")
        self.structure = structure
        self.system = system
        self.parameter_names: tuple[str, ...] = structure.parameter_names
        self.parameter_values = np.array([system.parameters[k] for k in self.parameter_names], float)
        numbers = lifting.numbers(system) if numbers is None else np.asarray(numbers, float)
        if numbers.size != structure.n_numbers:
            raise InputError(
                f"the system has {numbers.size} plain numbers (masses, lengths, constants) where the "
                f"structure has {structure.n_numbers}: it is not a system of this structure; "
                "assemble the system itself")
        #: The system's plain numbers, in the order of ``constrained.lifting``.
        self.numbers = numbers
        #: The values of the parametric Functions' last input p: the parameters, then the
        #: numbers, then the pair potentials' neighbour lists at the system's positions
        #: (``PairPotentials.data``: run data, refreshed by the runs that move far).
        self.parameter_vector = np.concatenate([self.parameter_values, numbers,
                                                structure.pair_potentials.data(system.positions)])
        self.n_particles = structure.n_particles
        self.n_coordinates = structure.n_coordinates
        self.masses = np.repeat(system.masses, 3)
        self.inverse_masses = 1.0 / self.masses
        for array in (self.parameter_values, self.numbers, self.parameter_vector, self.masses,
                      self.inverse_masses):
            array.flags.writeable = False
        self.constraint_owner = structure.constraint_owner
        self.n_constraints, self.n_position_rows = structure.n_constraints, structure.n_position_rows
        self.rheonomic = structure.rheonomic
        self.active_terms = structure.active_terms
        #: The system's data the numeric side needs, copied so the Model does not change.
        self.particle_names = structure.particle_names

    @functools.cached_property
    def constraint_labels(self) -> list[str]:
        """One label per constraint row (its plain numbers the system's)."""
        structure = self.structure
        if not structure.n_numbers:
            return structure.constraint_labels
        key = self.numbers.tobytes()  # (Models of equal numbers fill them once: a scene's check, its run)
        filled = structure.filled_labels
        if filled is None or filled[0] != key:
            labels = expressions.fill_all(structure.constraint_labels, self.numbers)
            filled = structure.filled_labels = (key, labels)
        return list(filled[1])

    @property
    def parameters(self) -> dict[str, float]:
        """The parameters' values, name -> number."""
        return dict(zip(self.parameter_names, self.parameter_values.tolist(), strict=True))

    def with_parameters(self, parameters: Mapping[str, float] | None = None) -> Model:
        """The Model for other values of some parameters (the rest keep theirs). Shares this
        Model's structure: nothing is parsed or differentiated again (``Structure.builds``
        does not grow). Masses, initial positions and velocities given by formulas follow
        (``model.system`` is ``system.with_parameters(parameters)``). Unknown names,
        non-finite values and masses that come out non-positive raise InputError."""
        if not parameters:
            return self
        return Model(self.system.with_parameters(parameters), structure=self.structure,
                     numbers=self.numbers)

    @functools.cached_property
    def symbols(self) -> Symbols:
        """Symbols of ``system`` with the parameters' values as numbers, for analyses that
        build their own expressions (effects' terms, formulas) to go with this Model's."""
        return Symbols(self.system)

    def _bound(self, name: str) -> ca.Function:
        return self.structure.bind(name, self.parameter_vector)

    def parametric(self, name: str, *, differentiable: bool = False) -> ca.Function:
        """The Function ``name`` with the parameter vector p as its last input (the
        structure's: shared by every Model of this structure, whatever the values; this
        Model's p is ``parameter_vector``); ``differentiable``: see ``Structure.function``."""
        return self.structure.function(name, differentiable=differentiable)

    @property
    def masses_follow_parameters(self) -> bool:
        """Whether the structure's masses are symbols of p (a plain number or a formula of the
        parameters): step graphs built for the structure then take them from p."""
        return self.structure.masses_symbolic

    constraint = functools.cached_property(lambda self: self._bound("constraint"))
    jacobian = functools.cached_property(lambda self: self._bound("jacobian"))
    velocity_terms = functools.cached_property(lambda self: self._bound("velocity_terms"))
    dynamics = functools.cached_property(lambda self: self._bound("dynamics"))
    energy = functools.cached_property(lambda self: self._bound("energy"))
    potential = functools.cached_property(lambda self: self._bound("potential"))
    kinetic = functools.cached_property(lambda self: self._bound("kinetic"))

    # --- batch evaluation along a trajectory ----------------------------------------------
    def evaluate(self, function: ca.Function, *columns: np.ndarray) -> list[np.ndarray]:
        """Evaluate ``function`` at many points at once (CasADi ``map``); columns are (T, k),
        outputs (rows, T·cols) as the mapped Function's. Dense inputs and outputs go through
        its FunctionBuffer: a (T, k) C-ordered array is the column-major (k, T) input as it
        is, so nothing is converted element by element (a DM of 10⁶ numbers costs ~0.15 s)."""
        n = columns[0].shape[0]
        mapped = _mapped(function, n)
        args = [np.ascontiguousarray(np.asarray(c, float).reshape(n, -1)) for c in columns]
        dense = all(function.size2_in(i) == 1 and mapped.sparsity_in(i).is_dense()  # column inputs
                    and mapped.nnz_in(i) == a.size for i, a in enumerate(args)) and all(
            mapped.sparsity_out(i).is_dense() for i in range(mapped.n_out()))
        if dense:
            buf, run = mapped.buffer()
            res = [np.empty(mapped.nnz_out(i)) for i in range(mapped.n_out())]
            for i, a in enumerate(args):
                buf.set_arg(i, memoryview(a))
            for i, r in enumerate(res):
                buf.set_res(i, memoryview(r))
            run()
            if not buf.ret():
                return [r.reshape(mapped.size2_out(i), mapped.size1_out(i)).T for i, r in enumerate(res)]
        out = mapped(*[a.T for a in args])  # sparse parts, or an evaluation error to raise
        out = out if isinstance(out, tuple) else (out,)
        return [np.asarray(o) for o in out]

    def __repr__(self) -> str:
        return (
            f"Model({self.n_particles} particles, {self.n_constraints} constraint rows, "
            f"active: {', '.join(sorted(self.active_terms)) or 'none'})"
        )


#: Functions mapped over n samples (``Model.evaluate``), the most recent few: blocks of one
#: size along a trajectory map once (a map of a large model's Function takes tens of ms).
_MAPPED: collections.OrderedDict = collections.OrderedDict()
MAPPED_KEPT = 8


def _mapped(function: ca.Function, n: int) -> ca.Function:
    key = (id(function), n)
    with _structures_lock:
        entry = _MAPPED.get(key)
        if entry is not None and entry[0] is function:
            _MAPPED.move_to_end(key)
            return entry[1]
    mapped = function.map(n)
    with _structures_lock:
        _MAPPED[key] = (function, mapped)
        while len(_MAPPED) > MAPPED_KEPT:
            _MAPPED.popitem(last=False)
    return mapped


def assemble(system, parameters: Mapping[str, float] | None = None, *, reuse: bool = True) -> Model:
    """Build the Model of a System (the only step that makes CasADi symbols), for the
    system's parameter values updated by ``parameters``.

    ``reuse``: a System with the same structure as one assembled before in this process (the
    same particles, constraints, effects, parameter names and definitions; initial state,
    parameter values and nonzero plain numbers — masses, lengths, constants — may differ)
    gets that Structure again instead of a new one
    (see ``structure_fingerprint`` and ``kept_structure``)."""
    require_system(system, "assemble")
    structure, numbers = kept_structure(system) if reuse else (None, None)
    return Model(system, structure=structure, numbers=numbers).with_parameters(parameters)


#: The Structures ``assemble`` keeps for reuse hold this many coordinates at most, in all.
STRUCTURE_CACHE_COORDINATES = 3000
_structures: collections.OrderedDict[str, Structure] = collections.OrderedDict()
#: [fingerprint, Structure] of the most recent system over STRUCTURE_CACHE_COORDINATES.
_largest: list = [None, None]
_structures_lock = threading.Lock()


def structure_fingerprint(system) -> str | None:
    """A hash of everything a Structure is built from: particle names and masses (numbers, or
    their formulas), each constraint and effect (its class and every attribute), the parameter
    names in order and the definitions. Not the initial state, not the parameters' values, not
    the nonzero plain numbers of masses and items' numeric fields (constrained.lifting: only
    where they stand). None when an item holds a value that cannot be described exactly (then
    nothing is reused)."""
    return _fingerprint(system)[0]


def _fingerprint(system) -> tuple[str | None, np.ndarray, tuple | None]:
    """``(structure_fingerprint(system), lifting.numbers(system), the walk for lifting.lift)``
    in one walk."""
    try:
        key, values, walked = lifting.fingerprint_walk(system)
    except (lifting.NotPlain, TypeError, ValueError):
        return None, lifting.numbers(system), None
    return key, np.array(values, float), walked


def kept_structure(system) -> tuple[Structure, np.ndarray | None]:
    """The Structure for ``system`` (kept, or built and kept) and the system's plain numbers
    (None: the Model walks them). Up to STRUCTURE_CACHE_COORDINATES coordinates in all are
    kept, the most recent first; a larger system is kept alone, in a slot of its own, so that
    reading a big scene and running it build its Structure once."""
    with collector_paused():  # (constrained.bulk: millions of objects for a large system)
        return _kept_structure(system)


def _kept_structure(system) -> tuple[Structure, np.ndarray | None]:
    big = 3 * system.n_particles > STRUCTURE_CACHE_COORDINATES
    key, numbers, walked = _fingerprint(system)
    if key is None:
        return Structure(system), numbers
    with _structures_lock:
        structure = _largest[1] if big and _largest[0] == key else _structures.get(key)
        if structure is not None:
            if not big:
                _structures.move_to_end(key)
            return structure, numbers
    structure = Structure(system, walked=walked)
    with _structures_lock:
        if big:
            _largest[:] = [key, structure]
            return structure, numbers
        _structures[key] = structure
        while sum(s.n_coordinates for s in _structures.values()) > STRUCTURE_CACHE_COORDINATES:
            _structures.popitem(last=False)
    return structure, numbers
