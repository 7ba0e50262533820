"""A consistent initial state: the given (x0, v0) brought onto f = 0 and J v + f_t = 0.

Initial assembly is kept apart from the projection a method does during a run (Simbody's
split): here Newton may take many iterations and a large correction is refused, with the
constraint that was violated named; in a run the projection only removes drift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import interrupt
from ..errors import InconsistentStateError
from ..manifold import residual
from ..manifold.algebra import DENSE, algebra_for
from ..manifold.manifold import RANK, Manifold, RankPolicy, constraint_values, redundant_rows, sparse_jacobian
from ..manifold.sparse_rank import as_scipy, sp
from ..model.regularity import unresolved_reason, unresolved_rods
from ..model.structure import Model


@dataclass(frozen=True)
class Start:
    """The start of a run: consistent ``x``, ``v`` (flat), the ``correction`` report (sizes of
    the position and velocity changes, the worst violation before) and the run's ``manifold``
    (which rows it solves with, its counters)."""

    x: np.ndarray
    v: np.ndarray
    correction: dict
    manifold: Manifold


def consistent_start(model: Model, x0, v0, t0: float = 0.0, *, max_correction: float = 1e-3,
                     size: float | None = None, policy: RankPolicy = RANK,
                     compiled: bool = False) -> Start:
    """Project (x0, v0) onto f = 0 and J v + f_t = 0, A v + b = 0 (minimum mass-weighted change).

    Refuses with InconsistentStateError when the position correction exceeds
    ``max_correction × size`` or when the constraints cannot all hold.
    """
    x0 = np.asarray(x0, float).ravel()
    v0 = np.asarray(v0, float).ravel()
    labels = model.constraint_labels
    f0 = constraint_values(model)(x0, t0)[0] if model.n_constraints else np.zeros(0)
    if model.n_constraints and not np.all(np.isfinite(f0)):
        bad = labels[int(np.argmax(~np.isfinite(f0)))]
        raise InconsistentStateError(f"constraint '{bad}' is not finite at the initial state")
    _refuse_undefined_gradient(model, x0, t0)
    for _, rod, length, smallest in unresolved_rods(model.system)[:1]:
        raise InconsistentStateError(f"constraint '{rod.label}': {unresolved_reason(rod, length, smallest)}")
    manifold = Manifold(model, rows=redundant_rows(model, x0, t0, policy), policy=policy, compiled=compiled)
    size = size or max(float(np.max(np.abs(x0), initial=0.0)), 1.0)
    # residuals and tolerances in metres: each row divided by its scale (constrained.residual)
    scales = residual.row_scales(model, x0, t0)[:model.n_position_rows] if model.n_constraints else np.ones(0)
    f0 = f0 / scales if np.all(np.isfinite(scales)) and np.all(scales > 0) else f0
    worst = int(np.argmax(np.abs(f0))) if f0.size else 0
    s_min = float(np.min(scales)) if scales.size and np.isfinite(np.min(scales)) else 1.0
    result = manifold.project_positions(x0, t0, tol=1e-13 * size * s_min, max_iter=50)
    x, err = result.x, result.residual
    if np.isfinite(err) and err > 1e-8 * size * s_min:
        err = residual.position_residual(model, x, t0)
    if not err <= 1e-8 * size:  # far off, or light particles between heavy ones: assemble first
        assembled = assemble_positions(model, x0, t0, scales, tol=1e-10 * size)
        if assembled is not None:
            x = manifold.project_positions(assembled, t0, tol=1e-13 * size * s_min, max_iter=50).x
            err = residual.position_residual(model, x, t0)
    dx = float(np.max(np.linalg.norm((x - x0).reshape(-1, 3), axis=1), initial=0.0))
    if err > 1e-8 * size or not np.isfinite(err):
        f = np.asarray(model.constraint(x, t0)).ravel() / np.where(scales > 0, scales, 1.0)
        k = int(np.nanargmax(np.abs(f)))
        from ..manifold.diagnostics import incompatible_constraints

        clash = incompatible_constraints(model, x0, t0)
        named = (f"; {clash.describe()}" if not clash.compatible else
                 "; check that the constraints are compatible (lengths, triangle inequalities, anchors)")
        raise InconsistentStateError(
            f"the constraints cannot all be satisfied near the initial state: after projection "
            f"constraint '{labels[k]}' is still violated by {abs(f[k]):.3g} m (at the given start the "
            f"worst was '{labels[worst]}', violated by {abs(f0[worst]):.3g} m){named}"
        )
    limit = max_correction * size
    if dx > limit:
        raise InconsistentStateError(
            f"the initial positions are too far from the constraints: constraint '{labels[worst]}' "
            f"is violated by {abs(f0[worst]):.3g} m at t = {t0:g}, and the nearest consistent state "
            f"moves a particle by {dx:.3g} m, more than the allowed {max_correction:g} × system size "
            f"{size:.3g} m = {limit:.3g} m. Correct the positions, or raise "
            "simulate.max_initial_correction"
        )
    if not manifold.redundant and dx > 1e-8 * size:
        # the rows may be dependent on the manifold though not at the given start
        rows = redundant_rows(model, x, t0, policy)
        if rows is not None:
            manifold = Manifold(model, rows=rows, policy=policy, compiled=compiled)
            x = manifold.project_positions(x, t0, tol=1e-13 * size * s_min, max_iter=50).x
    v = manifold.project_velocities(x, v0, t0)
    if manifold.redundant:
        _refuse_taut_self_stress(manifold, x, v, t0)
    dv = float(np.max(np.linalg.norm((v - v0).reshape(-1, 3), axis=1), initial=0.0))
    report = {
        "position": dx,
        "velocity": dv,
        "max_residual_before": float(np.max(np.abs(f0), initial=0.0)),
        "worst_constraint": labels[worst] if f0.size else None,
    }
    return Start(x, v, report, manifold)


#: Initial assembly (``assemble_positions``): Gauss–Newton iterations and line-search halvings
#: at most, and the largest model it takes on (a dense least-squares step each iteration).
ASSEMBLY_ITERATIONS, ASSEMBLY_HALVINGS, ASSEMBLY_MAX_COORDINATES = 200, 40, 3000


def assemble_positions(model: Model, x0, t0: float, scales: np.ndarray, tol: float) -> np.ndarray | None:
    """A configuration on f(x, t0) = 0 near x0, where the mass-weighted projection failed: the
    Gauss–Newton method on the rows in metres (f_i / s_i, ``scales`` s) with a backtracking line
    search on |f|², each step the minimum-norm solution of J dx = −f (least squares: dependent
    rows and a straightened kink are no obstacle). The mass-weighted step moves light particles
    most, so from a start a few per cent off, with 1 mg beads between 1 kg ones, it stalls where
    the light beads alone cannot close the rods; unweighted, the geometry decides. None when
    |f_i / s_i| ≤ ``tol`` (m) is not reached: |f|² has a minimum above zero there (the
    constraints cannot all hold), or the model is too large for dense steps."""
    rows = model.n_position_rows
    if not rows or model.n_coordinates > ASSEMBLY_MAX_COORDINATES:
        return None
    scales = np.where(np.isfinite(scales) & (scales > 0), scales, 1.0)
    values, jacobian = constraint_values(model), sparse_jacobian(model)
    algebra = algebra_for(rows)

    def scaled(x):
        f = np.asarray(values(x, t0)[0], float).ravel() / scales
        return f, float(f @ f)

    x = np.array(x0, float)
    f, merit = scaled(x)
    for _ in range(ASSEMBLY_ITERATIONS):
        if interrupt.requested():
            raise KeyboardInterrupt
        if not np.isfinite(merit):
            return None
        if np.max(np.abs(f)) <= tol:
            return x
        dx = _least_squares_step(algebra, jacobian(x, t0), rows, scales, f)
        alpha = 1.0
        for _ in range(ASSEMBLY_HALVINGS):
            f_new, merit_new = scaled(x + alpha * dx)
            if merit_new <= (1.0 - 1e-4 * alpha) * merit:
                break
            alpha *= 0.5
        else:
            return None  # no descent: a minimum of |f|² above zero
        x, f, merit = x + alpha * dx, f_new, merit_new
    return x if np.max(np.abs(f)) <= tol else None


def _least_squares_step(algebra, J, rows: int, scales: np.ndarray, f: np.ndarray) -> np.ndarray:
    """The minimum-norm least-squares dx of (J/s) dx = −f: NumPy's dense ``lstsq`` for a small
    model; for a large one dx = Jᵀy with the minimum-norm y of (J Jᵀ) y = −f by the sparse
    algebra (O(N) on a chain: the dense lstsq and J's conversion to a full array took 28 s for
    a 400-bead chain started 0.6 m off, 147 iterations)."""
    if algebra is DENSE:
        return np.linalg.lstsq(np.asarray(J.full(), float)[:rows] / scales[:, None], -f, rcond=None)[0]
    Js = sp.diags(1.0 / scales) @ as_scipy(J)[:rows]
    return Js.T @ algebra.schur_solve(Js, np.ones(Js.shape[1]), -f, full_rank=False)


def consistent_state(model: Model, x0, v0, t0: float = 0.0, *, max_correction: float = 1e-3,
                     size: float | None = None):
    """``consistent_start`` as a tuple (x, v, correction report)."""
    start = consistent_start(model, x0, v0, t0, max_correction=max_correction, size=size)
    return start.x, start.v, start.correction


#: The curvature of the motion may leave range(J) by this fraction of its size (round-off).
SELF_STRESS_RTOL = 1e-6


def _refuse_taut_self_stress(manifold: Manifold, x, v, t: float) -> None:
    """Refuse a start from which no motion is possible: dependent rows that carry a self-stress
    (a straight chain of rods pinned at both ends at exactly its length, the edge of a flat
    cloth between two pinned corners) and a motion that would bend them.

    At rest the motion starts along the acceleration a (moving: along v). Along a direction d
    the constraints demand J ẍ = −c with c = dᵀ ∂²f/∂x² d, the curvature term of γ (γ's part
    quadratic in the velocity, taken here by a symmetric difference of γ at v ± d). When c has a
    part r outside range(J) — along the self-stress space null(Jᵀ) — no acceleration meets it:
    the set can follow only by stretching, with forces that grow without bound. The rows
    carrying r are named."""
    model = manifold.model
    a, _ = manifold.accelerations(x, v, t)
    moving = float(np.linalg.norm(v)) > 1e-12 * max(1.0, float(np.linalg.norm(x)))
    d = v if moving else a
    if not float(np.linalg.norm(d)) > 0:
        return

    def gamma(w):
        return np.asarray(model.dynamics(x, w, t)[2], float).ravel()

    c = 0.5 * (gamma(v + d) + gamma(v - d)) - gamma(v)
    size = float(np.linalg.norm(c))
    if not size > 0 or not np.isfinite(size):
        return
    algebra = manifold.algebra
    J = algebra.matrix(model.velocity_terms(x, t)[0])  # every row of γ (velocity rows' A after J)
    ones = np.ones(model.n_coordinates)
    y = algebra.schur_solve(J, ones, c, full_rank=False)
    r = c - J @ (J.T @ y)  # the part of c outside range(J): along null(Jᵀ)
    if not float(np.linalg.norm(r)) > SELF_STRESS_RTOL * size:
        return
    weights = np.abs(r) / np.max(np.abs(r))
    rows = sorted(int(k) for k in np.flatnonzero(weights > 0.05))
    labels = model.constraint_labels
    named = ", ".join(f"'{labels[k]}'" for k in rows[:6])
    named += f" and {len(rows) - 6} more" if len(rows) > 6 else ""
    raise InconsistentStateError(
        f"no motion can start from this state: the constraints {named} form a taut, self-stressed "
        f"set (e.g. a straight chain of rods held at both ends at exactly its length) that the "
        f"{'motion' if moving else 'applied forces'} would bend, which they allow only by stretching, "
        "with forces that grow without bound; give the set slack (anchor its ends closer together) "
        "or start it bent (e.g. a sagging edge)")



def _refuse_undefined_gradient(model: Model, x0: np.ndarray, t0: float) -> None:
    """A constraint whose gradient is not finite at the start (a rod of length 0, whose
    particle sits on its anchor: the direction is undefined) is refused with its name. A scene
    is checked when it is built (scene.build ``regular_start``); this catches the same start
    reached by ``simulate(..., parameters=...)``, which otherwise failed inside the rank
    decision's QR with NumPy's bare "array must not contain infs or NaNs". One evaluation of
    J's nonzeros (the sparse Jacobian the runs use), at any size."""
    if not model.n_constraints:
        return
    J = sparse_jacobian(model)(x0, t0)
    values = np.asarray(J.nonzeros(), float).ravel()
    if np.all(np.isfinite(values)):
        return
    rows, _ = J.sparsity().get_triplet()
    row = int(np.asarray(rows)[~np.isfinite(values)][0])
    label = model.constraint_labels[row]
    item = model.system.constraints[int(model.constraint_owner[row])]
    why = item.why_undefined(model.particle_names, x0, t0) if hasattr(item, "why_undefined") else ""
    raise InconsistentStateError(
        f"constraint '{label}' is undefined at the initial state (t = {t0:g} s): "
        + (why or "its gradient is not finite there (e.g. a particle on the anchor of its rod, or a rod of "
           "length 0); move the particle, or give parameter values that keep the constraint regular"))
