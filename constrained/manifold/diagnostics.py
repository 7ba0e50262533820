"""Numerical diagnostics for hard cases: conditioning of the KKT solve along a run, rank drop
of the constraint Jacobian (singular configurations, named), incompatible constraint sets,
stiffness, and a scaled multiplier solve that stays accurate for extreme mass ratios.

Everything here reads a Model's public CasADi Functions (``jacobian``, ``dynamics``,
``constraint``) and a Trajectory; nothing changes the equations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .dense import schur_matrix
from .manifold import RANK, Manifold, dense_jacobian, sparse_jacobian

#: Smallest singular value of the row-normalized Jacobian below which a configuration counts as
#: singular: the rank policy's (constrained.manifold.RANK).
SINGULAR_SIGMA = RANK.singular_sigma
#: Above this many coordinates a singularity is found on the sparse J (``sparse_singularity``),
#: not by a dense SVD (the run's rank watch: the same limit).
DENSE_SVD_MAX = 300


def _jacobians(model, X: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Every row's gradient (J, then velocity rows' A) at each sample: (T, C, 3N)."""
    n = len(t)
    Jcat, _ = model.evaluate(model.velocity_terms, X.reshape(n, -1), t)
    return Jcat.reshape(model.n_constraints, n, model.n_coordinates).transpose(1, 0, 2)


# --- conditioning and singular configurations ---------------------------------------------------
@dataclass
class Conditioning:
    """Along a run: ``cond`` of J M⁻¹ Jᵀ (2-norm), ``cond_scaled`` of its Jacobi-scaled form,
    ``sigma_min`` the smallest singular value of the row-normalized J (0 at a singular
    configuration), and ``rank`` of J (relative cut-off ``SINGULAR_SIGMA``)."""

    t: np.ndarray
    cond: np.ndarray
    cond_scaled: np.ndarray
    sigma_min: np.ndarray
    rank: np.ndarray
    labels: list[str] = field(default_factory=list)

    @property
    def worst(self) -> int:
        """Index of the sample closest to a singular configuration."""
        return int(np.argmin(self.sigma_min))


def row_normalized(J: np.ndarray) -> np.ndarray:
    """J (C, 3N), or a stack of them (n, C, 3N), with every nonzero row of unit length."""
    norms = np.linalg.norm(J, axis=-1)
    return J / np.where(norms > 0, norms, 1.0)[..., None]


def conditioning(model, trajectory) -> Conditioning:
    """cond(J M⁻¹ Jᵀ)(t) and the distance to a singular configuration along ``trajectory``."""
    t = np.asarray(trajectory.t, float)
    n = len(t)
    if model.n_constraints == 0 or n == 0:
        z = np.ones(n)
        return Conditioning(t, z, z, z, np.zeros(n, int), [])
    J = _jacobians(model, trajectory.x, t)
    cond, cond_s, smin, rank = (np.empty(n) for _ in range(4))
    for k in range(n):
        A = schur_matrix(J[k], model.inverse_masses)
        sv = np.linalg.svd(A, compute_uv=False)
        cond[k] = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
        d = 1.0 / np.sqrt(np.maximum(np.diag(A), np.finfo(float).tiny))
        svs = np.linalg.svd(A * d[:, None] * d[None, :], compute_uv=False)
        cond_s[k] = svs[0] / svs[-1] if svs[-1] > 0 else np.inf
        svj = np.linalg.svd(row_normalized(J[k]), compute_uv=False)
        smin[k] = svj[-1] if svj.size >= J[k].shape[0] else 0.0
        rank[k] = int(np.sum(svj > SINGULAR_SIGMA * max(svj[0], 1e-300)))
    return Conditioning(t, cond, cond_s, smin, rank.astype(int), list(model.constraint_labels))


