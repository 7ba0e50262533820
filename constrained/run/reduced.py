"""The reduced route: Lagrange's equations in generalized coordinates ``q`` with ``x = x(q, t)``.

CasADi derives, with symbols ``q``, ``q̇`` and ``t``:

- ``ẋ = (∂x/∂q) q̇ + ∂x/∂t``, ``T = ½ Σ m_i |ẋ_i|²``;
- the effects' terms in q, by substituting ``x(q, t)``, ``ẋ(q, q̇, t)`` into the Cartesian
  expressions each effect builds (``V``, ``U``, ``R``, ``F``);
- ``L = T − V − U``, ``Q_j = Σ_i F_i · ∂x_i/∂q_j`` (applied forces);
- Lagrange's equations ``d/dt ∂L/∂q̇ − ∂L/∂q = Q − ∂R/∂q̇``; with
  ``d/dt ∂L/∂q̇ = (∂p/∂q̇) q̈ + (∂p/∂q) q̇ + ∂p/∂t`` they read ``M(q, t) q̈ = rhs(q, q̇, t)``,
  ``M = ∂²L/∂q̇²``, ``rhs = ∂L/∂q − (∂p/∂q) q̇ − ∂p/∂t + Q − ∂R/∂q̇``;
- velocity constraints (model/velocity.py) mapped to q, ``c(q, q̇, t) = Ã q̇ + b̃ = 0``, turn
  them into the Lagrange–d'Alembert equations ``M q̈ = rhs + Ãᵀμ``, ``Ã q̈ + γ̃ = 0`` (the
  map takes care of f = 0; the velocity rows keep their multipliers μ).

SciPy's DOP853 integrates ``(q, q̇)``; the samples are mapped back to ``x``, ``v`` and the
Cartesian Model supplies energy, residuals and (KKT) constraint forces, so a reduced
Trajectory reads like a Cartesian one. ``constrained.crosscheck.cross_check`` runs both routes
from the same start.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence

import casadi as ca
import numpy as np
from scipy.integrate import solve_ivp

from .. import interrupt
from ..errors import InputError, SimulationError
from ..model import expressions, velocity
from ..model.structure import Model, assemble
from ..model.symbols import Symbols
from .quantities import trajectory_from
from .trajectory import QUANTITIES, Trajectory

__all__ = ["ReducedModel"]

#: Relative tolerance (× system size) within which the map must satisfy every constraint.
MAP_RTOL = 1e-9
#: Relative singular-value cut-off for the rank of ∂x/∂q.
RANK_RTOL = 1e-9
#: Names a coordinate may not take (they mean something in formulas).
_RESERVED = frozenset({"t", "x", "y", "z", "r", "vx", "vy", "vz"}) | set(expressions.FUNCTIONS) | set(
    expressions.CONSTANTS
)


class _Singular(Exception):
    """Lagrange's equations gave a non-finite q̈ at (t, y): ends the integration."""

    def __init__(self, t: float, y: np.ndarray):
        super().__init__(t)
        self.t, self.y = float(t), np.array(y, float)


def _number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.number) or not math.isfinite(value):
        raise InputError(f"must be a finite number, got {value!r}", where=where)
    return float(value)


