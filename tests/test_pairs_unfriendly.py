"""Pair forces on scenes nobody in this repository chose (docs/hard-cases.md, section 12): closed-form
two-body physics (a Lennard-Jones dimer and trimer, a Kepler pair of a gram and a kilogram, a head-on
scattering across the cutoff), short bonds inside a repulsion with their pairs excluded, a fast particle
through a lattice, a collision and a skin far below the motion diagnosed by name."""

from __future__ import annotations

import math

import numpy as np
import pytest

import constrained as C
from constrained.model import pairs
from constrained.model.pairs import kernel
from constrained.model.structure import assemble

LJ = "4*eps*((s/r)**12 - (s/r)**6)"


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))


def lj(r, eps=1.0, s=1.0):
    """φ, φ', φ'' of the Lennard-Jones potential at r."""
    a, b = (s / r) ** 12, (s / r) ** 6
    return 4 * eps * (a - b), 4 * eps * (-12 * a + 6 * b) / r, 4 * eps * (156 * a - 42 * b) / r ** 2


def lj_cut(r, rc, eps=1.0):
    """φ_c, φ_c', φ_c'' of docs/scene-format.md: φ − φ(r_c) − (r − r_c) φ'(r_c) − ½ (r − r_c)² φ''(r_c)."""
    (p, d1, d2), (pc, d1c, d2c) = lj(r, eps), lj(rc, eps)
    return p - pc - (r - rc) * d1c - 0.5 * (r - rc) ** 2 * d2c, d1 - d1c - (r - rc) * d2c, d2 - d2c


def dimer(m1, m2, r, cutoff=None, v=0.0):
    """Two particles on the x axis r apart, centre of mass at rest at the origin; ``v`` the
    relative speed (closing)."""
    M = m1 + m2
    s = C.System(parameters={"eps": 1.0, "s": 1.0})
    s.add_particle("light", m1, [-m2 / M * r, 0, 0], [m2 / M * v, 0, 0])
    s.add_particle("heavy", m2, [m1 / M * r, 0, 0], [-m1 / M * v, 0, 0])
    s.add(C.Pairwise(LJ, cutoff=cutoff))
    return s


# --- closed-form two- and three-body physics ---------------------------------------------------
def test_lennard_jones_dimer_of_a_gram_and_a_kilogram_oscillates_at_its_reduced_mass():
    """ω² = φ''(r₀)/μ, μ = m₁m₂/(m₁ + m₂), r₀ = 2^(1/6) σ: from the normal modes, and from the
    period of a small oscillation run by dopri (the distance's upward crossings of its mean)."""
    m1, m2 = 1e-3, 1.0
    mu, r0 = m1 * m2 / (m1 + m2), 2 ** (1 / 6)
    omega = math.sqrt(lj(r0)[2] / mu)
    modes = C.modes(dimer(m1, m2, 1.1))
    assert np.max(np.abs(modes.eigenvalues.imag)) == pytest.approx(omega, rel=1e-9)
    period = 2 * math.pi / omega
    run = C.simulate(dimer(m1, m2, r0 + 1e-4), 3 * period, rtol=1e-11, atol=1e-14,
                     t_eval=np.linspace(0, 3 * period, 601))
    d = np.linalg.norm(run.x[:, 1] - run.x[:, 0], axis=1)
    d = d - d.mean()
    k = np.where((d[:-1] < 0) & (d[1:] >= 0))[0]
    ups = run.t[k] - d[k] * (run.t[k + 1] - run.t[k]) / (d[k + 1] - d[k])
    assert np.mean(np.diff(ups)) == pytest.approx(period, rel=1e-5)  # (O(a²) anharmonic shift: 2e-7)