@dataclass
class Singularity:
    """The constraints that become dependent at one state: ``sigma`` the smallest singular value
    of the row-normalized J, ``rows`` the constraint indices in the dependency (largest weight
    first), ``labels`` their names, ``weights`` their share in it."""

    sigma: float
    rows: list[int]
    labels: list[str]
    weights: list[float]

    def describe(self) -> str:
        names = ", ".join(f"'{name}'" for name in self.labels)
        return (
            f"the constraints {names} are (nearly) dependent there (smallest singular value of the "
            f"row-normalized constraint Jacobian {self.sigma:.2g}): a toggle / dead-centre "
            "configuration, where the motion can branch or the drive asks for a motion the "
            "constraints cannot make"
        )


def _normalized_jacobian(model, x, t) -> np.ndarray:
    J = dense_jacobian(model)(np.asarray(x, float).ravel(), t)[0]  # (a FunctionBuffer call)
    return row_normalized(J.reshape(model.n_coordinates, model.n_constraints).T)


def numerical_rank(model, x, t: float = 0.0) -> int:
    """Rank of the row-normalized J at (x, t) (relative cut-off ``SINGULAR_SIGMA``)."""
    sv = np.linalg.svd(_normalized_jacobian(model, x, t), compute_uv=False)
    return int(np.sum(sv > SINGULAR_SIGMA * max(sv[0], 1e-300))) if sv.size else 0


def rank_sigma(model, x, t: float, rank: int) -> float:
    """The rank-th singular value of the row-normalized J at (x, t): it falls to 0 where the
    constraints lose rank (redundant rows beyond ``rank`` do not count)."""
    return float(rank_sigmas(_normalized_jacobian(model, x, t)[None], rank)[0])


def rank_sigmas(Jn: np.ndarray, rank: int) -> np.ndarray:
    """``rank_sigma`` of a stack of row-normalized J (n, C, 3N): many states at once (a batch's)."""
    sv = np.linalg.svd(Jn, compute_uv=False)
    return sv[:, rank - 1] if 0 < rank <= sv.shape[1] else np.zeros(len(Jn))


def singularity(model, x, t: float = 0.0, *, rank: int | None = None, ignore: float = 0.05,
                rows=None) -> Singularity:
    """The near-dependency of the constraint rows at (x, t): the left singular vector of the
    row-normalized J for its rank-th singular value (default: the smallest that rows and
    coordinates allow), rows with weight above ``ignore``. Beyond DENSE_SVD_MAX coordinates
    (a dense J of the 100 x 100 cloth is 4.8 GB): ``sparse_singularity`` of ``rows`` (default
    all), the smallest singular value of those rows, which is the rank-th of all rows when
    ``rows`` are the independent ones."""
    if model.n_coordinates > DENSE_SVD_MAX:
        chosen = list(range(model.n_constraints)) if rows is None else list(rows)
        return sparse_singularity(model, x, t, chosen, ignore=ignore)[0]
    return dependency(_normalized_jacobian(model, x, t), model.constraint_labels, rank=rank, ignore=ignore)


def dependency(Jn: np.ndarray, labels, *, rank: int | None = None, ignore: float = 0.05) -> Singularity:
    """``singularity`` from a row-normalized J (C, 3N) at hand (a batch's member's)."""
    U, sv, _ = np.linalg.svd(Jn, full_matrices=True)
    k = min(Jn.shape) if rank is None else rank
    if k > sv.size or k <= 0:
        sigma, u = 0.0, U[:, -1]
    else:
        sigma, u = float(sv[k - 1]), U[:, k - 1]
    w = u**2
    order = _leading(w, ignore)
    return Singularity(sigma, order, [labels[k] for k in order], [float(w[k]) for k in order])


def _leading(w: np.ndarray, ignore: float) -> list[int]:
    """Rows by their weight, those above ``ignore``; of a dependency spread thinly over many rows
    (none above it, as along a long chain), the three largest, so that rows are named."""
    order = [int(k) for k in np.argsort(-w)]
    return [k for k in order if w[k] > ignore] or order[:3]


