"""simulate_many: many parameter variants advanced by one mapped step loop, each exactly as
its own run would go (same steps, same projections), failures reported per variant."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import constrained as C

PARAMETRIC = Path(__file__).resolve().parent.parent / "scenarios" / "double_pendulum_parametric.toml"


@pytest.fixture(scope="module")
def double():
    scene = C.load_scene(PARAMETRIC)
    return scene.system, C.assemble(scene.system)


def test_every_variant_ends_where_its_own_run_ends(double):
    system, model = double
    rng = np.random.default_rng(7)
    n = 12
    table = {"m1": rng.uniform(0.5, 2, n), "l2": rng.uniform(0.6, 1.4, n), "th1": rng.uniform(1.0, 2.5, n),
             "g": np.full(n, 9.81)}
    table["g"][4] = 1e300  # this variant's forces overflow: reported, the others finish
    t_eval = [0.5, 1.0, 2.0]
    ens = C.simulate_many(system, 2.0, table, t_eval=t_eval, rtol=1e-10, atol=1e-12, model=model,
                          compiled=False, block=5)
    assert ens.status[4] == "non-finite" and np.all(np.isnan(ens.x[4, -1]))
    assert ens.ok.sum() == n - 1 and len(ens) == n
    for k in np.flatnonzero(ens.ok):
        values = {name: float(table[name][k]) for name in table}
        tr = C.simulate(system, 2.0, model=model, parameters=values, rtol=1e-10, atol=1e-12, t_eval=t_eval,
                        outputs=[], compiled=False)
        np.testing.assert_allclose(ens.x[k], tr.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(ens.v[k], tr.v, rtol=0, atol=1e-11)
        # the rods keep their lengths: |p1| = l1 = 1, |p2 - p1| = l2
        assert abs(np.linalg.norm(ens.x[k, -1, 0]) - 1.0) < 1e-12
        assert abs(np.linalg.norm(ens.x[k, -1, 1] - ens.x[k, -1, 0]) - table["l2"][k]) < 1e-12


def test_threads_share_out_the_columns_without_changing_a_number(double):
    """Each column is advanced on its own, so two threads give the one-thread numbers exactly."""
    system, model = double
    rng = np.random.default_rng(3)
    table = {"m1": rng.uniform(0.5, 2, 20), "th1": rng.uniform(1.0, 2.5, 20)}
    one, two = (C.simulate_many(system, 1.0, table, rtol=1e-9, atol=1e-11, model=model, compiled=False,
                                block=16, threads=threads) for threads in (1, 2))
    assert one.stats["threads"] == 1 and two.stats["threads"] == 2
    assert np.array_equal(one.x, two.x) and np.array_equal(one.steps, two.steps)
    # and the rods still hold: |p1| = l1 = 1
    assert np.max(np.abs(np.linalg.norm(two.x[:, -1, 0], axis=-1) - 1.0)) < 1e-12


def test_a_start_far_off_the_constraints_is_refused_per_variant():
    """Numbers for positions, a parameter for the rod: a length the start misses by more
    than max_initial_correction (1e-3 of the size) is refused; a small miss is projected."""
    s = C.System(name="pendulum", parameters={"L": 1.0})
    s.add_particle("bob", 1.0, [1.0, 0.0, 0.0])
    s.add(C.Distance("bob", point=[0, 0, 0], length="L"), C.Plane("bob", [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    ens = C.simulate_many(s, 0.3, {"L": [1.0, 1.0005, 1.5]}, compiled=False)
    assert ens.status == ("completed", "completed", "inconsistent start")
    assert np.linalg.norm(ens.x[1, -1, 0]) == pytest.approx(1.0005, abs=1e-12)


def test_bad_tables_are_refused_with_their_names(double):
    system, model = double
    with pytest.raises(C.InputError, match="unknown parameter.*mass1.*m1"):
        C.simulate_many(system, 1.0, {"mass1": [1.0]}, model=model)
    with pytest.raises(C.InputError, match="same, non-zero length"):
        C.simulate_many(system, 1.0, {"m1": [1.0, 2.0], "l2": [1.0]}, model=model)
    with pytest.raises(C.InputError, match="not a finite number"):
        C.simulate_many(system, 1.0, {"m1": [1.0, float("nan")]}, model=model)


def test_progress_is_reported_up_to_the_end(double):
    system, model = double
    seen = []
    C.simulate_many(system, 1.0, {"m1": [1.0, 1.5, 2.0]}, model=model, compiled=False, progress=seen.append)
    assert seen and seen[-1] == 1.0 and all(0.0 <= f <= 1.0 for f in seen)
    assert seen == sorted(seen)  # the slowest variant only moves forward
    with pytest.raises(C.InputError, match="progress must be True"):
        C.simulate_many(system, 1.0, {"m1": [1.0]}, model=model, compiled=False, progress="yes")


def test_systems_of_one_structure_start_from_their_own_plain_numbers():
    """Two pendulums differing only in their plain-number start angles share a Structure (and its
    compiled start); each batched run starts from its own angle and ends where simulate does."""
    def pendulum(theta0: float) -> C.System:
        s = C.System(name="pendulum")
        s.parameters = {"g": 9.81}
        s.add_particle("bob", 1.0, [np.sin(theta0), -np.cos(theta0), 0.0])
        s.add(C.Distance("bob", point=[0, 0, 0], length=1.0), C.Plane("bob", [0, 0, 1]),
              C.Gravity([0, "-g", 0]))
        return s

    for theta0 in (0.6, 0.3):  # the second reuses what the first built
        system = pendulum(theta0)
        batch = C.simulate_many(system, 1.0, {"g": [9.81, 9.0]}, rtol=1e-10, atol=1e-12)
        single = C.simulate(system, 1.0, rtol=1e-10, atol=1e-12, parameters={"g": 9.0}, t_eval=[0.0, 1.0])
        np.testing.assert_allclose(batch.x[1, -1], single.x[-1], atol=1e-8)