def test_a_cutoff_moves_the_dimers_minimum_as_the_documented_shift_says():
    """With r_c = 2.5 σ the pair term is φ_c: its minimum r* (φ_c'(r*) = 0, found here by
    Newton) and ω² = φ_c''(r*)/μ, not φ's — 0.3 % longer and 3 % slower than the plain LJ
    dimer (the cost of smoothing to second order, docs/scene-format.md)."""
    m1, m2, rc = 1e-3, 1.0, 2.5
    mu = m1 * m2 / (m1 + m2)
    r = 2 ** (1 / 6)
    for _ in range(50):
        _, d1, d2 = lj_cut(r, rc)
        r -= d1 / d2
    eq = C.equilibrium(dimer(m1, m2, 1.1, cutoff=rc))
    assert np.linalg.norm(eq.x[1] - eq.x[0]) == pytest.approx(r, rel=1e-10)
    modes = C.modes(dimer(m1, m2, 1.1, cutoff=rc))
    omega = math.sqrt(lj_cut(r, rc)[2] / mu)
    assert np.max(np.abs(modes.eigenvalues.imag)) == pytest.approx(omega, rel=1e-8)
    plain = math.sqrt(lj(2 ** (1 / 6))[2] / mu)
    assert 0.02 < 1 - omega / plain < 0.05 and 0.002 < r / 2 ** (1 / 6) - 1 < 0.004


def test_the_pair_parameter_scales_the_frequency_without_a_rebuild():
    """ω ∝ √ε: modes(parameters={"eps": 4}) doubles the dimer's frequency."""
    system = dimer(1.0, 3.0, 1.1)
    w1 = np.max(np.abs(C.modes(system).eigenvalues.imag))
    w4 = np.max(np.abs(C.modes(system, parameters={"eps": 4.0}).eigenvalues.imag))
    assert w4 == pytest.approx(2 * w1, rel=1e-9)


def test_a_free_lennard_jones_trimer_rests_as_an_equilateral_triangle_with_its_modes():
    """Three equal masses m: sides 2^(1/6) σ, and (no tension at φ's minimum) the modes of a
    triangle of springs k = φ''(r₀): breathing ω² = 3k/m, the pair E ω² = 3k/(2m), the rest 0.
    (Statics and modes of a system without constraints: both raised ValueError before.)"""
    m = 2.0
    s = C.System(parameters={"eps": 1.0, "s": 1.0})
    for name, x in (("a", [0, 0, 0]), ("b", [1.2, 0.05, 0]), ("c", [0.5, 1.0, 0.1])):
        s.add_particle(name, m, x)
    s.add(C.Pairwise(LJ))
    eq = C.equilibrium(s)
    sides = [np.linalg.norm(eq.x[i] - eq.x[j]) for i, j in ((0, 1), (1, 2), (0, 2))]
    np.testing.assert_allclose(sides, 2 ** (1 / 6), rtol=1e-10)
    k = lj(2 ** (1 / 6))[2]
    omega = np.sort(np.abs(C.modes(s).eigenvalues.imag))[::2]  # (±iω pairs)
    np.testing.assert_allclose(omega[-3:], [math.sqrt(1.5 * k / m)] * 2 + [math.sqrt(3 * k / m)], rtol=1e-9)
    assert np.all(omega[:-3] < 1e-6 * omega[-1])


def test_a_kepler_pair_of_a_gram_and_a_kilogram():
    """V = −G m₁ m₂ / r, e = 0.6: after one period T = 2π √(a³/(G M)) the relative position
    returns, at T/2 the distance is a(1 + e), the energy is −G m₁ m₂/(2a) and the angular
    momentum about the centre of mass is kept."""
    G, m1, m2, e, rp = 1.0, 1e-3, 1.0, 0.6, 1.0
    M, a = m1 + m2, rp / (1 - e)
    vp = math.sqrt(G * M * (1 + e) / rp)
    period = 2 * math.pi * math.sqrt(a ** 3 / (G * M))
    s = C.System(parameters={"G": G, "m1": m1, "m2": m2})
    s.add_particle("planet", m1, [m2 / M * rp, 0, 0], [0, m2 / M * vp, 0])
    s.add_particle("star", m2, [-m1 / M * rp, 0, 0], [0, -m1 / M * vp, 0])
    s.add(C.Pairwise("-G*m1*m2/r"))
    run = C.simulate(s, period, rtol=1e-11, atol=1e-14, t_eval=[0, period / 2, period])
    rel = run.x[:, 0] - run.x[:, 1]
    assert np.linalg.norm(rel[-1] - rel[0]) < 1e-7 * rp
    assert np.linalg.norm(rel[1]) == pytest.approx(a * (1 + e), rel=1e-9)
    np.testing.assert_allclose(run.energy, -G * m1 * m2 / (2 * a), rtol=1e-9)
    L = m1 * np.cross(run.x[:, 0], run.v[:, 0]) + m2 * np.cross(run.x[:, 1], run.v[:, 1])
    np.testing.assert_allclose(L[:, 2], m1 * m2 / M * rp * vp, rtol=1e-10)


