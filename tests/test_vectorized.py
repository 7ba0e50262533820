"""The vectorized build (issue 28): a large model's kernels evaluated on whole columns and the
KKT solve's products with J written on J's nonzeros. It must give the Structure's numbers to
round-off — f, J and its products, f_t, γ, forces, energy, row scales, A = J M⁻¹ Jᵀ and its
solve (rows with one coordinate eliminated or not), accelerations, multipliers, projections
and whole dopri runs (the same steps) — on fine discretizations (1 cm links, grams), uneven
masses and lengths, moving anchors, springs, damping, pair forces and rows it does not map."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import constrained as C
from constrained.errors import SceneError
from constrained.manifold import dense, graph, mapped
from constrained.manifold.vectorized import build as vb
from constrained.manifold.vectorized import graphs as vg
from constrained.manifold.vectorized.columns import (
    MAX_SIGNATURES,
    Summation,
    binary,
    on_columns,
    shared_nodes,
    take,
    unique_rows,
)
from constrained.model.cache import ParametricView
from constrained.model.constraints import constraint_rows
from constrained.model.structure import Structure, assemble

LINK, MASS = 0.01, 0.01  # the rope of issue 28: 1 cm links, 10 g


def rope(n: int, *, varied: bool = False, moving: bool = False, extras: bool = False) -> C.System:
    """A planar rope of n particles released bent, hanging from the origin; ``varied``: every
    link and mass different; ``moving``: the anchor and the plane move with t (rheonomic);
    ``extras``: a spring, damping, a pair force and custom rows (what the kernels leave to the rest)."""
    s = C.System(name=f"rope of {n}")
    lengths = [LINK * (1 + 0.3 * np.sin(i) * varied) for i in range(n)]
    masses = [MASS * (1 + 0.5 * np.cos(i) * varied) for i in range(n)]
    angle = np.linspace(0.3, 1.2, n)
    at = np.cumsum(np.c_[np.cos(angle) * lengths, -np.sin(angle) * lengths, np.zeros(n)], axis=0)
    for i in range(n):
        s.add_particle(f"p{i}", masses[i], at[i], [0.0, 0.0, 0.0] if not moving else [0.01 * i, 0.0, 0.0])
    anchor = ["0.002*sin(3*t)", 0.0, 0.0] if moving else [0.0, 0.0, 0.0]
    s.add(C.Distance("p0", point=anchor, length=lengths[0]))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=lengths[i]))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1], "0.001*t" if moving else 0.0),
          C.Gravity([0, -9.81, 0]))
    if extras:
        s.add(C.Spring("p1", f"p{n - 1}", k=0.5, rest=0.02), C.Damping(0.01, ["p2", "p3"]),
              C.Pairwise("-1e-6/r", [f"p{i}" for i in range(0, n, 7)], where="effects[3]"),
              C.Custom(f"x_p{n // 2} - y_p{n // 2} - ({at[n // 2, 0] - at[n // 2, 1]})"))
    return s


def cloth(k: int) -> C.System:
    """A k × k cloth of 1 cm squares, 0.15 g a particle, pinned at two diagonal corners."""
    s = C.System(name=f"cloth {k}")
    for i in range(k):
        for j in range(k):
            s.add_particle(f"q{i}_{j}", 1.5e-4, [i * LINK, j * LINK, 0.002 * np.sin(i + 2 * j)])
    for i in range(k):
        for j in range(k):
            for di, dj in ((1, 0), (0, 1)):
                if i + di < k and j + dj < k:
                    d = np.hypot(LINK * di, LINK * dj)
                    length = float(np.linalg.norm(np.array([di * LINK, dj * LINK, 0.002 * (
                        np.sin(i + di + 2 * (j + dj)) - np.sin(i + 2 * j))])))
                    s.add(C.Distance(f"q{i}_{j}", f"q{i + di}_{j + dj}", length=length or d))
    far = (k - 1) * LINK
    s.add(C.Pin("q0_0", [0, 0, 0.0]), C.Pin(f"q{k - 1}_{k - 1}", [far, far, 0.002 * np.sin(3 * (k - 1))]))
    s.add(C.Gravity([0, 0, -9.81]))
    return s


SYSTEMS = {
    "rope": lambda: rope(60),
    "varied rope": lambda: rope(60, varied=True),
    "moving rope": lambda: rope(60, moving=True),
    "rope with extras": lambda: rope(60, extras=True),
    "cloth": lambda: cloth(8),
}


@pytest.fixture(params=sorted(SYSTEMS))
def system(request):
    return SYSTEMS[request.param]()


def _state(model, system, seed=0):
    rng = np.random.default_rng(seed)
    x = np.asarray(system.positions, float).ravel() + 1e-4 * rng.standard_normal(model.n_coordinates)
    v = 0.1 * rng.standard_normal(model.n_coordinates)
    return x, v, 0.37


def _close(a, b, tol=1e-11):
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = max(1.0, float(np.max(np.abs(b), initial=0.0)))
    assert np.max(np.abs(a - b), initial=0.0) <= tol * scale, np.max(np.abs(a - b)) / scale


def _mx_function(model, graph_of, *inputs):
    """A Function (symbols ``inputs`` of "x", "v", "t", then p) of ``graph_of(view, *symbols)``."""
    sizes = {"x": model.n_coordinates, "v": model.n_coordinates, "t": 1}
    symbols = [ca.MX.sym(k, sizes[k]) for k in inputs]
    P = ca.MX.sym("p", len(model.parameter_vector))
    out = graph_of(vg.VectorizedView(model, P), *symbols)
    out = list(out) if isinstance(out, tuple | list) else [out]
    function = ca.Function("f", [*symbols, P], out)

    def call(*args):
        res = function(*args, model.parameter_vector)
        return [np.array(ca.densify(ca.DM(o))) for o in (res if isinstance(res, tuple) else (res,))]
    return call


def test_the_build_gives_the_structures_f_J_ft_gamma_forces_energy_and_row_scales(system):
    model = assemble(system, reuse=False)
    x, v, t = _state(model, system)
    f, J = model.jacobian(x, t)
    J_t, f_t = model.velocity_terms(x, t)
    F, _, gamma = model.dynamics(x, v, t)
    view_f, view_J = _mx_function(model, lambda m, X, T: m.jacobian(X, T), "x", "t")(x, t)
    _close(view_f, np.array(f))
    _close(view_J, np.array(ca.densify(J)))
    _, vft = _mx_function(model, lambda m, X, T: m.velocity_terms(X, T), "x", "t")(x, t)
    _close(vft, np.array(ca.densify(f_t)))
    vF, _, vgamma = _mx_function(model, lambda m, X, V, T: m.dynamics(X, V, T), "x", "v", "t")(x, v, t)
    _close(vF, np.array(F))
    _close(vgamma, np.array(gamma), 1e-10)
    (E,) = _mx_function(model, lambda m, X, V, T: m.energy(X, V, T), "x", "v", "t")(x, v, t)
    _close(E, np.array(model.energy(x, v, t)))
    (s,) = _mx_function(model, lambda m, X, T: m.row_scales(X, T), "x", "t")(x, t)
    Jd = np.array(ca.densify(J))
    expected = np.max(np.linalg.norm(Jd.reshape(f.numel(), -1, 3), axis=2), axis=1)
    _close(s.ravel(), np.where(expected > 0, expected, 1.0))


def test_J_products_the_gram_and_its_solve_equal_dense_linear_algebra(system):
    model = assemble(system, reuse=False)
    x, v, t = _state(model, system, seed=1)
    Jd = np.array(ca.densify(model.jacobian(x, t)[1]))
    b = vb.vectorized_build(model.structure)
    rng = np.random.default_rng(2)
    y, lam = rng.standard_normal(model.n_coordinates), rng.standard_normal(len(Jd))
    B = rng.standard_normal((len(Jd), 2))
    X, T, Y, L, BB = (ca.MX.sym(k, n, m) for k, n, m in (("x", model.n_coordinates, 1), ("t", 1, 1),
                                                         ("y", model.n_coordinates, 1), ("l", len(Jd), 1),
                                                         ("B", len(Jd), 2)))
    P = ca.MX.sym("p", len(model.parameter_vector))
    Jv = b.evaluate(X, None, T, P, ("J",))["J"]
    minv = 1 / ca.vec(P[model.structure.mass_entries.tolist()])
    outs = [Jv.times(Y), Jv.transpose_times(L), ca.densify(Jv.gram(minv)), Jv.solve(minv, BB)]
    values = ca.Function("f", [X, T, Y, L, BB, P], outs)(x, t, y, lam, B, model.parameter_vector)
    A = Jd @ np.diag(model.inverse_masses) @ Jd.T
    _close(np.array(values[0]).ravel(), Jd @ y)
    _close(np.array(values[1]).ravel(), Jd.T @ lam)
    _close(np.array(values[2]), A)
    _close(np.array(values[3]), np.linalg.solve(A, B), 1e-8)
    if system.name.startswith("rope"):  # the plane's rows, one coordinate each: eliminated
        assert b.single is not None and len(b.single.rows) == system.n_particles


def test_accelerations_multipliers_and_projections_equal_the_unrolled_graphs(system):
    model = assemble(system, reuse=False)
    x, v, t = _state(model, system, seed=3)
    n3, P = model.n_coordinates, ca.MX.sym("p", len(model.parameter_vector))
    X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
    view = ParametricView(model, P)
    for ours, theirs in ((vg.acceleration_graph(view, X, V, T),
                          graph.acceleration_graph(view, X, V, T, linsol="ldl")),
                         (vg.projection_graph(view, X, V, T),
                          graph.projection_graph(view, X, V, T, linsol="ldl")),
                         (vg.position_step_graph(view, X, T), graph.position_step_graph(view, X, T)),
                         ([vg.velocity_correction_graph(view, X, V, T)],
                          [graph.velocity_correction_graph(view, X, V, T)])):
        f = ca.Function("f", [X, V, T, P], [ca.densify(o) for o in (*ours, *theirs)])
        out = [np.array(o) for o in f(x, v, t, model.parameter_vector)]
        for a, b in zip(out[:len(ours)], out[len(ours):], strict=True):
            _close(a, b, 1e-9)


def test_post_processing_of_a_large_model_equals_the_unrolled_route(system, monkeypatch):
    t_eval = np.linspace(0, 0.02, 5)
    runs = {}
    for label, start in (("vectorized", 0), ("unrolled", 10**9)):
        monkeypatch.setattr(vg, "VECTORIZED_FROM", start)
        model = assemble(system, reuse=False)
        runs[label] = C.simulate(system, 0.02, model=model, t_eval=t_eval, rtol=1e-9, atol=1e-12)
    a, b = runs["vectorized"], runs["unrolled"]
    assert a.stats["steps"] == b.stats["steps"]
    _close(a.x, b.x, 1e-10)
    for name in ("multipliers", "constraint_forces", "energy"):
        _close(getattr(a, name), getattr(b, name), 1e-8)
    assert np.max(a.constraint_residual) < 1e-12 and np.max(b.constraint_residual) < 1e-12


def test_a_fine_rope_run_by_dopri_takes_the_unrolled_steps(monkeypatch):
    """300 links of 1 cm and 10 g (900 coordinates: dopri's loop in the virtual machine)."""
    system = rope(300, varied=True)
    assert vg.applies(assemble(system))
    runs = {}
    for label, start in (("vectorized", vg.VECTORIZED_FROM), ("unrolled", 10**9)):
        monkeypatch.setattr(vg, "VECTORIZED_FROM", start)
        model = assemble(system, reuse=False)
        runs[label] = C.simulate(system, 0.05, model=model, rtol=1e-6, atol=1e-6, outputs=["multipliers"])
    a, b = runs["vectorized"], runs["unrolled"]
    assert a.stats["steps"] == b.stats["steps"] and a.stats["rejected"] == b.stats["rejected"]
    assert a.stats["evaluation"] == "virtual machine"
    _close(a.x[-1], b.x[-1], 1e-11)
    _close(a.v[-1], b.v[-1], 1e-8)
    _close(a.multipliers, b.multipliers, 1e-7)


def test_redundant_rows_of_a_large_model_take_the_minimum_norm_multipliers():
    """A doubled rod (dependent rows): the run solves with the independent rows, and the
    multipliers are the minimum-norm ones — the two copies share the load equally."""
    system = rope(120)
    system.add(C.Distance("p40", "p41", length=system.constraints[41].length))
    tr = C.simulate(system, 0.01, t_eval=[0.0, 0.01], rtol=1e-8, atol=1e-10)
    _close(tr.multipliers[:, 41], tr.multipliers[:, -1], 1e-9)
    assert np.all(np.isfinite(tr.constraint_forces))


def test_on_columns_evaluates_a_kernel_as_its_map_does():
    xl, c, t = ca.SX.sym("xl", 4), ca.SX.sym("c", 2), ca.SX.sym("t")
    kernel = ca.Function("k", [xl, c, t], [ca.vertcat(ca.sqrt(ca.sumsqr(xl[:2] - xl[2:])) - c[0],
                                                      c[1] * ca.sin(t) * xl[0], ca.SX(3.5))])
    rng = np.random.default_rng(5)
    Xv, Cv = rng.standard_normal((4, 11)), rng.standard_normal((2, 11))
    X, Cm, T = ca.MX.sym("X", 4, 11), ca.MX.sym("C", 2, 11), ca.MX.sym("t")
    cols = on_columns(kernel, [lambda j: X[j, :].T, lambda j: Cm[j, :].T, [T]], 11)
    ours = ca.Function("f", [X, Cm, T], [ca.horzcat(*cols[0])])(Xv, Cv, 0.7)
    theirs = kernel.map(11)(Xv, Cv, 0.7)
    _close(np.array(ours).T, np.array(theirs), 1e-15)


def test_shared_nodes_give_one_node_per_operation_on_the_same_nodes():
    """Within shared_nodes (dopri's step: a dozen accelerations at one p) the same gather or
    operation of the same nodes is one node; a different index, or outside, is another; the
    values are the gathers' (arithmetic progressions are slices)."""
    x = ca.MX.sym("x", 12)
    rng = np.random.default_rng(3)
    xv = rng.standard_normal(12)
    with shared_nodes():
        a, b = take(x, np.arange(2, 12, 3)), take(x, np.array([2, 5, 8, 11]))
        c = take(x, np.array([2, 5, 11, 8]))
        assert hash(a) == hash(b) and hash(c) != hash(a)
        assert hash(binary(ca.OP_MUL, a, c)) == hash(binary(ca.OP_MUL, a, c))
        assert hash(binary(ca.OP_MUL, a, c)) != hash(binary(ca.OP_MUL, c, a))
        both = take(ca.vertcat(x, 2 * x), np.arange(0, 24, 5))
        out = ca.Function("f", [x], [ca.vertcat(a, c, binary(ca.OP_MUL, a, c), both)])(xv)
    assert hash(take(x, np.arange(2, 12, 3))) != hash(take(x, np.arange(2, 12, 3)))
    expected = np.r_[xv[[2, 5, 8, 11]], xv[[2, 5, 11, 8]], xv[[2, 5, 8, 11]] * xv[[2, 5, 11, 8]],
                     np.r_[xv, 2 * xv][np.arange(0, 24, 5)]]
    _close(np.array(out).ravel(), expected, 1e-15)


@pytest.mark.parametrize("streams", [3, MAX_SIGNATURES + 40])
def test_summation_adds_every_entry_into_its_target(streams):
    """Regular and irregular index data (beyond MAX_SIGNATURES signatures: a sparse product),
    targets nobody names stay 0."""
    rng = np.random.default_rng(streams)
    lengths = [int(k) for k in rng.integers(1, 30, streams)]
    targets = [rng.integers(0, 60, k) for k in lengths]
    values = [rng.standard_normal(k) for k in lengths]
    summation = Summation(lengths, targets, 70)
    symbols = [ca.MX.sym(f"s{i}", k) for i, k in enumerate(lengths)]
    out = np.array(ca.Function("f", symbols, [summation(symbols)])(*values)).ravel()
    expected = np.zeros(70)
    for t, v in zip(targets, values, strict=True):
        np.add.at(expected, t, v)
    _close(out, expected, 1e-14)


def test_rows_of_one_shape_and_different_formulas_are_grouped_apart():
    """Custom rows with the same coordinates and numbers of entries but (more than MAX_KINDS)
    different formulas: each formula its own kernel (or the rest), none mixed up."""
    s = C.System(name="many formulas")
    n = 9 * (mapped.MAX_KINDS + 2)
    for i in range(n + 1):
        s.add_particle(f"p{i}", 1.0, [i * 0.1, 0.05 * np.sin(i), 0.0])
    for i in range(n):
        k = i % (mapped.MAX_KINDS + 2)
        s.add(C.Custom(f"(x_p{i + 1} - x_p{i})**2 + {k + 1}*(y_p{i + 1} - y_p{i})**2 - 0.01"))
    structure = Structure(s)
    build = mapped.mapped_build(structure)
    x = np.asarray(s.positions, float).ravel() + 0.01
    p = np.zeros(structure.expressions.p.numel())
    f_mapped = np.array(build.function("constraint")(x, 0.0, p))
    f_ref = np.array(structure.function("constraint")(x, 0.0, p))
    _close(f_mapped, f_ref, 1e-14)
    assert sum(g.index.shape[1] for g in build.rows) + len(build.rest_place) == n


def test_rods_built_together_are_the_expressions_each_rod_builds():
    from constrained.model import lifting
    from constrained.model.symbols import Symbols

    system, numbers = lifting.lift(rope(80, varied=True))
    s = Symbols(system, symbolic_parameters=True, numbers=len(numbers))
    pieces, batches = constraint_rows(system.constraints, s)
    assert batches  # (the rods of plain lengths: one formula)
    assert any(count > 1 for _, count, _ in pieces)  # (a column of rods kept whole)
    together = []
    for k, count, rows in pieces:  # (first constraint, count, its rows or (column, labels))
        if isinstance(rows, tuple):  # count constraints of one row each, or one of many (a plane)
            column, labels = rows
            assert column.numel() == len(labels) and (count == 1 or count == len(labels))
            pairs = [(column[i], labels[i]) for i in range(len(labels))]
            together += [pairs] if count == 1 else [[pair] for pair in pairs]
        else:
            assert count == 1 and k == len(together)
            together.append(rows)
    alone = [c.rows(s) for c in system.constraints]
    assert [len(r) for r in together] == [len(r) for r in alone]
    for a, b in zip(together, alone, strict=True):
        for (ea, la), (eb, lb) in zip(a, b, strict=True):
            assert la == lb and ca.is_equal(ea, eb, 50)


def test_the_start_check_of_a_large_model_names_a_rod_on_its_anchor(tmp_path):
    """A large scene (vectorized start check): a particle on its rod's anchor is refused at
    load time with the rod's key."""
    n = 120
    lines = [f'[[particles]]\nname = "p{i}"\nmass = 0.01\nposition = [{(i + 1) * LINK}, 0.0, 0.0]\n'
             for i in range(n)]
    lines[0] = '[[particles]]\nname = "p0"\nmass = 0.01\nposition = [0.0, 0.0, 0.0]\n'
    lines.append('[[constraints]]\ntype = "distance"\na = "p0"\npoint = [0.0, 0.0, 0.0]\nlength = 0.01\n')
    lines += [f'[[constraints]]\ntype = "distance"\na = "p{i - 1}"\nb = "p{i}"\nlength = {LINK}\n'
              for i in range(2, n)]
    lines.append('[[effects]]\ntype = "gravity"\ng = [0.0, -9.81, 0.0]\n[simulate]\nt_end = 0.1\n')
    path = tmp_path / "rope.toml"
    path.write_text("\n".join(lines))
    with pytest.raises(SceneError) as refused:
        C.load_scene(path)
    assert "constraints[0]" in str(refused.value)
    assert "undefined at the initial state" in str(refused.value)


def test_dense_checks_still_use_the_dense_route():
    """A small model keeps the unrolled build everywhere (the vectorized one starts at
    VECTORIZED_FROM coordinates)."""
    model = assemble(rope(20))
    assert not vg.applies(model) and dense is not None


@pytest.mark.parametrize("shape, top", [((20000, 3), 5), ((1000, 7), 40), ((50, 2), 2), ((0, 1), 1),
                                        ((30, 40), 10**6)])
def test_unique_rows_is_numpys_unique_of_rows(shape, top):
    """The integer-key unique of the Summation's signatures equals np.unique(axis=0): the same
    rows, in the same order, the same inverse (the last case too wide for one key)."""
    a = np.random.default_rng(1).integers(-1, top, size=shape)
    kinds, inverse = np.unique(a, axis=0, return_inverse=True)
    got_kinds, got_inverse = unique_rows(a)
    assert np.array_equal(kinds, got_kinds) and np.array_equal(inverse.ravel(), got_inverse)


def test_a_chain_spinning_in_free_space_with_no_effects_runs_as_a_rigid_rotation():
    """120 beads on a chain pinned at the origin, no gravity nor any other effect, spinning about
    z at ω (the vectorized build in the virtual machine: 360 coordinates). Its step graph took
    x, v and t as free symbols where F has no effect to come from, and every such run failed
    with a CasADi traceback. The straight chain turns rigidly: x_k(t) = r_k (cos ωt, sin ωt, 0),
    and rod k pulls with the centripetal force of the beads beyond it, ω² Σ_{j≥k} m_j r_j."""
    n, link, omega = 120, 0.01, 3.0
    masses = 0.01 * (1 + 0.5 * np.cos(np.arange(n)))  # (uneven: the tension is no simple formula)
    r = link * np.arange(1, n + 1)
    s = C.System(name="spinning chain")
    for i in range(n):
        s.add_particle(f"p{i}", float(masses[i]), [r[i], 0.0, 0.0], velocity=[0.0, omega * r[i], 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=link))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=link))
    T = 0.4
    traj = C.simulate(s, T, method="dopri", rtol=1e-10, atol=1e-12, t_eval=[0.0, T],
                      outputs=["multipliers"], compiled=False)
    expected = r[:, None] * np.array([np.cos(omega * T), np.sin(omega * T), 0.0])
    np.testing.assert_allclose(traj.x[-1], expected, atol=1e-9)
    tension = omega**2 * np.cumsum((masses * r)[::-1])[::-1]
    np.testing.assert_allclose(np.abs(traj.multipliers[-1]), tension, rtol=1e-7)


