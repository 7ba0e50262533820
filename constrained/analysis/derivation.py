"""Derivation checks on the reduced route: hand-derived equations, conservation laws, printouts.

- ``check_equations``: is a candidate equation of motion implied by Lagrange's equations?
  At random states (q, q̇, t) the accelerations q̈ come from ``M q̈ = rhs``; a right
  equation (any nonzero multiple or combination of Lagrange's equations) then vanishes,
  relative to the size of its terms.
- ``conservation``: conjugate momenta ``p = ∂L/∂q̇``, cyclic coordinates (``∂L/∂q_j = 0``
  and no non-conservative generalized force on q_j), the Hamiltonian ``H = p·q̇ − L`` and
  whether it equals ``T + V``; their drift along a reduced trajectory.
- ``describe`` (from constrained.printing): a readable printout of T, V, L and the equations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import InputError
from .candidates import check_generalized_forces, check_lagrangian  # noqa: F401 (public here too)
from .equations import EquationCheck, _reduced, check_equations  # noqa: F401 (public here too)
from .printing import describe, pretty, symbolic_reduced, to_sympy  # noqa: F401 (public here too)

__all__ = [
    "Conservation",
    "EquationCheck",
    "check_equations",
    "check_generalized_forces",
    "check_lagrangian",
    "conservation",
    "describe",
    "pretty",
    "symbolic_reduced",
    "to_sympy",
]

#: |∂L/∂q_j| below this × the scale of the Lagrangian's terms counts as zero (cyclic).
CYCLIC_RTOL = 1e-10


# --- conservation laws ------------------------------------------------------------------------


@dataclass
class Conservation:
    """Conserved quantities found in a reduced model, and their drift along a trajectory.

    ``cyclic``: coordinates with ∂L/∂q_j = 0 and no non-conservative force on them, nor a
    velocity constraint acting on them (their momenta p_j are conserved);
    ``structurally_cyclic``: those whose L does not even mention q_j; ``hamiltonian_conserved``:
    ∂L/∂t = 0, no non-conservative forces at all, and velocity constraints doing no work;
    ``hamiltonian_is_energy``: H = T + V at the sampled states (not for rheonomic maps or
    velocity-dependent potentials). Drifts (max |Δ| relative to the starting value, or to
    1 when that is zero) are filled in when a trajectory is given.
    """

    coordinates: list[str]
    cyclic: list[str]
    structurally_cyclic: list[str]
    hamiltonian_conserved: bool
    hamiltonian_is_energy: bool
    momenta: dict[str, np.ndarray] = field(default_factory=dict)
    hamiltonian: np.ndarray | None = None
    energy: np.ndarray | None = None
    momentum_drift: dict[str, float] = field(default_factory=dict)
    hamiltonian_drift: float | None = None
    energy_drift: float | None = None

    def summary(self) -> str:
        lines = []
        for c in self.coordinates:
            tag = "cyclic: p conserved" if c in self.cyclic else "not cyclic"
            drift = self.momentum_drift.get(c)
            more = f", drift {drift:.3g}" if drift is not None else ""
            lines.append(f"p_{c} = ∂L/∂{c}_dot  ({tag}{more})")
        if self.hamiltonian_conserved:
            h = "a constant of the motion: ∂L/∂t = 0, no non-conservative forces"
        else:
            h = "not conserved: L depends on t or non-conservative forces act"
        e = "h = T + V" if self.hamiltonian_is_energy else "h ≠ T + V"
        line = f"Jacobi integral h = p·q_dot − L  ({h}; {e}"
        if self.hamiltonian_drift is not None:
            line += f"; measured drift {self.hamiltonian_drift:.3g}"
        elif self.hamiltonian_conserved:
            line += "; not measured: pass a reduced trajectory to see its drift"
        if self.energy_drift is not None:
            line += f"; T + V drift {self.energy_drift:.3g}"
        lines.append(line + ")")
        return "\n".join(lines)

    @property
    def jacobi_integral_conserved(self) -> bool:
        """Whether the Jacobi integral h = p·q̇ − L (``hamiltonian``) is a constant of the motion."""
        return self.hamiltonian_conserved

    @property
    def jacobi_integral(self) -> np.ndarray | None:
        """h = p·q̇ − L along the trajectory given (None without one)."""
        return self.hamiltonian

    @property
    def jacobi_integral_drift(self) -> float | None:
        """max |h − h0| / |h0| along the trajectory given (None without one)."""
        return self.hamiltonian_drift


def _rel_drift(values: np.ndarray) -> float:
    values = np.asarray(values, float)
    if not len(values):
        return 0.0
    ref = abs(values[0]) if values[0] != 0 else 1.0
    return float(np.max(np.abs(values - values[0])) / ref)


def conservation(scene_or_model, trajectory=None, *, samples: int = 20, seed: int = 2,
                 parameters: dict | None = None) -> Conservation:
    """Find cyclic coordinates, decide whether H is conserved and equals T + V; with a
    reduced ``trajectory`` (from ``ReducedModel.solve``) also evaluate p, H, T + V along it."""
    rm = _reduced(scene_or_model, parameters)
    ex = rm.expressions
    L, q, qd, t = ex["L"], rm.q, rm.q_dot, rm.t
    Qs, Qds, Ts = rm.sample_states(samples, seed)
    # velocity constraints act on q_j through column j of Ã = ∂c/∂q̇: d/dt p_j = … + (Ãᵀμ)_j
    acting = ca.sum1(ca.fabs(ca.densify(ca.jacobian(ex["velocity_rows"], qd))))
    pieces = ca.Function("pieces", [q, qd, t], [
        ex["dL_dq"], ex["Q"], ca.gradient(ex["T"], q), ca.gradient(ex["V"], q), ca.gradient(ex["U"], q),
        ca.jacobian(L, t), ex["H"], ex["T"] + ex["V"], ex["T"], ex["V"], ex["U"], acting,
    ])
    n = rm.n
    dL = np.zeros((samples, n))
    Qnc = np.zeros((samples, n))
    held = np.zeros((samples, n))
    scale = np.zeros(samples)
    dLdt = np.zeros(samples)
    h_gap = np.zeros(samples)
    for i in range(samples):
        vals = [np.asarray(v).ravel() for v in pieces(Qs[i], Qds[i], Ts[i])]
        dL[i], Qnc[i], held[i] = vals[0], vals[1], vals[11] if vals[11].size else 0.0
        scale[i] = sum(float(np.sum(np.abs(vals[k]))) for k in (2, 3, 4, 8, 9, 10)) or 1.0
        dLdt[i] = float(vals[5][0])
        h_gap[i] = abs(float(vals[6][0]) - float(vals[7][0])) / scale[i]
    cyclic, structural = [], []
    for j, c in enumerate(rm.coordinates):
        struct = not ca.depends_on(L, q[j])
        numeric = bool(np.all(np.abs(dL[:, j]) <= CYCLIC_RTOL * scale))
        free_of_forces = bool(np.all(np.abs(Qnc[:, j]) <= CYCLIC_RTOL * scale)) and not np.any(held[:, j])
        if struct:
            structural.append(c)
        if (struct or numeric) and free_of_forces:
            cyclic.append(c)
    h_conserved = bool(np.all(np.abs(dLdt) <= CYCLIC_RTOL * scale)) and bool(
        np.all(np.abs(Qnc) <= CYCLIC_RTOL * scale[:, None])
    ) and (not rm.n_velocity_rows or rm.jacobi_integral_conserved())  # b̃ = 0: they do no work
    result = Conservation(
        coordinates=list(rm.coordinates),
        cyclic=cyclic,
        structurally_cyclic=structural,
        hamiltonian_conserved=h_conserved,
        hamiltonian_is_energy=bool(np.all(h_gap <= 1e-10)),
    )
    if trajectory is not None:
        info = trajectory.info
        if "q" not in info or "q_dot" not in info:
            raise InputError("the trajectory has no generalized coordinates: use ReducedModel.solve")
        Qt, Qdt, tt = np.asarray(info["q"]), np.asarray(info["q_dot"]), np.asarray(trajectory.t)
        P = rm._along(rm.momenta, Qt, Qdt, tt)
        H = rm._along(rm.hamiltonian, Qt, Qdt, tt).ravel()
        TVU = rm._along(rm.energies, Qt, Qdt, tt)
        E = TVU[:, 0] + TVU[:, 1]
        result.momenta = {c: P[:, j] for j, c in enumerate(rm.coordinates)}
        result.hamiltonian, result.energy = H, E
        result.momentum_drift = {c: _rel_drift(P[:, j]) for j, c in enumerate(rm.coordinates)}
        result.hamiltonian_drift = _rel_drift(H)
        result.energy_drift = _rel_drift(E)
    return result
