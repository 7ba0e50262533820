"""The vectorized build's row values at ONE numeric state, without building a Function.

A start asks for f, J's nonzeros and the row scales at x0 once each (scene.build's
``regular_start``, run.start's ``consistent_start``); each as a Function of the vectorized
build (``manifold.constraint_values``, ``sparse_jacobian``, ``residual.row_scales``) cost
20-60 ms of graph building on a 10,000-particle rope, for one call. Here the same evaluation
is done on numbers: each group's C loop (``fused``) or its SX kernel mapped over the
instances, the rest's SX Function, and the sums of ``columns.Summation`` as NumPy additions
in the same order — the numbers the Function gives, bit for bit (tests/test_at_point.py).

None where it cannot promise that (a Summation held as a sparse 0/1 product, a kernel without its C loop whose
operations are not all exactly rounded ones): the caller
builds the Function then.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ...codegen.fast_call import FastCall
from ...model.cache import structure_cache
from .build import DYNAMICS, ROW_OUTPUTS, VectorizedBuild, vectorized_build
from .columns import Summation


def summed(summation: Summation, streams: list[np.ndarray]) -> np.ndarray | None:
    """``summation(streams)`` on NumPy columns: each target's terms added left to right in the
    order the MX graph adds them; None for a Summation held as a matrix product."""
    if summation.n_targets == 0:
        return np.zeros(0)
    if summation.matrix is not None:
        return None
    parts = []
    for terms in summation.groups:
        total = None
        for s, positions in terms:
            value = streams[s][positions]
            total = value if total is None else total + value
        parts.append(total)
    if summation.zeros:
        parts.append(np.zeros(summation.zeros))
    return np.concatenate(parts)[summation.permutation]


#: The operations ``on_numbers`` does in NumPy: each correctly rounded in IEEE arithmetic, so
#: NumPy and CasADi's virtual machine give the same bits (not so sin, exp, pow: libraries differ).
EXACT = {ca.OP_ADD: np.add, ca.OP_SUB: np.subtract, ca.OP_MUL: np.multiply, ca.OP_DIV: np.divide,
         ca.OP_NEG: np.negative, ca.OP_SQRT: np.sqrt, ca.OP_SQ: np.square, ca.OP_FABS: np.fabs,
         ca.OP_TWICE: lambda a: 2.0 * a, ca.OP_INV: lambda a: 1.0 / a, ca.OP_ASSIGN: lambda a: a,
         ca.OP_FMIN: np.fmin, ca.OP_FMAX: np.fmax,
         # comparisons and logic as CasADi's: 1.0 or 0.0, NaN true where C's ``x ? … : …`` reads it so
         ca.OP_LT: lambda a, b: (a < b) * 1.0, ca.OP_LE: lambda a, b: (a <= b) * 1.0,
         ca.OP_EQ: lambda a, b: (a == b) * 1.0, ca.OP_NE: lambda a, b: (a != b) * 1.0,
         ca.OP_NOT: lambda a: (a == 0) * 1.0, ca.OP_IF_ELSE_ZERO: lambda c, a: np.where(c != 0, a, 0.0)}


class NotExact(Exception):
    """An operation outside ``EXACT``: the caller builds the Function."""


def on_numbers(kernel: ca.Function, inputs: list, n: int) -> list[list[np.ndarray]]:
    """``columns.on_columns`` on NumPy columns (n,): the instructions of the SX ``kernel`` in
    order; raises NotExact for an operation outside EXACT."""
    work: dict = {}
    outputs = [[None] * kernel.nnz_out(i) for i in range(kernel.n_out())]
    for k in range(kernel.n_instructions()):
        op, args, res = kernel.instruction_id(k), kernel.instruction_input(k), kernel.instruction_output(k)
        if op == ca.OP_CONST:
            work[res[0]] = np.float64(kernel.instruction_constant(k))
        elif op == ca.OP_INPUT:
            source = inputs[args[0]]
            work[res[0]] = source(args[1]) if callable(source) else np.float64(source[args[1]])
        elif op == ca.OP_OUTPUT:
            outputs[res[0]][res[1]] = work[args[0]]
        elif op not in EXACT:
            raise NotExact(op)
        else:
            work[res[0]] = EXACT[op](*(work[a] for a in args))
    return [[np.zeros(n) if value is None else np.broadcast_to(value, (n,)).astype(float) for value in out]
            for out in outputs]


def _dense(values) -> np.ndarray:
    return np.asarray(ca.DM(values).full(), float)


def _row_columns(b: VectorizedBuild, g, outputs: tuple, x, v, t, p) -> list[list[np.ndarray]]:
    """``VectorizedBuild._row_columns`` on numbers: for each output a list of columns."""
    kernel = b._kernel(g, outputs)
    variant = DYNAMICS if set(outputs) <= set(DYNAMICS) else ROW_OUTPUTS
    loop = b._loops().get((id(g), variant)) if b._moves(g, kernel) else None
    if loop is None:  # the kernel's instructions on columns, as ``on_columns`` does
        n = g.index.shape[1]
        values = np.concatenate([p, np.asarray(g.constants, float).reshape(-1)]) if g.constants.size else p
        inputs = [lambda j: x[g.index[j]], lambda j: v[g.index[j]], lambda j: values[g.sources[j]], [t],
                  lambda j: p[j]]
        return on_numbers(kernel, inputs, n)
    scalars = _call(b, loop.function, x, v, t, p)
    full = b._kernel(g, variant)
    start = np.concatenate([[0], np.cumsum([full.nnz_out(i) for i in range(full.n_out())])])
    return [scalars[start[variant.index(k)]:start[variant.index(k) + 1]] for k in outputs]


def _kernel_inputs(g, x, v, t, p) -> list:
    """A group's kernel inputs on numbers, as ``VectorizedBuild._columns`` gathers them."""
    values = np.concatenate([p, np.asarray(g.constants, float).reshape(-1)]) if g.constants.size else p
    return [lambda j: x[g.index[j]], lambda j: v[g.index[j]], lambda j: values[g.sources[j]], [t],
            lambda j: p[j]]


