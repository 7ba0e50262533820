"""The singular-configuration watch inside batches (docs/hard-cases.md §15): a member driven
into a limit position, where two rods become collinear and their rows lose rank, is stopped
there as its own ``simulate`` stops it — at the same state, in the same words, naming the
rows — while the others finish exactly as in a batch without it. It used to go on until its
step size reached its floor, and said "the step size collapsed".

The watch runs on each member's share of the batch's clock, as its own run's on its wall
time. The clocks here are fakes: the batch charges 1 s per call, a check costs 1 ns, and the
single run's watch is due after every call, so both check after every call and nothing is
timed."""

from __future__ import annotations

import csv
import os
import re
import signal
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.run.variants.watch import MemberSingular, MemberWatch
from constrained.solvers import watches

HARD = Path(__file__).resolve().parent.parent / "scenarios" / "hard"

#: A bead on a rod of 1 m from the origin O and on a rod to the fixed point B = (2, 0, 0)
#: whose length, √5 − c t, is drawn in at c m/s: the bead's angle θ from O follows
#: cos θ = (5 − ℓ²)/4 (no freedom is left in the plane). At ℓ = 1 the bead is at (1, 0, 0),
#: between O and B, the two rods are collinear and their rows dependent: the limit position,
#: reached at t* = (√5 − 1)/c; beyond it no position lies on both rods.
TWO_RODS = """
[parameters]
c = 1.0

[[particles]]
name = "bead"
mass = 1.0
position = [0.0, 1.0, 0.0]
velocity = ["0.5*sqrt(5)*c", 0.0, 0.0]

[[constraints]]
name = "rod OP"
type = "distance"
a = "bead"
point = [0.0, 0.0, 0.0]
length = 1.0

[[constraints]]
name = "rod PB"
type = "distance"
a = "bead"
point = [2.0, 0.0, 0.0]
length = "sqrt(5) - c*t"

[[constraints]]
name = "plane"
type = "plane"
particles = ["bead"]
normal = [0.0, 0.0, 1.0]

[[effects]]
type = "gravity"
g = [0.0, -9.81, 0.0]

[simulate]
t_end = 2.0
rtol = 1e-8
atol = 1e-10
"""
#: c = 1.0 and 0.8 reach the limit before t_end = 2 s (t* = 1.236 s, 1.545 s); c = 0.4 and
#: 0.5 do not (t* = 3.09 s, 2.47 s).
C_VALUES = [0.4, 1.0, 0.5, 0.8]
SINGULAR = (1, 3)
REGULAR = (0, 2)
T_END = 2.0
NUMBER = r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?"
STOPPED = "the run stopped early: "


def t_star(c: float) -> float:
    return (np.sqrt(5.0) - 1.0) / c


def closed_form(c: float, t) -> np.ndarray:
    """The bead's position (…, 3) at times t: cos θ = (5 − ℓ²)/4, ℓ = √5 − c t, y > 0."""
    ell = np.sqrt(5.0) - c * np.asarray(t, float)
    cos = (5.0 - ell ** 2) / 4.0
    return np.stack([cos, np.sqrt(1.0 - cos ** 2), np.zeros_like(cos)], axis=-1)


class Clock:
    """A fake clock: each read advances it by the next of ``steps`` (in turn)."""

    def __init__(self, *steps: float):
        self.now, self.steps, self.reads = 0.0, steps, 0

    def __call__(self) -> float:
        self.now += self.steps[self.reads % len(self.steps)]
        self.reads += 1
        return self.now


@pytest.fixture
def fake_clocks(monkeypatch):
    """The batch charges 1 s per call (each member is due from its first call on) and a check
    costs 1 ns; the single run's watch reads 1 s before a check and 1 ns across it (due after
    every call)."""
    monkeypatch.setattr(MemberWatch, "clock", staticmethod(Clock(1.0)))
    monkeypatch.setattr(MemberSingular, "clock", staticmethod(Clock(1e-9)))
    monkeypatch.setattr(watches, "time", SimpleNamespace(perf_counter=Clock(1.0, 1e-9)))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("singular") / "two_rods.toml"
    path.write_text(TWO_RODS)
    return path


