"""The rigid motions that are symmetries of a system, found rather than declared.

Every rigid motion of space has the generator ``ξ_i = ε + ω × x_i`` (a translation ε plus a
rotation ω about the origin), linear in ``s = (ω, ε) ∈ R⁶``. Each term's first-order change
under it (``symmetry.variation_checks``: δT, δV, δU, the power of dissipation and applied
forces along ξ, ``∇c_k·ξ`` of each constraint row) is then linear in s too: ``δ = D(x, v, t) s``.
The symmetries are the s with ``D s = 0`` at every state, i.e. the null space of D stacked over
random states on the constraint manifold, each row divided by the size of its terms so that a
singular value is a relative change. Noether's charge of each, ``Q = Σ p_i·(ε + ω × x_i)`` with
``p_i = m_i v_i − ∂U/∂v_i``, is conserved: ``ε·P + ω·L`` with P the momentum and L the
angular momentum about the origin.

The null space is written in a readable basis (reduced row echelon form in the order
ω_x, ω_y, ω_z, ε_x, ε_y, ε_z): translations along a direction, and rotations about an axis
through a point (a screw when ε has a part along ω, as for a bead on a helix).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ...errors import InputError
from ...model.structure import Model, assemble
from ..symmetry import SYMMETRY_RTOL, canonical_momentum, manifold_samples, momentum_of, variation_checks

#: Components below this (relative to the vector's largest) are printed and kept as 0.
CLEAN = 1e-9
#: Fewer sampled states than this (or than asked for) and the search refuses (InputError).
ENOUGH_STATES = 6
_AXES = "xyz"


@dataclass(frozen=True)
class RigidSymmetry:
    """A rigid motion ``ξ_i = translation + rotation × x_i`` that leaves L, the constraints and
    the non-conservative forces unchanged; ``name``: ``P_x``, ``L_z``, ``P·n``, ``L·n``;
    ``description``: the motion in words; ``charge``: ``Q(x, v, t) = Σ p_i·ξ_i`` (SX of the
    model's symbols)."""

    rotation: np.ndarray
    translation: np.ndarray
    name: str
    description: str
    charge: ca.SX


def _clean(vector: np.ndarray) -> np.ndarray:
    big = float(np.max(np.abs(vector), initial=0.0))
    out = np.where(np.abs(vector) <= CLEAN * big, 0.0, vector)
    return out + 0.0  # no -0.0 in the printout


def _numbers(vector: np.ndarray) -> str:
    return "(" + ", ".join(f"{c:.6g}" for c in vector) + ")"


def _axis_name(n: np.ndarray) -> str | None:
    """'x', 'y' or 'z' when the unit vector n is a coordinate axis (either sense), else None."""
    hits = np.flatnonzero(n)
    return _AXES[hits[0]] if len(hits) == 1 else None


def null_space_rows(matrix: np.ndarray, rtol: float) -> np.ndarray:
    """A basis of {s : matrix·s ≈ 0} (singular values ≤ rtol × √columns, the rows being relative
    changes) as the rows of its reduced row echelon form, pivots scaled to 1."""
    columns = matrix.shape[1]
    if matrix.shape[0] == 0:
        basis = np.eye(columns)
    else:
        _, sigma, vt = np.linalg.svd(matrix, full_matrices=True)
        sigma = np.concatenate([sigma, np.zeros(columns - len(sigma))])
        basis = vt[sigma <= rtol * np.sqrt(columns)]
    rows = basis.copy()
    pivot_row = 0
    for column in range(columns):
        if pivot_row == len(rows):
            break
        best = pivot_row + int(np.argmax(np.abs(rows[pivot_row:, column])))
        if abs(rows[best, column]) <= CLEAN:
            continue
        rows[[pivot_row, best]] = rows[[best, pivot_row]]
        rows[pivot_row] /= rows[pivot_row, column]
        for other in range(len(rows)):
            if other != pivot_row:
                rows[other] -= rows[other, column] * rows[pivot_row]
        pivot_row += 1
    return np.array([_clean(r) for r in rows[:pivot_row]]).reshape(-1, columns)


def _anchors(model: Model, rotations: list[tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray]:
    """Points to name an axis by, in order: the scene's fixed points (pivots, pins), the point
    where all the rotations' axes meet (a sphere's centre), the origin."""
    points = []
    for constraint in model.system.constraints:
        point = getattr(constraint, "point", None)
        try:
            point = np.asarray(point, dtype=float).ravel() if point is not None else None
        except (TypeError, ValueError):  # a moving point (formulas of t)
            continue
        if point is not None and point.size == 3 and np.all(np.isfinite(point)):
            points.append(point)
    if len(rotations) >= 2:  # ε_k = −ω_k × c for every k: c by least squares, kept if exact
        A = np.vstack([np.cross(np.eye(3), w).T for w, _ in rotations])  # A c = c × ω (= ε)
        b = np.concatenate([e for _, e in rotations])
        c = np.linalg.lstsq(A, b, rcond=None)[0]
        if np.allclose(A @ c, b, rtol=0, atol=1e-9 * max(1.0, float(np.max(np.abs(b))))):
            points.append(c)
    return points


def _describe(rotation: np.ndarray, translation: np.ndarray, size: float,
              anchors: list[np.ndarray] = ()) -> tuple[str, str]:
    """(name, description) of the generator ε + ω × x; a rotation's axis is named through the
    first of ``anchors`` on it, else through its point nearest the origin."""
    if not np.any(rotation):
        n = translation / np.linalg.norm(translation)
        axis = _axis_name(n)
        return (f"P_{axis}" if axis else f"P·{_numbers(n)}",
                f"translation along {axis or _numbers(n)}")
    w = float(np.linalg.norm(rotation))
    n = rotation / w
    axis = _axis_name(n)
    point = np.cross(rotation, translation) / w**2
    for anchor in anchors:  # on the axis: ε⊥ = −ω × anchor
        if np.linalg.norm(np.cross(anchor - point, n)) <= CLEAN * size:
            point = anchor
            break
    point = _clean(np.concatenate([point, [size]]))[:3]
    pitch = float(translation @ n) / w
    name = f"L_{axis}" if axis else f"L·{_numbers(n)}"
    where = f"about the {axis} axis" if axis else f"about the axis {_numbers(n)}"
    text = f"rotation {where} through {_numbers(point)}"
    if abs(pitch) > CLEAN * size:
        return f"{name} + {pitch:.6g}·P_{axis}" if axis else f"{name} (screw)", \
            f"screw motion {where} through {_numbers(point)}, {pitch:.6g} m along it per radian"
    if np.any(point):
        name += f" about {_numbers(point)}"
    return name, text


def _generator(rotation, translation, x):
    """ξ = (ε + ω × x_i) for each particle, as one column (3N) of the positions ``x`` (3N)."""
    n = x.numel() // 3
    return ca.vec(ca.repmat(translation, 1, n) + ca.cross(ca.repmat(rotation, 1, n), ca.reshape(x, 3, n)))


def _largest_move(rotation: np.ndarray, translation: np.ndarray, x: np.ndarray) -> float:
    """max_i |ε + ω × x_i| at the positions ``x`` (3N)."""
    positions = np.asarray(x, float).reshape(-1, 3)
    return float(np.max(np.linalg.norm(translation + np.cross(rotation, positions), axis=1), initial=0.0))


def rigid_symmetries(model, *, samples: int = 12, seed: int = 0,
                     rtol: float = SYMMETRY_RTOL) -> list[RigidSymmetry]:
    """The rigid motions that are symmetries of ``model`` (a Model, System or Scene; module
    docstring), each with its Noether charge, translations first; [] when there is none. A
    motion that moves no particle at any sampled state (a rotation about the line every
    particle is held on) is left out: its charge is 0.
    Checked at ``samples`` random states on the constraint manifold near the start
    (``symmetry.manifold_samples``)."""
    if not isinstance(model, Model):
        model = assemble(getattr(model, "system", model))
    s = model.symbols
    x, v, t = s.x, s.v, s.t
    generator = ca.SX.sym("s", 6)  # ω, ε
    xi = _generator(generator[:3], generator[3:], x)
    checks = variation_checks(model, xi)
    if not checks:
        return []
    changes = ca.vertcat(*[c for _, c, _ in checks])
    scales = ca.vertcat(*[sc for _, _, sc in checks])
    size = max(float(model.system.size()), 1e-300)
    # rotations scaled by the system's size, so that every column is a displacement of its order
    unit = np.diag([1 / size] * 3 + [1.0] * 3)
    matrix_of = ca.Function("rigid_variations", [x, v, t], [ca.jacobian(changes, generator)])
    scale_of = ca.Function("rigid_scales", [x, v, t, generator], [scales])
    blocks = []
    states = manifold_samples(model, samples, seed)
    if len(states) < min(samples, ENOUGH_STATES):  # (a few states cannot rule out a false motion)
        raise InputError(f"only {len(states)} states on the constraints could be sampled near the start "
                         f"(of {samples} asked for): too few to tell a symmetry from a coincidence")
    for xs, vs, ts in states:
        D = np.asarray(matrix_of(xs, vs, ts)) @ unit
        scale = sum(np.asarray(scale_of(xs, vs, ts, unit[:, j])).ravel() for j in range(6))
        keep = scale > 0  # a term with no variation terms at all cannot change
        blocks.append(D[keep] / scale[keep, None])
    stacked = np.vstack(blocks) if blocks else np.zeros((0, 6))
    if not np.all(np.isfinite(stacked)):
        stacked = stacked[np.all(np.isfinite(stacked), axis=1)]
    found = []
    momentum = canonical_momentum(model)
    motions = []
    for row in null_space_rows(stacked, rtol):
        row = unit @ row
        rotation, translation = _clean(row[:3]), row[3:]
        if np.any(rotation):  # ε to the scale of the rotation's own displacements
            translation = np.where(np.abs(translation) <= CLEAN * size * np.linalg.norm(rotation), 0.0,
                                   translation) + 0.0
        else:
            translation = _clean(translation)
        scale = float(np.linalg.norm(rotation)) or float(np.linalg.norm(translation))
        rotation, translation = rotation / scale, translation / scale
        if max(_largest_move(rotation, translation, xs) for xs, _, _ in states) > CLEAN * size:
            motions.append((rotation, translation))  # (else it moves nothing: L_x of a bead on the x axis)
    anchors = _anchors(model, [(w, e) for w, e in motions if np.any(w)])
    for rotation, translation in motions:
        name, description = _describe(rotation, translation, size, anchors)
        xi_row = _generator(ca.DM(rotation), ca.DM(translation), x)
        found.append(RigidSymmetry(rotation, translation, name, description, ca.dot(momentum, xi_row)))
    return sorted(found, key=lambda symmetry: bool(np.any(symmetry.rotation)))  # translations first


def charge_in_coordinates(reduced, symmetry: RigidSymmetry) -> ca.SX:
    """``Q(q, q̇, t) = Σ p_i·ξ_i`` in a reduced model's coordinates: ``p_i = m_i ẋ_i − ∂U/∂v_i``
    and ``ξ_i = ε + ω × x_i`` at ``x(q, t)``, ``ẋ(q, q̇, t)`` (the reduced model's masses and
    parameters: symbols when it was built with ``symbolic_parameters``)."""
    s = reduced.symbols
    masses = ca.vertcat(*[ca.SX(m) for m in s.masses for _ in range(3)])
    momentum = momentum_of(s, reduced.system.effects, masses)
    xi = _generator(ca.DM(symmetry.rotation), ca.DM(symmetry.translation), s.x)
    ex = reduced.expressions
    mapped = ca.densify(ca.vertcat(ex["x"], ex["x_dot"]))
    return ca.substitute(ca.dot(momentum, xi), ca.vertcat(s.x, s.v), mapped)


def combination_of(reduced, charge: ca.SX, momenta: list[int],
                   rtol: float = SYMMETRY_RTOL) -> np.ndarray | None:
    """Coefficients c with ``Q = Σ c_j p_j`` over the momenta of the coordinates ``momenta``
    (a numeric reduced model's ``charge_in_coordinates``) at its sample states, or None when Q is
    not such a combination (then it is a conserved quantity of its own)."""
    p = reduced.expressions["p"]
    columns = ca.vertcat(*[p[j] for j in momenta]) if momenta else ca.SX(0, 1)
    fun = ca.Function("charge_and_momenta", [reduced.q, reduced.q_dot, reduced.t], [charge, columns])
    rows, values = [], []
    for q, qd, t in zip(*reduced.sample_states(12, 3), strict=True):
        value, ps = fun(q, qd, t)
        values.append(float(value))
        rows.append(np.asarray(ps).ravel())
    A, b = np.array(rows).reshape(len(values), len(momenta)), np.array(values)
    c = np.linalg.lstsq(A, b, rcond=None)[0] if momenta else np.zeros(0)
    size = float(np.max(np.abs(b), initial=0.0)) + float(np.max(np.abs(A), initial=0.0))
    return c if np.max(np.abs(A @ c - b), initial=0.0) <= rtol * max(size, 1e-300) else None
