"""Whole-column arithmetic for CasADi MX graphs: a small SX kernel evaluated on columns of
instances, and sums of many columns into targets by index data.

``on_columns(kernel, inputs)`` replays the instructions of an SX Function with every scalar
replaced by a column (n, 1) of n instances (or a scalar shared by all): one MX node per
instruction, each a loop over n numbers in CasADi's virtual machine, where ``kernel.map(n)``
would interpret the whole instruction list once per instance.

``Summation`` adds entries of several columns ("streams") into targets, y[t] = Σ s_k[i_k]
over the (stream, position) pairs that name target t. Targets with the same sequence of
streams (a *signature*: on a chain, every inner rod's row of J v sums the same six streams)
are summed together as gathers and additions of whole columns, and one permutation puts them
in target order: O(entries) work in a few nodes, where a product with a constant 0/1 matrix
would cost an indexed update per entry.

Within ``shared_nodes()`` (in this thread; a graph of many evaluations at one state of the parameters, as a
dopri step with its dozen accelerations) ``take``, ``binary``, ``shared`` and the operations of
``on_columns`` return the node already built for the same operation on the same nodes: what
depends on p and the masses alone (a plane's row of J, m⁻¹ at a stream's coordinates, their
products) is computed once per call, not once per evaluation — CasADi's own ``cse`` finds the
same, but compares nodes by their serialized data and took 2 s on the 10,000-particle rope.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

import casadi as ca
import numpy as np

#: Beyond this many signatures a Summation is a product with a constant sparse 0/1 matrix.
MAX_SIGNATURES = 256

#: The node memos of the graphs this thread is building (``shared_nodes``), innermost last.
_LOCAL = threading.local()


def _memos() -> list[dict]:
    memos = getattr(_LOCAL, "memos", None)
    if memos is None:
        memos = _LOCAL.memos = []
    return memos


@contextmanager
def shared_nodes():
    """Within: the same operation on the same nodes gives the same node (see the module)."""
    memos = _memos()
    memos.append({})
    try:
        yield
    finally:
        memos.pop()


def shared(key: tuple, build, *keep):
    """build(), or the node built for ``key`` before within ``shared_nodes``; ``keep``: the
    objects whose identity ``key`` names, held so that it is not reused."""
    memos = _memos()
    if not memos:
        return build()
    memo = memos[-1]
    if key not in memo:
        memo[key] = (build(), keep)
    return memo[key][0]


def _node(value) -> int:
    """The identity of an MX node (what ``shared``'s keys name), or a number's value."""
    return hash(value) if isinstance(value, ca.MX) else ("value", float(value))


def binary(op: int, a, b):
    """ca.MX.binary(op, a, b), shared within ``shared_nodes``."""
    return shared((op, _node(a), _node(b)), lambda: ca.MX.binary(op, a, b), a, b)


def take(column, index: np.ndarray):
    """column[index] (MX), the column itself when index is 0, 1, …, n − 1."""
    plan = _plan(np.asarray(index, dtype=np.int64))
    if plan.whole and plan.index.size == column.numel():
        return column
    memos = _memos()
    if memos:
        key = ("take", hash(column), plan.index.size, plan.digest)
        memo = memos[-1]
        hit = memo.get(key)
        if hit is not None and (hit[1][1] is plan or np.array_equal(hit[1][1].index, plan.index)):
            return hit[0]
        value = plan.gather(column)
        if value.is_op(ca.OP_GETNONZEROS) and value.class_name().endswith("GetNonzerosSliceE"):
            # a gather of a gather is one gather of the source: the same slice of it reached
            # another way (λ's rows from the solve and from λ assembled) is the same node
            source, where = value.dep(0), value.info()["slice"]
            value = shared(("slice", hash(source), where["start"], where["stop"], where["step"]),
                           lambda: value, source)
        memo[key] = (value, (column, plan))
        return value
    return plan.gather(column)


#: From this many entries a gather's index is handed to CasADi as a DM (``_Gather``).
INDEX_MATRIX_FROM = 64
#: How many index entries the kept ``_Gather``s hold at most (then they start afresh).
KEPT_ENTRIES = 2_000_000
#: index bytes' (size, hash) -> its ``_Gather``.
_PLANS: dict[tuple, _Gather] = {}


class _Gather:
    """How an index array is gathered, worked out once per content: the same index arrays (a
    Summation's positions, a group's coordinates) are gathered from new columns at every
    evaluation of a step's dozen (0.07 s of a 100 x 100 cloth's step graph otherwise).
    An arithmetic progression as a slice (the same node, built without a list); a long
    index as a DM column, which CasADi reads as integer indices: the same node as
    ``column[index.tolist()]``, where a Python list of 20,000 indices costs CasADi about 1 ms
    to convert at every gather, a kept DM 0.1 ms."""

    def __init__(self, index: np.ndarray, digest: int):
        self.index, self.digest = index, digest
        self.whole = bool(np.array_equal(index, np.arange(index.size)))
        self.slice = self.matrix = None
        if index.size > 1:
            step = int(index[1] - index[0])
            if step > 0 and np.all(np.diff(index) == step):
                self.slice = slice(int(index[0]), int(index[-1]) + 1, step)
        if self.slice is None and index.size >= INDEX_MATRIX_FROM:
            self.matrix = ca.DM(index.astype(float).tolist())

    def gather(self, column):
        if self.slice is not None:
            return column[self.slice]
        return column[self.index.tolist() if self.matrix is None else self.matrix]


def _plan(index: np.ndarray) -> _Gather:
    """The ``_Gather`` of ``index`` (int64), kept by its content."""
    digest = hash(index.tobytes())
    key = (index.size, digest)
    plan = _PLANS.get(key)
    if plan is not None and np.array_equal(plan.index, index):
        return plan
    if sum(k[0] for k in _PLANS) + index.size > KEPT_ENTRIES:
        _PLANS.clear()
    plan = _PLANS[key] = _Gather(index.copy(), digest)
    return plan


def on_columns(kernel: ca.Function, inputs: list, n: int) -> list[list]:
    """The outputs of the SX ``kernel`` evaluated on columns: ``inputs[i]`` is a list (or a
    callable j -> value) giving, for each element j of input i, an MX column (n, 1) or a
    scalar shared by every instance. Returns, for each output, a list of MX columns (n, 1)."""
    work: dict[int, object] = {}
    outputs = [[None] * kernel.nnz_out(i) for i in range(kernel.n_out())]
    for k in range(kernel.n_instructions()):
        op, args, res = kernel.instruction_id(k), kernel.instruction_input(k), kernel.instruction_output(k)
        if op == ca.OP_CONST:
            value = kernel.instruction_constant(k)
            work[res[0]] = shared(("constant", value), lambda value=value: ca.MX(value))
        elif op == ca.OP_INPUT:
            source = inputs[args[0]]
            work[res[0]] = source(args[1]) if callable(source) else source[args[1]]
        elif op == ca.OP_OUTPUT:
            outputs[res[0]][res[1]] = work[args[0]]
        elif op == ca.OP_CALL or len(args) not in (1, 2):
            raise ValueError(f"{kernel.name()}: instruction {op} cannot be evaluated on columns")
        elif len(args) == 1:
            a = work[args[0]]
            work[res[0]] = shared((op, hash(a)), lambda op=op, a=a: ca.MX.unary(op, a), a)
        else:
            work[res[0]] = binary(op, work[args[0]], work[args[1]])
    for out in outputs:
        for j, value in enumerate(out):
            if value is None:  # a structural zero
                out[j] = ca.MX.zeros(n, 1)
            elif value.numel() == 1 and n != 1:  # shared by every instance (a constant, t, p)
                out[j] = shared(("repmat", hash(value), n), lambda v=value: ca.repmat(v, n, 1), value)
    return outputs


def sorted_unique(a) -> np.ndarray:
    """``np.unique(a)`` of integers, by a sort: NumPy 2.3+ finds the unique values of an array
    (asked for no indices) with a hash table, 5-10 times slower than sorting the 10⁴-10⁵
    indices of a large model (0.05 s of a 10,000-link chain's vectorized build)."""
    a = np.sort(np.asarray(a).ravel())
    return a[np.concatenate(([True], a[1:] != a[:-1]))] if a.size else a


def triplet(sparsity: ca.Sparsity) -> tuple[np.ndarray, np.ndarray]:
    """The rows and columns of a pattern's nonzeros (CasADi's order), int64: ``get_triplet``
    from the rows and the column offsets (one list from CasADi, not two: 0.03 s of the
    400,000 entries of a cloth's L)."""
    row = np.asarray(sparsity.row(), np.int64)
    return row, np.repeat(np.arange(sparsity.size2(), dtype=np.int64), np.diff(sparsity.colind()))


def unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(a, axis=0, return_inverse=True)`` for an integer array a (n, w) of entries
    ≥ −1, the rows in the same (lexicographic) order: each row read as one integer in base
    max(a) + 2 where that fits in 63 bits, so NumPy sorts integers, not rows compared as
    bytes (a 10,000-link chain's sums: 0.4 s before)."""
    base = int(a.max(initial=-1)) + 2
    if a.shape[1] * np.log2(max(base, 2)) >= 62:
        kinds, inverse = np.unique(a, axis=0, return_inverse=True)
        return kinds, inverse.ravel()
    key = np.zeros(len(a), np.int64)
    for column in a.T:
        key = key * base + (column + 1)
    keys, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return a[first], inverse.ravel()


class Summation:
    """y (n_targets,) with y[t] = Σ streams[s][i] over the entries (s, i) whose target is t,
    for columns ``streams`` of the given ``lengths`` and ``targets`` (one index array per
    stream, an entry per element); targets nobody names are 0. Index data only: built once,
    applied to any columns of those lengths (``__call__``)."""

    def __init__(self, lengths: list[int], targets: list[np.ndarray], n_targets: int):
        self.lengths, self.n_targets = [int(k) for k in lengths], int(n_targets)
        sid = np.repeat(np.arange(len(lengths)), lengths).astype(np.int64)
        pos = np.concatenate([np.arange(k) for k in lengths] or [np.zeros(0, np.int64)]).astype(np.int64)
        tgt = np.concatenate([np.asarray(t, np.int64) for t in targets] or [np.zeros(0, np.int64)])
        self.matrix = None
        order = np.lexsort((pos, sid, tgt))  # by target, then stream, then position
        sid, pos, tgt = sid[order], pos[order], tgt[order]
        counts = np.bincount(tgt, minlength=self.n_targets)
        width = int(counts.max(initial=0))
        rank = np.arange(tgt.size) - np.repeat(np.cumsum(counts) - counts, counts)
        signature = np.full((self.n_targets, max(width, 1)), -1, dtype=np.int64)
        where = np.full((self.n_targets, max(width, 1)), -1, dtype=np.int64)
        signature[tgt, rank], where[tgt, rank] = sid, pos
        kinds, inverse = unique_rows(signature)
        if len(kinds) > MAX_SIGNATURES:  # irregular: one sparse product
            flat = np.concatenate([[0], np.cumsum(self.lengths)])[sid] + pos
            self.matrix = ca.DM(ca.Sparsity.triplet(self.n_targets, int(sum(self.lengths)), tgt.tolist(),
                                                    flat.tolist()), 1.0)
            return
        by_kind = np.argsort(inverse, kind="stable")
        bounds = np.searchsorted(inverse[by_kind], np.arange(len(kinds) + 1))
        self.groups, placed, zeros = [], [], None
        # signatures in the order of their first target: where each covers a range of targets
        # (a chain's rows: the rest, the rods, the planes) no permutation is needed at the end
        for u in sorted(range(len(kinds)), key=lambda u: by_kind[bounds[u]]):
            kind, members = kinds[u], by_kind[bounds[u]:bounds[u + 1]]
            if kind[0] < 0:  # targets nobody names
                zeros = members
                continue
            self.groups.append([(int(s), where[members, r]) for r, s in enumerate(kind) if s >= 0])
            placed.append(members)
        self.zeros = 0 if zeros is None else len(zeros)
        order = np.concatenate([*placed, zeros] if zeros is not None else placed or [np.zeros(0, np.int64)])
        self.permutation = np.empty(self.n_targets, dtype=np.int64)
        self.permutation[order] = np.arange(self.n_targets)

    def __call__(self, streams: list):
        if self.n_targets == 0:
            return ca.MX(0, 1)
        if self.matrix is not None:
            return ca.mtimes(self.matrix, ca.vertcat(*streams))
        parts = []
        for terms in self.groups:
            total = None
            for s, positions in terms:
                value = take(streams[s], positions)
                total = value if total is None else binary(ca.OP_ADD, total, value)
            parts.append(total)
        if self.zeros:
            parts.append(ca.MX.zeros(self.zeros, 1))
        together = shared(("vertcat", *map(hash, parts)), lambda: ca.vertcat(*parts), *parts)
        return take(together, self.permutation)