@pytest.mark.parametrize("method", ["dopri", "rodas"])
def test_head_on_scattering_across_the_cutoff(method):
    """A gram thrown at a kilogram from exactly the cutoff, into a well of ε = 1e-4 J (set by
    ``parameters=``, 2.2 times its relative energy): it turns where φ_c(r) = ½ μ v² and comes
    back out past r_c with its relative speed v (the energy of φ_c is kept across r_c)."""
    m1, m2, rc, v, eps = 1e-3, 1.0, 1.5, 0.3, 1e-4
    mu = m1 * m2 / (m1 + m2)
    run = C.simulate(dimer(m1, m2, rc, cutoff=rc, v=v), 12.0, method=method, rtol=1e-10, atol=1e-13,
                     t_eval=np.linspace(0, 12, 4801), parameters={"eps": eps})
    d = np.linalg.norm(run.x[:, 1] - run.x[:, 0], axis=1)
    lo, hi = 0.9, 2 ** (1 / 6)  # φ_c falls from above ½ μ v² to its minimum between them: bisect
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if lj_cut(mid, rc, eps)[0] > 0.5 * mu * v * v else (lo, mid)
    assert d.min() == pytest.approx(lo, abs=1e-5)  # (sampled every 2.5 ms; the turn is slow)
    assert d[-1] > 2 * rc
    relative = run.v[-1, 0] - run.v[-1, 1]
    assert np.linalg.norm(relative) == pytest.approx(v, rel=1e-8)
    assert np.ptp(run.energy) < 1e-8 * 0.5 * mu * v * v


# --- excluded pairs ------------------------------------------------------------------------------
def dumbbells(k: int, bond: float, cutoff=None):
    """k rigid dumbbells (rods of ``bond``) on a lattice of spacing 2, r⁻¹² between all beads,
    the rods' own pairs excluded."""
    rng = np.random.default_rng(3)
    side = math.ceil(k ** (1 / 3))
    centres = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:k] * 2.0
    s = C.System()
    x = []
    for c in centres:
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        x += [c - bond / 2 * u, c + bond / 2 * u]
    for i, p in enumerate(x):
        s.add_particle(f"p{i}", 1.0, p)
    for i in range(k):
        s.add(C.Distance(f"p{2 * i}", f"p{2 * i + 1}", length=bond))
    s.add(C.Pairwise("1/r**12", cutoff=cutoff, exclude_bonded=True))
    return s, np.ravel(x)


def unbonded_sum(x, rc=None):
    """(V, F) over every pair but the dumbbells' own, by NumPy (shifted at rc as documented)."""
    X = x.reshape(-1, 3)
    i, j = np.triu_indices(len(X), 1)
    keep = ~((j == i + 1) & (i % 2 == 0))
    i, j = i[keep], j[keep]
    d = X[i] - X[j]
    r = np.linalg.norm(d, axis=1)
    v, g = r ** -12.0, -12 * r ** -13.0
    if rc is not None:
        v = v - rc ** -12 + 12 * rc ** -13 * (r - rc) - 78 * rc ** -14 * (r - rc) ** 2
        g = g + 12 * rc ** -13 - 156 * rc ** -14 * (r - rc)
        v, g = np.where(r < rc, v, 0), np.where(r < rc, g, 0)
    f = -(g / r)[:, None] * d
    F = np.zeros_like(X)
    np.add.at(F, i, f)
    np.add.at(F, j, -f)
    return v.sum(), F.ravel()