def _gradient_columns(b: VectorizedBuild, g, x, v, t, p) -> list[np.ndarray]:
    """``VectorizedBuild._gradient_columns`` on numbers: g's C loop where it has one, else its
    kernel's instructions (NotExact outside EXACT)."""
    kernel = b._gradient_kernel(g)
    loop = b._loops().get((id(g), "gradient")) if b._moves(g, kernel) else None
    if loop is None:
        return on_numbers(kernel, _kernel_inputs(g, x, v, t, p), g.index.shape[1])[0]
    return list(_call(b, loop.function, x, v, t, p))


def sequential_sum(values: np.ndarray) -> float:
    """Σ values added left to right from 0 (CasADi's dot product and ``sum1`` loops; NumPy's
    ``sum`` adds pairwise, in another order)."""
    return float(np.cumsum(values)[-1]) + 0.0 if values.size else 0.0


def forces_and_energy_at(b: VectorizedBuild, x, v, t: float, p, masses) -> tuple | None:
    """The applied forces F (3N,) and the energy T + V + U − v·∂U/∂v at one numeric state,
    the numbers of ``manifold.forces_and_energy``'s Function (``VectorizedBuild.evaluate``'s F,
    ``energy``) bit for bit, without building it; None where a kernel without its C loop has
    operations outside EXACT or a sum is a matrix product."""
    x, v, p = (np.asarray(a, float).ravel() for a in (x, v, p))
    masses = np.asarray(masses, float).ravel()
    try:
        gradients = [col for g in b.mapped.terms for col in _gradient_columns(b, g, x, v, t, p)]
        values = [on_numbers(b._value_kernel(g), _kernel_inputs(g, x, v, t, p), g.index.shape[1])[0][0]
                  for g in b.mapped.terms]
    except NotExact:
        return None
    # (F of the rest is read only where it has forces, or no term has: else it is zeros)
    outputs = ("F", "E") if b.rest_forces or not gradients else ("E",)
    rest = b._rest_function(outputs)
    *F_rest, E_rest = (_dense(value).ravel()
                       for value in _call(b, rest.function, *rest.arguments(x, v, t, p)))
    if gradients:
        potential = summed(b.by_force, gradients)
        if potential is None:
            return None
        F = F_rest[0] - potential if b.rest_forces else -potential
    else:
        F = F_rest[0]
    E = 0.5 * sequential_sum((masses * v) * v) + E_rest[0]
    for column in values:
        E = E + sequential_sum(np.asarray(column, float))
    return F, E


def _call(b: VectorizedBuild, function: ca.Function, *args) -> list:
    """``function(*args)``'s outputs, through a FastCall (kept beside the build) where they are
    dense: no DM of 3N numbers in, nor of n per output out."""
    if not all(function.sparsity_out(i).is_dense() for i in range(function.n_out())):
        out = function(*args)
        return list(out) if isinstance(out, tuple | list) else [out]
    calls = b.__dict__.setdefault("_fast_calls", {})  # id -> (Function, FastCall)
    kept = calls.get(id(function))
    if kept is None or kept[0] is not function:
        kept = calls[id(function)] = (function, FastCall(function))
    return kept[1](*args)


