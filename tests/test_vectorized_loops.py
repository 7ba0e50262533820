"""The vectorized build's C loops (issue 28): a group's kernel over its instances
(``vectorized.fused``), J's products and the KKT solve with its own LDLᵀ
(``vectorized.products``), and a Runge–Kutta step's combinations (``codegen.combination``).
They must be what runs where a C compiler is found, give the columns' numbers to round-off
(test_vectorized.py checks them against dense linear algebra and the unrolled route with the
loops on; here the same checks run with them off), and fall back where they cannot be had."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import test_vectorized as tv

import constrained as C
from constrained.codegen import combination, compiled, external
from constrained.manifold.vectorized import build as vb
from constrained.manifold.vectorized import fused
from constrained.manifold.vectorized import graphs as vg
from constrained.model.cache import ParametricView
from constrained.model.structure import assemble
from constrained.solvers import dopri

needs_compiler = pytest.mark.skipif(not compiled.enabled(), reason="no C compiler")


@needs_compiler
@pytest.mark.parametrize("name", ["rope", "cloth", "rope with extras"])
def test_the_loops_are_what_a_large_model_runs_on(name):
    system = tv.SYSTEMS[name]()
    b = vb.vectorized_build(assemble(system, reuse=False).structure)
    assert b.products() is not None
    assert len(b._loops()) == 2 * len(b.mapped.rows) + len(b.mapped.terms)  # every group: whitelisted


@needs_compiler
def test_a_dopri_step_of_a_fine_rope_calls_the_loops(monkeypatch):
    """The step in the virtual machine: every acceleration through the loops (no CasADi ldl),
    the stages combined in one pass."""
    steps = []
    original = dopri.Dopri._step_function

    def keep(self, *args, **kwargs):
        steps.append(original(self, *args, **kwargs))
        return steps[-1]
    monkeypatch.setattr(dopri.Dopri, "_step_function", keep)
    system = tv.rope(120)
    tr = C.simulate(system, 0.002, model=assemble(system, reuse=False), rtol=1e-6, atol=1e-6)
    assert tr.stats["evaluation"] == "virtual machine"
    names = {f.name() for step in steps for f in step.find_functions()}
    assert any(n.startswith("rows_") for n in names)
    assert any(n.endswith("_solve1") for n in names) and any(n.endswith("_solve2") for n in names)
    assert any(n.startswith("combination_") for n in names) and any(n.startswith("sum_") for n in names)


@pytest.mark.parametrize("name", sorted(tv.SYSTEMS))
def test_without_compiled_code_the_columns_give_the_same_numbers(name, monkeypatch):
    """CONSTRAINED_COMPILE=0: no loops; J's products, the solve, the accelerations and the
    projections are the columns' and still those of dense linear algebra."""
    monkeypatch.setenv("CONSTRAINED_COMPILE", "0")
    system = tv.SYSTEMS[name]()
    b = vb.vectorized_build(assemble(system, reuse=False).structure)
    assert b.products() is None and not b._loops()
    tv.test_J_products_the_gram_and_its_solve_equal_dense_linear_algebra(system)
    tv.test_accelerations_multipliers_and_projections_equal_the_unrolled_graphs(system)


@needs_compiler
def test_a_fine_rope_run_takes_the_same_steps_with_the_loops_and_without(monkeypatch):
    """300 links of 1 cm and uneven masses: the loops change the numbers only by rounding."""
    runs = {}
    for label, setting in (("loops", "1"), ("columns", "0")):
        monkeypatch.setenv("CONSTRAINED_COMPILE", setting)
        system = tv.rope(300, varied=True)
        runs[label] = C.simulate(system, 0.05, model=assemble(system, reuse=False), rtol=1e-6, atol=1e-6,
                                 outputs=["multipliers"])
    a, b = runs["loops"], runs["columns"]
    assert a.stats["steps"] == b.stats["steps"] and a.stats["rejected"] == b.stats["rejected"]
    tv._close(a.x[-1], b.x[-1], 1e-11)
    tv._close(a.multipliers, b.multipliers, 1e-7)