class ReducedModel:
    """Lagrange's equations of ``system`` in the generalized coordinates ``coordinates``.

    ``map``: particle name -> three formulas (strings or numbers) in the coordinates, ``t``
    and the parameters (the system's, updated by ``parameters``). ``initial`` / ``rates``
    (name -> value) are the default start and centre the checks of the map: at ``samples``
    random states near ``initial`` and t in [t0, t0 + 1] every constraint must hold
    (``f(x(q, t), t) = 0`` within 1e-9 × size) and ``rank ∂x/∂q`` must equal the number of
    coordinates and the system's degrees of freedom; otherwise InputError.

    CasADi Functions (flat vectors): ``position(q, t) -> x``, ``velocity(q, q̇, t) -> ẋ``,
    ``map_jacobian(q, t) -> ∂x/∂q``, ``lagrangian(q, q̇, t) -> L``,
    ``energies(q, q̇, t) -> (T, V, U)``, ``mass_rhs(q, q̇, t) -> (M, rhs)``,
    ``acceleration(q, q̇, t) -> q̈``, ``lagrange_residual(q, q̇, q̈, t) -> M q̈ − rhs``,
    ``momenta(q, q̇, t) -> p = ∂L/∂q̇``, ``hamiltonian(q, q̇, t) -> H = p·q̇ − L``,
    with velocity constraints ``velocity_multipliers(q, q̇, t) -> μ`` (then M q̈ − rhs = Ãᵀμ,
    and the rates are brought onto Ã q̇ + b̃ = 0 by ``consistent_rates``),
    ``lagrangian_gradient(q, q̇, t) -> ∂L/∂q``, ``nonconservative_force(q, q̇, t) -> Q − ∂R/∂q̇``.
    """

    def __init__(
        self,
        system,
        coordinates: Sequence[str],
        map: Mapping[str, Sequence],  # noqa: A002 - the name of the scene key
        *,
        parameters: Mapping[str, float] | None = None,
        initial: Mapping[str, float] | None = None,
        rates: Mapping[str, float] | None = None,
        t0: float = 0.0,
        model: Model | None = None,
        samples: int = 20,
        seed: int = 0,
        check: bool = True,
        symbolic_parameters: bool = False,
    ):
        # the system's own parameters take the given values everywhere (masses, effects, map);
        # other names are extra numbers for the map's formulas
        own = {k: v for k, v in (parameters or {}).items() if k in system.parameters}
        system = system.with_parameters(own)
        self.system = system
        self.symbolic_parameters = symbolic_parameters
        self.model = None if symbolic_parameters else (model or assemble(system)).with_parameters(own)
        coords = self._coordinates(coordinates, system)
        self.coordinates: list[str] = coords
        self.map = map
        n = len(coords)
        self.n = n
        s = Symbols(system, symbolic_parameters=symbolic_parameters)
        self.parameters = dict(s.parameters)  # numbers, or SX symbols named after them
        for k, v in (parameters or {}).items():
            if not isinstance(k, str) or not k.isidentifier():
                raise InputError(f"parameter name {k!r} must be a plain identifier", where="parameters")
            if k not in own:
                self.parameters[k] = _number(v, f"parameters.{k}")
        self.initial = self._values(initial, "initial", complete=initial is not None)
        self.spread = np.maximum(1.0, np.abs(self.initial))  # of sample_states; check_map may narrow it
        self.rates = self._values(rates, "rates", complete=False)
        self.t0 = _number(t0, "t0")

        self.symbols = s
        t = s.t
        q = ca.vertcat(*[ca.SX.sym(c) for c in coords])
        qd = ca.vertcat(*[ca.SX.sym(f"{c}_dot") for c in coords])
        qdd = ca.vertcat(*[ca.SX.sym(f"{c}_ddot") for c in coords])
        self.q, self.q_dot, self.q_ddot, self.t = q, qd, qdd, t
        #: names a formula in this model may use: coordinates, rates, accelerations, t, parameters
        self.names: dict[str, object] = {"t": t, **self.parameters}
        for j, c in enumerate(coords):
            self.names[c] = q[j]
            self.names[f"{c}_dot"] = qd[j]
            self.names[f"{c}_ddot"] = qdd[j]
        self.map_formulas = self._parse_map(map, system)
        xq = self.map_formulas
        Jq = ca.jacobian(xq, q)
        xdot = ca.mtimes(Jq, qd) + ca.jacobian(xq, t)
        masses = ca.vertcat(*[ca.SX(m) for m in s.masses for _ in range(3)]) if symbolic_parameters \
            else ca.DM(np.repeat(system.masses, 3))
        T = 0.5 * ca.dot(masses * xdot, xdot)

        slots: dict[str, list] = {"potential": [], "generalized_potential": [], "dissipation": [],
                                  "applied_force": []}
        for effect in system.effects:
            slots[effect.slot].append(ca.SX(effect.term(s)))
        cart = ca.vertcat(s.x, s.v)
        red = ca.densify(ca.vertcat(xq, xdot))

        def subst(expr):
            return ca.substitute(expr, cart, red)

        V = subst(sum(slots["potential"], ca.SX(0)))
        U = subst(sum(slots["generalized_potential"], ca.SX(0)))
        R = subst(sum(slots["dissipation"], ca.SX(0)))
        F = subst(sum(slots["applied_force"], ca.SX.zeros(3 * system.n_particles)))
        L = T - V - U
        Q = ca.mtimes(Jq.T, F) - ca.gradient(R, qd)
        p = ca.gradient(L, qd)
        M = ca.jacobian(p, qd)
        dLdq = ca.gradient(L, q)
        rhs = dLdq - ca.mtimes(ca.jacobian(p, q), qd) - ca.jacobian(p, t) + Q
        H = ca.dot(p, qd) - L
        # velocity constraints in q: c(q, q̇, t) = Ã q̇ + b̃ = 0, with multipliers μ (Lagrange–d'Alembert)
        rows = [e for c in system.constraints if getattr(c, "level", "") == "velocity" for e, _ in c.rows(s)]
        c_q = subst(ca.vertcat(*rows)) if rows else ca.SX(0, 1)
        self.n_velocity_rows = c_q.numel()
        self.expressions = {"x": xq, "x_dot": xdot, "T": T, "V": V, "U": U, "R": R, "L": L,
                            "Q": Q, "p": p, "M": M, "rhs": rhs, "H": H, "dL_dq": dLdq, "velocity_rows": c_q}
        self.rheonomic = bool(ca.depends_on(xq, t))
        self.active_terms = frozenset(k for k, v in slots.items() if v)
        if symbolic_parameters:  # expressions in the parameters' names, for printing: no Functions
            return

        args, names = [q, qd, t], ["q", "q_dot", "t"]
        self.position = ca.Function("position", [q, t], [xq], ["q", "t"], ["x"])
        self.velocity = ca.Function("velocity", [q, qd, t], [xdot], names, ["v"])
        self.map_jacobian = ca.Function("map_jacobian", [q, t], [Jq], ["q", "t"], ["dx_dq"])
        self.lagrangian = ca.Function("lagrangian", args, [L], names, ["L"])
        self.energies = ca.Function("energies", args, [T, V, U], names, ["T", "V", "U"])
        self.mass_rhs = ca.Function("mass_rhs", args, [M, rhs], names, ["M", "rhs"])
        self.lagrange_residual = ca.Function(
            "lagrange_residual", [q, qd, qdd, t], [ca.mtimes(M, qdd) - rhs],
            ["q", "q_dot", "q_ddot", "t"], ["E"],
        )
        self.momenta = ca.Function("momenta", args, [p], names, ["p"])
        self.hamiltonian = ca.Function("hamiltonian", args, [H], names, ["H"])
        self.lagrangian_gradient = ca.Function("lagrangian_gradient", args, [dLdq], names, ["dL_dq"])
        self.nonconservative_force = ca.Function("nonconservative_force", args, [Q], names, ["Q"])
        if rows:  # M q̈ = rhs + Ãᵀμ, Ã q̈ + γ̃ = 0: the bordered system, solved symbolically
            acc, mu = velocity.lagrange_dalembert(M, rhs, c_q, q, qd, t)
            self.acceleration = ca.Function("acceleration", args, [acc], names, ["q_ddot"])
            self.velocity_multipliers = ca.Function("velocity_multipliers", args, [mu], names, ["mu"])
            self._velocity_level = ca.Function("velocity_level", args, [
                ca.jacobian(c_q, qd), ca.substitute(c_q, qd, ca.SX.zeros(n)), M])
            self.rates = self.consistent_rates(self.initial, self.rates, self.t0)
        elif n <= 3:  # small: a symbolic solve in SX is cheapest to evaluate
            acc = ca.solve(M, rhs)
            self.acceleration = ca.Function("acceleration", args, [acc], names, ["q_ddot"])
        else:
            Qm, Qd, Tm = ca.MX.sym("q", n), ca.MX.sym("q_dot", n), ca.MX.sym("t")
            Mm, rm = self.mass_rhs(Qm, Qd, Tm)
            self.acceleration = ca.Function(
                "acceleration", [Qm, Qd, Tm], [ca.solve(Mm, rm, "qr")], names, ["q_ddot"]
            )
        Y, Ty = ca.MX.sym("y", 2 * n), ca.MX.sym("t")
        self._ode = ca.Function("ode", [Y, Ty], [ca.vertcat(Y[n:], self.acceleration(Y[:n], Y[n:], Ty))])
        if check:
            self.check_map(samples=samples, seed=seed)

    # --- construction helpers ------------------------------------------------------------
    @classmethod
    def from_scene(cls, scene, *, parameters=None, **kwargs) -> ReducedModel:
        """The ReducedModel of a Scene's validated ``[reduced]`` section."""
        red = getattr(scene, "reduced", None)
        if not red:
            raise InputError("the scene has no [reduced] section (coordinates, initial, rates, map)",
                             where="reduced")
        kwargs.setdefault("t0", scene.settings.get("t_start", 0.0) if scene.settings else 0.0)
        return cls(scene.system, red["coordinates"], red["map"], parameters=parameters,
                   initial=red.get("initial"), rates=red.get("rates"), **kwargs)

    @staticmethod
    def _coordinates(coordinates, system) -> list[str]:
        if isinstance(coordinates, str) or not isinstance(coordinates, Sequence) or not coordinates:
            raise InputError(f"must be a non-empty list of names, got {coordinates!r}",
                             where="reduced.coordinates")
        taken = set(system.parameters) | set(system.definitions)
        for p in system.names:
            taken |= {f"{a}_{p}" for a in ("x", "y", "z", "vx", "vy", "vz")}
        out: list[str] = []
        for c in coordinates:
            if not isinstance(c, str) or not c.isidentifier():
                raise InputError(f"coordinate name {c!r} must be a plain identifier",
                                 where="reduced.coordinates")
            if c in out:
                raise InputError(f"coordinate '{c}' is listed twice", where="reduced.coordinates")
            if c in _RESERVED or c in taken or c.endswith(("_dot", "_ddot")):
                raise InputError(f"the coordinate name '{c}' is taken (a name formulas already use)",
                                 where="reduced.coordinates")
            out.append(c)
        return out

    def _values(self, values, what: str, *, complete: bool) -> np.ndarray:
        values = dict(values or {})
        for k in values:
            if k not in self.coordinates:
                raise InputError(f"'{k}' is not a coordinate (coordinates: {', '.join(self.coordinates)})",
                                 where=f"reduced.{what}.{k}")
        if complete:
            for c in self.coordinates:
                if c not in values:
                    raise InputError(f"missing the value of '{c}'", where=f"reduced.{what}.{c}")
        return np.array([_number(values.get(c, 0.0), f"reduced.{what}.{c}") for c in self.coordinates])

    def _parse_map(self, mapping, system):
        if not isinstance(mapping, Mapping):
            raise InputError("must be a table particle name -> [x, y, z] formulas", where="reduced.map")
        for k in mapping:
            if k not in system.names:
                raise InputError(f"names unknown particle '{k}' (particles: {', '.join(system.names)})",
                                 where=f"reduced.map.{k}")
        names = {"t": self.names["t"], **self.parameters}
        names.update({c: self.names[c] for c in self.coordinates})
        rows = []
        for pname in system.names:
            if pname not in mapping:
                raise InputError(f"particle '{pname}' is not mapped; every particle needs x, y, z",
                                 where=f"reduced.map.{pname}")
            entries = mapping[pname]
            if isinstance(entries, str) or not isinstance(entries, Sequence) or len(entries) != 3:
                raise InputError(f"must be a list of 3 formulas (x, y, z), got {entries!r}",
                                 where=f"reduced.map.{pname}")
            for k, e in enumerate(entries):
                rows.append(ca.SX(expressions.parse(e, names, where=f"reduced.map.{pname}[{k}]")))
        return ca.vertcat(*rows)

    def consistent_rates(self, q, q_dot, t: float) -> np.ndarray:
        """q̇ brought onto the velocity constraints Ã q̇ + b̃ = 0, the change M(q)-weighted (the
        Cartesian start's mass-weighted projection, in q); as it is without velocity rows."""
        qd = np.asarray(q_dot, float).ravel()
        if not self.n_velocity_rows:
            return qd
        A, b, M = (np.asarray(a, float) for a in self._velocity_level(q, qd, t))
        MiAt = np.linalg.solve(M, A.T)
        return qd - MiAt @ np.linalg.lstsq(A @ MiAt, A @ qd + b.ravel(), rcond=1e-12)[0]

    # --- checks of the map -----------------------------------------------------------------
    def sample_states(self, samples: int = 20, seed: int = 0):
        """Random (q, q̇, t) near the initial values: q = q0 + U(−½, ½)·``spread`` (max(1, |q0|),
        narrowed by ``check_map`` where the map is not defined that far out), q̇ ~ N(0, 1) + rates,
        t ∈ [t0, t0 + 1]. The first sample is (q0, rates, t0)."""
        rng = np.random.default_rng(seed)
        Q = self.initial + rng.uniform(-0.5, 0.5, (samples, self.n)) * self.spread
        Qd = self.rates + rng.standard_normal((samples, self.n))
        Ts = self.t0 + rng.uniform(0.0, 1.0, samples)
        Q[0], Qd[0], Ts[0] = self.initial, self.rates, self.t0
        return Q, Qd, Ts

    def jacobi_integral_conserved(self, samples: int = 20, seed: int = 2, rtol: float = 1e-10) -> bool:
        """Whether the Jacobi integral (energy function) ``h = Σ q̇_j ∂L/∂q̇_j − L`` is a
        constant of the motion: ``dh/dt = −∂L/∂t + Q·q̇`` vanishes when ``L`` has no explicit t
        (structurally, or numerically at sampled states) and the non-conservative generalized
        forces do no work (Q·q̇ = 0 at the sampled states: damping does, a magnetic force given
        as an applied force does not). It exists for driven (rheonomic) maps too, e.g. a bead
        on a uniformly rotating hoop, where ``h ≠ T + V`` and ``T + V`` is not conserved."""
        cached = getattr(self, "_jacobi", None)
        if cached is not None:
            return cached
        ex = self.expressions
        L, Q, T, V, U = ex["L"], ex["Q"], ex["T"], ex["V"], ex["U"]
        q, qd, t = self.q, self.q_dot, self.t
        c = ex["velocity_rows"]  # their forces work at the rate −μ·b̃: none when b̃ = c(q̇ = 0) = 0
        b, Aqd = ca.substitute(c, qd, ca.SX.zeros(self.n)), ca.mtimes(ca.jacobian(c, qd), qd)
        probe = ca.Function("jacobi_probe", [q, qd, t], [
            ca.jacobian(L, t), ca.dot(Q, qd) / (1 + ca.norm_1(qd)),
            ca.fabs(T) + ca.fabs(V) + ca.fabs(U) + ca.norm_1(ca.gradient(L, qd)),
            ca.norm_1(b) - rtol * (1 + ca.norm_1(Aqd))])
        ok = True
        for qs, qds, ts in zip(*self.sample_states(samples, seed), strict=True):
            dLdt, power, scale, works = (np.asarray(v, float).ravel() for v in probe(qs, qds, ts))
            size = max(float(scale[0]), 1e-300)
            if abs(float(dLdt[0])) > rtol * size or abs(float(power[0])) > rtol * size or works[0] > 0:
                ok = False
                break
        self._jacobi = ok
        return ok

    def check_map(self, samples: int = 20, seed: int = 0) -> None:
        """Refuse a map that leaves the constraint manifold or does not parametrize it.

        ``|f(x(q, t), t)| ≤ 1e-9 × size`` at every sample, and ``rank ∂x/∂q = n = DOF``. Where the
        map is not finite at some samples but is at the initial values (a domain such as
        sqrt(l² − X²), |X| < l), the samples' ``spread`` is halved until it is finite at all."""
        from ..manifold.constraint_report import constraint_report

        where = "reduced.map"
        for _ in range(40):
            Q, _, Ts = self.sample_states(samples, seed)
            X = [np.asarray(self.position(q, t)).ravel() for q, t in zip(Q, Ts, strict=True)]
            bad = [i for i, x in enumerate(X) if not np.all(np.isfinite(x))]
            if not bad or bad[0] == 0:
                break
            self.spread = self.spread / 2
        if bad:
            raise InputError(f"the map is not finite at {self._state_text(Q[bad[0]], None, Ts[bad[0]])}",
                             where=where)
        size = max(self.system.size(), max(float(np.max(np.abs(x), initial=0.0)) for x in X), 1e-300)
        report = constraint_report(self.system, X[0], float(Ts[0]), model=self.model)
        dof = report.generic_degrees_of_freedom
        if self.n != dof:
            few = "too few" if self.n < dof else "too many"
            raise InputError(
                f"{few} coordinates: the constraints leave {dof} degree(s) of freedom "
                f"(3N = {report.n_coordinates} coordinates, constraint rank {report.generic_rank}), "
                f"but the map has {self.n} ({', '.join(self.coordinates)})",
                where="reduced.coordinates",
            )
        if self.model.n_position_rows:
            worst, worst_k = -1.0, 0
            for k, (x, t) in enumerate(zip(X, Ts, strict=True)):
                f = np.abs(np.asarray(self.model.constraint(x, t)).ravel())
                if f.max() > worst:
                    worst, worst_k, row = float(f.max()), k, int(np.argmax(f))
            if worst > MAP_RTOL * size:
                label = self.model.constraint_labels[row]
                raise InputError(
                    f"the map violates constraint {row} ({label}) by {worst:.3g} at "
                    f"{self._state_text(Q[worst_k], None, Ts[worst_k])}; x(q, t) must satisfy every "
                    "constraint for all q",
                    where=where,
                )
        ranks = []
        for q, t in zip(Q, Ts, strict=True):
            sv = np.linalg.svd(np.asarray(self.map_jacobian(q, t)), compute_uv=False)
            ranks.append(int(np.sum(sv > RANK_RTOL * sv[0])) if sv.size and sv[0] > 0 else 0)
        if max(ranks) < self.n:
            raise InputError(
                f"the coordinates are dependent: rank ∂x/∂q is at most {max(ranks)} near the initial "
                f"values, less than the {self.n} coordinates ({', '.join(self.coordinates)})",
                where=where,
            )

    def _state_text(self, q, qd=None, t=None) -> str:
        parts = [f"{c} = {v:.6g}" for c, v in zip(self.coordinates, q, strict=True)]
        if qd is not None:
            parts += [f"{c}_dot = {v:.6g}" for c, v in zip(self.coordinates, qd, strict=True)]
        if t is not None:
            parts.append(f"t = {t:.6g}")
        return ", ".join(parts)

    # --- the state map ---------------------------------------------------------------------
    def state(self, q, q_dot, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(x, v) as (N, 3) arrays at (q, q̇, t)."""
        x = np.asarray(self.position(q, t)).reshape(-1, 3)
        v = np.asarray(self.velocity(q, q_dot, t)).reshape(-1, 3)
        return x, v

    def _along(self, function: ca.Function, *columns) -> np.ndarray:
        n = len(columns[0])
        args = [np.asarray(c, float).reshape(n, -1).T for c in columns]
        return np.asarray(function.map(n)(*args)).T.reshape(n, -1)

    # --- integration -----------------------------------------------------------------------
    def solve(
        self,
        t_end: float,
        *,
        t_start: float | None = None,
        initial=None,
        rates=None,
        rtol: float = 1e-10,
        atol: float = 1e-10,
        t_eval=None,
        outputs=None,
        max_step: float = math.inf,
        progress=None,
    ) -> Trajectory:
        """Integrate M q̈ = rhs with DOP853 from (initial, rates) at t_start to t_end.

        Returns a Trajectory of the mapped x, v with the Cartesian quantities (energy from
        the Cartesian energy function, constraint residuals, KKT multipliers/forces at the
        mapped states); ``progress(t)``, if given, is told the time reached. ``info`` holds
        ``coordinates``, ``q``, ``q_dot`` (T, n) and ``hamiltonian`` (T,)."""
        t0 = self.t0 if t_start is None else _number(t_start, "t_start")
        t_end = _number(t_end, "t_end")
        if t_end <= t0:
            raise InputError(f"t_end ({t_end:g} s) must be later than t_start ({t0:g} s)")
        q0 = self.initial if initial is None else self._vector(initial, "initial")
        qd0 = self.consistent_rates(q0, self.rates if rates is None else self._vector(rates, "rates"), t0)
        if t_eval is not None:
            t_eval = np.asarray(t_eval, float).ravel()
        ode = self._ode
        nfev = [0]

        def fun(t, y):
            nfev[0] += 1
            out = np.asarray(ode(y, t)).ravel()
            if not np.all(np.isfinite(out)):  # (DOP853 given NaN at its start loops forever)
                raise _Singular(t, y)
            return out

        stopped_at: list[float] = []

        def stop(t, y):  # Ctrl-C (constrained.interrupt): a terminal event ends the run at the
            if progress is not None:  # end of the step in which it was seen (a root there)
                progress(t)
            if not interrupt.requested():
                return 1.0
            if not stopped_at:
                stopped_at.append(t)
            return stopped_at[0] - t

        stop.terminal = True
        started = time.perf_counter()
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                sol = solve_ivp(fun, (t0, t_end), np.concatenate([q0, qd0]), method="DOP853", rtol=rtol,
                                atol=atol, t_eval=t_eval, max_step=max_step, events=stop)
        except _Singular as exc:  # at the start: the input's fault (exit 2); later: the run stops
            text = self._singular_text(exc.t, exc.y[:self.n])
            if exc.t == t0:
                raise InputError(text, where="reduced.initial") from None
            raise SimulationError(text) from None
        wall = time.perf_counter() - started
        Y = sol.y.T
        n = self.n
        Qs, Qds, ts = Y[:, :n], Y[:, n:], np.asarray(sol.t)
        X = self._along(self.position, Qs, ts)
        V = self._along(self.velocity, Qs, Qds, ts)
        wanted = set(QUANTITIES) if outputs is None else set(outputs)
        stats = {"nfev": int(sol.nfev), "wall_time_s": wall, "method": "reduced DOP853"}
        traj = trajectory_from(self.model, ts, X, V, wanted, stats)
        if "action" in wanted and len(ts) >= 2:
            from .action_integral import action

            traj.action = action(self.model, traj).cumulative
        traj.info.update({
            "route": "reduced",
            "coordinates": list(self.coordinates),
            "q": Qs,
            "q_dot": Qds,
            "hamiltonian": self._along(self.hamiltonian, Qs, Qds, ts).ravel() if len(ts) else np.zeros(0),
            # the same h = p·q̇ − L under its mechanics name, and whether it is a constant here
            "jacobi_integral_conserved": self.jacobi_integral_conserved(),
            "rtol": rtol,
            "atol": atol,
        })
        if not sol.success:
            raise SimulationError(f"the reduced route stopped early: {sol.message}", trajectory=traj)
        return traj

    def _singular_text(self, t: float, q: np.ndarray) -> str:
        """Why Lagrange's equations M(q) q̈ = rhs have no finite q̈ at (q, t): the rank of ∂x/∂q
        (below n: the coordinates are singular there, M = (∂x/∂q)ᵀ m (∂x/∂q) too)."""
        Jq = np.asarray(self.map_jacobian(q, t), float)
        rank = int(np.linalg.matrix_rank(Jq)) if np.all(np.isfinite(Jq)) else -1
        at = ", ".join(f"{c} = {v:.6g}" for c, v in zip(self.coordinates, q, strict=True))
        why = (f"the coordinates are singular there (rank ∂x/∂q = {rank} < {self.n}: M(q) is singular, like "
               "the pole of spherical angles, where the azimuth is undefined)" if 0 <= rank < self.n else
               "the equations give non-finite accelerations there")
        return (f"the reduced route stopped at t = {t:.6g} s, q = ({at}): {why}; Lagrange's equations in "
                "these coordinates have no solution through that point. Start away from it, or choose "
                "coordinates that are regular along the motion (the Cartesian route has no such point)")

    def _vector(self, values, what: str) -> np.ndarray:
        if isinstance(values, Mapping):
            return self._values(values, what, complete=what == "initial")
        arr = np.asarray(values, float).ravel()
        if arr.size != self.n:
            raise InputError(f"needs {self.n} values ({', '.join(self.coordinates)}), got {arr.size}",
                             where=what)
        return arr

    def __repr__(self) -> str:
        return (f"ReducedModel({', '.join(self.coordinates)} for {self.system.name or 'system'}; "
                f"{'rheonomic' if self.rheonomic else 'scleronomic'} map)")