@pytest.mark.parametrize("cutoff", [None, 3.0])
@pytest.mark.parametrize("cells", [True, False])
def test_a_short_bond_inside_the_repulsion_is_left_out_not_subtracted(cutoff, cells, monkeypatch):
    """27 dumbbells of 0.01 m inside an r⁻¹² repulsion (a bonded pair's φ = 1e24): the mapped
    kernel (1,431 pairs) gives the energy and forces of the other pairs to round-off, through
    the neighbour list (cell list in C, or SciPy's tree) and through every pair. Subtracting
    the excluded pairs after the sums, as before, lost every other force (100 % error)."""
    monkeypatch.setattr(kernel, "CELLS", cells)
    system, x = dumbbells(27, 0.01, cutoff)
    model = assemble(system, reuse=False)
    assert len(model.structure.pairs) == 1
    V_ref, F_ref = unbonded_sum(x, cutoff)
    scale = np.abs(F_ref).max()
    structure, p = model.structure, model.parameter_vector
    listed = np.asarray(structure.function("dynamics")(x, 0 * x, 0.0, p)[0]).ravel()
    every = np.asarray(model.dynamics(x, 0 * x, 0.0)[0]).ravel()
    for F in (listed, every):
        np.testing.assert_allclose(F, F_ref, rtol=0, atol=1e-12 * scale)
    assert float(structure.function("potential")(x, 0.0, p)) == pytest.approx(V_ref, rel=1e-12)
    assert float(model.potential(x, 0.0)) == pytest.approx(V_ref, rel=1e-12)


def test_a_gas_of_short_dumbbells_in_their_own_repulsion_conserves_energy():
    """27 dumbbells of 0.05 m (bonded φ = 4e15 J) flying apart at about 1 m/s, under dopri (the
    fused list), rodas (the differentiable every-pair sum) and rattle: the energy is kept and the
    rods hold (subtracted, the bonded pairs swamped every force of the gas)."""
    system, _ = dumbbells(27, 0.05, cutoff=3.0)
    rng = np.random.default_rng(8)
    for q in system.particles:
        q.velocity = rng.normal(0, 0.5, 3)
    model = assemble(system, reuse=False)
    for method, options in (("dopri", {}), ("rodas", {}), ("rattle", {"dt": 5e-4})):
        run = C.simulate(system, 0.02, model=model, method=method, rtol=1e-9, atol=1e-11,
                         t_eval=[0, 0.01, 0.02],
                         **options)
        kinetic = 0.5 * np.sum(system.masses[None, :, None] * run.v ** 2, axis=(1, 2))
        assert np.ptp(run.energy) < 1e-6 * kinetic.max(), method
        bonds = np.linalg.norm(run.x[:, 1::2] - run.x[:, ::2], axis=2)
        np.testing.assert_allclose(bonds, 0.05, rtol=1e-9)


# --- neighbour lists and diagnoses -------------------------------------------------------------
def test_a_fast_particle_through_a_lattice_meets_every_neighbour():
    """A 1 g bullet at 400 m/s through a lattice of 54 beads (spacing 0.7, cutoff 0.8, skin 0.05:
    it crosses a skin in 0.1 ms): the run through neighbour lists equals the one summing every
    pair, and the bullet is deflected (it met the beads)."""
    def scene():
        s = C.System()
        grid = np.stack(np.meshgrid(np.arange(6), np.arange(3), np.arange(3), indexing="ij"), -1)
        for i, p in enumerate(grid.reshape(-1, 3) * 0.7):
            s.add_particle(f"p{i}", 1.0, p)
        s.add_particle("bullet", 1e-3, [-3, 0.72, 0.73], [400.0, 0, 0])
        s.add(C.Pairwise("0.01/r**6", cutoff=0.8, skin=0.05))
        return s

    times = np.linspace(0, 0.03, 7)
    listed = C.simulate(scene(), 0.03, model=assemble(scene(), reuse=False), rtol=1e-10, atol=1e-12,
                        t_eval=times)
    with pytest.MonkeyPatch.context() as patch:  # no list ever: every pair, all the run
        patch.setattr(kernel, "CELLS", False)
        patch.setattr(pairs.neighbours, "pair_rows", lambda y, reach, capacity, excluded=None: None)
        every = C.simulate(scene(), 0.03, model=assemble(scene(), reuse=False), rtol=1e-10, atol=1e-12,
                           t_eval=times)
    np.testing.assert_allclose(listed.x, every.x, atol=1e-6)
    assert listed.v[-1, -1, 0] < 0  # bounced back
    assert np.ptp(listed.energy) < 1e-8 * np.abs(listed.energy).max()


