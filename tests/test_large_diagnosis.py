"""The diagnosis of a stopped run on a large model (issue 28, found on a 100 x 100 cloth whose
RATTLE run stopped at 0.29 s): it must not build a dense J (4.8 GB there) nor one CasADi
Function per effect (its 19,602 springs: minutes), and it must name what the per-effect route
named — the strongest effect, the non-finite one, the singular rows."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import test_vectorized as tv

import constrained as C
from constrained.manifold import diagnostics
from constrained.manifold.manifold import Manifold
from constrained.model.structure import assemble


def _sheet(k: int = 12, *, wild: str = "0") -> C.System:
    """A cloth of k x k with shear springs, damping on some particles and an applied force
    (``wild``: its x component) on one: every kind of effect, one per spring."""
    s = tv.cloth(k)
    for i in range(k - 1):
        for j in range(k - 1):
            s.add(C.Spring(f"q{i}_{j}", f"q{i + 1}_{j + 1}", k=0.5 + 0.01 * (i + j), rest=0.014))
    s.add(C.Damping(0.003, [f"q{i}_{i}" for i in range(k)]),
          C.Force(f"q{k // 2}_{k // 3}", [wild, "0.01*t", "-0.002"]))
    return s


def _state(model, system):
    rng = np.random.default_rng(3)
    x = np.asarray(system.positions, float).ravel() + 2e-3 * rng.standard_normal(model.n_coordinates)
    return x, rng.standard_normal(model.n_coordinates), 0.4


def _per_effect(model, x, v, t):
    """The strongest effect found one Function per effect (the route this replaced)."""
    s, best = model.symbols, None
    for k, effect in enumerate(model.system.effects):
        term = effect.term(s)
        if isinstance(term, int | float):
            continue
        if effect.slot == "applied_force":
            force = term
        else:
            force = -ca.gradient(term, s.x if effect.slot == "potential" else s.v)
        F = np.asarray(ca.Function("f", [s.x, s.v, s.t], [force])(x, v, t), float).reshape(-1, 3)
        big = np.max(np.abs(F), axis=1, keepdims=True)  # (scaled: |F| may overflow)
        norms = big.ravel() * np.linalg.norm(F / np.where(big > 0, big, 1.0), axis=1)
        i = int(np.argmax(norms))
        if best is None or norms[i] > best[3]:
            best = (k, effect.label, model.system.particles[i].name, float(norms[i]))
    return best


class _Counted:
    """ca.Function, counted."""

    def __init__(self):
        self.calls, self.original = 0, ca.Function

    def __call__(self, *a, **k):
        self.calls += 1
        return self.original(*a, **k)


@pytest.mark.parametrize("wild", ["0", "3*x_q1_1", "exp(500*(1 + t))"])
def test_the_strongest_effect_is_the_per_effect_answer_from_one_function(wild, monkeypatch):
    system = _sheet(wild=wild)
    model = assemble(system, reuse=False)
    x, v, t = _state(model, system)
    expected = _per_effect(model, x, v, t)
    counted = _Counted()
    monkeypatch.setattr(ca, "Function", counted)
    found = diagnostics._strongest_effect(model, model.symbols, x, v, t)
    assert counted.calls == 1
    assert found[:3] == expected[:3]
    assert found[3] == pytest.approx(expected[3], rel=1e-12)
    if wild.startswith("exp"):
        assert found[1].startswith("force on")


def test_a_non_finite_effect_is_named_from_one_function(monkeypatch):
    system = _sheet(wild="log(x_q0_0 - 5)")
    model = assemble(system, reuse=False)
    x, v, t = _state(model, system)
    counted = _Counted()
    monkeypatch.setattr(ca, "Function", counted)
    message = diagnostics.nonfinite_cause(model, x, v, t)
    assert counted.calls == 1
    assert "force on q6_4" in message and "non-finite force" in message


def test_a_large_models_diagnosis_takes_j_sparse(monkeypatch):
    """Above DENSE_SVD_MAX coordinates no dense J is built; the sparse route's σ and rows are
    the dense SVD's where both apply (a small cloth)."""
    small = tv.cloth(3)
    small_model = assemble(small, reuse=False)
    xs = np.asarray(small.positions, float).ravel()
    dense = diagnostics.singularity(small_model, xs, 0.0)
    sparse, _ = diagnostics.sparse_singularity(small_model, xs, 0.0, list(range(small_model.n_constraints)))
    assert sparse.sigma == pytest.approx(dense.sigma, rel=5e-3)  # (inverse iteration to 1e-3 in σ²)
    assert dense.labels[0] in sparse.labels  # (near-equal σ: the vectors may mix; the leading row is named)

    system = _sheet(14)
    model = assemble(system, reuse=False)
    assert model.n_coordinates > diagnostics.DENSE_SVD_MAX
    monkeypatch.setattr(diagnostics, "dense_jacobian", lambda *a: pytest.fail("a dense J was built"))
    x, v, t = _state(model, system)
    message = diagnostics.likely_cause(model, x, 1e-3 * v, t, Manifold.at(model, x, t))
    assert message.startswith("likely cause:")
    assert 0 < diagnostics.singularity(model, x, t).sigma < 1


