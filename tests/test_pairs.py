"""Pair potentials as one mapped kernel (constrained.model.pairs, issue 28): the energy and the
forces of the kernel, with and without a cutoff, against the sum over every pair written out
in CasADi by hand here and differentiated by CasADi; the neighbour list rebuilt as particles
cross its cells; momentum and energy conserved by a gas with a cutoff; the build does not grow
with the pairs (CasADi instructions counted, not seconds)."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

import constrained as C
from constrained.errors import InputError
from constrained.manifold.manifold import Manifold
from constrained.model import pairs
from constrained.model.structure import Structure, assemble


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))


def gas(n: int, *, expr="eps*(s/r)**12", cutoff=None, skin=None, spacing=1.1, jitter=0.08, speed=0.3,
        particles=None, bonds=(), exclude_bonded=False, trap=0.05, seed=1) -> C.System:
    """n particles of unequal masses near a cubic lattice (spacing m) with random velocities of
    zero total momentum, a pairwise potential, and (``trap`` > 0) a weak harmonic trap on each."""
    rng = np.random.default_rng(seed)
    side = math.ceil(n ** (1 / 3))
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    x = (grid - (side - 1) / 2) * spacing + rng.normal(0, jitter, (n, 3))
    m = 1.0 + 0.5 * rng.random(n)
    v = rng.normal(0, speed, (n, 3))
    v -= (m[:, None] * v).sum(0) / m.sum()
    s = C.System(parameters={"eps": 0.7, "s": 0.9})
    for i in range(n):
        s.add_particle(f"p{i}", float(m[i]), x[i], v[i])
    for i, j in bonds:
        s.add(C.Distance(f"p{i}", f"p{j}", length=float(np.linalg.norm(x[i] - x[j]))))
    names = None if particles is None else [f"p{i}" for i in particles]
    s.add(C.Pairwise(expr, names, cutoff=cutoff, skin=skin, exclude_bonded=exclude_bonded))
    if trap:  # V = trap |x_i|² on each
        s.add(*[C.Spring(f"p{i}", point=[0, 0, 0], k=2 * trap) for i in range(n)])
    return s


def reference(system, phi, *, cutoff=None, particles=None, excluded=()):
    """(V(x), F(x)) of the pair sum written out pair by pair in SX (φ a Python function of r),
    F = −∂V/∂x by CasADi; with a cutoff, each pair's φ(r) − φ(rc) − (r − rc) φ'(rc)
    − ½ (r − rc)² φ''(rc) below rc and 0 beyond (the documented shift)."""
    n = system.n_particles
    x = ca.SX.sym("x", 3 * n)
    r = ca.SX.sym("r")
    f = phi(r)
    if cutoff is not None:
        d1 = ca.jacobian(f, r)
        at = [ca.substitute(e, r, ca.SX(cutoff)) for e in (f, d1, ca.jacobian(d1, r))]
        f = ca.if_else(r < cutoff, f - at[0] - (r - cutoff) * at[1] - 0.5 * (r - cutoff) ** 2 * at[2], 0)
    pair = ca.Function("pair", [r], [f])
    listed = list(range(n)) if particles is None else list(particles)
    V = ca.SX(0)
    for a in range(len(listed)):
        for b in range(a + 1, len(listed)):
            i, j = listed[a], listed[b]
            if (i, j) in excluded or (j, i) in excluded:
                continue
            V += pair(ca.norm_2(x[3 * i:3 * i + 3] - x[3 * j:3 * j + 3]))
    return ca.Function("reference", [x], [V, -ca.gradient(V, x)])


def pair_parts(model, x, p=None):
    """(V, F) of the model's pair potentials alone at x: its potential and forces minus those
    of the trap (a Model of the same system without the pairwise effect)."""
    structure = model.structure
    p = model.parameter_vector if p is None else p
    zeros = np.zeros_like(x)
    F = np.asarray(structure.function("dynamics")(x, zeros, 0.0, p)[0]).ravel()
    V = float(structure.function("potential")(x, 0.0, p))
    return V, F


def trap_parts(system, x):
    s = C.System()
    for q in system.particles:
        s.add_particle(q.name, q.mass, q.position)
    s.add(*[e for e in system.effects if not isinstance(e, C.Pairwise)])
    m = assemble(s, reuse=False)
    return float(m.potential(x, 0.0)), np.asarray(m.dynamics(x, np.zeros_like(x), 0.0)[0]).ravel()


def lj_soft(r):
    return 0.7 * (0.9 / r) ** 12


CASES = {
    "all pairs, 45 particles (padded last block)": dict(n=45),
    "all pairs, a subset of 37 with bonds excluded": dict(
        n=50, particles=range(5, 42), bonds=[(5, 6), (6, 7), (20, 30)], exclude_bonded=True),
    "cutoff 1.8 m, 64 particles": dict(n=64, cutoff=1.8),
    "cutoff 1.5 m, skin 0.4 m, 100 particles, bonds excluded": dict(n=100, cutoff=1.5, skin=0.4,
                                                                     bonds=[(0, 1), (1, 2), (50, 51)],
                                                                     exclude_bonded=True),
}


@pytest.mark.parametrize("case", CASES.values(), ids=CASES.keys())
def test_kernel_energy_and_forces_are_the_pair_sum_and_its_gradient(case):
    system = gas(**case)
    model = assemble(system, reuse=False)
    assert len(model.structure.pairs) == 1  # the mapped kernel, not the SX pair sum
    excluded = set(case.get("bonds", ())) if case.get("exclude_bonded") else set()
    ref = reference(system, lj_soft, cutoff=case.get("cutoff"), particles=case.get("particles"),
                    excluded=excluded)
    x = np.asarray(system.positions).ravel()
    rng = np.random.default_rng(4)
    V_trap, F_trap = trap_parts(system, x)
    for sample in (x, x + rng.normal(0, 0.02, x.size)):
        V, F = pair_parts(model, sample)
        V_trap, F_trap = trap_parts(system, sample)
        V_ref, F_ref = (np.asarray(v).ravel() for v in ref(sample))
        assert V - V_trap == pytest.approx(float(V_ref[0]), rel=1e-12, abs=1e-13)
        np.testing.assert_allclose(F - F_trap, F_ref, rtol=1e-10, atol=1e-11 * np.abs(F_ref).max())
        # the bound Model (every pair, no neighbour list) gives the same numbers
        np.testing.assert_allclose(np.asarray(model.dynamics(sample, 0 * sample, 0.0)[0]).ravel(), F,
                                   rtol=1e-11, atol=1e-12 * np.abs(F).max())


def test_a_cutoff_beyond_the_system_gives_the_all_pairs_sum():
    """r^-12 at a cutoff 1000 × the system's size: the shift is ~1e-36 of a pair's energy."""
    plain, cut = gas(60), gas(60, cutoff=1e4)
    x = np.asarray(plain.positions).ravel()
    V0, F0 = pair_parts(assemble(plain, reuse=False), x)
    V1, F1 = pair_parts(assemble(cut, reuse=False), x)
    assert V1 == pytest.approx(V0, rel=1e-13)
    np.testing.assert_allclose(F1, F0, rtol=1e-12, atol=1e-13 * np.abs(F0).max())


def test_parameters_of_the_pair_formula_are_inputs():
    """eps and s are parameters: another value of them builds nothing and scales V as it should."""
    system = gas(40, cutoff=2.0)
    model = assemble(system, reuse=False)
    builds = Structure.builds
    other = model.with_parameters({"eps": 1.4})
    assert Structure.builds == builds
    x = np.asarray(system.positions).ravel()
    V_trap = trap_parts(system, x)[0]
    doubled = 2 * (pair_parts(model, x)[0] - V_trap)
    assert pair_parts(other, x)[0] - V_trap == pytest.approx(doubled, rel=1e-12)


def test_neighbour_list_is_rebuilt_when_particles_cross_cells():
    """A list built at one configuration, the particles then moved by more than half the skin
    (across cells of the Morton grid): the stale list is never used (the graph sums every
    pair: exact), ``PairPotentials.refreshed`` rebuilds it, and the rebuilt one is exact and fast."""
    system = gas(80, cutoff=1.6, skin=0.2)
    model = assemble(system, reuse=False)
    structure = model.structure
    (term,) = structure.pairs
    x0 = np.asarray(system.positions).ravel()
    p0 = model.parameter_vector
    assert structure.pair_potentials.refreshed(p0, x0) is None  # fresh where it was built
    rng = np.random.default_rng(7)
    step = rng.normal(size=(80, 3))
    step *= 0.7 / np.linalg.norm(step, axis=1, keepdims=True)  # every particle moves 0.7 m
    x1 = x0 + step.ravel()
    assert not term.fresh(x1, p0[term.offset:])
    start = term.offset + 1 + 3 * term.n  # the pairs: after valid and x_ref
    end = start + (1 + pairs.ROW) * term.capacity
    pairs0 = p0[start:end]
    p1 = structure.pair_potentials.refreshed(p0, x1)
    assert p1 is not None and term.fresh(x1, p1[term.offset:])
    pairs1 = p1[start:end]
    assert not np.array_equal(pairs0, pairs1)  # other pairs are near
    ref = reference(system, lj_soft, cutoff=1.6)
    V_trap, F_trap = trap_parts(system, x1)
    V_ref, F_ref = (np.asarray(v).ravel() for v in ref(x1))
    for p in (p0, p1):  # stale (every pair) and rebuilt (the list): both exact
        V, F = pair_parts(model, x1, p)
        assert V - V_trap == pytest.approx(float(V_ref[0]), rel=1e-12)
        np.testing.assert_allclose(F - F_trap, F_ref, rtol=1e-10, atol=1e-11 * np.abs(F_ref).max())
    # the run's manifold rebuilds its list as it evaluates far from the start
    manifold = Manifold(model)
    manifold.accelerations(x1, np.zeros_like(x1), 0.0)
    assert term.fresh(x1, manifold._p[term.offset:])


def test_a_list_beyond_its_capacity_is_not_used():
    """All particles crowded into one spot: more neighbour blocks than the room kept for them;
    the data says so (its first entry 0) and the sum goes over every pair, still exact (the bound
    Model's every-pair sum, checked against the written-out sum above)."""
    system = gas(600, cutoff=1.2)
    model = assemble(system, reuse=False)
    (term,) = model.structure.pairs
    x = 0.1 * np.asarray(system.positions).ravel()  # 1000x denser than at the start
    data = term.data(x)
    assert data[0] == 0 and np.isfinite(data).all() and not term.fresh(x, data)
    p = model.parameter_vector.copy()
    p[term.offset:term.offset + term.size] = data
    V, F = pair_parts(model, x, p)
    F_all = np.asarray(model.dynamics(x, 0 * x, 0.0)[0]).ravel()
    assert V == pytest.approx(float(model.potential(x, 0.0)), rel=1e-12)
    np.testing.assert_allclose(F, F_all, rtol=1e-10, atol=1e-11 * np.abs(F_all).max())


def _momentum(traj, masses):
    return np.einsum("n,tnk->tk", masses, traj.v)


def test_gas_with_a_cutoff_keeps_momentum_and_energy():
    """A free gas (no trap) of 90 particles of unequal masses with a cutoff, run long enough
    for particles to leave their blocks (the list is rebuilt during the run): total momentum is
    kept to round-off (the pair forces are equal and opposite) and the energy to the tolerance;
    the run matches the same gas run with no neighbour list (every pair summed)."""
    system = gas(90, cutoff=1.6, skin=0.16, trap=0, speed=1.0)
    model = assemble(system, reuse=False)
    (term,) = model.structure.pairs
    traj = C.simulate(system, 3.0, model=model, rtol=1e-9, atol=1e-9, t_eval=np.linspace(0, 3, 31),
                      outputs={"energy"})
    masses = system.masses
    P = _momentum(traj, masses)
    scale = np.abs(masses[None, :, None] * traj.v).sum(axis=1).max()  # Σ|m v|: round-off's scale
    assert np.max(np.abs(P - P[0])) < 1e-13 * scale
    assert np.ptp(traj.energy) < 1e-7 * np.abs(traj.energy).max()
    moved = np.linalg.norm(traj.x[-1] - traj.x[0], axis=1)
    assert np.median(moved) > 10 * term.skin  # the list was rebuilt many times
    with pytest.MonkeyPatch.context() as patch:  # no list fits: every pair, all the run
        patch.setattr(pairs.neighbours, "pair_rows", lambda y, reach, capacity, excluded=None: None)
        every = C.simulate(system, 3.0, model=assemble(system, reuse=False), rtol=1e-9, atol=1e-9,
                           t_eval=np.linspace(0, 3, 31), outputs=set())
    np.testing.assert_allclose(traj.x, every.x, atol=1e-6)


def test_the_build_does_not_grow_with_the_pairs():
    """The Functions carrying the pairs hold the same CasADi instructions for 41 and 250
    particles (820 and 31,125 pairs); 2,001 particles add one call of the outer map per GROUP
    blocks; the pair kernel is the same size throughout."""
    def sizes(n, cutoff=None):
        s = C.System()
        for i in range(n):
            s.add_particle(f"p{i}", 1.0, [i, 0.1 * i ** 1.5, 0.0])
        s.add(C.Pairwise("1/r", cutoff=cutoff))
        structure = Structure(s)
        (term,) = structure.pairs
        return structure.function("dynamics").n_instructions(), term._pair.n_instructions(), term.n_blocks

    small, large, huge = sizes(41), sizes(250), sizes(2001)
    assert small[0] == large[0]
    groups = math.ceil(huge[2] / pairs.GROUP)
    assert huge[0] <= small[0] + 12 * (groups - 1)
    assert small[1] == large[1] == huge[1]
    with_cutoff = sizes(41, cutoff=3.0), sizes(601, cutoff=3.0)
    assert with_cutoff[1][0] <= with_cutoff[0][0] + 12 * (math.ceil(with_cutoff[1][2] / pairs.GROUP) - 1)


def test_scene_keys_of_a_pairwise_effect(tmp_path):
    text = """
[[particles]]
name = "a"
mass = 1.0
position = [0, 0, 0]
[[particles]]
name = "b"
mass = 1.0
position = [1, 0, 0]
[[constraints]]
type = "distance"
a = "a"
b = "b"
length = 1.0
[[effects]]
type = "pairwise"
expr = "1/r"
cutoff = 2.0
skin = 0.1
exclude_bonded = true
[simulate]
t_end = 0.1
"""
    path = tmp_path / "pair.toml"
    path.write_text(text)
    scene = C.load_scene(path)
    (effect,) = scene.system.effects
    assert (effect.cutoff, effect.skin, effect.exclude_bonded) == (2.0, 0.1, True)
    for bad, says in (("cutoff = -1.0", "positive length"), ('cutoff = "rc"', "positive length"),
                      ("exclude_bonded = 1", "true")):
        path.write_text(text.replace("cutoff = 2.0" if "cutoff" in bad else "exclude_bonded = true", bad))
        with pytest.raises(InputError, match=says):
            C.load_scene(path)
    with pytest.raises(InputError, match="give a cutoff"):
        C.Pairwise("1/r", skin=0.1)


def test_two_particles_on_one_spot_are_refused_at_the_start(tmp_path):
    """1/r with two of 40 particles at the same place: the scene's start check names the
    pairwise effect (its mapped kernel's energy is not finite there)."""
    lines = []
    for i in range(40):
        x = 0.0 if i == 39 else float(i)
        lines.append(f'[[particles]]\nname = "p{i}"\nmass = 1.0\nposition = [{x}, 0, 0]\n')
    lines.append('[[effects]]\ntype = "pairwise"\nexpr = "1/r"\n[simulate]\nt_end = 0.1\n')
    path = tmp_path / "clash.toml"
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"effects\[0\].*undefined at the initial state"):
        C.load_scene(path)