def sparse_singularity(model, x, t: float, rows: list[int], *, start=None,
                       ignore: float = 0.05) -> tuple[Singularity, np.ndarray | None]:
    """(``Singularity`` of ``rows``, its vector): the smallest eigenvalue σ² of S = Ĵ Ĵᵀ (Ĵ the
    rows' J, each row normalized) and its eigenvector u, by inverse iteration on S's sparse
    LU — O(N) on a chain — from ``start`` (the vector of an earlier call, else random); σ = 0
    where a row's gradient vanishes or S is exactly singular (no direction to name)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    J = sparse_jacobian(model)(np.asarray(x, float).ravel(), t)  # (J, then velocity rows' A)
    r, c = J.sparsity().get_triplet()
    J = sp.csr_matrix((np.asarray(J.nonzeros()).ravel(), (r, c)), shape=J.shape)[rows]
    norms = np.sqrt(np.asarray(J.multiply(J).sum(axis=1)).ravel())
    u = np.zeros(len(rows))

    def described(sigma: float, u: np.ndarray) -> Singularity:
        w = u**2
        order = _leading(w, ignore)
        labels = model.constraint_labels
        return Singularity(sigma, [rows[k] for k in order], [labels[rows[k]] for k in order],
                           [float(w[k]) for k in order])
    if np.any(norms == 0):
        u[int(np.argmin(norms))] = 1.0
        return described(0.0, u), None
    Jn = sp.diags(1.0 / norms) @ J
    S = (Jn @ Jn.T).tocsc()
    try:
        lu = spla.splu(S)
    except RuntimeError:  # exactly singular
        return described(0.0, u), None
    y = start if start is not None and len(start) == S.shape[0] else \
        np.random.default_rng(0).standard_normal(S.shape[0])
    lam = np.inf
    for _ in range(20):  # inverse iteration: y → S⁻¹ y converges to σ_min²'s eigenvector
        y = y / np.linalg.norm(y)
        z = lu.solve(y)
        estimate = 1.0 / float(np.dot(y, z)) if np.dot(y, z) > 0 else 0.0
        converged = abs(estimate - lam) <= 1e-3 * abs(estimate)
        lam, y = estimate, z
        if converged:
            break
    y = y / np.linalg.norm(y)
    return described(float(np.sqrt(max(lam, 0.0))), y), y


# --- incompatible constraint sets -----------------------------------------------------------------
@dataclass
class Incompatibility:
    """The least-squares closest state to the constraints and what stays violated there.
    ``compatible`` is False when no state satisfies all constraints near the start: ``residual``
    is then the smallest max |f| found and ``labels`` the constraints still violated at that
    state (a set that cannot hold together)."""

    compatible: bool
    residual: float
    labels: list[str]
    violations: list[float]
    x: np.ndarray

    def describe(self) -> str:
        if self.compatible:
            return "the constraints are compatible"
        items = ", ".join(f"'{n}' ({v:+.3g})" for n, v in zip(self.labels, self.violations, strict=True))
        return (
            f"the constraints cannot all hold: at the closest state (least squares) these stay "
            f"violated: {items}; they contradict each other (lengths, triangle inequalities, anchors)"
        )


def incompatible_constraints(model, x0=None, t: float = 0.0, *, tol: float = 1e-8,
                             max_iter: int = 200) -> Incompatibility:
    """Minimize ½|f(x, t)|² from ``x0`` (Levenberg–Marquardt on the constraint rows) and name
    the constraints that stay violated at the minimum. ``tol`` is relative to the size of x."""
    x = np.asarray(model.system.positions if x0 is None else x0, float).ravel().copy()
    scale = max(float(np.max(np.abs(x), initial=0.0)), 1.0)
    mu = 1e-3
    f, J = (np.asarray(a) for a in model.jacobian(x, t))
    f = f.ravel()
    cost = 0.5 * float(f @ f)
    for _ in range(max_iter):
        if np.max(np.abs(f), initial=0.0) <= tol * scale:
            break
        g = J.T @ f
        H = J.T @ J
        step = np.linalg.solve(H + mu * (np.diag(np.diag(H)) + 1e-12 * np.eye(len(x))), -g)
        fn = np.asarray(model.constraint(x + step, t)).ravel()
        cn = 0.5 * float(fn @ fn)
        if np.isfinite(cn) and cn < cost:
            x, cost, mu = x + step, cn, max(mu / 3, 1e-12)
            f, J = (np.asarray(a) for a in model.jacobian(x, t))
            f = f.ravel()
            if np.linalg.norm(step) <= 1e-14 * scale:
                break
        else:
            mu *= 4
            if mu > 1e12:
                break
    res = float(np.max(np.abs(f), initial=0.0))
    compatible = res <= tol * scale
    bad = [] if compatible else [int(k) for k in np.argsort(-np.abs(f)) if abs(f[k]) > 1e-3 * res]
    labels = model.constraint_labels
    return Incompatibility(compatible, res, [labels[k] for k in bad], [float(f[k]) for k in bad], x)


def likely_cause(model, x, v, t: float, manifold: Manifold | None = None) -> str:
    """The likely cause of a stop at its last good state (x, v, t): a rank drop (``RANK.singular_cause``),
    rows dropped as redundant at the start and bent apart since, or a particle's blow-up."""
    try:
        manifold = manifold or Manifold.at(model, x, t)
        if model.n_constraints:
            n3, rows = model.n_coordinates, manifold.rows
            rank = model.n_constraints if rows is None else len(rows)
            sing = singularity(model, x, t, rank=min(rank, n3), rows=rows)
            if sing.sigma < RANK.singular_cause(rank):
                return f"likely cause: a singular configuration at t = {t:.6g} s: {sing.describe()}"
            full = rows is not None and singularity(model, x, t, rank=min(model.n_constraints, n3))
            # rows dependent at the start, bent apart since
            if full and full.sigma < RANK.singular_cause(model.n_constraints):
                return (f"likely cause: a taut, self-stressed set bent by the motion at t = {t:.6g} s "
                        f"(e.g. a straight edge pinned at both ends that the rest pulls sideways, which "
                        f"it allows only by stretching): {full.describe()}; give the set slack")
        strongest = _strongest_effect(model, model.symbols, np.asarray(x, float).ravel(),
                                      np.asarray(v, float).ravel(), t)
        if strongest is not None and strongest[3] > 1e100:  # one step of it overflows the state
            k, label, particle, size = strongest
            return (f"likely cause: effect {k} ('{label}') pushes particle '{particle}' with a force of "
                    f"{size:.3g} N at t = {t:.6g} s: a formula overflows there (e.g. exp of a large "
                    "number); check the formula, its units and its scale")
        a, lam = manifold.accelerations(x, v, t)
        fast = fast_across_constraints(model, x, v, t, a, lam)
        if fast:
            return fast
        acc = np.linalg.norm(np.asarray(a).reshape(-1, 3), axis=1)
        k = int(np.nanargmax(np.where(np.isfinite(acc), acc, np.inf)))
        if acc[k] == 0:  # (ggl at t = 0 on a 1,000-bead chain at rest: "forces that blow up … 0 m/s²")
            return ("likely cause: none found at the last good state: its constraints are regular and no "
                    "particle accelerates there (no force blows up); try another method or tolerance")
        name = model.particle_names[k]
        ordinary = _ordinary_acceleration(model, v)
        if acc[k] <= BLOW_UP * ordinary:  # (a chain under gravity: "forces that blow up … 9.81 m/s²")
            return (f"likely cause: none found at the last good state: its constraints are regular and no "
                    f"force is large there (the largest acceleration, particle '{name}''s {acc[k]:.3g} m/s², "
                    f"is of the order of gravity and of the motion's v²/size, {ordinary:.3g} m/s²); try "
                    "another method or tolerance")
        pos = ", ".join(f"{c:.4g}" for c in np.asarray(x).reshape(-1, 3)[k])
        pair = ""  # a pair potential pushing hardest: the two particles closing in on its singularity
        if strongest is not None and strongest[3] > 0 and hasattr(model.system.effects[strongest[0]],
                                                                  "closest_pair"):
            pair = (f"; the strongest force is effect {strongest[0]}'s ('{strongest[1]}')"
                    + _closest_pair(model, model.system.effects[strongest[0]], x))
        return (f"likely cause: forces that blow up: at the last good state particle '{name}' at "
                f"({pos}) m has acceleration {acc[k]:.3g} m/s²{pair}")
    except Exception:  # a diagnosis must never hide the stop itself
        return "likely cause: a singular configuration, stiffness, or forces that blow up"


