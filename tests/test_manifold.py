"""The one KKT/Schur solve and projection policy (constrained.manifold), used by every method.

Closed forms: a 1e6 kg bob hanging on two identical rods with a 1e-6 kg bob on a string below
it, at rest. Each rod carries half of (m_heavy + m_light) g, the string m_light g — twelve
orders of magnitude apart, with two rows that are exactly dependent.
"""

import threading

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.manifold.dense import independent_rows, schur_solve
from constrained.manifold.manifold import RANK, Manifold, ProjectionStatus, redundant_rows

G = 9.81
M_HEAVY, M_LIGHT = 1e6, 1e-6
ROD = (M_HEAVY + M_LIGHT) * G / 2  # each of two identical rods
STRING = M_LIGHT * G

SCENE = f"""
[scene]
name = "heavy bob on two rods, light bob on a string"

[[particles]]
name = "heavy"
mass = {M_HEAVY}
position = [0.0, -1.0, 0.0]

[[particles]]
name = "light"
mass = {M_LIGHT}
position = [0.0, -2.0, 0.0]

[[constraints]]
name = "rod1"
type = "distance"
a = "heavy"
point = [0.0, 0.0, 0.0]
length = 1.0

[[constraints]]
name = "rod2"
type = "distance"
a = "heavy"
point = [0.0, 0.0, 0.0]
length = 1.0

[[constraints]]
name = "string"
type = "distance"
a = "heavy"
b = "light"
length = 1.0

[[effects]]
type = "gravity"
g = [0.0, -{G}, 0.0]

[simulate]
t_end = 0.5

[outputs]
quantities = ["multipliers", "constraint_forces", "constraint_residual"]
plots = []
"""

METHODS = {"projection": [], "dopri": [], "baumgarte": [], "idas": [], "ggl": [], "pantelides": [],
           "rattle": ["--set", "simulate.dt=0.001"], "rodas": []}


def mass_ratio_system() -> C.System:
    s = C.System(name="mass ratio")
    s.add_particle("heavy", M_HEAVY, [0, -1.0, 0])
    s.add_particle("light", M_LIGHT, [0, -2.0, 0])
    s.add(C.Distance("heavy", point=[0, 0, 0], length=1.0), C.Distance("heavy", point=[0, 0, 0], length=1.0),
          C.Distance("heavy", "light", length=1.0), C.Gravity([0, -G, 0]))
    return s


def test_the_solve_splits_identical_rows_and_keeps_the_light_one():
    s = mass_ratio_system()
    model = C.assemble(s)
    x = s.positions.ravel()
    F, J, gamma = (np.asarray(o, float) for o in model.dynamics(x, np.zeros(6), 0.0))
    b = -gamma.ravel() - J @ (model.inverse_masses * F.ravel())
    lam = schur_solve(J, model.inverse_masses, b)
    np.testing.assert_allclose(-lam, [ROD, ROD, STRING], rtol=1e-12)
    # the dependency is found in the mass-weighted rows, whatever the mass spread
    assert independent_rows(J, model.inverse_masses).tolist() == [0, 2]
    assert redundant_rows(model, x, 0.0) == (0, 2)
    # a matrix right-hand side solves column by column
    both = schur_solve(J, model.inverse_masses, np.column_stack([b, 2 * b]))
    np.testing.assert_allclose(both[:, 1], 2 * lam, rtol=1e-12)


