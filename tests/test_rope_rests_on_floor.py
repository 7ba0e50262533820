"""The rope of test_rope_slams_floor with restitution 0: it lands and stays down, the beads near
the kink lifting off and landing again as the hanging part pulls them (session 14: the run
never ended).

A bead stopped by a plastic impact that the rope then pulls up has a held force of the
forbidden sign, so the holding test lets it go: it starts the next segment free, touching,
with normal speed ~1e-14 m/s and a gap a round-off below zero (-7.9e-16 m, where the impact
instant was located). Its gap, watched as it was, read that round-off as a landing 5.6e-16 s
after the segment's start; the transition then changed nothing (the bead let go again, nothing
recorded), and the loop went on for ever: 5,185 segments in 120 s, t stuck at 0.142806942537 s
of 0.214 s, 41 events recorded (so the event budget never stopped it). Now such a row is
watched as it opens from where it started, and a run also stops after ``max_events`` segments."""

from __future__ import annotations

import numpy as np
import pytest
from test_rope_slams_floor import FLOOR, LINK, MASS
from test_rope_slams_floor import _rope_over_a_floor as rope_over_a_floor

import constrained as C
from constrained.model.structure import assemble
from constrained.run import hybrid
from constrained.run.unilateral import impact

N = 60
T_END = 1.5 * np.sqrt(2 * abs(FLOOR) / 9.81)  # the free fall to the floor takes 2/3 of it
G = 9.81


def _rope_over_a_floor(n: int = N) -> C.System:
    """n beads on 1 cm links hung from the origin by the first, released horizontal at rest in
    z = 0 above a one-sided, perfectly inelastic floor y >= FLOOR under every bead (the rope
    of test_rope_slams_floor with restitution 0)."""
    return rope_over_a_floor(n, restitution=0.0)


#: Segments the rope may take (30 when written): past it the run is stopped here, so that a
#: loop of segments fails this test instead of hanging it.
SEGMENT_BUDGET = 3 * N