@pytest.mark.parametrize("n", [2, 30])  # written out; one mapped kernel
def test_a_collision_under_an_attraction_names_the_pair(n):
    """A gram falling straight onto a kilogram under −1/r (no angular momentum: r → 0 in finite
    time): the stop names the pair effect and the two particles closing in."""
    s = C.System()
    for i in range(n - 2):
        s.add_particle(f"q{i}", 1.0, [10 + 3 * i, 0, 0])
    s.add_particle("a", 1e-3, [0, 0, 0])
    s.add_particle("b", 1.0, [1, 0, 0])
    s.add(C.Pairwise("-1/r", cutoff=5.0))
    with pytest.raises(C.SimulationError) as stop:
        C.simulate(s, 2.0)
    message = str(stop.value)
    assert "effect 0's ('pairwise" in message and "particles 'a' and 'b'" in message, message


def test_a_skin_far_below_the_motion_is_named_when_the_steps_collapse():
    """cutoff 1e-20 m (a skin of 1e-21 m) among particles moving 0.3 m/s: the list allows steps of
    1e-21 s; the collapse names the list, its skin and the fastest particle (it said "forces that
    blow up ... acceleration 0 m/s²")."""
    rng = np.random.default_rng(0)
    s = C.System()
    for i, (x, v) in enumerate(zip(rng.uniform(0, 1, (30, 3)), rng.normal(0, 0.1, (30, 3)), strict=True)):
        s.add_particle(f"p{i}", 1.0, x, v)
    s.add(C.Pairwise("1e-3/r**6", cutoff=1e-20))
    with pytest.raises(C.SimulationError) as stop:
        C.simulate(s, 0.1)
    message = str(stop.value)
    assert "neighbour list of 'pairwise" in message and "skin, 1e-21 m" in message, message
    assert "acceleration 0" not in message


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", '"2"'])
def test_a_cutoff_that_is_no_length_is_refused_naming_the_key(value, tmp_path):
    path = tmp_path / "cut.toml"
    path.write_text('[[particles]]\nname = "a"\nmass = 1.0\nposition = [0, 0, 0]\n'
                    '[[particles]]\nname = "b"\nmass = 1.0\nposition = [1.5, 0, 0]\n'
                    f'[[effects]]\ntype = "pairwise"\nexpr = "1/r**12"\ncutoff = {value}\n')
    with pytest.raises(C.InputError, match=r"effects\[0\]\.cutoff"):
        C.load_scene(path)


def test_a_scene_of_rods_with_a_cut_off_pair_force_passes_its_start_check(tmp_path):
    """Found by a differential probe (session 17): a chain of 30 rods of 10 cm with a pairwise
    1e-6/r⁶ cut off at 0.35 m, read from a scene, stopped with a CasADi traceback in the scene's
    start check (its parameter vector lacked the pair potential's neighbour list: 403 entries
    where 3,308 were expected on 200 beads). It runs now, and its energy (the pair potential
    included) is kept to the run's tolerance."""
    from constrained.cli.main import main

    n = 30
    lines = ["[scene]", 'name = "chain with a cut-off pair force"']
    for i in range(n):
        lines += ["[[particles]]", f'name = "p{i}"', "mass = 0.01",
                  f"position = [{0.1 * (i + 1):.3f}, 0.0, 0.0]"]
    lines += ["[[constraints]]", 'type = "distance"', 'a = "p0"', "point = [0.0, 0.0, 0.0]", "length = 0.1"]
    for i in range(n - 1):
        lines += ["[[constraints]]", 'type = "distance"', f'a = "p{i}"', f'b = "p{i + 1}"', "length = 0.1"]
    lines += ["[[effects]]", 'type = "gravity"', "g = [0.0, -9.81, 0.0]",
              "[[effects]]", 'type = "pairwise"', 'expr = "1e-6/r**6"', "cutoff = 0.35",
              "[simulate]", "t_end = 0.05", "rtol = 1e-10", "atol = 1e-12",
              "[outputs]", 'quantities = ["positions", "energy"]', "plots = []"]
    scene = tmp_path / "chain.toml"
    scene.write_text("\n".join(lines) + "\n")
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    energy = np.load(tmp_path / "out" / "trajectory.npz")["energy"]
    assert np.max(np.abs(energy - energy[0])) < 1e-8 * max(1.0, abs(energy[0]))
