"""Velocity constraints: rows ``c(x, v, t) = a(x, t)·v + b(x, t) = 0`` that no position
function f(x, t) = 0 need stand behind (rolling, knife edges, skates: non-holonomic).

Each row gets a multiplier μ like a holonomic row's λ: the equations of motion read

    M x'' = F + Jᵀλ + Aᵀμ,    f(x, t) = 0,    A v + b = 0,

with ``A = ∂c/∂v`` (so ``Aᵀμ`` acts along the forbidden velocities, d'Alembert's virtual
displacements being those with ``J δx = 0`` and ``A δx = 0``). Differentiated once:
``A x'' + γ_v = 0`` with ``γ_v = (∂c/∂x) v + ∂c/∂t`` (CasADi AD; ∂c/∂x includes ∂A/∂x·v).
The constraint force does work at the rate ``(Aᵀμ)·v = −μ·b``: none when b = 0 (a skate,
a rolling ball), some when b ≠ 0 (a prescribed slip, a belt's speed).

A formula must be linear in the velocities: ``∂c/∂v`` may not depend on v (checked here by
CasADi, so the scene reports it with the item's key), and must involve at least one.

Types: ``Velocity`` (any formula), ``KnifeEdge`` (a particle's velocity has no component
across a body-fixed direction), ``Rolling`` (no slip where a ball, or a particle, touches
a plane). ``rows_assembled`` and ``lagrange_dalembert`` are what the Cartesian Structure and
the reduced route (generalized coordinates) build from the rows; ``at_rest`` is what statics
says of them at an equilibrium.
"""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca
import numpy as np

from ..errors import InputError
from .constraints import Constraint, _fmt


class VelocityConstraint(Constraint):
    """Base class: ``rows(s)`` returns [(c_k(x, v, t) linear in v, label_k), ...]."""

    kind = "velocity constraint"
    level = "velocity"
    two_sided_only = ("velocity constraint forbids a velocity both ways: it has no gap that could "
                      "open (a one-sided contact is a position constraint: a 'plane' or 'surface')")

    def _checked(self, expr, s, label: str, where: str):
        """``expr`` after the check that it is linear in the velocities and involves one."""
        expr = ca.SX(expr)
        a = ca.jacobian(expr, s.v)
        if a.nnz() == 0:
            raise InputError(f"'{label}' involves no velocity, so it is a condition on the positions: "
                             "write it as a position constraint (type = \"custom\")", where=where)
        if ca.depends_on(a, s.v):
            raise InputError(f"'{label}' is not linear in the velocities (its derivative with respect to "
                             "them still depends on them): a velocity constraint must read "
                             "a(x, t)·v + b(x, t) = 0", where=where)
        if not _affine_at_samples(expr, a, s.v):
            raise InputError(f"'{label}' is not linear in the velocities (it jumps or steps with them, as "
                             "sign, floor or ceil of a velocity do, whose derivative is 0): a velocity "
                             "constraint must read a(x, t)·v + b(x, t) = 0", where=where)
        return expr


def _affine_at_samples(expr, a, v) -> bool:
    """``expr == a·v + expr(v = 0)`` at a few fixed pseudo-random points of all its symbols.

    ∂c/∂v free of v is not enough: sign, floor and ceil have derivative 0, so ``sign(vx_p)``
    passes that test while being no a(x, t)·v + b(x, t). Points where the formula is not
    finite (a log or sqrt of a negative sample) say nothing and are skipped."""
    symbols = ca.symvar(expr)
    if not symbols:
        return True
    arg = ca.vertcat(*symbols)
    residual = expr - ca.mtimes(a, v) - ca.substitute(expr, v, ca.SX.zeros(v.numel()))
    scale = ca.fabs(expr) + ca.fabs(ca.substitute(expr, v, ca.SX.zeros(v.numel())))
    f = ca.Function("affine_check", [arg], [residual, scale])
    rng = np.random.default_rng(20261127)
    for _ in range(6):
        r, m = (float(z) for z in f(rng.uniform(-7.3, 9.1, arg.numel())))
        if np.isfinite(r) and np.isfinite(m) and abs(r) > 1e-9 * (1.0 + m):
            return False
    return True