def _runs_as_the_columns(system: C.System, monkeypatch) -> None:
    """A run of 0.05 s with the loops takes the steps of one with the columns (CasADi's own
    LDLᵀ), to rounding, on the constraints to 1e-12."""
    runs = {}
    for label, setting in (("loops", "1"), ("columns", "0")):
        monkeypatch.setenv("CONSTRAINED_COMPILE", setting)
        runs[label] = C.simulate(system, 0.05, model=assemble(system, reuse=False), rtol=1e-8, atol=1e-8,
                                 outputs=["multipliers", "constraint_residual"])
    a, c = runs["loops"], runs["columns"]
    assert a.stats["steps"] == c.stats["steps"] > 5
    tv._close(a.x[-1], c.x[-1], 1e-11)
    tv._close(a.multipliers, c.multipliers, 1e-7)
    assert np.max(a.constraint_residual) < 1e-12


def _wavy_rope(n: int) -> C.System:
    """A rope in 3-D (no plane: no rows eliminated) of uneven masses, its rods listed in a
    shuffled order: A is tridiagonal only in an order the LDLᵀ must find."""
    s = C.System(name="wavy rope")
    rng = np.random.default_rng(1)
    points = [np.zeros(3)] + [np.array([0.01 * (k + 1), 0.0, 0.002 * np.sin(k)]) for k in range(n)]
    for k in range(n):
        s.add_particle(f"p{k}", 0.01 * (1 + rng.uniform()), points[k + 1])
    rods = [C.Distance("p0", point=[0, 0, 0], length=float(np.linalg.norm(points[1])))]
    rods += [C.Distance(f"p{k - 1}", f"p{k}", length=float(np.linalg.norm(points[k + 1] - points[k])))
             for k in range(1, n)]
    for k in rng.permutation(n):
        s.add(rods[k])
    s.add(C.Gravity([0, -9.81, 0]))
    return s


@needs_compiler
def test_a_rope_listed_shuffled_in_3d_is_solved_as_a_path_and_runs_as_the_columns(monkeypatch):
    """Its A is a path in another order (the twisted tridiagonal LDLᵀ, permuted); the run takes
    the steps the columns (CasADi's own LDLᵀ) take, to rounding."""
    from constrained.manifold.vectorized import ldl

    system = _wavy_rope(200)
    b = vb.vectorized_build(assemble(system, reuse=False).structure)
    assert b.single is None
    order = ldl.path_order(b.gram.sparsity)
    assert order is not None and not np.array_equal(order, np.arange(len(order)))
    _runs_as_the_columns(system, monkeypatch)


@needs_compiler
def test_a_branching_rope_is_solved_by_short_columns_and_runs_as_the_columns(monkeypatch):
    """A rope of 150 links with a second rope of 60 hanging from its 40th bead (a Y: the three
    rods at the junction couple their rows, so A's graph is not a path): the short-column LDLᵀ;
    the run takes the columns' (CasADi's LDLᵀ's) steps, to rounding."""
    from constrained.manifold.vectorized import ldl

    s = C.System(name="branching rope")
    rng = np.random.default_rng(4)
    for k in range(150):
        s.add_particle(f"a{k}", 0.01 * (1 + rng.uniform()), [0.01 * (k + 1), 0.0, 0.0])
    for k in range(60):
        s.add_particle(f"b{k}", 0.005 * (1 + rng.uniform()), [0.4, -0.01 * (k + 1), 0.0])
    s.add(C.Distance("a0", point=[0, 0, 0], length=0.01))
    s.add(*[C.Distance(f"a{k - 1}", f"a{k}", length=0.01) for k in range(1, 150)])
    s.add(C.Distance("a39", "b0", length=0.01))
    s.add(*[C.Distance(f"b{k - 1}", f"b{k}", length=0.01) for k in range(1, 60)])
    s.add(C.Plane([*(f"a{k}" for k in range(150)), *(f"b{k}" for k in range(60))], [0, 0, 1]))
    s.add(C.Gravity([0, -9.81, 0]))
    b = vb.vectorized_build(assemble(s, reuse=False).structure)
    gram = b.gram if b.single is None else b.single.gram
    assert ldl.factorization(gram.sparsity)[0] == "short columns"
    _runs_as_the_columns(s, monkeypatch)


