"""Groups from the scene's batches (constrained.manifold.vectorized.grouping.batched): rows and
potential terms that a run of items builds by one vectorized formula (rods, springs, a plane
over many particles, gravity: ``model.symbols.Batch``) are grouped from the batch's particles
and entries of p instead of being compared one by one with candidate kernels. The groups must
be exactly those that discovery finds — the same kernels, coordinates, data and order — on
unfriendly systems: springs and rods running both ways, rods whose lengths are formulas among
plain ones, zero rest lengths, a pin, a moving plane; and a batch that misstates its instances
must be caught by its sample and left to discovery."""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest

import constrained as C
from constrained.manifold.mapped import MappedBuild
from constrained.manifold.vectorized import grouping
from constrained.model.structure import Structure


def _cloth(side: int, *, both_ways: bool = True, formulas: bool = False) -> C.System:
    """A side × side cloth of 1 cm squares and 15 mg beads (uneven where ``formulas``), rods
    along the grid, shear springs along both diagonals (one of them from the higher-numbered
    bead when ``both_ways``), pinned at one corner, under gravity."""
    s = C.System(name="cloth", parameters={"L": 0.01} if formulas else None)
    name = [[f"p{i}_{j}" for j in range(side)] for i in range(side)]
    for i in range(side):
        for j in range(side):
            s.add_particle(name[i][j], 0.015 * (1 + 0.2 * ((i * 7 + j) % 3)), [0.01 * i, 0.01 * j, 0.0])
    rods = []
    for i in range(side):
        for j in range(side):
            if j + 1 < side:  # every fifth rod's length a formula when ``formulas`` (no batch form)
                length = "L" if formulas and (i + j) % 5 == 0 else 0.01
                rods.append(C.Distance(name[i][j], name[i][j + 1], length=length))
            if i + 1 < side:
                rods.append(C.Distance(name[i + 1][j] if both_ways and j % 2 else name[i][j],
                                       name[i][j] if both_ways and j % 2 else name[i + 1][j], length=0.01))
    s.add(*rods, C.Pin(name[0][0], [0, 0, 0]))
    springs = []
    for i in range(side - 1):
        for j in range(side - 1):
            springs.append(C.Spring(name[i][j], name[i + 1][j + 1], k=2.0, rest=0.01 * np.sqrt(2)))
            a, b = (name[i + 1][j], name[i][j + 1]) if both_ways else (name[i][j + 1], name[i + 1][j])
            springs.append(C.Spring(a, b, k=2.0 + 0.1 * (i % 2), rest=0.0 if (i + j) % 4 == 0 else 0.014))
    s.add(*springs, C.Gravity([0, 0, -9.81]))
    return s


def _rope(n: int, *, moving_plane: bool = False) -> C.System:
    s = C.System(name="rope", parameters={"w": 3.0} if moving_plane else None)
    for i in range(n):
        s.add_particle(f"p{i}", 0.01 * (1 + 0.5 * np.cos(i)), [0.01 * (i + 1), 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.01))
    for i in range(1, n):  # the second half listed from the far end
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=0.01) if i < n // 2 else
              C.Distance(f"p{i}", f"p{i - 1}", length=0.01 * (1 + 0.01 * np.sin(i))))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1], "0.01*sin(w*t)" if moving_plane else 0.0),
          C.Gravity([0.5, -9.81, 0]))
    return s


def _same_groups(a: list, b: list, t, t_b=None) -> None:
    """The groups ``a`` and ``b`` alike: index data, parts and kernels (``t_b``: b's time symbol,
    when its groups were built on other symbols)."""
    assert len(a) == len(b)
    for g, h in zip(a, b, strict=True):
        for field in ("index", "sources", "constants", "place"):
            assert np.array_equal(getattr(g, field), getattr(h, field)), field
        assert g.parts == h.parts
        assert (ca.Function("k", [g.xl, g.c, t], [g.local]).serialize()
                == ca.Function("k", [h.xl, h.c, t if t_b is None else t_b], [h.local]).serialize())


def _builds(system: C.System) -> tuple[MappedBuild, MappedBuild, Structure]:
    structure = Structure(system)
    batched = MappedBuild(structure)
    structure.expressions = dataclasses.replace(structure.expressions, row_batches=(), term_batches=())
    return batched, MappedBuild(structure), structure


@pytest.mark.parametrize("system", [_cloth(9), _cloth(9, both_ways=False), _cloth(9, formulas=True),
                                    _rope(150), _rope(150, moving_plane=True)],
                         ids=["cloth", "cloth one way", "cloth with formulas", "rope", "rope, moving plane"])
