"""Analysis of the constraints: rank, degrees of freedom, redundancy, singular configurations."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..model.structure import Model, assemble
from ..model.system import require_system
from ..threads import one_blas_thread
from .algebra import algebra_for
from .manifold import RANK, redundant_rows
from .sparse_rank import independent_rows_sparse

#: Relative pivot size below which a row of the (row-normalized) Jacobian counts as dependent:
#: the rank policy's (constrained.manifold.RANK).
RANK_TOL = RANK.dependent_rtol


class SingularConfigurationWarning(UserWarning):
    """The rank of J at this state is lower than at nearby states."""


@dataclass
class ConstraintReport:
    """What the constraints say at one state (x, t).

    ``degrees_of_freedom = n_coordinates − rank`` (rank of J = ∂f/∂x: the configuration's
    freedom); ``redundant`` names rows implied by the others; ``singular`` is True when the
    rank here is below the generic rank (the rank at nearby, perturbed states), so the count
    here overstates the freedom. ``n_constraints``, ``labels`` and ``residuals`` are the rows
    of f. Velocity constraints (``velocity_labels``: their rows) restrict the velocities
    further: ``velocity_degrees_of_freedom = n_coordinates − velocity_rank``, the rank of
    [J; A] (equal to the configuration's freedom without them).
    """

    n_coordinates: int
    n_constraints: int
    rank: int
    generic_rank: int
    labels: list[str]
    residuals: np.ndarray
    redundant: list[str] = field(default_factory=list)
    velocity_labels: list[str] = field(default_factory=list)
    velocity_rank: int | None = None

    @property
    def degrees_of_freedom(self) -> int:
        return self.n_coordinates - self.rank

    @property
    def velocity_degrees_of_freedom(self) -> int:
        """3N − rank [J; A]: the independent velocities the constraints leave."""
        return self.n_coordinates - (self.rank if self.velocity_rank is None else self.velocity_rank)

    @property
    def generic_degrees_of_freedom(self) -> int:
        return self.n_coordinates - self.generic_rank

    @property
    def singular(self) -> bool:
        return self.rank < self.generic_rank

    @property
    def max_residual(self) -> float:
        return float(np.max(np.abs(self.residuals), initial=0.0))

    @property
    def worst(self) -> str | None:
        if not len(self.residuals):
            return None
        return self.labels[int(np.argmax(np.abs(self.residuals)))]


def jacobian_rank(J: np.ndarray) -> tuple[int, np.ndarray]:
    """Rank of J and the pivot order of its rows (QR with column pivoting on Jᵀ).

    Rows are normalized first, so the rank does not depend on the units of each constraint.
    Returns (rank, order): ``order[:rank]`` are independent rows.
    """
    C = J.shape[0]
    if C == 0:
        return 0, np.zeros(0, dtype=int)
    norms = np.linalg.norm(J, axis=1)
    Jn = J / np.where(norms > 0, norms, 1.0)[:, None]
    import scipy.linalg as sla  # (on first use: 0.1 s of imports)

    _, R, order = sla.qr(Jn.T, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    if diag.size == 0 or diag[0] == 0:
        return 0, order
    rank = int(np.sum(diag > RANK_TOL * diag[0]))
    return rank, order


def constraint_report(system, x=None, t: float = 0.0, *, model: Model | None = None, samples: int = 3,
                      seed: int = 0) -> ConstraintReport:
    """Rank of J = ∂f/∂x at (x, t) (default: the system's initial positions), redundancy,
    the rank of [J; A] when there are velocity constraints,
    and the generic rank from ``samples`` random perturbations of x (seeded). Independent
    rows are shown by a cheap factorization; dependent ones are found by the pivoted QR of the
    dense J up to SPARSE_FROM rows, beyond by the sparse Gram factorization (sparse_rank)."""
    require_system(system, "constraint_report")
    model = model or assemble(system)
    x = (system.positions if x is None else np.asarray(x, float)).ravel()
    report = _position_report(model, system, x, t, samples, seed)
    C_f = model.n_position_rows
    if C_f < model.n_constraints:  # velocity rows: the rank of [J; A] too (rows of f kept first)
        with one_blas_thread():
            rows = redundant_rows(model, x, t)
        kept = range(model.n_constraints) if rows is None else rows
        report.redundant += [model.constraint_labels[k] for k in range(C_f, model.n_constraints)
                             if k not in kept]
        report.velocity_labels = list(model.constraint_labels[C_f:])
        report.velocity_rank = len(kept)
    return report


def _position_report(model: Model, system, x, t, samples: int, seed: int) -> ConstraintReport:
    """The report on the rows of f (see ``constraint_report``)."""
    f, J_sparse = model.jacobian(x, t)
    f = np.asarray(f).ravel()
    C = model.n_position_rows
    algebra = algebra_for(C)
    if C and algebra.full_row_rank(J_sparse, model.inverse_masses):
        # independent rows (shown in O(N) on a chain by a sparse factorization): rank C here,
        # and nearby too, since the rank cannot exceed the number of rows
        return ConstraintReport(n_coordinates=model.n_coordinates, n_constraints=C, rank=C, generic_rank=C,
                                labels=list(model.constraint_labels[:C]), residuals=f, redundant=[])
    with one_blas_thread():  # constrained/threads.py: spin-waiting BLAS threads cost more than they give
        if algebra.name == "sparse":
            report = _sparse_report(model, system, x, t, f, J_sparse, samples, seed)
            if report is not None:
                return report
        return _dense_report(model, system, x, t, f, np.asarray(J_sparse), samples, seed)


def _perturbed_states(system, x, t, samples: int, seed: int):
    """(x + 0.1·size·N(0, 1), t + U(0, 1)) ``samples`` times, seeded: where the generic rank is read."""
    rng = np.random.default_rng(seed)
    size = system.size()
    for _ in range(samples):
        yield x + 0.1 * size * rng.standard_normal(x.shape), t + rng.uniform()


def _sparse_report(model: Model, system, x, t, f, J, samples, seed) -> ConstraintReport | None:
    """The rank, redundancy and generic rank of a large J by the sparse Gram factorization of
    its row-normalized rows (constrained.sparse_rank: O(N) on a chain, never a dense J);
    None when that factorization fails."""
    rows = independent_rows_sparse(J)
    if rows is None:
        return None
    rank, generic = rows.size, rows.size
    for xp, tp in _perturbed_states(system, x, t, samples, seed):
        nearby = independent_rows_sparse(model.jacobian(xp, tp)[1])
        generic = max(generic, rank if nearby is None else nearby.size)
    redundant = np.setdiff1d(np.arange(model.n_position_rows), rows)
    return ConstraintReport(
        n_coordinates=model.n_coordinates, n_constraints=model.n_position_rows, rank=rank,
        generic_rank=generic, labels=list(model.constraint_labels[:model.n_position_rows]), residuals=f,
        redundant=[model.constraint_labels[k] for k in redundant])


def _dense_report(model: Model, system, x, t, f, J, samples, seed) -> ConstraintReport:
    """The rank-revealing (dense) route of ``constraint_report``, for dependent rows."""
    rank, order = jacobian_rank(J)
    # rows beyond the rank: implied by the others; report them in scene order
    redundant_rows = sorted(order[rank:].tolist())
    generic = rank
    for xp, tp in _perturbed_states(system, x, t, samples, seed):
        generic = max(generic, jacobian_rank(np.asarray(model.jacobian(xp, tp)[1]))[0])
    return ConstraintReport(
        n_coordinates=model.n_coordinates,
        n_constraints=model.n_position_rows,
        rank=rank,
        generic_rank=generic,
        labels=list(model.constraint_labels[:model.n_position_rows]),
        residuals=f,
        redundant=[model.constraint_labels[k] for k in redundant_rows],
    )


def degrees_of_freedom(system, x=None, t: float = 0.0) -> int:
    """3N − rank J at (x, t): the configuration's freedom (velocity constraints leave it as it
    is; ``constraint_report(...).velocity_degrees_of_freedom`` counts the velocities). Warns
    (SingularConfigurationWarning) when the configuration is singular, i.e. the rank is lower
    here than nearby and the count overstates the freedom."""
    require_system(system, "degrees_of_freedom")
    report = constraint_report(system, x, t)
    if report.singular:
        warnings.warn(
            f"singular configuration: rank J is {report.rank} here but {report.generic_rank} at "
            f"nearby states, so 3N − rank = {report.degrees_of_freedom} overstates the freedom "
            f"({report.generic_degrees_of_freedom} away from this configuration)",
            SingularConfigurationWarning,
            stacklevel=2,
        )
    return report.degrees_of_freedom