@needs_compiler
@pytest.mark.parametrize("with_y", [True, False])
def test_a_combination_is_y_plus_the_weighted_columns(with_y):
    rng = np.random.default_rng(4)
    n, k = 1001, 7
    y, K, c = rng.standard_normal(n), rng.standard_normal((k, n)), rng.standard_normal(k)
    f = combination.combination(n, k, with_y=with_y)
    out = f(*([y] if with_y else []), *K, c)
    np.testing.assert_allclose(np.asarray(out).ravel(), (y if with_y else 0) + c @ K, rtol=1e-13, atol=1e-13)
    assert combination.combination(n, 0) is None
    assert combination.combination(n, combination.MAX_TERMS + 1) is None


@needs_compiler
def test_combinations_from_the_cache_are_loaded_one_by_one_and_equal_the_compiled_ones(tmp_path, monkeypatch):
    """A cached library's entry points are loaded when first asked for (not all 32), without
    the compiler, and give the numbers of the freshly compiled library, bit for bit, for
    every k and both forms; a library the cache does not hold is compiled whole."""
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(combination, "_libraries", {})
    rng = np.random.default_rng(11)
    n = 257
    y, K = rng.standard_normal(n), rng.standard_normal((combination.MAX_TERMS, n))
    c = rng.standard_normal(combination.MAX_TERMS) * 10.0 ** rng.integers(-8, 8, combination.MAX_TERMS)
    cases = [(k, with_y) for k in range(1, combination.MAX_TERMS + 1) for with_y in (True, False)]

    def values():
        return {(k, w): np.asarray(combination.combination(n, k, with_y=w)(*([y][:w]), *K[:k], c[:k]))
                for k, w in cases}
    fresh = combination.combination(n, 3)  # compiled: every entry loaded
    assert all(f is not None for f in combination._libraries[n].loaded)
    compiled_values = values()

    def no_compiler(command):
        raise AssertionError("the compiler ran for a cached library")
    monkeypatch.setattr(compiled, "_compile", no_compiler)
    monkeypatch.setattr(combination, "_libraries", {})
    again = combination.combination(n, 3)
    assert [f is not None for f in combination._libraries[n].loaded].count(True) == 1
    np.testing.assert_array_equal(np.asarray(again(y, *K[:3], c[:3])), np.asarray(fresh(y, *K[:3], c[:3])))
    cached_values = values()
    for case in cases:
        np.testing.assert_array_equal(cached_values[case], compiled_values[case], err_msg=str(case))


@needs_compiler
def test_a_c_function_is_compiled_once_and_loaded_from_the_cache(tmp_path, monkeypatch):
    """The second build of the same source loads the library (the compiler is not run), a
    null output is skipped, and a null input reads as zeros."""
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    body = ("  int i;\n  for (i = 0; i < 3; ++i) { if (y) y[i] = 2 * (x ? x[i] : 0); if (z) z[i] = 1; }\n"
            "  return 0;")
    args = (["x"], [ca.Sparsity.dense(3, 1)], ["y", "z"], [ca.Sparsity.dense(3, 1)] * 2)
    f = external.c_function("twice_test", body, *args)
    np.testing.assert_array_equal(np.asarray(f([1, 2, 3])[0]).ravel(), [2, 4, 6])
    X = ca.MX.sym("x", 3)
    g = ca.Function("g", [X], [f(X)[0]])  # z not wanted: a null output
    np.testing.assert_array_equal(np.asarray(g([1, 1, 1])).ravel(), [2, 2, 2])
    zero = ca.Function("h", [X], [f(ca.MX(3, 1))[0] + X])  # a structurally zero input
    np.testing.assert_array_equal(np.asarray(zero([1, 2, 3])).ravel(), [1, 2, 3])

    def no_compiler(command):
        raise AssertionError("the compiler ran for a cached library")
    monkeypatch.setattr(compiled, "_compile", no_compiler)
    again = external.c_function("twice_test", body, *args)
    np.testing.assert_array_equal(np.asarray(again([1, 2, 3])[0]).ravel(), [2, 4, 6])


def test_a_kernel_outside_the_whitelist_has_no_loop():
    xl, vl, t = ca.SX.sym("xl", 2), ca.SX.sym("vl", 2), ca.SX.sym("t")
    c, p = ca.SX.sym("c", 0), ca.SX.sym("p", 0)
    kernel = ca.Function("k", [xl, vl, c, t, p], [ca.erfinv(xl[0] / 3) - xl[1]])
    index = np.array([[0, 2], [1, 3]])
    table = external.IndexTable()
    assert fused.loop_body(fused.flat(kernel), index, np.zeros((0, 2)), np.zeros(0), 4, 0, table) is None
    ok = ca.Function("k", [xl, vl, c, t, p], [ca.erf(xl[0] / 3) - xl[1]])
    assert fused.loop_body(fused.flat(ok), index, np.zeros((0, 2)), np.zeros(0), 4, 0, table) is not None