def test_batched_groups_are_the_groups_discovery_finds(system):
    batched, discovered, structure = _builds(system)
    t = structure.expressions.t
    _same_groups(batched.rows, discovered.rows, t)
    _same_groups(batched.terms, discovered.terms, t)
    assert np.array_equal(batched.rest_place, discovered.rest_place)
    rest = [batched.rest_slots["potential"], discovered.rest_slots["potential"]]
    assert len(rest[0]) == len(rest[1])
    # every instance was grouped: the rods and springs of plain numbers come from batches
    assert batched.mapped_instances == discovered.mapped_instances > 0


def test_the_scene_states_its_batches():
    e = Structure(_cloth(9)).expressions
    rods, springs = 2 * 9 * 8, 2 * 8 * 8
    assert sorted(len(b.items) for b in e.row_batches) == [rods]
    # the springs of zero rest length have no batch form (another formula); gravity's summands do
    zero_rest = sum((i + j) % 4 == 0 for i in range(8) for j in range(8))
    assert sorted(len(b.items) for b in e.term_batches) == sorted([springs - zero_rest, 81])


def test_a_batch_that_misstates_its_instances_is_left_to_discovery():
    """Particles shifted by one along the rope: the sample shows the kernel is not those rows,
    so the batch claims nothing and discovery groups them as before."""
    structure = Structure(_rope(120))
    e = structure.expressions
    rods = max(e.row_batches, key=lambda b: len(b.items))
    wrong = [(rods.items + rods.offsets, np.roll(rods.particles, 1, axis=0), rods.numbers)]
    claimed = grouping.batched(e.rows, wrong, e.x, e.t, e.p, {}, ca.SX.sym("c", grouping.MAX_CONSTANTS), {})
    assert not claimed.any()
    lied = grouping.grouped(e.rows, e.x, e.t, e.p, {}, wrong)
    found = grouping.grouped(e.rows, e.x, e.t, e.p, {})
    _same_groups(lied[0], found[0], e.t)
    assert lied[1] == found[1]


def test_a_batched_model_runs_as_the_discovered_one():
    """The whole step on the groups from batches: a cloth's accelerations and multipliers equal
    those of the groups found by discovery, bit for bit."""
    batched, discovered, structure = _builds(_cloth(6))
    system = _cloth(6)
    x = np.asarray(system.positions, float).ravel() + 1e-4 * np.sin(np.arange(3 * 36))
    v = 0.1 * np.cos(np.arange(3 * 36))
    p = np.asarray(C.assemble(system).parameter_vector, float)
    for name in ("dynamics",):
        a = batched.function(name)(x, v, 0.3, p)
        b = discovered.function(name)(x, v, 0.3, p)
        for u, w in zip(a, b, strict=True):
            assert np.array_equal(np.asarray(ca.DM(u)), np.asarray(ca.DM(w)))


def test_what_a_batchs_first_row_reads_is_its_whole_pattern():
    """``_read_by`` looks among the batch's particles and entries of p; the positions must be
    the whole vectors' Jacobian pattern, also where the row reads t, reads a coordinate or an
    entry of p outside the batch's, a velocity, or the particles repeat."""
    x, v, p, t = ca.SX.sym("x", 12), ca.SX.sym("v", 12), ca.SX.sym("p", 6), ca.SX.sym("t")
    cases = [  # (row, particles, numbers)
        (ca.sqrt((x[3] - x[9]) ** 2 + (x[4] - x[10]) ** 2) - p[2], [1, 3], [2]),
        (x[5] * t - p[4] * p[1], [1], [4, 1]),
        (x[5] - x[0] - p[0], [1], [0]),  # x[0]: particle 0, not the batch's
        (x[5] - p[3], [1], [4]),  # p[3]: not the batch's
        (x[5] * v[5] - p[0], [1], [0]),  # a velocity
        ((x[6] - x[8]) ** 2 + p[5], [2, 2], [5, 5]),  # particles and numbers repeated
        (ca.SX(0.5) * p[1], [0], [1]),  # no coordinate
    ]
    for row, particles, numbers in cases:
        index0, reads0 = grouping._read_by(row, x, t, p, np.array(particles), np.array(numbers))
        assert np.array_equal(index0, ca.jacobian_sparsity(row, x).get_col())
        assert np.array_equal(reads0, ca.jacobian_sparsity(row, p).get_col())
