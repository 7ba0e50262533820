"""The neighbour list's forces as one fused C loop (constrained.model.pairs.fused): the same
numbers as the mapped kernel and a NumPy sum, every whitelisted operation translated exactly,
the mapped kernel where the loop cannot be had, and a compile-cache key that a new process
finds again."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from test_pairs import gas, numpy_pair_sum, pair_parts, trap_parts

import constrained as C
from constrained.codegen import compiled
from constrained.codegen.scalar_c import C_OPERATIONS, scalar_c
from constrained.model.pairs import fused, kernel, neighbours
from constrained.model.structure import assemble

needs_compiler = pytest.mark.skipif(not compiled.enabled(), reason="no C compiler")


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))


def _listed_forces(monkeypatch, use_fused: bool):
    monkeypatch.setattr(kernel, "FUSED", use_fused)
    bonds = [(10, 11), (11, 12), (40, 41)]
    system = gas(150, cutoff=1.7, skin=0.3, jitter=0.25, particles=range(5, 140), bonds=bonds,
                 exclude_bonded=True)
    model = assemble(system, reuse=False)
    (term,) = model.structure.pairs
    x = np.asarray(system.positions).ravel() + 0.05 * np.random.default_rng(2).normal(size=450)
    return model, term, x, pair_parts(model, x)


@needs_compiler
def test_the_fused_loop_gives_the_mapped_kernel_and_the_numpy_sum(monkeypatch):
    """A disordered gas (a subset, bonded pairs excluded, parameters in φ): the
    fused loop is what the force Function runs, and its forces equal the mapped kernel's and a
    NumPy sum over the pairs within r_c."""
    model, term, x, (V, F) = _listed_forces(monkeypatch, True)
    assert term._sums("force")[1].class_name() == "JitFunction"
    _, mapped_term, _, (V_m, F_m) = _listed_forces(monkeypatch, False)
    assert mapped_term._sums("force")[1].class_name() == "MXFunction"
    np.testing.assert_allclose(F, F_m, rtol=1e-12, atol=1e-13 * np.abs(F_m).max())
    assert V == pytest.approx(V_m, rel=1e-13)  # (the energy is the mapped kernel's in both)
    system = model.system
    _, F_trap = trap_parts(system, x)
    _, F_ref = numpy_pair_sum(x, range(5, 140), 1.7, excluded={(10, 11), (11, 12), (40, 41)})
    np.testing.assert_allclose(F - F_trap, F_ref, rtol=1e-9, atol=1e-10 * np.abs(F_ref).max())


@needs_compiler
def test_the_fused_loop_sums_the_energy_with_the_forces_when_asked(monkeypatch):
    """``forces_and_potential`` (RATTLE's energy watch at every step) takes the fused loop with
    its energy: W = Σ φ_c(r_ij) over the pairs within r_c (plus the trap's ½ k |x|²) equals the
    NumPy sum and the mapped kernel's energy, and F the force Function's."""
    model, term, x, (V, F) = _listed_forces(monkeypatch, True)
    assert term._sums("both")[1].class_name() == "JitFunction"
    F_both, W = model.structure.function("forces_and_potential")(x, 0 * x, 0.0, model.parameter_vector)
    V_trap, _ = trap_parts(model.system, x)
    V_ref, _ = numpy_pair_sum(x, range(5, 140), 1.7, excluded={(10, 11), (11, 12), (40, 41)})
    assert float(W) - V_trap == pytest.approx(V_ref, rel=1e-11)
    assert float(W) == pytest.approx(V, rel=1e-13)  # (the mapped kernel's, through "potential")
    np.testing.assert_allclose(np.asarray(F_both).ravel(), F, rtol=1e-14, atol=1e-14 * np.abs(F).max())


@needs_compiler
def test_a_compiled_rattle_runs_energy_watch_is_the_trajectorys_energy():
    """A gas with a cutoff, RATTLE compiled: the fused loop's energy at every step (the watch)
    gives the largest change of h that the trajectory's energy, summed over every pair after
    the run, shows at the same steps."""
    system = gas(64, cutoff=1.8)
    dt, steps = 2e-3, 100
    run = C.simulate(system, steps * dt, method="rattle", dt=dt, compiled=True,
                     t_eval=np.linspace(0.0, steps * dt, steps + 1))
    assert run.stats["evaluation"] == "compiled"
    change = run.energy - run.energy[0]
    k = int(np.argmax(np.abs(change)))
    assert abs(change[k]) > 1e-9 * abs(run.energy[0])  # (the energy moved at all)
    assert run.stats["energy_start"] == pytest.approx(run.energy[0], rel=1e-12)
    assert run.stats["energy_change"] == pytest.approx(change[k], rel=1e-6)
    assert run.stats["energy_change_t"] == pytest.approx(run.t[k], abs=1e-12)


def _whitelist_cases():
    r = ca.SX.sym("r")
    u = r / 2  # in (0.55, 0.95): asin, acos, atanh defined; acosh of r ≥ 1.1
    pieces = [r + 1, r - 3, r * r, 1 / r, -r, ca.exp(-r), ca.log(r), r ** u, r ** 3, r ** 0.5,
              ca.sqrt(r), 2 * r, ca.sin(r), ca.cos(r), ca.tan(u), ca.asin(u), ca.acos(u), ca.atan(r),
              ca.sinh(r), ca.cosh(r), ca.tanh(r), ca.asinh(r), ca.acosh(r), ca.atanh(u),
              ca.atan2(r, u), ca.hypot(r, u), ca.erf(u), ca.log1p(r), ca.expm1(-r), ca.fabs(u - 0.7),
              ca.floor(3 * r), ca.ceil(3 * r), ca.fmod(7 * r, 1.3), ca.fmin(r, 1.5), ca.fmax(r, 1.5),
              ca.copysign(r, u - 0.7), ca.sign(u - 0.7), r < 1.5, r <= 1.5, r == 1.5, r != 1.5,
              ca.logic_not(r < 1.5), ca.logic_and(r < 1.8, r > 1.2), ca.logic_or(r < 1.2, r > 1.8),
              ca.if_else(r < 1.5, ca.exp(r), ca.sin(r))]
    return r, pieces


@needs_compiler
def test_every_whitelisted_operation_is_translated_to_the_same_number(tmp_path):
    """Each SX operation the translation knows, written to C by ``scalar_c`` and compiled,
    gives CasADi's own value (to rounding) at several r."""
    r, pieces = _whitelist_cases()
    f = ca.Function("pieces", [r], pieces)
    ops = {f.instruction_id(k) for k in range(f.n_instructions())}
    assert ops - {ca.OP_INPUT, ca.OP_OUTPUT, ca.OP_CONST} <= set(C_OPERATIONS)
    assert len(ops & set(C_OPERATIONS)) >= 40  # (the whole whitelist but a few CasADi folds away)
    code = scalar_c(f, ["x0"], [f"y[{k}]" for k in range(len(pieces))])
    assert code is not None
    body = f"const casadi_real x0 = x[0];\n{{\n{code}\n}}\n"  # (no return: the outputs are copied after)
    jit = ca.Function.jit("translated", body, ["x"], ["y"], [ca.Sparsity.dense(1, 1)],
                          [ca.Sparsity.dense(len(pieces), 1)],
                          {"compiler": "shell", "jit_options": {"directory": str(tmp_path)}})
    for value in (1.13, 1.37, 1.5, 1.66, 1.91):
        expected = np.array([float(o) for o in f(value)])
        got = np.asarray(jit(value)).ravel()
        np.testing.assert_allclose(got, expected, rtol=2e-15, atol=1e-300)


def test_an_operation_outside_the_whitelist_is_not_translated():
    r = ca.SX.sym("r")
    assert scalar_c(ca.Function("f", [r], [ca.erfinv(r / 3)]), ["r"], ["y"]) is None
    assert scalar_c(ca.Function("f", [r], [r + ca.inf]), ["r"], ["y"]) is None  # (no C literal)
    t, q = ca.SX.sym("t"), ca.SX.sym("q", 0)
    assert fused.fused_forces("f", r, t, q, ca.erfinv(r / 3), n=4, size=60, capacity=4, cutoff=1.0) is None


def test_without_compiled_code_the_mapped_kernel_serves(monkeypatch):
    """``CONSTRAINED_COMPILE=0``: no C compiled at run time, the fused loop included; the
    forces are the mapped kernel's."""
    monkeypatch.setenv("CONSTRAINED_COMPILE", "0")
    _, term, _, _ = _listed_forces(monkeypatch, True)
    assert term._sums("force")[1].class_name() == "MXFunction"


@needs_compiler
def test_the_fused_kernel_serializes_alike_when_built_again():
    """Its serialization is part of the compile cache's key of every step loop that holds it:
    two builds (as two runs make) must give the same text, so the next run finds the library."""
    r, t, q = ca.SX.sym("r"), ca.SX.sym("t"), ca.SX.sym("q", 1)
    g = -ca.jacobian(q[0] * (1 / r) ** 12, r) / r
    built = [fused.fused_forces("pairs_fused_force", r, t, q, g, n=5, size=1 + 15 + 9 * 8, capacity=8,
                                cutoff=1.0) for _ in range(2)]
    assert built[0] is not None and built[0].serialize() == built[1].serialize()


@needs_compiler
def test_rattle_runs_its_chained_steps_compiled_and_says_so():
    """The chained steps (several chain lengths, one library) compile under distinct names and
    run as machine code: the stats say so only when they do, and the trajectory is the
    virtual machine's."""
    s = C.System()
    s.add_particle("a", 1.0, [1.0, 0.0, 0.0])
    s.add_particle("b", 2.0, [1.0, -1.0, 0.0], [0.3, 0.0, 0.1])
    s.add(C.Distance("a", point=[0, 0, 0], length=1.0), C.Distance("a", "b", length=1.0),
          C.Gravity([0, 0, -9.81]))
    runs = {setting: C.simulate(s, 0.5, method="rattle", dt=1e-3, compiled=setting)
            for setting in (True, False)}
    assert compiled.last_error is None
    assert runs[True].stats["evaluation"] == "compiled"
    assert runs[False].stats["evaluation"] == "virtual machine"
    np.testing.assert_allclose(runs[True].x, runs[False].x, rtol=0, atol=1e-12)


def _cell_rows(y, reach, capacity, inner):
    from constrained.codegen.fast_call import FastCall
    from constrained.model.pairs import cells

    out = FastCall(cells.rows_function(len(y), capacity, reach, inner))(y.ravel())[0]
    if out[0] != 1:
        return None
    return out[1:1 + capacity], out[1 + capacity:]


def _listed_pairs(I, J, n):
    i = np.repeat(I, kernel.ROW).astype(int)
    j = J.astype(int)
    return i[j < n], j[j < n]


CLOUDS = {
    "uniform cube, 700": lambda rng: rng.random((700, 3)) * 700 ** (1 / 3),
    "two far clusters (the grid coarsened)": lambda rng: np.concatenate(
        [rng.random((300, 3)) * 6, 1e4 + rng.random((300, 3)) * 6]),
    "a flat sheet, 400": lambda rng: np.column_stack([rng.random((400, 2)) * 20, np.zeros(400)]),
}


@needs_compiler
@pytest.mark.parametrize("cloud", CLOUDS.values(), ids=CLOUDS.keys())
def test_the_cell_list_writes_the_rows_of_the_tree(cloud):
    """The C cell list's rows hold the same pairs as SciPy's tree and NumPy's (``neighbours.
    pair_rows``), in the same rows (the same points, in order), each point's pairs within the
    cutoff before its others; too small a capacity, or a point not finite, gives no list."""
    rng = np.random.default_rng(7)
    y = cloud(rng)
    n, reach, inner = len(y), 1.3, 1.1
    rows = neighbours.rows_needed(neighbours.pairs_within(y, reach)[0], n)
    I0, J0 = neighbours.pair_rows(y, reach, rows + 4)
    I1, J1 = _cell_rows(y, reach, rows + 4, inner)
    np.testing.assert_array_equal(I1, I0)
    i1, j1 = _listed_pairs(I1, J1, n)
    assert sorted(zip(*_listed_pairs(I0, J0, n), strict=True)) == sorted(zip(i1, j1, strict=True))
    assert len(i1) > n / 4  # (pairs there are)
    far = np.linalg.norm(y[i1] - y[j1], axis=1) >= inner
    for point in np.unique(i1):
        mine = far[i1 == point]
        assert not np.any(mine[:-1] > mine[1:])  # near, then far
    assert _cell_rows(y, reach, rows - 1, inner) is None
    y[5, 1] = np.nan
    assert _cell_rows(y, reach, rows + 4, inner) is None


@needs_compiler
def test_a_term_builds_the_same_list_by_cells_as_by_the_tree(monkeypatch):
    """A pair term's data (its reference positions and rows) is the same whichever builds it."""
    system = gas(150, cutoff=1.7, skin=0.3, jitter=0.25, particles=range(5, 140))
    data = {}
    for use_cells in (True, False):
        monkeypatch.setattr(kernel, "CELLS", use_cells)
        (term,) = assemble(system, reuse=False).structure.pairs
        data[use_cells] = term.data(np.asarray(system.positions))
        assert (term._cell_rows is not False) == use_cells
    start = 1 + 3 * term.n
    np.testing.assert_array_equal(data[True][:start + term.capacity], data[False][:start + term.capacity])
    listed = {k: _listed_pairs(v[start:start + term.capacity], v[start + term.capacity:], term.n)
              for k, v in data.items()}
    assert len(listed[True][0])
    assert sorted(zip(*listed[True], strict=True)) == sorted(zip(*listed[False], strict=True))


METHODS = {"dopri": {}, "rodas": {}, "idas": {}, "ggl": {}, "baumgarte": {}, "projection": {},
           "pantelides": {}, "rattle": {"dt": 2e-4}}


@pytest.fixture(scope="module")
def bonded_gas():
    """A gas with a cutoff (its neighbour list in p) and rigid bonds whose pairs are excluded,
    and a reference run (dopri at 1e-11)."""
    system = gas(64, cutoff=1.8, bonds=[(0, 1), (1, 2), (10, 11)], exclude_bonded=True)
    reference = C.simulate(system, 0.1, method="dopri", rtol=1e-11, atol=1e-13, t_eval=[0.0, 0.1])
    return system, reference


@pytest.mark.parametrize("method", METHODS)
def test_every_method_runs_pairs_with_a_cutoff_beside_constraints(bonded_gas, method):
    """Constraints and a cutoff's neighbour list in p together (p longer than the constraint
    Functions' own parameters; the implicit methods differentiate the listed forces): every
    method runs, holds the bonds and lands on the reference."""
    system, reference = bonded_gas
    run = C.simulate(system, 0.1, method=method, rtol=1e-9, atol=1e-11, t_eval=[0.0, 0.1], **METHODS[method])
    assert run.info["status"] == "completed"
    x = run.x[-1].reshape(-1, 3)
    for i, j in [(0, 1), (1, 2), (10, 11)]:
        start = np.linalg.norm(np.subtract(system.positions[i], system.positions[j]))
        assert np.linalg.norm(x[i] - x[j]) == pytest.approx(start, abs=1e-7)
    moved = np.abs(reference.x[-1] - reference.x[0]).max()  # ~0.09 m
    # (a run without the pair forces lands ~0.05 m from the reference)
    assert np.abs(run.x[-1] - reference.x[-1]).max() < 1e-2 * moved


@needs_compiler
def test_two_fused_terms_one_of_time_in_a_compiled_run(monkeypatch):
    """Two pairwise effects with cutoffs (one φ of t and a parameter, on a subset): each runs
    its own fused loop; the forces at t = 0.7 s are the mapped kernels', and a compiled run
    (both loops in one library) lands where the virtual machine's does."""
    def system():
        s = gas(80, cutoff=1.8)
        s.add(C.Pairwise("0.3*exp(-r/s)*(1 + 0.5*sin(3*t))", [f"p{i}" for i in range(20, 80)], cutoff=1.5))
        return s

    forces = {}
    for use_fused in (True, False):
        monkeypatch.setattr(kernel, "FUSED", use_fused)
        model = assemble(system(), reuse=False)
        kinds = {term._sums("force")[1].class_name() for term in model.structure.pairs}
        assert kinds == ({"JitFunction"} if use_fused else {"MXFunction"})
        x = np.asarray(model.system.positions).ravel()
        forces[use_fused] = np.asarray(model.structure.function("dynamics")(x, 0 * x, 0.7,
                                                                            model.parameter_vector)[0]).ravel()
    np.testing.assert_allclose(forces[True], forces[False], rtol=1e-12,
                               atol=1e-13 * np.abs(forces[False]).max())
    monkeypatch.setattr(kernel, "FUSED", True)
    runs = [C.simulate(system(), 0.2, method="dopri", rtol=1e-11, atol=1e-13, compiled=setting,
                       t_eval=[0, 0.2]) for setting in (True, False)]
    assert runs[0].stats["evaluation"] == "compiled"
    np.testing.assert_allclose(runs[0].x[-1], runs[1].x[-1], rtol=0, atol=1e-12)