def values_at(b: VectorizedBuild, x, v, t: float, p, outputs: tuple) -> dict | None:
    """``VectorizedBuild.evaluate(x, v, t, p, outputs)`` at numbers (flat arrays; v None:
    zeros): f, f_t, γ, scale per row (C,) and "J" as J's nonzeros in its sparsity's order
    (``jacobian_sparsity``); None where a sum is a matrix product (see the module)."""
    x = np.asarray(x, float).ravel()
    v = np.zeros(b.n3) if v is None else np.asarray(v, float).ravel()
    p = np.asarray(p, float).ravel()
    rows = {k: [] for k in outputs}
    for g in b.mapped.rows:
        try:
            columns = _row_columns(b, g, outputs, x, v, t, p)
        except NotExact:
            return None
        for k, values in zip(outputs, columns, strict=True):
            rows[k] += values
    if outputs:
        function = b._rest_function(outputs)
        rest = _call(b, function.function, *function.arguments(x, v, t, p))
    else:
        rest = []
    result = {}
    for k, value in zip(outputs, rest, strict=True):
        value = _dense(value).ravel()
        total = summed(b.by_nonzero if k == "J" else b.by_place, rows[k] + [value])
        if total is None:
            return None
        result[k] = total
    return result


class JacobianAt(ca.DM):
    """J at one state (a sparse DM) that keeps its nonzeros as the NumPy array it was made from:
    ``nonzeros()`` gives that array (read-only), not a list of 0.1 M floats made again at each
    read (4 ms on a 100 x 100 cloth: a start reads J three times), and ``compressed_columns()``
    the build's (colind, row) of its sparsity (``get_ccs`` as NumPy)."""

    def __init__(self, b: VectorizedBuild, nonzeros: np.ndarray):
        nonzeros = np.asarray(nonzeros, float).ravel()
        super().__init__(b.jacobian_sparsity, nonzeros.tolist())  # (a list: 2x faster than an array)
        nonzeros.flags.writeable = False
        self._nonzeros, self._columns = nonzeros, b.jacobian_columns

    def nonzeros(self) -> np.ndarray:
        return self._nonzeros

    def compressed_columns(self) -> tuple[np.ndarray, np.ndarray]:
        return self._columns


#: Calls of a large model's f, J's nonzeros or row scales per structure answered on numbers
#: (``numeric_first``) before the Function is built: a start's few (20-60 ms of graph building
#: each on a 10,000-particle rope), not a run's projections (a Function call is cheaper then).
NUMERIC_CALLS = 4


def _numbers_first(model, key: str, general, on_numbers):
    """A call that answers with ``on_numbers(*args)`` (None: it cannot) for the structure's first
    NUMERIC_CALLS calls of ``key``, then with the Function ``general()`` builds (once per
    structure, under ``(prefix, "structural", key)`` of ``structure_cache``)."""
    cache, prefix = structure_cache(model)
    counted, built = (*prefix, "numeric calls", key), (*prefix, "structural", key)
    function = None

    def call(*args):
        nonlocal function
        if function is None and built not in cache and cache.get(counted, 0) < NUMERIC_CALLS:
            with np.errstate(all="ignore"):
                values = on_numbers(*args)
            if values is not None:
                cache[counted] = cache.get(counted, 0) + 1
                return values
        function = function or general()
        return function(*args)

    return call


def numeric_first(model, key: str, outputs: tuple, general):
    """``(x, t) -> [value]`` for a large model (the vectorized build): the value of the last of
    ``outputs`` ("J": J's nonzeros) computed on numbers (``values_at``: the Function's numbers,
    without building it) for the structure's first NUMERIC_CALLS calls of ``key``, then the
    call ``general()`` gives (``_numbers_first``)."""
    b, p = vectorized_build(model.structure), model.parameter_vector

    def on_numbers(x, t):
        values = values_at(b, x, None, t, p, outputs)
        return None if values is None else [values[outputs[-1]]]

    return _numbers_first(model, key, general, on_numbers)


def forces_first(model, general):
    """``(x, v, t) -> [F, [E]]`` for a large model (the vectorized build): ``forces_and_energy_at``
    for the structure's first NUMERIC_CALLS calls (a start's check of finite forces, the run's,
    its last sample's energy: a Function of 20-130 ms of graph building for each one call), then
    the call ``general()`` gives (the Function's, built once per structure)."""
    b, p, masses = vectorized_build(model.structure), model.parameter_vector, model.masses

    def on_numbers(x, v, t):
        values = forces_and_energy_at(b, x, v, t, p, masses)
        return None if values is None else [values[0], np.array([values[1]])]

    return _numbers_first(model, "forces_and_energy", general, on_numbers)