def _own(system, c: float, **options):
    """Member c's own run: its trajectory, or the SimulationError that stopped it."""
    try:
        return C.simulate(system, T_END, parameters={"c": c}, method="dopri", rtol=1e-8, atol=1e-10,
                          outputs=[], compiled=False, **options)
    except C.SimulationError as error:
        return error


def _stop(message: str) -> tuple[float, float, set[str], float]:
    """(the instant named, σ, the rows named, the last good state's time) of the watch's sentence."""
    t = float(re.match(rf"singular configuration reached at t = ({NUMBER}) s; likely cause: ",
                       message).group(1))
    names = re.search(r"the constraints (.*) are \(nearly\) dependent there", message).group(1)
    sigma = float(re.search(rf"constraint Jacobian ({NUMBER})\)", message).group(1))
    last = float(re.search(rf"the last good state is at t = ({NUMBER}) s", message).group(1))
    return t, sigma, set(re.findall(r"'([^']*)'", names)), last


def test_members_driven_into_the_limit_stop_there_as_their_own_runs_and_the_others_equal_theirs(
        scene, fake_clocks):
    """The members c = 1.0 and 0.8 stop within 1e-7 s before their own t*, with status "singular
    configuration" and their own run's sentence, word for word: the instant, the two rods
    (σ < 1e-4), the last good state. With the single run's calls (64 attempts, no output times
    between) and checks after every call, they stop after their own run's steps and
    rejections, at its last state. The others are bit for bit those of the batch without the watch (whose
    singular members crawl on until their step size reaches its floor), within 1e-12 m of
    their own runs, and on the closed form."""
    system = C.load_scene(scene).system
    ens = C.simulate_many(system, T_END, {"c": C_VALUES}, rtol=1e-8, atol=1e-10, compiled=False)
    assert ens.status == ("completed", "singular configuration", "completed", "singular configuration")
    for j in SINGULAR:
        t, sigma, names, last = _stop(ens.messages[j])
        assert abs(t - t_star(C_VALUES[j])) < 1e-5 and last == t
        assert names == {"rod OP", "rod PB"} and sigma < 1e-4
        assert np.all(np.isnan(ens.x[j]))  # (no output time before the stop but t_end)
        alone = _own(system, C_VALUES[j])
        assert isinstance(alone, C.SimulationError)
        assert str(alone) == STOPPED + ens.messages[j]
        assert t_star(C_VALUES[j]) - 1e-7 < alone.trajectory.t[-1] < t_star(C_VALUES[j])
        assert ens.steps[j] == alone.trajectory.stats["steps"]
        assert ens.rejected[j] == alone.trajectory.stats["rejected"]

    off = C.simulate_many(system, T_END, {"c": C_VALUES}, rtol=1e-8, atol=1e-10, compiled=False,
                          singular_tol=None)
    assert [off.status[j] for j in SINGULAR] == ["step size collapsed"] * 2
    assert all(off.steps[j] > ens.steps[j] for j in SINGULAR)
    without = C.simulate_many(system, T_END, {"c": [C_VALUES[j] for j in REGULAR]}, rtol=1e-8,
                              atol=1e-10, compiled=False)
    for other in (off, without):
        rows = list(REGULAR) if other is off else [0, 1]
        np.testing.assert_array_equal(other.x[rows], ens.x[list(REGULAR)])
        np.testing.assert_array_equal(other.v[rows], ens.v[list(REGULAR)])
        np.testing.assert_array_equal(other.steps[rows], ens.steps[list(REGULAR)])
    for j in REGULAR:
        assert ens.status[j] == "completed"
        own = _own(system, C_VALUES[j], t_eval=[T_END])
        np.testing.assert_allclose(ens.x[j, -1], own.x[-1], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ens.v[j, -1], own.v[-1], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ens.x[j, -1, 0], closed_form(C_VALUES[j], T_END), rtol=0, atol=1e-8)