#: A stop's largest acceleration counts as "forces that blow up" only above this many times
#: ``_ordinary_acceleration``.
BLOW_UP = 100.0


def _ordinary_acceleration(model, v) -> float:
    """What no blow-up exceeds: the largest uniform gravity (numbers) plus the largest v²/size of
    the state (a particle turning on a circle of the system's size)."""
    g = 0.0
    for effect in model.system.effects:
        if type(effect).__name__ == "Gravity":
            try:
                g = max(g, float(np.linalg.norm(np.asarray(effect.g, float))))
            except (TypeError, ValueError):  # (a formula of t or of the parameters)
                pass
    speed2 = float(np.max(np.sum(np.asarray(v, float).reshape(-1, 3) ** 2, axis=1), initial=0.0))
    return g + speed2 / max(model.system.size(), 1e-300)


#: A particle that swings across its constraints this many times faster than the state moves
#: (rates squared) is named as the likely cause of a stop (``fast_across_constraints``).
FAST_ACROSS = 1e6


def fast_across_constraints(model, x, v, t: float, a, lam) -> str | None:
    """The particle that oscillates fastest across its constraints, where that is much faster
    than the state moves. The constraint forces bend with the constraints: K = Σ_r λ_r ∂²f_r/∂x²
    acts as a stiffness, so particle i oscillates at ω_i² ≈ ‖K_ii‖ / m_i (a bead of mass m
    between two rods of length ℓ in tension T: 2 T / (m ℓ)). A 1 mg bead between two 1 t beads
    on 0.1 m rods: ω = 4.4e5 rad/s against a swing of 3 rad/s; every step has to follow it, and
    the stop was called "forces that blow up" at an acceleration of 0.49 m/s². Up to
    DENSE_SVD_MAX coordinates (a dense Hessian); None when no particle is that fast."""
    n3 = model.n_coordinates
    x, v, a = (np.asarray(z, float).ravel() for z in (x, v, a))
    if not model.n_constraints or n3 > DENSE_SVD_MAX:
        return None
    X = ca.MX.sym("x", n3)
    f = model.constraint(X, t)
    weights = np.asarray(lam, float).ravel()[:f.numel()]
    K = np.asarray(ca.Function("curvature", [X], [ca.hessian(ca.dot(ca.DM(weights), f), X)[0]])(x), float)
    masses = 1.0 / np.asarray(model.inverse_masses, float).reshape(-1, 3)[:, 0]
    blocks = [np.linalg.norm(K[3 * i:3 * i + 3, 3 * i:3 * i + 3], 2) for i in range(n3 // 3)]
    omega2 = np.asarray(blocks) / masses
    size = max(float(np.ptp(x.reshape(-1, 3), axis=0).max(initial=0.0)), 1e-3)
    motion2 = max(float(np.max(np.linalg.norm(a.reshape(-1, 3), axis=1))) / size
                  + float(np.max(np.linalg.norm(v.reshape(-1, 3), axis=1))) ** 2 / size ** 2, 1e-12)
    k = int(np.argmax(omega2))
    if not omega2[k] > FAST_ACROSS * motion2:
        return None
    omega = float(np.sqrt(omega2[k]))
    return (f"likely cause: particle '{model.particle_names[k]}' ({masses[k]:.3g} kg) oscillates across its "
            f"constraints at ω ≈ {omega:.3g} rad/s (period {2 * np.pi / omega:.3g} s) at t = {t:.6g} s, "
            f"{omega / np.sqrt(motion2):.3g} times faster than the motion: the constraint forces on it, "
            f"turning with the constraints, act as a spring of {blocks[k]:.3g} N/m on a mass "
            f"{np.max(masses) / masses[k]:.3g} times lighter than the heaviest, and every step has to "
            "follow it; take steps shorter than that period (dopri and projection do so by themselves; "
            "rattle: reduce dt), "
            "or give the particle a mass nearer its neighbours'")


# --- non-finite values ----------------------------------------------------------------------------
def nonfinite_cause(model, x, v, t: float) -> str:
    """The likely cause of non-finite values (energy, forces, multipliers) at the state (x, v, t):
    the effects whose term or force is not finite there, else the constraints, else
    ``likely_cause``. A diagnosis only: the equations are not changed."""
    s = model.symbols
    x = np.asarray(x, float).ravel()
    v = np.asarray(v, float).ravel()
    found = []
    try:
        mapped = _pair_values(model, x, t)
        pieces, bounds = [], [0]  # every effect's term and force (their nonzeros): one Function
        for k, effect in enumerate(model.system.effects):
            if k in mapped:  # a pair potential's mapped kernel (no term per pair to build)
                bounds.append(bounds[-1])
                continue
            term = effect.term(s)
            if isinstance(term, int | float):  # a constant formula (folded by the parser)
                term = ca.SX(term)
            wrt = {"potential": (s.x,), "generalized_potential": (s.x, s.v), "dissipation": (s.v,)}
            parts = [term, *(ca.gradient(term, z) for z in wrt.get(effect.slot, ()))]  # (a force: none)
            column = ca.vertcat(*[ca.vec(p) for p in parts])
            pieces += column.nonzeros()
            bounds.append(bounds[-1] + column.nnz())
        terms = ca.Function("terms", [s.x, s.v, s.t], [ca.vertcat(*pieces)]) if pieces else None
        everything = np.asarray(terms(x, v, t)).ravel() if pieces else np.zeros(0)
        for k, effect in enumerate(model.system.effects):
            values = (np.concatenate([[mapped[k][0]], mapped[k][1]]) if k in mapped
                      else everything[bounds[k]:bounds[k + 1]])
            if not np.all(np.isfinite(values)):
                what = {"potential": "potential energy or its force", "applied_force": "force",
                        "dissipation": "damping force", "generalized_potential": "generalized potential"}
                found.append(f"effect {k} ('{effect.label}') gives a non-finite "
                             f"{what.get(effect.slot, 'term')} ({values[0]:.3g})"
                             + _closest_pair(model, effect, x))
        if not found and model.n_constraints:  # (J's nonzeros: a dense J of a cloth is GBs)
            f, J = model.jacobian(x, t)
            bad = ~np.isfinite(np.asarray(f, float).ravel())
            r, _ = J.sparsity().get_triplet()
            bad[np.asarray(r, np.int64)[~np.isfinite(np.asarray(J.nonzeros(), float).ravel())]] = True
            rows = np.flatnonzero(bad)
            found += [f"constraint '{model.constraint_labels[r]}' is not finite (or its gradient)"
                      for r in rows[:3]]
        if not found:
            strongest = _strongest_effect(model, s, x, v, t)
            if strongest is not None:
                k, label, particle, size = strongest
                if size > 1e100:  # finite, but one step of it overflows the state
                    found.append(f"effect {k} ('{label}') pushes particle '{particle}' with a force "
                                 f"of {size:.3g} N")
    except Exception:  # a diagnosis must never hide the stop itself
        found = []
    if not found:
        return likely_cause(model, x, v, t)
    return (f"likely cause: {'; '.join(found)} at the state reached at t = {t:.6g} s: a formula "
            "overflows there (beyond ~1.8e308, e.g. exp of a large number) or divides by zero; "
            "check the formula, its units and its scale")


def _closest_pair(model, effect, x) -> str:
    """For a pair potential (``pairwise``): "; closest pair: particles 'a' and 'b', d m apart"
    (where φ(r) is most likely singular); else ""."""
    closest = effect.closest_pair(model.system, x) if hasattr(effect, "closest_pair") else None
    if closest is None:
        return ""
    a, b, d = closest
    return f"; closest pair: particles '{a}' and '{b}', {d:.3g} m apart"


def _pair_values(model, x, t) -> dict:
    """effect index -> (V, F) of the model's pair potentials built as mapped kernels."""
    structure = model.structure
    if not getattr(structure, "pairs", ()):
        return {}
    values = structure.pair_potentials.values(x, t, model.parameter_vector)
    return dict(zip(structure.pair_owner, values, strict=True))


def _strongest_effect(model, s, x, v, t):
    """(index, label, particle, |F|) of the effect with the largest force on one particle (the
    first effect, then particle, of equal ones). Every effect's force is one column of one
    Function's sparse output (−∂V/∂x of potential terms, −∂R/∂v of dissipation, applied
    forces): O(N + effects), where a Function per effect took minutes on a cloth's springs."""
    import casadi as ca

    n = model.n_particles
    found = []  # (effect, particle, |F|)
    mapped = _pair_values(model, x, t)
    columns, owners = {"potential": [], "dissipation": [], "applied_force": []}, {}
    for k, effect in enumerate(model.system.effects):
        if k in mapped:
            F = mapped[k][1].reshape(-1, 3)
            big = np.max(np.abs(F), axis=1, keepdims=True)
            norms = big.ravel() * np.linalg.norm(F / np.where(big > 0, big, 1.0), axis=1)
            i = int(np.argmax(norms))
            found.append((k, i, float(norms[i])))
            continue
        term = effect.term(s)
        if isinstance(term, int | float) or effect.slot not in columns:
            continue
        columns[effect.slot].append(term)
        owners.setdefault(effect.slot, []).append(k)
    outputs, slots = [], []
    for slot, terms in columns.items():
        if not terms:
            continue
        if slot == "applied_force":
            outputs.append(ca.horzcat(*terms).T)  # (effects, 3N)
        else:
            outputs.append(-ca.jacobian(ca.vertcat(*terms), s.x if slot == "potential" else s.v))
        slots.append(slot)
    if outputs:
        values = ca.Function("forces", [s.x, s.v, s.t], outputs)(x, v, t)
        values = values if isinstance(values, list | tuple) else [values]
        for slot, F in zip(slots, values, strict=True):
            rows, cols = (np.asarray(a, np.int64) for a in F.sparsity().get_triplet())
            data = np.abs(np.asarray(F.nonzeros(), float).ravel())
            pairs, at = np.unique(rows * n + cols // 3, return_inverse=True)  # (effect row, particle)
            big = np.zeros(len(pairs))
            with np.errstate(invalid="ignore"):  # (a NaN force: its effect is not the strongest)
                np.maximum.at(big, at, data)  # scaled: |F| itself may be near overflow
                sums = np.zeros_like(big)
                np.add.at(sums, at, (data / np.where(big[at] > 0, big[at], 1.0)) ** 2)
                norms = np.nan_to_num(big * np.sqrt(sums), nan=-1.0)
            top = np.flatnonzero(norms == norms.max()) if len(norms) else []
            found += [(owners[slot][int(pairs[q] // n)], int(pairs[q] % n), float(norms[q])) for q in top]
    if not found:
        return None
    k, i, size = max(found, key=lambda f: (f[2], -f[0], -f[1]))
    return k, model.system.effects[k].label, model.system.particles[i].name, size