def test_the_sparse_jacobian_kept_at_one_state_is_given_there_alone():
    """``manifold.sparse_jacobian`` keeps its last value: asked again at the same x and t it gives
    it, at any other x or t (a moving anchor: J depends on t) the Jacobian there — each equal
    to the Structure's J, never a stale one."""
    from constrained.manifold.manifold import sparse_jacobian

    model = assemble(rope(120, varied=True, moving=True))
    assert vg.applies(model)
    x0 = np.asarray(model.system.positions, float).ravel()
    x1 = x0 + 1e-3 * np.sin(np.arange(x0.size))
    jacobian = sparse_jacobian(model)
    for x, t in ((x0, 0.0), (x0, 0.0), (x1, 0.0), (x0, 0.0), (x0, 0.7), (x1, 0.7), (x1, 0.7)):
        J = jacobian(x, t)
        expected = np.asarray(ca.DM(model.velocity_terms(x, t)[0]).full())
        assert np.max(np.abs(np.asarray(J.full()) - expected)) < 1e-12
    assert jacobian(x1, 0.7) is jacobian(x1.copy(), 0.7)  # (the kept one: no second evaluation)


def test_the_start_checks_of_forces_share_one_evaluation_with_the_structures_numbers():
    """scene.build's check of a large model's potentials (``potential_forces_finite``) and the
    run's check of a finite start (run.simulate) share ``manifold.forces_and_energy`` (on numbers
    for a structure's first calls, tests/test_at_point.py, then one Function built once per
    structure): F and the energy there are the Structure's, and a non-finite force is seen."""
    from constrained.manifold import manifold
    from constrained.model.cache import structure_cache
    from constrained.run import simulate

    model = assemble(rope(120, varied=True))
    x0, v0 = (np.asarray(a, float).ravel() for a in (model.system.positions, model.system.velocities))
    v0 = v0 + 0.1 * np.cos(np.arange(v0.size))
    assert manifold.potential_forces_finite(model)(x0, v0, 0.0)
    cache, prefix = structure_cache(model)
    assert cache[(*prefix, "numeric calls", "forces_and_energy")] == 1
    F, E = simulate.forces_and_energy(model)(x0, v0, 0.0)  # (the name the run calls)
    assert cache[(*prefix, "numeric calls", "forces_and_energy")] == 2
    _close(F, np.asarray(model.dynamics(x0, v0, 0.0)[0], float).ravel(), 1e-12)
    _close(E, float(model.energy(x0, v0, 0.0)), 1e-12)
    x_bad = x0.copy()
    x_bad[4] = np.nan
    assert not manifold.potential_forces_finite(model)(x_bad, v0, 0.0)


