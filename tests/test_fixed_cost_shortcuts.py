"""Shortcuts of a run's fixed cost (issue 28) against the long way they replace: the archive
``write_npz`` writes against ``np.savez``'s, member by member."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
import structure_reference

from constrained.run.trajectory import Trajectory, write_npz


def _members(data: bytes) -> list[tuple]:
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return [(info.filename, info.compress_type, info.file_size, info.CRC, archive.read(info))
                for info in archive.infolist()]


ARRAYS = {
    "x": np.random.default_rng(1).normal(size=(7, 5, 3)),
    "t": np.linspace(0, 1, 7),
    "empty": np.zeros((0, 4)),
    "ints": np.arange(12, dtype=np.int32).reshape(3, 4),
    "big-endian": np.arange(5, dtype=">f8"),
    "flags": np.array([True, False, True]),
    "complex": np.array([1 + 2j, -0.5j]),
    "fortran": np.asfortranarray(np.arange(12.0).reshape(3, 4)),
    "strided": np.arange(20.0)[::3],
    "scalar": np.float64(2.5),
    "meta": np.array('{"names": ["a", "é"], "n": 3}'),
    "bytes": np.array([b"ab", b"c"]),
    "record": np.zeros(3, dtype=[("a", "<f8"), ("b", "<i4")]),
    "long header": np.zeros(2, dtype=[(f"field_{k}" * 40, "<f8") for k in range(400)]),
}


@pytest.mark.filterwarnings("ignore:Stored array in format 2.0")
@pytest.mark.parametrize("names", [list(ARRAYS), ["t"], []], ids=["all", "one", "none"])
def test_write_npz_writes_what_savez_writes(names):
    """The same members in the same order, each with the same bytes (header and data) and CRC;
    np.load gives the same arrays."""
    arrays = {k: ARRAYS[k] for k in names}
    ours, theirs = io.BytesIO(), io.BytesIO()
    write_npz(ours, arrays)
    np.savez(theirs, **arrays)
    assert _members(ours.getvalue()) == _members(theirs.getvalue())
    with np.load(io.BytesIO(ours.getvalue()), allow_pickle=True) as data:  # (the long header)
        assert data.files == names
        for k in names:
            assert np.array_equal(data[k], arrays[k]) and data[k].dtype == np.asarray(arrays[k]).dtype


def test_a_saved_trajectory_loads_bit_for_bit(tmp_path):
    rng = np.random.default_rng(3)
    T, N = 5, 4
    traj = Trajectory(t=np.linspace(0, 1, T), x=rng.normal(size=(T, N, 3)), v=rng.normal(size=(T, N, 3)),
                      multipliers=rng.normal(size=(T, 3)), energy=rng.normal(size=T),
                      particle_names=[f"p{i}" for i in range(N)], constraint_labels=["a", "b", "c"],
                      info={"method": "dopri"})
    back = Trajectory.load(traj.save(tmp_path / "trajectory.npz"))
    for k, value in traj.arrays().items():
        assert np.array_equal(back[k], value) and back[k].dtype == value.dtype
    assert back.particle_names == traj.particle_names and back.info == traj.info
    assert back.constraint_forces is None


def test_redundant_rows_kept_for_the_same_state_only():
    """``redundant_rows`` gives the kept answer for the same x, t and policy alone: the value
    computed anew at each of the states asked in turn, dependent rows and independent ones."""
    import constrained as C
    from constrained.manifold import manifold
    from constrained.manifold.rank_policy import RankPolicy
    from constrained.model.structure import assemble

    s = C.System(name="two rods")
    s.add_particle("p", 1.0, [1.0, 0.0, 0.0])
    s.add(C.Distance("p", point=[0, 0, 0], length=1.0), C.Distance("p", point=[2, 0, 0], length=1.0))
    model = assemble(s)
    aligned, bent = np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.1, 0.0])
    loose = RankPolicy(dependent_rtol=1e-30, cholesky_rtol=1e-30)
    rank = manifold.RANK
    asked = [(aligned, 0.0, rank), (aligned, 0.0, rank), (bent, 0.0, rank), (aligned, 0.0, rank),
             (aligned, 1.0, rank), (aligned, 0.0, loose), (bent, 0.0, loose), (aligned, 0.0, rank)]
    for x, t, policy in asked:
        kept = manifold.redundant_rows(model, x, t, policy)
        assert kept == manifold._redundant_rows(model, x, t, policy)
        assert kept == (None if x is bent else (0,)) or policy is loose


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.uint16, np.intp])
def test_sorted_unique_is_numpys_unique(dtype):
    """``sorted_unique`` (a sort) gives what ``np.unique`` gives (a hash table in NumPy 2.3+): the
    same values, dtype and shape, for empty, single, repeated, negative and 2-D input."""
    from constrained.manifold.vectorized.columns import sorted_unique

    rng = np.random.default_rng(7)
    low = 0 if np.dtype(dtype).kind == "u" else -50
    cases = [np.zeros(0, dtype), np.array([3], dtype), np.full(9, 4, dtype), np.arange(20, dtype=dtype)[::-1],
             rng.integers(low, 50, 1000).astype(dtype), rng.integers(low, 5, (30, 4)).astype(dtype)]
    for a in cases:
        ours, theirs = sorted_unique(a), np.unique(a)
        assert ours.dtype == theirs.dtype and ours.shape == theirs.shape and np.array_equal(ours, theirs)


def _structure_data_item_by_item(system):
    """``structure_data``'s items (tests/structure_reference.py) walked one by one, each item's
    names found anew (the long way its run-wise walk replaces)."""
    from constrained.model import lifting

    values, walked = [], []
    masses = [lifting.lifted_mass(p, values) for p in system.particles]
    described = [[p.name, ["formula", p.formulas["mass"]] if "mass" in p.formulas else lifting.plain_data(m)]
                 for p, m in zip(system.particles, masses, strict=True)]
    runs, header = [], None
    for item in (*system.constraints, *system.effects):
        lifted = lifting.lifted_fields(item, values)
        walked.append(lifted)
        rest = [(k, v) for k, v in vars(item).items() if k not in lifted]
        key = (type(item), tuple(lifted), tuple(k for k, _ in rest))
        if key != header:
            header = key
            runs.append([type(item).__module__, type(item).__qualname__, list(key[1]), list(key[2]), []])
        runs[-1][4].append([[lifting._plain_value(v) for v in lifted.values()],
                            [lifting._plain_value(v) for _, v in rest]])
    data = [described, runs, list(system.parameters), lifting.plain_data(system.definitions)]
    return data, values, [masses, walked, values]


def _items_of_every_shape():
    """Runs of one class broken by other classes, by attributes added to one item or given in
    another order, by a subclass, by a class whose numeric fields are a list; formulas, points,
    names, one-sided rods, masses of formulas."""
    import constrained as C

    class Rod(C.Distance):
        numbers = ["length", "point"]

    s = C.System(name="shapes", parameters={"L": 0.5})
    for i in range(8):
        s.add_particle(f"p{i}", "2*L" if i == 3 else 0.1 * (i + 1), [0.3 * i, 0.1, 0.0])
    rods = [C.Distance(f"p{i}", f"p{i + 1}", length=0.3) for i in range(6)]
    rods[2].note = "an extra attribute"
    rods[4] = C.Distance("p4", "p5", length="L", name="named")
    rods[5] = C.Distance("p5", "p6", length=0.3, unilateral=True, restitution=0.5)
    reordered = C.Distance("p6", "p7", length=0.3)
    reordered.__dict__ = dict(reversed(list(reordered.__dict__.items())))
    s.add(C.Distance("p0", point=[0, 0.1, 0], length=0.3), *rods, reordered, Rod("p1", "p7", length=1.0),
          Rod("p2", point=[0.0, 1.0, 0.0], length=2.0), C.Plane(["p0", "p1"], [0, 0, 1], 0.0),
          C.Gravity([0, -9.81, 0]), C.Spring("p0", "p2", k=3.0, rest=0.0), C.Damping(0.1, ["p1"]))
    return s


@pytest.mark.parametrize("make", ["shapes", "rope", "mixed"])
def test_structure_data_run_by_run_is_item_by_item(make):
    """The fingerprint's data, values and walk are those of the item-by-item walk (so the
    fingerprint is the same text hashed)."""
    import constrained as C

    if make == "shapes":
        system = _items_of_every_shape()
    elif make == "rope":
        system = C.System(name="rope")
        for i in range(70):
            system.add_particle(f"p{i}", 0.01, [0.01 * (i + 1), 0.0, 0.0])
        system.add(*[C.Distance(f"p{i - 1}", f"p{i}", length=0.01) for i in range(1, 70)],
                   C.Gravity([0, -9.81, 0]))
    else:
        from test_fixed_cost import _mixed

        system = _mixed()
    walked: list = []
    data, values = structure_reference.structure_data(system, walked)
    reference, reference_values, reference_walk = _structure_data_item_by_item(system)
    assert data == reference and values == reference_values
    assert walked == reference_walk


def test_pieces_sliced_one_by_one_are_the_split_pieces():
    """Symbols' positions and numbers: the first few sliced out, the rest from one split; the
    same SX elements as a split of the whole column, in order."""
    import casadi as ca

    from constrained.model.symbols import _Pieces

    column = ca.SX.sym("x", 3 * 50)
    pieces, whole = _Pieces(column, 3), ca.vertsplit(column, 3)
    asked = [pieces[k] for k in (7, *range(50))]  # (past SPLIT_FROM: from the split)
    assert pieces.pieces is not None
    for k, piece in zip((7, *range(50)), asked, strict=True):
        assert piece.shape == (3, 1) and all(ca.is_equal(piece[i], whole[k][i]) for i in range(3))


def test_lifted_copies_set_fields_as_setattr_does():
    """``lift``'s copy of an item stores the lifted fields in its dict for a plain class, and
    goes through setattr where the class sets an attribute otherwise (a property's setter)."""
    import constrained as C
    from constrained.model import lifting

    class Watched(C.Distance):
        numbers = ("point", "length")

        @property
        def length(self):
            return self._length

        @length.setter
        def length(self, value):
            self._length, self.set_through = value, True

    s = C.System([C.Particle("a", 1.0, [1, 0, 0]), C.Particle("b", 2.0, [0, 1, 0])])
    s.add(C.Distance("a", "b", length=1.5), Watched("a", "b", length=0.5))
    lifted, values = lifting.lift(s)
    plain, watched = lifted.constraints
    assert plain is not s.constraints[0] and type(plain) is C.Distance and plain.length == lifting.Number(2)
    assert list(vars(plain)) == list(vars(s.constraints[0])) and s.constraints[0].length == 1.5
    assert watched.set_through and watched.length == lifting.Number(3) and values.tolist() == [1, 2, 1.5, 0.5]


def _large_start_cases():
    from test_vectorized import rope

    import constrained as C

    off = rope(120, varied=True)
    off.particles[7].position = np.asarray(off.particles[7].position, float) + [2e-6, -1e-6, 0.0]
    springs = rope(110, moving=True)
    springs.add(*(C.Spring(f"p{i}", f"p{i + 5}", k=3.0, rest=0.04) for i in range(0, 100, 4)))
    return {"on its rows": (rope(120), False), "a particle off its rods": (off, True),
            "moving anchor and springs": (springs, None)}


@pytest.mark.parametrize("case", ["on its rows", "a particle off its rods", "moving anchor and springs"])
def test_a_large_start_builds_the_newton_step_only_off_its_rows_with_the_eager_numbers(case, monkeypatch):
    """A large model's manifold builds each fast path when first called: a start already on
    f = 0 is found so by f alone (no Newton step Function), one off it takes the Newton steps;
    the start (x, v, the correction report, the counters) is bit for bit that of the fast paths
    built all at once, and so is a run from it."""
    import constrained as C
    from constrained.manifold import manifold
    from constrained.manifold.vectorized import graphs as vg
    from constrained.model.structure import Model, Structure
    from constrained.run.start import consistent_start

    system, newton = _large_start_cases()[case]
    results = []
    for eager in (False, True):
        if eager:
            def all_at_once(model, rows, compiled):
                return manifold._FastPaths("virtual machine", vg.fast_path_functions(model))
            monkeypatch.setattr(manifold, "_fast_paths", all_at_once)
        model = Model(system, structure=Structure(system))
        assert vg.applies(model)
        x0, v0 = (np.asarray(a, float).ravel() for a in (system.positions, system.velocities))
        start = consistent_start(model, x0, v0, 0.0)
        if not eager and newton is not None:
            assert start.manifold._fast.built("newton_step") == newton
        run = C.simulate(system, 2e-4, model=model, rtol=1e-7, atol=1e-9)
        results.append((start, run))
    (lazy, run_lazy), (full, run_full) = results
    assert np.array_equal(lazy.x, full.x) and np.array_equal(lazy.v, full.v)
    assert lazy.correction == full.correction
    assert lazy.manifold.counters.as_dict() == full.manifold.counters.as_dict()
    for name in ("t", "x", "v"):
        assert np.array_equal(getattr(run_lazy, name), getattr(run_full, name))