def test_the_energy_along_a_run_uses_each_samples_list():
    """quantities.energy_along with a cutoff: sample by sample through each sample's neighbour
    list, the same numbers as the bound Model's every-pair sum."""
    from constrained.run.quantities import energy_along

    system = gas(70, cutoff=1.5, skin=0.15)
    model = assemble(system, reuse=False)
    rng = np.random.default_rng(2)
    x0 = np.asarray(system.positions).ravel()
    X = np.array([x0 + rng.normal(0, s, x0.size) for s in (0.0, 0.1, 0.3, 0.6)])
    V = rng.normal(size=X.shape)
    t = np.array([0.0, 0.1, 0.2, 0.3])
    every = model.evaluate(model.energy, X, V, t)[0].ravel()
    np.testing.assert_allclose(energy_along(model, X, V, t), every, rtol=1e-12)


@pytest.mark.slow
def test_an_ensemble_runs_a_gas_with_a_cutoff():
    """simulate_many over values of the pair formula's parameter: each variant carries its own
    neighbour list in p (the every-pair sum where it goes stale) and equals its own run."""
    system = gas(30, cutoff=1.6)
    ens = C.simulate_many(system, 0.5, {"eps": [0.5, 1.0]}, rtol=1e-9, atol=1e-11)
    assert all(status == "completed" for status in ens.status)
    one = C.simulate(system, 0.5, parameters={"eps": 1.0}, rtol=1e-9, atol=1e-11, outputs=set(),
                     t_eval=[0.0, 0.5])
    np.testing.assert_allclose(ens.x[1, -1], one.x[-1], atol=1e-8)