class Velocity(VelocityConstraint):
    """Any formula ``a(x, t)·v + b(x, t) = 0`` in particle coordinates x_NAME …, velocities
    vx_NAME …, t and the parameters."""

    def __init__(self, expr: str, *, name=None, where=None, unilateral: bool = False,
                 restitution: float = 0.0):
        self.expr, self.name, self.where = expr, name, where
        self._one_sided(unilateral, restitution)

    @property
    def label(self) -> str:
        return self.name or f"{self.expr} = 0"

    def rows(self, s):
        where = f"{self._where()}.expr"
        return [(self._checked(s.parse(self.expr, where, velocities=True), s, self.label, where), self.label)]


class KnifeEdge(VelocityConstraint):
    """A knife edge, skate or sleigh runner: the velocity of ``particle`` has no component
    across a body-fixed direction given by two particles.

    ``across = [a, b]``: v_p · ê = 0 with ê = (x_b − x_a)/|x_b − x_a| (any dimension);
    ``along = [a, b]`` with the ``normal`` n of the plane the blade moves on: the blade
    points from a to b, and v_p · ê = 0 with ê = n × (x_b − x_a) / |n × (x_b − x_a)|.
    The row is in m/s and its multiplier μ is the blade's sideways force in N.
    """

    numbers = ("normal",)

    def __init__(self, particle: str, *, across: Sequence[str] | None = None,
                 along: Sequence[str] | None = None, normal=None, name=None, where=None,
                 unilateral: bool = False, restitution: float = 0.0):
        self.particle, self.across, self.along, self.normal = particle, across, along, normal
        self.name, self.where = name, where
        self._one_sided(unilateral, restitution)
        where = self._where()
        if (across is None) == (along is None):
            raise InputError("give exactly one of 'across' (two particles across the blade) or 'along' "
                             "(two particles along it, with the plane's 'normal')", where=where)
        pair, key = (across, "across") if across is not None else (along, "along")
        if (isinstance(pair, str) or not isinstance(pair, Sequence) or len(pair) != 2
                or not all(isinstance(p, str) for p in pair)):
            raise InputError(f"must be a list of two particle names, got {pair!r}", where=f"{where}.{key}")
        if pair[0] == pair[1]:
            raise InputError(f"names the same particle '{pair[0]}' twice: two particles give the direction",
                             where=f"{where}.{key}")
        if along is not None and normal is None:
            raise InputError("'along' needs the 'normal' of the plane the blade moves on (the sideways "
                             "direction is normal × along)", where=where)
        if across is not None and normal is not None:
            raise InputError("'normal' goes with 'along'; 'across' gives the forbidden direction itself",
                             where=f"{where}.normal")
        if (normal is not None and not isinstance(normal, str) and isinstance(normal, Sequence | np.ndarray)
                and all(isinstance(c, int | float) and not isinstance(c, bool) and c == 0 for c in normal)):
            raise InputError("the normal vector is zero: the blade's sideways direction is normal × along, "
                             "so give the normal of the plane the blade moves on", where=f"{where}.normal")
        self.across = list(across) if across is not None else None
        self.along = list(along) if along is not None else None

    def why_undefined(self, names: Sequence[str], positions, t: float = 0.0) -> str:
        """Why the blade's direction ê is undefined at ``positions`` (N, 3) ('' when it is not):
        the two particles coincide, or (``along``) the blade is parallel to the normal."""
        a, b = self.across if self.across is not None else self.along
        names = list(names)
        if a not in names or b not in names:
            return ""
        pos = np.asarray(positions, float).reshape(-1, 3)
        d = pos[names.index(b)] - pos[names.index(a)]
        key = "across" if self.across is not None else "along"
        if not np.any(d):
            return (f"the particles '{a}' and '{b}' that give the blade's direction ('{key}') are at the "
                    "same position, so the direction (x_b − x_a)/|x_b − x_a| is undefined (0/0); move one "
                    "of them, or name two particles of the body that stay apart")
        if self.across is None:
            try:
                n = np.asarray(self.normal, float)
            except (TypeError, ValueError):  # a normal given by formulas of t
                return ""
            if not np.any(np.cross(n, d)):
                return (f"the blade '{a}'→'{b}' is parallel to the plane's normal {_fmt(self.normal)}, so "
                        "the sideways direction n × (x_b − x_a) is 0 and undefined; 'along' names two "
                        "particles along the blade, in the plane the blade moves on")
        return ""

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        if self.across is not None:
            return f"knife edge {self.particle} (no velocity along {self.across[0]}→{self.across[1]})"
        a, b = self.along
        return f"knife edge {self.particle} (blade {a}→{b}, normal {_fmt(self.normal)})"

    def rows(self, s):
        where = self._where()
        a, b = self.across if self.across is not None else self.along
        d = s.position(b, where) - s.position(a, where)
        if self.across is None:
            d = ca.cross(s.point(self.normal, f"{where}.normal"), d)
        e = d / ca.norm_2(d)
        row = ca.dot(e, s.velocity(self.particle, where))
        return [(self._checked(row, s, self.label, where), self.label)]