@pytest.fixture(scope="module")
def rope():
    run_segment, count = hybrid.run_segment, [0]

    def budgeted(*args, **kw):
        count[0] += 1
        assert count[0] <= SEGMENT_BUDGET, f"more than {SEGMENT_BUDGET} segments by t = {args[4]:.17g} s"
        return run_segment(*args, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(hybrid, "run_segment", budgeted)
        return C.simulate(_rope_over_a_floor(), T_END, method="dopri", rtol=1e-6, atol=1e-6, compiled=False)


def test_an_inelastic_rope_lands_and_the_run_completes_with_bounded_work(rope):
    assert rope.info["status"] == "completed" and rope.t[-1] == pytest.approx(T_END)
    impacts = [r for r in rope.events if r.kind == "impact"]
    first = min(r.t for r in impacts)
    assert sum(r.t == first for r in impacts) >= N // 3  # the flat part lands at one instant
    assert all(r.extra["restitution"] == 0.0 for r in impacts)
    # the work is bounded: 58 impacts, 4 other events, 30 segments when written. Every bead
    # lands at most a few times (each landing is plastic: no bounce sequence), so a few
    # events per bead bound it; the old loop's segments were unbounded.
    assert len(rope.events) <= 3 * N
    assert rope.stats["segments"] <= SEGMENT_BUDGET
    assert max(sum(r.constraint == c for r in impacts) for c in {r.constraint for r in impacts}) <= 5


def test_the_inelastic_rope_stays_on_the_allowed_side_and_loses_energy(rope):
    y = rope.x.reshape(len(rope.t), N, 3)[:, :, 1]
    assert y.min() >= FLOOR - 1e-9
    assert np.max(rope.constraint_residual) < 1e-9
    # a plastic impact only loses energy, and between them the motion keeps it
    scale = MASS * G * abs(FLOOR) * N
    assert np.max(np.diff(rope.energy)) <= 1e-9 * scale
    impacts = [r for r in rope.events if r.kind == "impact"]
    assert all(r.energy_lost >= 0 for r in impacts)
    # each bead landing at speed u loses all its normal kinetic energy, ½ m u²; the first
    # burst lands at the free-fall speed √(2 g |FLOOR|)
    burst = [r for r in impacts if r.t == impacts[0].t]
    u = np.sqrt(2 * G * abs(FLOOR))
    assert burst[0].energy_lost == pytest.approx(0.5 * MASS * u**2 * len(burst), rel=1e-3)
    assert rope.energy[-1] < rope.energy[0] - 0.3 * scale


def test_the_landed_flat_part_is_held_on_the_floor_pressed_by_its_weight(rope):
    """The beads of the first burst (the flat far end) stay down, held: y = FLOOR, the floor
    pushing (never pulling), the far end's beads by their weight m g."""
    impacts = [r for r in rope.events if r.kind == "impact"]
    t1 = impacts[0].t
    burst = sorted(int(r.constraint.rsplit("[p", 1)[1].rstrip("]")) for r in impacts if r.t == t1)
    after = rope.t > t1
    y = rope.x.reshape(len(rope.t), N, 3)[after][:, burst, 1]
    assert np.max(np.abs(y - FLOOR)) < 1e-9
    floor_rows = [k for k, label in enumerate(rope.constraint_labels) if "offset -0.1" in label]
    mu = rope.multipliers[:, floor_rows]
    assert mu.min() >= -1e-9 * MASS * G  # the floor never pulls
    held_rows = [floor_rows[i] for i in burst]
    for seg in rope.info["segments"]:
        if seg["t_start"] >= t1:
            assert all(rope.constraint_labels[k] in seg["held"] for k in held_rows)
    # the last five beads (the far end, lying flat and still) are pressed by their weight
    assert rope.multipliers[-1, floor_rows[-5:]] == pytest.approx(MASS * G, rel=1e-6)


def test_a_bead_dropped_on_an_inelastic_floor_rests_held_by_its_weight():
    s = C.System(name="bead onto an inelastic floor")
    s.add_particle("b", MASS, [0.0, 0.0, 0.0], [0.3, 0.0, 0.0])
    s.add(C.Gravity([0, -G, 0]), C.Plane(["b"], [0, 1, 0], FLOOR, unilateral=True, restitution=0.0))
    traj = C.simulate(s, 0.4, method="dopri", rtol=1e-6, atol=1e-6, compiled=False)
    assert traj.info["status"] == "completed"
    (landing,) = traj.events
    assert landing.kind == "impact" and landing.t == pytest.approx(np.sqrt(2 * abs(FLOOR) / G), rel=1e-9)
    assert traj.info["segments"][-1]["held"] == [traj.constraint_labels[0]]
    after = traj.t > landing.t
    assert np.allclose(traj.x[after, 0, 1], FLOOR, atol=1e-12)
    assert np.allclose(traj.v[after, 0, 1], 0.0, atol=1e-12)
    assert np.allclose(traj.v[after, 0, 0], 0.3, rtol=1e-12)  # it slides on, frictionless
    assert traj.multipliers[after, 0] == pytest.approx(MASS * G, rel=1e-9)


def test_an_impact_does_not_release_a_resting_neighbour_for_a_round_off_impulse():
    """Two beads on a floor joined along it, one resting and one landing: the resting bead's
    floor impulse is zero but for round-off, which must not lift it off."""
    s = C.System(name="two beads")
    s.add_particle("a", MASS, [0.0, FLOOR, 0.0], [0.0, 0.0, 0.0])
    s.add_particle("b", MASS, [LINK, FLOOR, 0.0], [0.0, -1.4, 0.0])
    s.add(C.Distance("a", "b", length=LINK), C.Gravity([0, -G, 0]))
    s.add(C.Plane(["a", "b"], [0, 1, 0], FLOOR, unilateral=True, restitution=0.0))
    model = assemble(s, reuse=False)
    x = np.asarray(s.positions, float).ravel()
    v = np.asarray(s.velocities, float).ravel()
    v = v + 1e-15 * np.arange(v.size)  # a state with round-off in it (the resting bead's
    # floor row moving off at 1e-15 m/s: holding it takes a pull of 1e-17 N·s, a round-off)
    floor = [k for k, label in enumerate(model.constraint_labels) if "offset" in label]
    out = impact(model, x, v, 0.0, [0, floor[0]], [floor[1]], {floor[1]: 0.0})
    assert out.released == ()
    assert out.impulse[floor[1]] == pytest.approx(MASS * 1.4, rel=1e-9)
    assert abs(out.v.reshape(2, 3)[0, 1]) < 1e-12  # the resting bead stays


def test_a_run_past_its_segment_budget_stops_naming_the_constraint():
    """Segments whose transitions record nothing count against ``max_events`` too (the old
    loop recorded nothing, so the event budget never stopped it)."""
    failure = hybrid._chattering([], {"plane [p21]": 11, "plane [p22]": 1}, 10, 0.1428)
    assert failure.status.name == "STEP_LIMIT"
    assert "more than 10 segments" in failure and "11 of them of 'plane [p21]'" in failure