def test_a_fourbar_driven_past_its_limit_stops_there_in_the_members_that_reach_it(fake_clocks):
    """scenarios/hard/fourbar_limit.toml (a non-Grashof four-bar whose crank is driven at w rad/s):
    coupler and rocker become collinear at the crank angle arccos(0.3), at t* = arccos(0.3)/w.
    Over 3 s the members w = 1.0 and 0.5 reach it and stop there, naming the coupler, the rocker
    and the drive, at the instant and with the rows of their own runs; w = 0.3 and 0.35 do not,
    and complete."""
    system = C.load_scene(HARD / "fourbar_limit.toml").system
    speeds = [0.3, 1.0, 0.35, 0.5]
    ens = C.simulate_many(system, 3.0, {"w": speeds}, rtol=1e-10, atol=1e-12, compiled=False)
    assert ens.status == ("completed", "singular configuration", "completed", "singular configuration")
    for j in SINGULAR:
        t, sigma, names, last = _stop(ens.messages[j])
        limit = np.arccos(0.3) / speeds[j]
        assert abs(t - limit) < 1e-5 and last == t and sigma < 1e-4
        assert {"coupler BC", "rocker DC"} <= names
        # (the scene's start velocity is w = 1's: each run removes its part across the crank)
        with pytest.warns(C.InitialStateWarning), pytest.raises(C.SimulationError) as alone:
            C.simulate(system, 3.0, parameters={"w": speeds[j]}, method="dopri", rtol=1e-10, atol=1e-12,
                       outputs=[], compiled=False)
        own_t, own_sigma, own_names, _ = _stop(str(alone.value)[len(STOPPED):])
        assert own_t == t and own_names == names and own_sigma < 1e-4
        assert limit - 1e-6 < alone.value.trajectory.t[-1] < limit


def test_output_times_keep_the_samples_before_the_limit(scene, fake_clocks):
    """With output times every 0.2 s, a singular member keeps its samples before its stop —
    its own run's, and on the closed form — and NaN after; it still stops at t* (to the six
    digits printed) naming the two rods, as its own run does."""
    system = C.load_scene(scene).system
    t_eval = np.linspace(0.0, T_END, 11)
    ens = C.simulate_many(system, T_END, {"c": C_VALUES}, t_eval=t_eval, rtol=1e-8, atol=1e-10,
                          compiled=False)
    assert [ens.status[j] for j in SINGULAR] == ["singular configuration"] * 2
    for j in SINGULAR:
        c = C_VALUES[j]
        t, _, names, _ = _stop(ens.messages[j])
        assert abs(t - t_star(c)) < 1e-5 and names == {"rod OP", "rod PB"}
        before = t_eval < t
        assert np.all(np.isnan(ens.x[j, ~before]))
        np.testing.assert_allclose(ens.x[j, before, 0], closed_form(c, t_eval[before]), rtol=0, atol=1e-8)
        alone = _own(system, c, t_eval=t_eval)
        kept = alone.trajectory
        np.testing.assert_allclose(ens.x[j, :len(kept.t)], kept.x, rtol=0, atol=1e-12)
        own_t, _, own_names, _ = _stop(str(alone)[len(STOPPED):])
        assert abs(own_t - t) < 1e-5 and own_names == names


def test_the_sparse_watch_of_a_large_member_stops_it_as_its_own_run(scene, fake_clocks):
    """Beside 100 free particles (303 coordinates: beyond DENSE_WATCH_MAX) each member's own
    run's sparse watch (inverse iteration on Ĵ Ĵᵀ) judges it: the member c = 1.0 stops with
    its own run's sentence, word for word, and steps; c = 0.4 completes."""
    system = C.load_scene(scene).system
    for k in range(100):
        system.add_particle(f"spectator{k}", 1.0, [float(k), 5.0, 0.0])
    assert C.assemble(system).n_coordinates > watches.DENSE_WATCH_MAX
    ens = C.simulate_many(system, T_END, {"c": [0.4, 1.0]}, rtol=1e-8, atol=1e-10, compiled=False)
    assert ens.status == ("completed", "singular configuration")
    alone = _own(system, 1.0)
    assert str(alone) == STOPPED + ens.messages[1]
    assert ens.steps[1] == alone.trajectory.stats["steps"]
    np.testing.assert_allclose(ens.x[0, -1, 0], closed_form(0.4, T_END), rtol=0, atol=1e-8)