@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_runs_the_mass_ratio_scene_with_the_right_forces(method, tmp_path):
    scene = tmp_path / "mass_ratio.toml"
    scene.write_text(SCENE)
    out = tmp_path / "out"
    code = main(["run", str(scene), "--out", str(out), "--quiet", "--set", f"simulate.method={method}",
                 *METHODS[method]])
    assert code == 0
    data = np.load(out / "trajectory.npz")
    assert data["t"][-1] == pytest.approx(0.5)
    lam = data["multipliers"]
    np.testing.assert_allclose(-lam[:, 0], ROD, rtol=1e-6)
    np.testing.assert_allclose(-lam[:, 1], ROD, rtol=1e-6)
    np.testing.assert_allclose(-lam[:, 2], STRING, rtol=1e-6)
    # the net force on the light bob is the string's: m_light g upward
    np.testing.assert_allclose(data["constraint_forces"][:, 1, 1], STRING, rtol=1e-6)
    # at rest it stays at rest
    assert np.max(np.abs(data["x"] - data["x"][0])) < 1e-9


def test_statics_of_the_mass_ratio_scene():
    eq = C.equilibrium(mass_ratio_system())
    np.testing.assert_allclose(-eq.multipliers, [ROD, ROD, STRING], rtol=1e-9)
    # both bobs swing with ω² = g / L about this equilibrium: a stable one, not "soft modes"
    assert eq.stable is True
    np.testing.assert_allclose(np.sort(eq.frequencies_squared), [G, G, G, G], rtol=1e-4)


def test_projection_result_is_typed_and_reports_its_iterations():
    s = mass_ratio_system()
    model = C.assemble(s)
    manifold = Manifold.at(model, s.positions, 0.0)
    assert manifold.redundant and manifold.rows == (0, 2)
    off = s.positions.ravel() + np.array([1e-3, 0, 0, 0, 2e-3, 0])
    result = manifold.project_positions(off, 0.0, tol=1e-14)
    assert result.status is ProjectionStatus.CONVERGED and result.converged
    assert 1 <= result.iterations <= 8 and result.residual <= 1e-14
    f = np.asarray(model.constraint(result.x, 0.0)).ravel()
    assert np.max(np.abs(f)) <= 1e-14
    # one Jacobian (and factorization) per Newton step; after each step f alone is checked
    assert manifold.counters.njev == result.iterations and manifold.counters.nfev == result.iterations
    # an incompatible pair of lengths cannot be reached: Newton stalls, and says so
    bad = C.System()
    bad.add_particle("p", 1.0, [1.0, 0, 0])
    bad.add(C.Distance("p", point=[0, 0, 0], length=1.0), C.Distance("p", point=[0, 0, 0], length=1.5))
    stuck = Manifold(C.assemble(bad)).project_positions(np.array([1.0, 0, 0]), 0.0, tol=1e-12)
    assert not stuck.converged and stuck.status in (ProjectionStatus.STALLED, ProjectionStatus.MAX_ITERATIONS)
    assert stuck.residual > 0.1


def test_one_model_serves_two_threads_with_identical_results():
    from test_solvers import double_pendulum

    system = double_pendulum()
    model = C.assemble(system)
    t = np.linspace(0, 1, 11)
    alone = {m: C.simulate(system, 1.0, method=m, model=model, t_eval=t, compiled=False)
             for m in ("projection", "dopri")}
    results = {}

    def run(method):
        results[method] = C.simulate(system, 1.0, method=method, model=model, t_eval=t, compiled=False)

    threads = [threading.Thread(target=run, args=(m,)) for m in ("projection", "dopri")]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for m, tr in alone.items():
        assert np.array_equal(results[m].x, tr.x) and np.array_equal(results[m].v, tr.v)
        # counters belong to the run: the same work counted the same way each time
        for key in ("nfev", "njev", "nlu", "projections", "steps"):
            assert results[m].stats[key] == tr.stats[key], key
    assert not hasattr(model, "counters") and not hasattr(model, "redundant")


def test_the_rank_policy_is_one_set_of_thresholds():
    assert RANK.dependent_rtol < RANK.cholesky_rtol
    from constrained.manifold import constraint_report as analysis
    from constrained.manifold import diagnostics

    assert analysis.RANK_TOL == RANK.dependent_rtol
    assert diagnostics.SINGULAR_SIGMA == RANK.singular_sigma