class Rolling(VelocityConstraint):
    """No slip where a body touches a plane of unit normal n̂ (``normal``, fixed numbers).

    ``radius`` R > 0: a ball centred on ``particle`` c, a rigid body whose orientation the
    particles ``a`` and ``b`` give (with c, not on one line). The body's material point at
    the contact, P = x_c − R n̂, has the velocity

        v_P = v_c + α ė₁ + β ė₂ + γ ė₃,   e₁ = x_a − x_c, e₂ = x_b − x_c, e₃ = e₁ × e₂,

    with (α, β, γ) the body coordinates of P − x_c in (e₁, e₂, e₃) (for a rigid body
    ė_i = ω × e_i, so v_P = v_c + ω × (P − x_c)). ``radius`` 0: the particle itself touches
    (v_P = v_c). The two rows are t₁·v_P = 0, t₂·v_P = 0 along the plane (m/s; μ is the
    friction force in N). The centre's height is a position constraint the scene gives
    (a ``plane`` at offset R), as are the body's distances.
    """

    numbers = ("radius",)

    def __init__(self, particle: str, *, normal, radius=0.0, a: str | None = None, b: str | None = None,
                 name=None, where=None, unilateral: bool = False, restitution: float = 0.0):
        self.particle, self.normal, self.radius, self.a, self.b = particle, normal, radius, a, b
        self.name, self.where = name, where
        #: Whether a ball rolls (radius > 0, or a formula), or the particle itself touches.
        self.ball = isinstance(radius, str) or (isinstance(radius, int | float) and radius > 0)
        self._one_sided(unilateral, restitution)
        where = self._where()
        if (isinstance(normal, str) or not isinstance(normal, Sequence | np.ndarray) or len(normal) != 3
                or not all(isinstance(c, int | float) and not isinstance(c, bool) and np.isfinite(c)
                           for c in normal)):
            raise InputError(f"must be three numbers (a fixed plane), got {normal!r}",
                             where=f"{where}.normal")
        if not any(normal):
            raise InputError("the normal vector is zero", where=f"{where}.normal")
        if isinstance(radius, bool) or not (isinstance(radius, str) and radius.strip()
                                            or isinstance(radius, int | float) and radius >= 0):
            raise InputError(f"must be a number of metres ≥ 0 (or a formula of the parameters), got "
                             f"{radius!r}", where=f"{where}.radius")
        if self.ball and (a is None or b is None):
            raise InputError("a rolling ball (radius > 0) needs two more particles 'a' and 'b' of its body, "
                             "which with the centre give its orientation", where=where)
        if self.ball and len({particle, a, b}) < 3:
            raise InputError("'particle', 'a' and 'b' must be three different particles of the body",
                             where=where)
        if not self.ball and (a is not None or b is not None):
            raise InputError("'a' and 'b' give the body of a rolling ball: give a 'radius' > 0 with them, "
                             "or leave them out (radius 0: the particle itself does not slide)", where=where)
        self.normal = [float(c) for c in normal]

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        if self.ball:
            return f"rolling {self.particle} (radius {_fmt(self.radius)} m, normal {_fmt(self.normal)})"
        return f"no slip {self.particle} (normal {_fmt(self.normal)})"

    def tangents(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n̂, t₁, t₂): the unit normal and an orthonormal basis of the plane."""
        n = np.asarray(self.normal, float) / np.linalg.norm(self.normal)
        t1 = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
        t1 /= np.linalg.norm(t1)
        return n, t1, np.cross(n, t1)

    def rows(self, s):
        where = self._where()
        n, t1, t2 = (ca.DM(u) for u in self.tangents())
        vc = s.velocity(self.particle, where)
        if self.ball:  # the body's material point at the contact
            xc = s.position(self.particle, where)
            e1, e2 = s.position(self.a, where) - xc, s.position(self.b, where) - xc
            d1, d2 = s.velocity(self.a, where) - vc, s.velocity(self.b, where) - vc
            e3, d3 = ca.cross(e1, e2), ca.cross(d1, e2) + ca.cross(e1, d2)
            r = -s.time_function(self.radius, f"{where}.radius") * n
            det = ca.dot(e3, e3)  # e₁·(e₂ × e₃) = |e₁ × e₂|²
            alpha, beta, gamma = (ca.dot(ca.cross(e2, e3), r) / det, ca.dot(ca.cross(e3, e1), r) / det,
                                  ca.dot(e3, r) / det)
            vc = vc + alpha * d1 + beta * d2 + gamma * d3
        return [(self._checked(ca.dot(t, vc), s, self.label, where), f"{self.label} [t{k + 1}]")
                for k, t in enumerate((t1, t2))]


VELOCITY_TYPES = {"velocity": Velocity, "knife_edge": KnifeEdge, "rolling": Rolling}


def velocity_level(system, rows: list, J, f_t, gamma, x, v, t) -> tuple:
    """(G, c₀, γ) of the velocity level: the holonomic rows' J, f_t, γ followed by the velocity
    rows' A, b, γ_v (``rows_assembled``), so that G v + c₀ = 0 and G x'' + γ = 0."""
    if not rows:
        return J, f_t, gamma
    if any(getattr(item, "unilateral", False) for item in system.constraints):
        raise InputError("one-sided constraints and velocity constraints in one system are not supported "
                         "yet: make the one-sided constraints two-sided", where="constraints")
    A, b, gamma_v = rows_assembled(rows, x, v, t)
    return ca.vertcat(J, A), ca.vertcat(f_t, b), ca.vertcat(gamma, gamma_v)


