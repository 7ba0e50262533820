"""Issue 16 (scale): the sparse routes of the report, the start and post-processing give what
the dense routes give, and the closed forms at large N.

Correctness only; the timings are benchmarks/big_chain.py's (docs/performance.md).
"""

import itertools

import casadi as ca
import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.manifold import algebra
from constrained.manifold import constraint_report as analysis
from constrained.manifold.algebra import DENSE, SPARSE
from constrained.manifold.dense import schur_solve
from constrained.manifold.graph import row_scales_expr
from constrained.manifold.sparse_rank import independent_rows_sparse
from constrained.manifold.sparse_rows import row_max
from constrained.model.regularity import undefined_items
from constrained.run import quantities
from constrained.run.start import consistent_start
from constrained.solvers.dopri import CHUNK_COORDINATE_ATTEMPTS, CHUNKS, Dopri


def planar_chain(n: int, *, bend: float = 0.5, duplicates=(), masses=None) -> C.System:
    """N unit links from the origin, bent by ``bend`` from the vertical, in the plane z = 0;
    ``duplicates``: links k (between p{k-1} and p{k}) held by a second, redundant rod."""
    s = C.System(name=f"{n}-link chain")
    for i in range(n):
        mass = 1.0 if masses is None else masses[i]
        s.add_particle(f"p{i}", mass, [(i + 1) * np.sin(bend), -(i + 1) * np.cos(bend), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=1.0))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=1.0))
    for k in duplicates:
        s.add(C.Distance(f"p{k - 1}", f"p{k}", length=1.0, name=f"duplicate rod {k}"))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    return s


def chain_and_cube(n: int = 50) -> C.System:
    """A chain with three duplicated rods and, beside it, a cube with all 28 rods (10 of them
    implied by the others): 131 rows (beyond SPARSE_FROM), 13 redundant; masses spread."""
    rng = np.random.default_rng(3)
    s = planar_chain(n, duplicates=(5, 20, 41), masses=rng.uniform(0.5, 5.0, n))
    corners = np.array(list(itertools.product([-0.5, 0.5], repeat=3))) + [10.0, 0.0, 0.0]
    for i, p in enumerate(corners):
        s.add_particle(f"c{i}", 1.0 + i, p)
    for i, j in itertools.combinations(range(8), 2):
        s.add(C.Distance(f"c{i}", f"c{j}", length=float(np.linalg.norm(corners[i] - corners[j]))))
    return s


# --- the report: DOF, rank, redundancy --------------------------------------------------------
@pytest.fixture
def no_dense_rank(monkeypatch):
    """Fail if the dense rank-revealing QR (C × 3N) is used."""
    def refuse(*args, **kwargs):
        raise AssertionError("the dense pivoted QR was used")

    monkeypatch.setattr(analysis, "_dense_report", refuse)
    monkeypatch.setattr(analysis, "jacobian_rank", refuse)


@pytest.mark.parametrize("duplicates", [(), (700,), (3, 1500, 1999)])
def test_planar_chain_report_closed_form_at_large_n(no_dense_rank, duplicates):
    """A planar N-link chain (N rods + N plane rows) has rank 2N and N degrees of freedom,
    whatever redundant rods are added; each added rod is reported redundant (or its twin)."""
    n = 2000
    system = planar_chain(n, duplicates=duplicates)
    report = C.constraint_report(system)
    assert report.n_constraints == 2 * n + len(duplicates)
    assert report.rank == report.generic_rank == 2 * n
    assert report.degrees_of_freedom == n and not report.singular
    assert len(report.redundant) == len(duplicates)
    # of two equal rods the one later in the scene is named, as the dense pivoted QR names it
    assert report.redundant == [f"duplicate rod {k}" for k in duplicates]


def test_sparse_report_equals_dense_report(monkeypatch):
    system = chain_and_cube()
    sparse = C.constraint_report(system)
    monkeypatch.setattr(algebra, "SPARSE_FROM", 10**9)
    dense = C.constraint_report(system)
    assert sparse.n_constraints == dense.n_constraints == 131
    assert (sparse.rank, sparse.generic_rank, len(sparse.redundant)) == (dense.rank, dense.generic_rank, 13)
    assert sparse.degrees_of_freedom == dense.degrees_of_freedom == 3 * 58 - 118
    assert sparse.redundant[:3] == dense.redundant[:3] == [f"duplicate rod {k}" for k in (5, 20, 41)]
    # the cube's: the latest in scene order of each dependent set (the dense QR's pivoting
    # picks others); either way the rows kept are independent and span all the rows
    model = C.assemble(system)
    J = np.asarray(model.jacobian(system.positions.ravel(), 0.0)[1])
    kept = [i for i, label in enumerate(sparse.labels) if label not in sparse.redundant]
    assert np.linalg.matrix_rank(J[kept]) == len(kept) == sparse.rank


