"""The mapped build (constrained.mapped): repeated rows and potential terms as one kernel each,
applied with CasADi ``map``. It must give the Structure's numbers to round-off — f, J, f_t,
γ, forces, row scales, accelerations, multipliers, whole compiled trajectories — hold each
kind of row or term once whatever N, and serve every parameter value without rebuilding or
recompiling anything."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import constrained as C
from constrained.codegen import compiled
from constrained.manifold import mapped
from constrained.manifold.manifold import acceleration_function
from constrained.model import lifting
from constrained.model.cache import structure_cache
from constrained.model.held import held
from constrained.model.structure import Structure, assemble
from constrained.run.simulate import consistent_state

needs_cc = pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler on this machine")


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))


def chain(n: int, *, pairs: bool = False, parametric: bool = False, varied: bool = False) -> C.System:
    """A planar chain hanging from the origin; ``pairs``: a weak attraction between every pair
    of particles; ``parametric``: mass, length, g and a moving plane (rheonomic) as parameters;
    ``varied``: every link's length and every particle's mass a different number."""
    s = C.System(name=f"chain of {n}",
                 parameters={"m": 1.3, "l": 0.9, "g": 9.81, "w": 2.0} if parametric else None)
    lengths = [1.0 + 0.05 * i if varied else 1.0 for i in range(n)]
    reach = np.cumsum(lengths)
    for i in range(n):
        at = ([f"{i + 1}*l*sin(0.5)", f"-{i + 1}*l*cos(0.5)", 0.0] if parametric
              else [reach[i] * np.sin(0.5), -reach[i] * np.cos(0.5), 0.0])
        s.add_particle(f"p{i}", "m" if parametric else 1.0 + 0.1 * i * varied, at)
    s.add(C.Distance("p0", point=[0, 0, 0], length="l" if parametric else lengths[0]))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length="l" if parametric else lengths[i]))
    offset = "0.01*sin(w*t)" if parametric else 0.0
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1], offset),
          C.Gravity(["0", "-g", "0"] if parametric else [0, -9.81, 0]))
    if pairs:
        s.add(C.Pairwise("-0.05/r"))
    return s


def _dense(value) -> np.ndarray:
    return np.array(ca.densify(ca.DM(value)))


CASES = [dict(), dict(pairs=True), dict(parametric=True), dict(pairs=True, parametric=True),
         dict(varied=True)]


@pytest.mark.parametrize("options", CASES, ids=lambda o: "-".join(o) or "plain")
def test_mapped_functions_give_the_structures_numbers(options):
    system = chain(12, **options)
    structure = Structure(system)
    build = mapped.MappedBuild(structure)
    assert build.mapped_instances >= 11 + 12 + 12  # rods, plane rows, gravity terms
    rng = np.random.default_rng(3)
    x, v, t = rng.normal(size=36), rng.normal(size=36), 0.37
    # the parameters, then the plain numbers (constrained.lifting)
    p = [1.1, 0.8, 7.0, 3.0] * bool(options.get("parametric")) + lifting.numbers(system).tolist()
    for name, args in (("constraint", (x, t)), ("jacobian", (x, t)), ("velocity_terms", (x, t)),
                       ("dynamics", (x, v, t)), ("forces_and_potential", (x, v, t))):
        want = structure.function(name)(*args, p)
        got = build.function(name)(*args, p)
        want, got = (want, got) if isinstance(want, tuple) else ((want,), (got,))
        for a, b in zip(want, got, strict=True):
            assert a.shape == b.shape
            np.testing.assert_allclose(_dense(b), _dense(a), rtol=1e-13, atol=1e-13, err_msg=name)
    # W = h − ½ vᵀMv (the energy watch's): the energy Function's, less the kinetic energy
    masses = np.asarray(structure.function("masses")(p)).ravel()
    W = float(build.function("forces_and_potential")(x, v, t, p)[1])
    assert W == pytest.approx(float(structure.function("energy")(x, v, t, p)) - 0.5 * masses @ (v * v),
                              rel=1e-12, abs=1e-12)
    from constrained.manifold.graph import row_scales_expr

    J = structure.function("jacobian")(x, t, p)[1]
    np.testing.assert_array_equal(_dense(build.function("row_scales")(x, t, p)),
                                  _dense(row_scales_expr(J, 12)))


def test_each_kind_is_held_once_whatever_n():
    """The mapped Functions of a 32- and a 48-link chain with all-pairs forces have the same
    graphs (the same number of operations), only longer index data; the pairs are one pair
    kernel (constrained.model.pairs), not a group of summands."""
    small, large = (mapped.MappedBuild(Structure(chain(n, pairs=True))) for n in (32, 48))
    assert [g.index.shape[1] for g in large.rows] == [47, 48]  # rods, plane rows
    assert [g.index.shape[1] for g in large.terms] == [48]  # gravity
    assert len(large.structure.pairs) == 1 and large.structure.pairs[0].n == 48
    assert list(large.rest_place) == [0]  # the rod to the anchor is the one of its kind
    for name in mapped.NAMES:
        assert small.function(name).n_instructions() == large.function(name).n_instructions(), name


def test_numbers_are_lifted_into_data_so_differing_numbers_share_a_kernel():
    """Rods of different lengths and particles of different masses are one kind each; their
    numbers are columns of data beside the index columns."""
    system = chain(12, varied=True)
    build = mapped.MappedBuild(Structure(system))
    rods, planes = build.rows
    assert rods.index.shape[1] == 11 and planes.index.shape[1] == 12
    P = ca.MX.sym("p", len(lifting.numbers(system)))  # the lengths are entries of p
    lengths = ca.Function("lengths", [P], [rods.data(P)])(lifting.numbers(system))
    np.testing.assert_array_equal(np.sort(np.asarray(lengths).ravel()), 1.0 + 0.05 * np.arange(1, 12))
    (gravity,) = build.terms
    assert gravity.index.shape[1] == 12 and list(build.rest_place) == [0]
    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [2.5 * ca.sin(x[0]) - x[1] / 7.0])
    c = ca.SX.sym("c", 4)
    expr, values = mapped.lifted(f, c)
    assert values == [("c", 2.5), ("c", 7.0)]
    assert float(ca.Function("g", [x, c], [expr])([0.3, 2.0], [2.5, 7.0, 0, 0])) == float(f([0.3, 2.0]))
    assert mapped.lifted(f, c[:1]) is None  # more numbers than room: kept as they are


def test_summands_unfold_sums_differences_and_negations():
    a, b, c = ca.SX.sym("a"), ca.SX.sym("b"), ca.SX.sym("c")
    terms = mapped.summands(-(a * b - (c + ca.sin(a))) + 2)
    values = [float(ca.Function("f", [a, b, c], [e])(0.3, 0.7, 1.1)) for e in terms]
    assert len(terms) == 4
    assert sum(values) == pytest.approx(-(0.3 * 0.7 - (1.1 + np.sin(0.3))) + 2, abs=1e-15)


@pytest.mark.parametrize("options", CASES[1:3] + CASES[4:], ids=["pairs", "parametric", "varied"])
def test_mapped_accelerations_and_multipliers_equal_the_unmapped(options):
    system = chain(12, **options)
    model = assemble(system, reuse=False)
    x, v, _ = consistent_state(model, system.positions, system.velocities, 0.0, size=system.size())
    p = model.parameter_vector
    plain = acceleration_function(model, parametric=True)(x, v, 0.0, p)
    with_map = mapped.acceleration_function(model)(x, v, 0.0, p)
    for a, b in zip(plain, with_map, strict=True):
        np.testing.assert_allclose(_dense(b), _dense(a), rtol=1e-12, atol=1e-12)


@needs_cc
@pytest.mark.parametrize("options", CASES[1:3] + CASES[4:], ids=["pairs", "parametric", "varied"])
def test_a_compiled_mapped_step_loop_runs_the_unmapped_trajectory(options, monkeypatch):
    monkeypatch.setattr(mapped, "MAPPED_FROM", 0)  # map this small chain
    system = chain(12, **options)
    kw = dict(method="dopri", rtol=1e-9, atol=1e-11, t_eval=np.linspace(0, 1, 6),
              outputs=["multipliers"])
    model = assemble(system, reuse=False)
    got = C.simulate(system, 1.0, model=model, compiled=True, **kw)
    assert got.stats["evaluation"] == "compiled"
    cache, prefix = structure_cache(model)
    assert (*prefix, "acceleration", None, "mapped") in cache  # the loop was built on the map
    want = C.simulate(system, 1.0, model=assemble(system, reuse=False), compiled=False, **kw)
    assert got.stats["steps"] == want.stats["steps"]
    np.testing.assert_allclose(got.x, want.x, rtol=0, atol=1e-11)
    np.testing.assert_allclose(got.v, want.v, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got.multipliers, want.multipliers, rtol=1e-9, atol=1e-9)


@needs_cc
def test_new_parameter_values_neither_rebuild_nor_recompile_the_mapped_loop(monkeypatch):
    monkeypatch.setattr(mapped, "MAPPED_FROM", 0)
    builds = []
    original = compiled._build
    monkeypatch.setattr(compiled, "_build", lambda *a, **k: builds.append(1) or original(*a, **k))
    system = chain(10, parametric=True)
    model = assemble(system, reuse=False)
    kw = dict(method="dopri", rtol=1e-9, atol=1e-11, t_eval=[0.0, 0.5], outputs=set())
    C.simulate(system, 0.5, model=model, compiled=True, **kw)
    assert len(builds) == 1
    structures = Structure.builds
    for values in ({"m": 0.7, "l": 1.1}, {"g": 3.0, "w": 5.0}):
        tr = C.simulate(system, 0.5, model=model, parameters=values, compiled=True, **kw)
        assert tr.stats["evaluation"] == "compiled"
        fresh = system.with_parameters(values)
        ref = C.simulate(fresh, 0.5, model=assemble(fresh, reuse=False), compiled=False, **kw)
        np.testing.assert_allclose(tr.x[-1], ref.x[-1], rtol=0, atol=1e-11)
    assert len(builds) == 1, "a new parameter value compiled again"
    assert Structure.builds == structures + 2  # the two fresh references only


def test_small_models_and_held_rows_keep_the_unmapped_build():
    model = assemble(chain(12), reuse=False)
    assert not mapped.applies(model)  # 36 coordinates: below MAPPED_FROM
    big = assemble(chain(mapped.MAPPED_FROM // 3), reuse=False)
    assert mapped.applies(big)
    assert not mapped.applies(held(big, range(1, big.n_constraints)))