def test_the_singular_watch_does_not_stop_a_long_straight_chain(monkeypatch):
    """A straight chain of R rods at rest is regular, yet its smallest σ (the row-normalized J's)
    is ≈ 1.1/R, its longest mode: at 12,000 rods 9.3e-5, under the default singular_tol 1e-4,
    and such a chain was stopped at its first check as "a singular configuration". The watch's
    threshold scales as 1/R beyond 100 rows (``RankPolicy.singular_watch``). Here 1,000 rods with
    singular_tol = 2e-3, above their σ: the run goes to its end, the chain where it was."""
    n = 1000
    s = C.System(name="straight chain")
    for i in range(n):
        s.add_particle(f"p{i}", 0.01, [0.01 * (i + 1), 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.01))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=0.01))
    model = assemble(s)
    x0 = np.asarray(s.positions, float).ravel()
    sigma = diagnostics.sparse_singularity(model, x0, 0.0, list(range(n)))[0].sigma
    assert 1.0 / n < sigma < 1.2 / n < 2e-3  # (the old rule, σ < tol, stopped it)
    assert diagnostics.RANK.singular_watch(2e-3, n) < sigma / 5
    from constrained.solvers import watches

    monkeypatch.setattr(watches, "FIRST_CHECK_S", 0.0)  # (checked from the first step on)
    traj = C.simulate(s, 0.05, method="dopri", singular_tol=2e-3, t_eval=np.linspace(0.0, 0.05, 11))
    np.testing.assert_allclose(traj.x[-1], traj.x[0], atol=1e-12)
    assert traj.info.get("status", "completed") == "completed"


def test_a_stop_under_gravity_alone_is_not_put_down_to_forces_that_blow_up():
    """Old: a stop at a state where nothing is large (a 150-bead chain of 1 cm links released
    horizontal: every bead accelerates at g) read "likely cause: forces that blow up: … particle
    'p0' … has acceleration 9.81 m/s²". An acceleration of the order of gravity and of the
    motion's v²/size is now said to be ordinary; a bob falling into a 1/r potential (a real
    blow-up, far above both) is still named."""
    n, g = 150, 9.81
    s = C.System(name="rope")
    for i in range(n):
        s.add_particle(f"p{i}", 0.01, [(i + 1) * 0.01, 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.01))
    for i in range(n - 1):
        s.add(C.Distance(f"p{i}", f"p{i + 1}", length=0.01))
    s.add(C.Gravity([0, -g, 0]))
    model = assemble(s)
    x = np.asarray(s.positions, float).ravel()
    message = diagnostics.likely_cause(model, x, 0 * x, 0.0)
    assert "blow up" not in message and message.startswith("likely cause: none found")
    assert "of the order of gravity" in message and "9.81 m/s²" in message
    fall = C.System([C.Particle("p", 1.0, [1.0, 0.0, 0.0])], [],  # (released at 1 m: its size)
                    [C.Potential("-1/sqrt(x_p**2 + y_p**2 + z_p**2)")])
    x = np.array([1e-4, 0.0, 0.0])  # the last good state near r = 0: a = 1/r² = 1e8 m/s², v = √(2/r)
    message = diagnostics.likely_cause(assemble(fall), x, np.array([-141.4, 0.0, 0.0]), 0.0)
    assert "likely cause: forces that blow up" in message and "particle 'p'" in message