def rows_assembled(rows: list, x, v, t) -> tuple:
    """(A, b, γ_v) of the velocity rows c (SX expressions in x, v, t, linear in v):
    A = ∂c/∂v, b = c(v = 0), γ_v = (∂c/∂x) v + ∂c/∂t, so that d/dt c = A x'' + γ_v."""
    c = ca.vertcat(*rows)
    A = ca.jacobian(c, v)
    b = ca.substitute(c, v, ca.SX.zeros(v.numel()))
    gamma = ca.jtimes(c, x, v) + (ca.jacobian(c, t) if ca.depends_on(c, t) else 0)
    return A, b, gamma


def lagrange_dalembert(M, rhs, c, q, qd, t) -> tuple:
    """(q̈, μ) of the Lagrange–d'Alembert equations in generalized coordinates,

        M(q, t) q̈ = rhs + Ãᵀ μ,     Ã q̈ + γ̃ = 0,

    for the velocity rows c(q, q̇, t) = Ã q̇ + b̃ (Ã = ∂c/∂q̇, γ̃ = (∂c/∂q) q̇ + ∂c/∂t): the
    bordered system [[M, −Ãᵀ], [Ã, 0]] [q̈; μ] = [rhs; −γ̃] solved symbolically (small n)."""
    A = ca.jacobian(c, qd)
    gamma = ca.jtimes(c, q, qd) + (ca.jacobian(c, t) if ca.depends_on(c, t) else 0)
    n, k = q.numel(), c.numel()
    K = ca.blockcat([[M, -A.T], [A, ca.SX(k, k)]])
    solution = ca.solve(K, ca.vertcat(rhs, -gamma))
    return solution[:n], solution[n:]