def test_a_few_pairs_are_written_out_with_the_same_cutoff_and_exclusions():
    """20 particles (190 pairs, below MAPPED_PAIRS_FROM): the pair sum is the SX graph's, one
    term per pair, with the same shift at the cutoff and the same bonded pairs left out."""
    case = dict(n=20, cutoff=1.5, bonds=[(0, 1), (3, 4)], exclude_bonded=True)
    system = gas(**case)
    model = assemble(system, reuse=False)
    assert model.structure.pairs == ()
    x = np.asarray(system.positions).ravel() + np.random.default_rng(5).normal(0, 0.05, 60)
    V_ref, F_ref = (np.asarray(v).ravel() for v in reference(system, lj_soft, cutoff=1.5,
                                                             excluded={(0, 1), (3, 4)})(x))
    V_trap, F_trap = trap_parts(system, x)
    V, F = pair_parts(model, x)
    assert V - V_trap == pytest.approx(float(V_ref[0]), rel=1e-12)
    np.testing.assert_allclose(F - F_trap, F_ref, rtol=1e-10, atol=1e-11 * np.abs(F_ref).max())


@pytest.mark.parametrize("n", [20, 400])  # written out pair by pair; one mapped kernel
def test_two_particles_on_one_point_are_named_by_the_run_and_the_scene(n, tmp_path, capsys):
    """A pair potential singular at r = 0 with two of N particles started on one point (an
    unfriendly start: a lattice with one bead placed twice). The refusal names the two
    particles, from Python and from a scene file, whichever way the sum is built."""
    from constrained.cli.main import main

    positions = [[0.01 * (i % 20), 0.01 * (i // 20), 0.0] for i in range(n)]
    system = C.System(name="lattice")
    for i, x in enumerate(positions):
        system.add_particle(f"c{i}", 1e-3, x)
    system.add_particle("twice", 1e-3, positions[7])
    system.add(C.Pairwise("1e-9/r**6"))
    with pytest.raises(C.SimulationError) as stop:
        C.simulate(system, 0.01)
    assert "particles 'c7' and 'twice', 0 m apart" in str(stop.value), str(stop.value)

    particles = "\n".join(f'[[particles]]\nname = "c{i}"\nmass = 1e-3\nposition = {x}\n'
                          for i, x in enumerate(positions))
    scene = tmp_path / "lattice.toml"
    scene.write_text(f'[scene]\nname = "lattice"\n{particles}\n[[particles]]\nname = "twice"\nmass = 1e-3\n'
                     f'position = {positions[7]}\n[[effects]]\ntype = "pairwise"\nexpr = "1e-9/r**6"\n'
                     '[simulate]\nt_end = 0.01\n[outputs]\nplots = []\n')
    capsys.readouterr()
    assert main(["check", str(scene)]) == 2
    err = capsys.readouterr().err
    assert "effects[0]" in err and "particles 'c7' and 'twice', start at the same position" in err, err


def test_rattle_refreshes_the_neighbour_list_and_matches_every_pair():
    """The same free gas under ``rattle`` (fixed steps, forces carried from step to step): its
    chained steps stop where a list goes stale and the run rebuilds it (many times: the
    particles move many skins), momentum is kept to round-off, the energy of a symplectic
    method stays bounded, and the run equals the same run summing every pair all along."""
    system = gas(90, cutoff=1.6, skin=0.16, trap=0, speed=1.0)
    model = assemble(system, reuse=False)
    (term,) = model.structure.pairs
    potentials = model.structure.pair_potentials
    rebuilt = []
    original = type(potentials).refreshed

    def counted(self, p, x):
        out = original(self, p, x)
        rebuilt.append(out is not None)
        return out

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(type(potentials), "refreshed", counted)
        traj = C.simulate(system, 3.0, model=model, method="rattle", dt=2e-3,
                          t_eval=np.linspace(0, 3, 31), outputs={"energy"})
    assert sum(rebuilt) >= 5  # the list was rebuilt during the run
    moved = np.linalg.norm(traj.x[-1] - traj.x[0], axis=1)
    assert np.median(moved) > 10 * term.skin
    masses = system.masses
    P = _momentum(traj, masses)
    scale = np.abs(masses[None, :, None] * traj.v).sum(axis=1).max()
    assert np.max(np.abs(P - P[0])) < 1e-13 * scale
    assert np.ptp(traj.energy) < 1e-3 * np.abs(traj.energy).max()  # O(dt²), not drifting
    with pytest.MonkeyPatch.context() as patch:  # no list fits: every pair, all the run
        patch.setattr(pairs.neighbours, "pair_rows", lambda y, reach, capacity, excluded=None: None)
        every = C.simulate(system, 3.0, model=assemble(system, reuse=False), method="rattle", dt=2e-3,
                           t_eval=np.linspace(0, 3, 31), outputs=set())
    np.testing.assert_allclose(traj.x, every.x, atol=1e-9)


def numpy_pair_sum(x, particles, cutoff, excluded=()):
    """(V, F) of lj_soft shifted at the cutoff (φ_c of the module's docstring), summed over the
    pairs of ``particles`` closer than the cutoff by NumPy, the bonded ``excluded`` left out."""
    y = x.reshape(-1, 3)
    listed = np.asarray(list(particles))
    i, j = np.triu_indices(len(listed), 1)
    i, j = listed[i], listed[j]
    keep = np.array([(a, b) not in excluded and (b, a) not in excluded for a, b in zip(i, j, strict=True)])
    i, j = i[keep], j[keep]
    d = y[i] - y[j]
    r = np.linalg.norm(d, axis=1)
    near = r < cutoff
    i, j, d, r = i[near], j[near], d[near], r[near]

    def phi(r):
        return 0.7 * (0.9 / r) ** 12

    rc = cutoff
    d1, d2 = -12 * phi(rc) / rc, 156 * phi(rc) / rc ** 2
    V = np.sum(phi(r) - phi(rc) - (r - rc) * d1 - 0.5 * (r - rc) ** 2 * d2)
    slope = -12 * phi(r) / r - d1 - (r - rc) * d2  # φ_c'(r)
    f = -(slope / r)[:, None] * d  # on i; j takes −f
    F = np.zeros_like(y)
    np.add.at(F, i, f)
    np.add.at(F, j, -f)
    return V, F.ravel()


def test_the_pair_list_kernel_is_the_numpy_sum_within_the_cutoff():
    """A disordered gas (a subset of its particles, bonded pairs excluded) with a cutoff: the
    forces through the pair list (rows of ROW pairs, padded, and empty rows at its end) equal a
    NumPy sum over the pairs within r_c; so do those through a list built before the particles
    moved less than skin/2 (still valid, not rebuilt) and more (stale: every pair summed)."""
    bonds = [(10, 11), (11, 12), (40, 41), (70, 90)]
    system = gas(150, cutoff=1.7, skin=0.3, jitter=0.25, particles=range(5, 140), bonds=bonds,
                 exclude_bonded=True)
    model = assemble(system, reuse=False)
    (term,) = model.structure.pairs
    x0 = np.asarray(system.positions).ravel()
    data = term.data(x0)
    start = 1 + 3 * term.n + term.capacity  # the rows' neighbours J
    n_pairs = int(np.sum(data[start:start + pairs.ROW * term.capacity] < term.n))
    assert 0 < n_pairs < term.n * (term.n - 1) // 2  # a list, not every pair
    assert term.capacity % pairs.GROUP_ROWS == 0 and data[start - 1] == term.n  # empty rows at the end
    rng = np.random.default_rng(11)
    step = rng.normal(size=(150, 3))
    step /= np.linalg.norm(step, axis=1, keepdims=True)
    for moved, fresh in ((0.0, True), (0.1, True), (0.4, False)):  # skin/2 = 0.15 m
        x = x0 + moved * step.ravel()
        assert term.fresh(x, data) == fresh
        p = model.parameter_vector.copy()
        p[term.offset:term.offset + term.size] = data
        V, F = pair_parts(model, x, p)
        V_trap, F_trap = trap_parts(system, x)
        V_ref, F_ref = numpy_pair_sum(x, range(5, 140), 1.7, excluded=set(bonds))
        assert V - V_trap == pytest.approx(V_ref, rel=1e-11)
        np.testing.assert_allclose(F - F_trap, F_ref, rtol=1e-9, atol=1e-10 * np.abs(F_ref).max())


@pytest.mark.parametrize("n", [40, 700])  # pairs found by brute force; by cKDTree
def test_the_pair_rows_hold_every_pair_within_reach_once(n):
    """``neighbours.pair_rows`` on a random cloud: each pair closer than the reach is in exactly
    one row (held by its lower index), no other pair is, a row holds at most ROW, the empty
    places and rows hold the placeholders; a capacity too small gives None."""
    from scipy.spatial.distance import pdist, squareform

    rng = np.random.default_rng(n)
    y = rng.random((n, 3)) * n ** (1 / 3)
    reach = 1.3
    rows_needed = pairs.neighbours.rows_needed(pairs.neighbours.pairs_within(y, reach)[0], n)
    I, J = pairs.neighbours.pair_rows(y, reach, rows_needed + 5)
    R = pairs.ROW
    assert len(I) == rows_needed + 5 and len(J) == R * len(I)
    assert np.all(I[rows_needed:] == n) and np.all(J[R * rows_needed:] == n + 1)
    i = np.repeat(I, R).astype(int)
    j = J.astype(int)
    real = j < n
    found = sorted(zip(i[real].tolist(), j[real].tolist(), strict=True))
    near = np.argwhere(np.triu(squareform(pdist(y)) <= reach, 1))
    assert found == sorted(map(tuple, near.tolist()))
    assert pairs.neighbours.pair_rows(y, reach, rows_needed - 1) is None


def test_dopri_steps_stay_where_the_neighbour_list_holds():
    """An explicit step's stages must not carry a particle past the list's margin (else its
    forces sum every pair: exact, but O(N²)): at a loose tolerance, where dopri's own steps
    would be longer, each accepted step is at most STEP_SHARE · (1 − REFRESH_SHARE) · skin/2
    over the fastest particle's speed at its start, and that bound is what sets them."""
    system = gas(64, cutoff=1.8)  # skin 0.18 m (0.1 r_c)
    run = C.simulate(system, 1.0, method="dopri", rtol=1e-4, atol=1e-6)
    h = np.diff(run.t)
    speed = np.sqrt((run.v[:-1].reshape(len(h), -1, 3) ** 2).sum(-1).max(-1))
    limit = pairs.potentials.STEP_SHARE * (1 - pairs.potentials.REFRESH_SHARE) * 0.18 / 2 / speed
    assert np.all(h <= limit * (1 + 1e-9))
    assert np.mean(np.isclose(h, limit, rtol=1e-9)) > 0.5
    # and the run is the same motion as at a tight tolerance (the limit costs steps, not accuracy)
    tight = C.simulate(system, 1.0, method="dopri", rtol=1e-10, atol=1e-12, t_eval=[0.0, 1.0])
    assert np.abs(run.x[-1] - tight.x[-1]).max() < 1e-3