def test_sparse_independent_rows_match_the_pivoted_qr():
    system = chain_and_cube()
    model = C.assemble(system)
    rng = np.random.default_rng(5)
    for x in (system.positions.ravel(), system.positions.ravel() + 0.05 * rng.standard_normal(3 * 58)):
        J = model.jacobian(x, 0.0)[1]
        dense = DENSE.independent_rows(np.asarray(J), model.inverse_masses)
        sparse = SPARSE.independent_rows(J, model.inverse_masses)
        assert sparse.size == dense.size
        assert np.linalg.matrix_rank(np.asarray(J)[sparse]) == sparse.size
        assert independent_rows_sparse(J).size == analysis.jacobian_rank(np.asarray(J))[0]


def test_sparse_minimum_norm_solve_equals_the_svd():
    system = chain_and_cube()
    model = C.assemble(system)
    rng = np.random.default_rng(8)
    x = system.positions.ravel()
    v = rng.standard_normal(x.size)  # off the velocity constraints: b is not consistent
    F, J, gamma = (np.asarray(o, float) for o in model.dynamics(x, v, 0.0))
    b = -gamma.ravel() - J @ (model.inverse_masses * F.ravel())
    B = np.stack([b, rng.standard_normal(b.size)], axis=1)
    for rhs in (b, B):
        dense = schur_solve(J, model.inverse_masses, rhs, full_rank=False)
        sparse = SPARSE.schur_solve(model.jacobian(x, 0.0)[1], model.inverse_masses, rhs)
        assert np.max(np.abs(sparse - dense)) <= 1e-11 * np.max(np.abs(dense))


# --- post-processing: no dense (samples × rows × coordinates) arrays ----------------------------
def test_multipliers_and_forces_of_the_sparse_path_equal_the_dense_path(monkeypatch):
    """Redundant rows: beyond SPARSE_FROM rows the multipliers are solved sample by sample on
    the sparse J; they equal the dense blocks' minimum-norm ones (duplicated rods share the
    load equally), and the constraint forces Jᵀλ equal the dense product."""
    system = chain_and_cube()
    tr = C.simulate(system, 0.05, rtol=1e-8, outputs=set(), t_eval=np.linspace(0, 0.05, 4))
    model = C.assemble(system)
    X, V, t = tr.x.reshape(len(tr.t), -1), tr.v.reshape(len(tr.t), -1), tr.t
    sparse = quantities.multipliers_along(model, X, V, t)
    forces = quantities.constraint_forces_along(model, X, t, sparse)
    monkeypatch.setattr(algebra, "SPARSE_FROM", 10**9)
    dense = quantities.multipliers_along(model, X, V, t)
    assert np.all(np.isfinite(sparse))
    assert np.max(np.abs(sparse - dense)) <= 1e-10 * np.max(np.abs(dense))
    labels = model.constraint_labels
    assert np.allclose(sparse[:, labels.index("duplicate rod 20")], sparse[:, 20], rtol=1e-9)
    J = model.evaluate(model.jacobian, X, t)[1].reshape(model.n_constraints, len(t), -1).transpose(1, 0, 2)
    expected = np.einsum("kci,kc->ki", J, sparse).reshape(forces.shape)
    assert np.max(np.abs(forces - expected)) <= 1e-12 * np.max(np.abs(expected))


def test_full_rank_multipliers_at_large_n_satisfy_the_dynamics():
    n = 1500
    system = planar_chain(n)
    model = C.assemble(system)
    x, v = system.positions.ravel(), np.zeros(3 * n)
    lam = quantities.multipliers_along(model, x[None], v[None], np.zeros(1))[0]
    F, J, gamma = model.dynamics(x, v, 0.0)
    J = SPARSE.matrix(J)
    a = model.inverse_masses * (np.asarray(F).ravel() + J.T @ lam)
    assert np.max(np.abs(J @ a + np.asarray(gamma).ravel())) <= 1e-9 * 9.81 * n


# --- the pieces that were O(N²) -------------------------------------------------------------
@pytest.mark.parametrize("kind", [ca.SX, ca.MX])
def test_row_scales_equal_the_per_particle_loop(kind):
    """The O(nnz) row maximum gives, bit for bit, max over particles of |∂f_i/∂x_p|."""
    rng = np.random.default_rng(2)
    for _ in range(30):
        rows, n = int(rng.integers(1, 12)), int(rng.integers(1, 9))
        M = rng.standard_normal((rows, 3 * n)) * (rng.random((rows, 3 * n)) < 0.3)
        M[0] = 0.0  # a row with no stored entry
        pattern = ca.DM(M).sparsity()
        J = kind.sym("J", pattern)
        scales = ca.Function("s", [J], [row_scales_expr(J, n)])
        got = np.asarray(scales(ca.DM(pattern, ca.DM(M).nonzeros()))).ravel()
        norms = np.sqrt((M.reshape(rows, n, 3) ** 2).sum(axis=2)).max(axis=1)
        assert np.array_equal(got, np.where(norms > 0, norms, 1.0))