# --- at rest ------------------------------------------------------------------------------------
# At rest (v = 0) a velocity row a·v + b = 0 reads b(x, t) = 0; it lasts while ∂b/∂t = 0 too
# (its acceleration-level row has γ_v = ∂b/∂t at v = 0). Where rest is allowed, d'Alembert's
# principle asks F + Jᵀλ + Aᵀμ = 0: the velocity rows' forces do no work at rest (power
# −μ·b = 0), but they can hold a system the holonomic constraints alone would let go — a
# skate standing across a slope is held by its blade. Such equilibria come in families, and
# the energy method decides their stability only where μ = 0.

#: A velocity row's force counts as zero below this fraction of the forces at the equilibrium.
REST_FORCE_RTOL = 1e-9


def _require_rest(model, x: np.ndarray, t: float, size: float) -> None:
    """Refuse a configuration where rest breaks a velocity row: b(x, t) ≠ 0 (rest not
    allowed) or ∂b/∂t ≠ 0 (it would not last), within round-off of the row's scale."""
    C_f, C = model.n_position_rows, model.n_constraints
    if C_f == C:
        return
    zero = np.zeros_like(x)
    _, b = model.velocity_terms(x, t)
    _, G, gamma = model.dynamics(x, zero, t)
    G = np.asarray(G, float).reshape(C, -1)
    b, gamma = np.asarray(b, float).ravel(), np.asarray(gamma, float).ravel()
    for k in range(C_f, C):
        scale = float(np.max(np.linalg.norm(G[k].reshape(-1, 3), axis=1), initial=0.0)) or 1.0
        what = ("b ≠ 0 at v = 0: it prescribes a velocity" if abs(b[k]) > 1e-12 * scale * size else
                "∂b/∂t ≠ 0 at v = 0: rest would not last" if abs(gamma[k]) > 1e-12 * scale * size else None)
        if what:
            raise InputError(f"no static equilibrium: the velocity constraint '{model.constraint_labels[k]}' "
                             f"does not allow rest ({what})")


def at_rest(model, x: np.ndarray, t: float, size: float, G: np.ndarray, multipliers: np.ndarray,
            force_scale: float) -> tuple[str, bool]:
    """At an equilibrium x of ``model`` (G = [J; A] there, the multipliers [λ; μ]): the
    report's sentence on the velocity rows and whether they carry a force there (('', False)
    without velocity rows). A configuration where rest breaks a velocity row is refused
    (InputError: b ≠ 0, rest not allowed, or ∂b/∂t ≠ 0, it would not last)."""
    C_f = model.n_position_rows
    if C_f == model.n_constraints:
        return "", False
    _require_rest(model, x, t, size)
    force = G[C_f:].T @ multipliers[C_f:]
    if np.max(np.abs(force), initial=0.0) <= REST_FORCE_RTOL * force_scale:
        return ("velocity constraints: no force at this equilibrium (μ = 0: the holonomic constraints "
                "balance the applied forces); at rest they do no work", False)
    # μ ≠ 0 may only be a share of a load the holonomic rows could carry alone: a velocity row
    # that repeats the derivative of a holonomic one (a bead on the plane z = 0 and v_z = 0)
    # takes half of it in the minimum-norm split. It holds the system only where the total
    # constraint force Gᵀ[λ; μ] is not in the row space of J: min_λ' |Jᵀλ' − Gᵀ[λ; μ]| > 0.
    total = G.T @ multipliers
    J = G[:C_f]
    alone = np.linalg.lstsq(J.T, total, rcond=None)[0] if C_f else np.zeros(0)
    left = total - J.T @ alone if C_f else total
    if np.max(np.abs(left), initial=0.0) <= REST_FORCE_RTOL * force_scale:
        return ("velocity constraints: they repeat holonomic ones here and share their load (μ ≠ 0 by "
                "the minimum-norm split), but the holonomic constraints alone balance the applied "
                "forces; at rest they do no work", False)
    return ("velocity constraints: they hold the system at rest here (μ ≠ 0, as a skate's blade holds it "
            "across a slope) and do no work (power −μ·b = 0); such equilibria form families, and the "
            "energy method does not decide their stability", True)