@pytest.mark.parametrize("name", sorted(SYSTEMS) + ["large rope"])
def test_a_velocity_at_rest_is_projected_without_a_solve_to_what_the_solve_gives(name):
    """``graph.no_velocity_correction``: v = +0.0 everywhere with no f_t stays v (the solve's
    v − dv, bit for bit, and its counters); a moving constraint, −0.0 or any motion solve."""
    from constrained.manifold.manifold import Manifold
    from constrained.model.structure import Model

    no_velocity_correction = graph.no_velocity_correction
    system = rope(120, varied=True) if name == "large rope" else SYSTEMS[name]()  # (the vectorized build)
    model = Model(system, structure=Structure(system))
    x = np.asarray(system.positions, float).ravel()
    rest = np.zeros(model.n_coordinates)
    signed = rest.copy()
    signed[4] = -0.0
    assert no_velocity_correction(model, rest) == (not model.rheonomic)
    assert not no_velocity_correction(model, signed)
    assert not no_velocity_correction(model, _state(model, system)[1])
    m = Manifold(model)
    (dv,) = m._fast.velocity_correction(x, rest, 0.37, model.parameter_vector)
    solved = rest - dv
    got = m.project_velocities(x, rest, 0.37)
    assert np.array_equal(got, solved)
    assert not model.rheonomic or np.any(got)  # (a moving anchor: a velocity to reach)
    assert (m.counters.njev, m.counters.nlu) == (1, 1)