def test_row_max_of_a_dense_row_and_empty_rows():
    Q = ca.DM([[0, 0, 0, 0], [3, -1, 7, 2], [0, 5, 0, 0]])
    Q = ca.sparsify(Q)
    assert np.asarray(row_max(Q)).ravel().tolist() == [0.0, 7.0, 5.0]


def test_undefined_items_found_in_one_evaluation():
    s = C.System()
    for name, p in (("a", [1, 0, 0]), ("b", [2, 0, 0]), ("c", [2, 0, 0])):
        s.add_particle(name, 1.0, p)
    s.add(C.Distance("a", point=[0, 0, 0], length=1.0), C.Distance("b", "c", length=1.0),
          C.Distance("a", point=[1, 0, 0], length=1.0), C.Gravity([0, -9.81, 0]))
    found = [(section, i) for section, i, _ in undefined_items(s, 0.0)]
    assert found == [("constraints", 1), ("constraints", 2)]


def test_particle_names_stay_unique():
    s = C.System()
    for i in range(5):
        s.add_particle(f"p{i}", 1.0, [i, 0, 0])
    with pytest.raises(C.InputError, match="duplicate particle name 'p3'"):
        s.add_particle("p3", 1.0, [0, 0, 0])
    copy = s.copy()
    copy.particles.pop()
    copy.add_particle("p4", 1.0, [0, 0, 0])  # freed in the copy
    with pytest.raises(C.InputError, match="duplicate particle name 'p4'"):
        s.add_particle("p4", 1.0, [0, 0, 0])


def test_evaluate_through_the_buffer_equals_the_mapped_call():
    system = planar_chain(4)
    model = C.assemble(system)
    rng = np.random.default_rng(1)
    X, V, t = rng.standard_normal((5, 12)), rng.standard_normal((5, 12)), rng.random(5)
    for function, args in ((model.energy, (X, V, t)), (model.dynamics, (X, V, t)),
                           (model.jacobian, (X, t)), (model.constraint, (X, t))):
        mapped = function.map(5)(*[np.asarray(a, float).reshape(5, -1).T for a in args])
        mapped = mapped if isinstance(mapped, tuple) else (mapped,)
        for got, want in zip(model.evaluate(function, *args), mapped, strict=True):
            assert np.array_equal(got, np.asarray(want))


def test_dopri_builds_only_the_chains_of_attempts_that_fit():
    system = planar_chain(1500)  # 4,500 coordinates: chains of 8, not of 64
    start = consistent_start(C.assemble(system), system.positions, system.velocities)
    solver = Dopri(start.manifold, rtol=1e-6, atol=1e-8)
    assert set(solver._chunks) == {k for k in CHUNKS if k * 4500 <= CHUNK_COORDINATE_ATTEMPTS} | {1} == {1, 8}


def test_constrained_run_of_a_big_chain_reports_closed_form_dof(tmp_path, capsys):
    """The whole command on a 2,000-link chain released horizontal (plus one duplicated rod):
    the report gives N degrees of freedom; the arrays are finite."""
    n = 2000
    lines = ["[scene]", 'name = "big chain"']
    for i in range(n):
        lines += ["[[particles]]", f'name = "p{i}"', "mass = 1.0", f"position = [{i + 1}.0, 0.0, 0.0]"]
    lines += ["[[constraints]]", 'type = "distance"', 'a = "p0"', "point = [0.0, 0.0, 0.0]", "length = 1.0"]
    for i in range(1, n):
        lines += ["[[constraints]]", 'type = "distance"', f'a = "p{i - 1}"', f'b = "p{i}"', "length = 1.0"]
    lines += ["[[constraints]]", 'type = "distance"', 'a = "p9"', 'b = "p10"', "length = 1.0"]
    lines += ["[[constraints]]", 'type = "plane"', "particles = [" + ", ".join(f'"p{i}"' for i in range(n))
              + "]", "normal = [0.0, 0.0, 1.0]"]
    lines += ["[[effects]]", 'type = "gravity"', "g = [0.0, -9.81, 0.0]"]
    lines += ["[simulate]", "t_end = 0.02", "rtol = 1e-6", "atol = 1e-8", "[outputs]", "plots = []"]
    scene = tmp_path / "chain.toml"
    scene.write_text("\n".join(lines) + "\n")
    assert main(["run", str(scene), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert f"particles {n}, constraint rows {2 * n + 1}, degrees of freedom {n}" in out
    with np.load(tmp_path / "out" / "trajectory.npz") as data:
        assert np.all(np.isfinite(data["multipliers"])) and np.all(np.isfinite(data["constraint_forces"]))
        assert np.allclose(data["multipliers"][-1, 10], data["multipliers"][-1, n], rtol=1e-8)