# --- a row whose coefficient vanishes along a run -------------------------------------------------
# A row a(x, t)·v + b whose coefficient a = ∂c/∂v passes through 0 (y·vx = 0 as y crosses 0)
# loses rank there: at that instant it says nothing, and its multiplier has a pole, μ ~ 1/|a|,
# while the force Aᵀμ it exerts stays finite. The row-normalized watch of a run (solvers.watches)
# cannot see it (a normalized row keeps length 1), so the run's samples are checked here.

#: A velocity row whose |∂c/∂v| falls below this fraction of its largest value along a run has
#: lost rank there.
VANISHING_RTOL = 1e-6
#: At most this many samples of a run are checked (evenly spread, the first and last kept).
VANISHING_SAMPLES = 2000


def coefficient_norms(model, X, t) -> np.ndarray:
    """(K, n): |a_k(x_i, t_i)| = |∂c_k/∂v| of the K velocity rows at the n states (X (n, 3N))."""
    C_f = model.n_position_rows
    out = np.empty((model.n_constraints - C_f, len(t)))
    for i, (x, ti) in enumerate(zip(X, t, strict=True)):
        A = ca.DM(model.velocity_terms(np.asarray(x, float).ravel(), float(ti))[0])[C_f:, :]
        out[:, i] = np.sqrt(np.asarray(ca.sum2(A * A), float).ravel())
    return out


def vanishing_rows(model, t, X, reference=None) -> list[dict]:
    """The velocity rows whose coefficient a_k = ∂c_k/∂v (nearly) vanishes at a sample:
    |a_k(x_i)| < VANISHING_RTOL · max(|a_k| over the samples and at ``reference`` (x, t)).
    [{"row": label, "t": the sample's time, "ratio": |a_k| there over that maximum}], the
    smallest ratio of each row; [] without velocity rows."""
    C_f, C = model.n_position_rows, model.n_constraints
    t = np.asarray(t, float).ravel()
    if C_f == C or t.size == 0:
        return []
    X = np.asarray(X, float).reshape(t.size, -1)
    keep = np.unique(np.linspace(0, t.size - 1, min(t.size, VANISHING_SAMPLES)).round().astype(int))
    norms = coefficient_norms(model, X[keep], t[keep])
    scale = norms.max(axis=1)
    if reference is not None:
        scale = np.maximum(scale, coefficient_norms(model, [reference[0]], [reference[1]])[:, 0])
    found = []
    for k in range(C - C_f):
        ratio = norms[k] / scale[k] if scale[k] > 0 else np.zeros(len(keep))
        i = int(np.argmin(ratio))
        if not ratio[i] >= VANISHING_RTOL:
            found.append({"row": model.constraint_labels[C_f + k], "t": float(t[keep[i]]),
                          "ratio": float(ratio[i])})
    return found


def describe_vanishing(found: list[dict]) -> str:
    """The sentence on ``vanishing_rows``' result (empty when none)."""
    if not found:
        return ""
    rows = "; ".join(f"'{f['row']}' at t = {f['t']:.6g} s (|∂c/∂v| down to {f['ratio']:.2g} of its largest)"
                     for f in found)
    return (f"velocity constraint(s) lose rank along the run: {rows}. There the row's coefficient "
            "a(x) = ∂c/∂v vanishes, so the row says nothing at that instant and its multiplier μ has "
            "a pole (μ ~ 1/|a|: the multipliers near it are huge, the constraint force Aᵀμ stays "
            "finite); write the constraint so that its coefficient does not vanish (divide the row "
            "by the factor that does), or read constraint_forces instead of multipliers there")