def test_forces_of_p_alone_are_found_without_asking_casadi_through_the_loops(monkeypatch):
    """dopri's step computes forces of p alone once (``statics``). CasADi's dependency test
    through a C loop assumes every output depends on every input: at 10,000 beads of cloth
    that was a dense 30,000-column pattern per output, and 22 GB. The test asks the SX."""
    original = ca.depends_on

    def sx_only(expression, symbols):
        assert not isinstance(expression, ca.MX), "depends_on on an MX graph"
        return original(expression, symbols)
    springs = tv.rope(120)
    for i in range(0, 118, 2):
        springs.add(C.Spring(f"p{i}", f"p{i + 2}", k=3.0, rest=0.02))
    for system, varies in ((tv.rope(120), False), (springs, True)):
        model = assemble(system, reuse=False)
        monkeypatch.setattr(ca, "depends_on", sx_only)
        view = ParametricView(model, ca.MX.sym("p", len(model.parameter_vector)))
        _, forces = vg.statics(view)
        monkeypatch.setattr(ca, "depends_on", original)
        assert (forces is None) == varies
        assert vb.vectorized_build(model.structure).mapped.terms or not varies


def test_a_compiler_that_fails_leaves_the_columns(tmp_path, monkeypatch):
    """A C compiler that fails (here ``false``): no loops, the reason kept, and the run as before."""
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", "false")
    system = tv.rope(120)
    model = assemble(system, reuse=False)
    b = vb.vectorized_build(model.structure)
    assert b.products() is None and not b._loops()
    assert compiled.last_error and "compiler failed" in compiled.last_error
    tr = C.simulate(system, 0.002, model=model, rtol=1e-6, atol=1e-6)
    assert np.max(tr.constraint_residual) < 1e-9


@needs_compiler
def test_an_index_table_reads_back_every_byte_and_integer(tmp_path, monkeypatch):
    """The table's string literal (shortest octal escapes, each followed by another escape)
    gives the compiled loops exactly the integers added, at the places ``add`` names."""
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    table = external.IndexTable()
    first = np.arange(-3, 300, dtype=np.int64)
    second = np.array([0, 7, 8, 63, 92, 34, 48, 2**31 - 1, 255, 256, 65535, 65536])
    at = [table.add(first), table.add(second)]
    n = len(first) + len(second)
    body = (f"  int i;\n  const int *a = {at[0]}, *b = {at[1]};\n"
            f"  for (i = 0; i < {len(first)}; ++i) out[i] = a[i];\n"
            f"  for (i = 0; i < {len(second)}; ++i) out[{len(first)} + i] = b[i];\n  return 0;")
    f = external.c_functions([("table_test", body, ["x"], [ca.Sparsity.dense(1, 1)], ["out"],
                               [ca.Sparsity.dense(n, 1)])], table.c, key=table.data())[0]
    np.testing.assert_array_equal(np.asarray(f(0)).ravel(), np.concatenate([first, second]))


@needs_compiler
def test_an_element_is_the_value_whether_it_steps_evenly_or_not(tmp_path, monkeypatch):
    """``element``: evenly stepping indices (up, down, constant, one) as ``a + b i``, the rest read
    from the table; both give back every value."""
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    arrays = [np.arange(5, 50, 3), np.arange(40, 0, -2), np.full(7, 9), np.array([4]), np.arange(12),
              np.array([0, 1, 2, 4, 5]), np.array([3, 3, 4])]
    table = external.IndexTable()
    expressions = [external.element(table, a) for a in arrays]
    assert sum("TABLE" in e for e in expressions) == 2
    n = sum(len(a) for a in arrays)
    loops, at = [], 0
    for a, e in zip(arrays, expressions, strict=True):
        loops.append(f"  for (i = 0; i < {len(a)}; ++i) out[{at} + i] = {e};")
        at += len(a)
    body = "  casadi_int i;\n" + "\n".join(loops) + "\n  return 0;"
    f = external.c_functions([("element_test", body, ["x"], [ca.Sparsity.dense(1, 1)], ["out"],
                               [ca.Sparsity.dense(n, 1)])], table.c, key=table.data())[0]
    np.testing.assert_array_equal(np.asarray(f(0)).ravel(), np.concatenate(arrays))