def test_a_member_whose_share_never_comes_due_is_looked_at_where_its_step_fails(scene, fake_clocks,
                                                                              monkeypatch):
    """A batched member costs far less wall time than its own run (a compiled batch of these four
    members ends in 5 ms): its share may never come due. Here the batch's clock stands still,
    so no member is ever checked on the way: the singular members go on until their step size
    reaches its floor, a few chunks past the state where their own runs stop, and are then
    looked at once more, there: at the limit, to the six digits printed, naming the same rods as
    their own runs. The others are bit for bit those of the batch that checks every call."""
    system = C.load_scene(scene).system
    checked = C.simulate_many(system, T_END, {"c": C_VALUES}, rtol=1e-8, atol=1e-10, compiled=False)
    monkeypatch.setattr(MemberWatch, "clock", staticmethod(Clock(0.0)))
    ens = C.simulate_many(system, T_END, {"c": C_VALUES}, rtol=1e-8, atol=1e-10, compiled=False)
    assert ens.status == checked.status
    for j in SINGULAR:
        assert ens.steps[j] > checked.steps[j]  # (on to the step size's floor)
        t, sigma, names, last = _stop(ens.messages[j])
        own_t, _, own_names, _ = _stop(checked.messages[j])  # (its own run's: the first test)
        assert t == own_t and names == own_names and last == t and sigma < 1e-4
        assert abs(t - t_star(C_VALUES[j])) < 1e-5
    np.testing.assert_array_equal(ens.x[list(REGULAR)], checked.x[list(REGULAR)])
    np.testing.assert_array_equal(ens.steps[list(REGULAR)], checked.steps[list(REGULAR)])


def test_ctrl_c_still_stops_a_batch_whose_members_are_watched_at_the_next_call(scene, fake_clocks):
    """Ctrl-C (SIGINT sent from the progress callback after the second call), with every member
    checked after every call: the batch stops at its next check and returns, raising nothing;
    the singular members, still short of their limit, are "interrupted" after two calls of 64
    attempts; the others, complete after the first call, keep their end state."""
    system = C.load_scene(scene).system
    calls = []

    def progress(fraction: float) -> None:
        calls.append(fraction)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)

    ens = C.simulate_many(system, T_END, {"c": C_VALUES}, rtol=1e-8, atol=1e-10, compiled=False,
                          progress=progress)
    assert len(calls) == 2 and ens.stats["interrupted"]
    for j in SINGULAR:
        assert ens.status[j] == "interrupted" and ens.messages[j] == ""
        assert ens.steps[j] + ens.rejected[j] == 2 * 64
    for j in REGULAR:
        assert ens.status[j] == "completed"
        np.testing.assert_allclose(ens.x[j, -1, 0], closed_form(C_VALUES[j], T_END), rtol=0, atol=1e-8)


def test_a_sweep_row_of_a_member_at_the_limit_carries_the_watchs_reason(scene, fake_clocks, tmp_path, capsys):
    """The batched sweep over c: each singular row's status is its own run's sentence (the
    instant, just before t*, and the two rods), the others are ordinary rows whose end positions
    equal their own runs' at the batch's output times and the closed form, and the sweep exits 0
    with the count of failed runs on stderr (docs/sweeps.md)."""
    code = main(["sweep", str(scene), "--vary", f"parameters.c={C_VALUES}", "--out", str(tmp_path), "--quiet",
                 "--scheduler", "sequential"])
    assert code == 0
    assert "2 of 4 runs failed" in capsys.readouterr().err
    rows = list(csv.DictReader(open(tmp_path / "summary.csv")))
    assert [r["path"] for r in rows] == ["batched"] * 4
    system = C.load_scene(scene).system
    for j, row in enumerate(rows):
        c = float(row["parameters.c"])
        assert c == C_VALUES[j]
        if j in SINGULAR:
            t, sigma, names, _ = _stop(row["status"])
            assert abs(t - t_star(c)) < 1e-5 and names == {"rod OP", "rod PB"} and sigma < 1e-4
            assert row["x_bead"] == ""
            continue
        own = _own(system, c, t_eval=np.linspace(0.0, T_END, 21))
        assert row["status"] == "ok"
        assert abs(float(row["x_bead"]) - own.x[-1, 0, 0]) < 1e-12
        assert abs(float(row["y_bead"]) - own.x[-1, 0, 1]) < 1e-12
        np.testing.assert_allclose([float(row["x_bead"]), float(row["y_bead"])], closed_form(c, T_END)[:2],
                                   rtol=0, atol=1e-8)