@needs_compiler
@pytest.mark.parametrize("name", ["rope", "cloth", "rope with extras"])
def test_the_products_library_is_found_in_the_cache_by_the_index_data_alone(name, tmp_path, monkeypatch):
    """A second build of an equal structure loads J's products and the LDLᵀ by the build's
    index data (no source written: neither A's index data nor the symbolic factorization is
    built, and the compiler does not run), and they give the first library's numbers, bit for
    bit; other index data (one stream's coordinates in another order) is another library's."""
    from constrained.manifold.vectorized import products

    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    system = tv.SYSTEMS[name]()
    first = vb.vectorized_build(assemble(system, reuse=False).structure)
    assert first.products() is not None
    model = assemble(system, reuse=False)
    second = vb.vectorized_build(model.structure)

    def refused(*args, **kwargs):
        raise AssertionError("the source was written for a cached library")
    monkeypatch.setattr(compiled, "_compile", refused)
    monkeypatch.setattr(products, "ldl_bodies", refused)
    assert second.products() is not None
    assert "gram" not in (second.single.__dict__ if second.single is not None else {})  # (not built)
    rng = np.random.default_rng(5)
    streams = [rng.standard_normal(len(r)) for r in first.rows]
    minv, y = rng.uniform(1, 3, first.n3), rng.standard_normal(first.n3)
    lam, B = rng.standard_normal(first.n_rows), rng.standard_normal((first.n_rows, 2))
    for kind, args in (("times", (*streams, y)), ("transpose_times", (*streams, lam))):
        assert np.array_equal(np.asarray(first.products().f[kind](*args)),
                              np.asarray(second.products().f[kind](*args)))
    S = [ca.DM(s) for s in streams]
    for k in (1, 2):
        a = np.asarray(ca.evalf(first.products().solve(S, ca.DM(minv), ca.DM(B[:, :k]))))
        b = np.asarray(ca.evalf(second.products().solve(S, ca.DM(minv), ca.DM(B[:, :k]))))
        assert np.array_equal(a, b)
    from types import SimpleNamespace

    def swapped(b, s):  # one stream's coordinates in another order
        cols = [c[::-1] if k == s else c for k, c in enumerate(b.cols)]
        return SimpleNamespace(n_rows=b.n_rows, n3=b.n3, rows=b.rows, cols=cols)
    assert products._decided_by(SimpleNamespace(n_rows=second.n_rows, n3=second.n3, rows=second.rows,
                                                cols=second.cols)) == products._decided_by(second)
    assert products._decided_by(swapped(second, 0)) != products._decided_by(second)


@needs_compiler
@pytest.mark.parametrize("name", ["cloth", "moving rope", "rope with extras"])
def test_a_state_without_velocities_reads_the_loops_as_with_zero_velocities(name):
    """``evaluate`` with V None (a projection's f, J, row scales; γ at v = 0): the loops are
    called with x in v's place where the outputs taken do not read v (a constant input costs
    CasADi 10-20 ms at each call on a large model): the bits of V = 0 given, and γ still v = 0's."""
    system = tv.SYSTEMS[name]()
    model = assemble(system, reuse=False)
    b = vb.vectorized_build(model.structure)
    x, _, t = tv._state(model, system)
    X, T = ca.MX.sym("x", model.n_coordinates), ca.MX.sym("t")
    P = ca.MX.sym("p", len(model.parameter_vector))
    for outputs in (("f", "J", "scale"), ("f", "J", "f_t", "scale"), ("gamma",), ("J", "gamma")):
        values = {}
        for label, V in (("none", None), ("zeros", ca.MX.zeros(model.n_coordinates))):
            out = b.evaluate(X, V, T, P, outputs)
            graph = [out[k].matrix() if k == "J" else out[k] for k in outputs]
            values[label] = ca.Function("f", [X, T, P], graph)(x, t, model.parameter_vector)
            values[label] = [np.array(ca.DM(v)).ravel() for v in (values[label] if len(outputs) > 1
                                                                    else [values[label]])]
        for a, z in zip(values["none"], values["zeros"], strict=True):
            assert np.array_equal(a, z)
