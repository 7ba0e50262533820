"""The collapse watch inside batches (docs/hard-cases.md §15, "nothing may hang"): a member
whose steps collapse towards a finite-time blow-up is stopped as its own ``simulate`` stops
it — within a few thousand steps, at the same state, in the same words — while the others
finish exactly as in a batch without it. It used to crawl on until its step size reached its
floor: 10,261,543 steps for a rod of length 1 − t, where its own run stops after 2,535.

Nothing here is timed: the budgets are counts of steps, Ctrl-C is a signal sent from the
progress callback."""

from __future__ import annotations

import csv
import os
import re
import signal

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main

#: A pendulum whose rod, of length 1 − c t, is drawn in at c m/s: it reaches zero length at
#: t* = 1/c, where the bob's speed (its angular momentum over a vanishing radius) blows up.
#: The start is drawn in with the rod (radial velocity −c), so every member starts on it.
SHRINKING_ROD = """
[parameters]
c = 1.0

[[particles]]
name = "bob"
mass = 1.0
position = [0.6, -0.8, 0.0]
velocity = ["-0.6*c", "0.8*c", 0.0]

[[constraints]]
name = "rod"
type = "distance"
a = "bob"
point = [0.0, 0.0, 0.0]
length = "1 - c*t"

[[constraints]]
type = "plane"
particles = ["bob"]
normal = [0.0, 0.0, 1.0]

[[effects]]
type = "gravity"
g = [0.0, -9.81, 0.0]

[simulate]
t_end = 1.5
rtol = 1e-8
atol = 1e-10
max_steps = 100000
"""
#: Only c = 1.25 reaches zero length before t_end = 1.5 s: at t* = 1/c = 0.8 s. The others
#: end with a rod of 1 − 1.5 c (0.25 m for c = 0.5: their steps shrink, but do not collapse).
C_VALUES = [0.2, 0.5, 1.25, 0.1]
COLLAPSING = 2
T_STAR = 1 / C_VALUES[COLLAPSING]
T_END = 1.5
NUMBER = r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?"
#: Every run's step budget here (simulate's default is 20,000,000): a batch without the
#: watch fails in seconds with "step limit" instead of crawling on for 20 minutes.
MAX_STEPS = 100_000


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("collapse") / "shrinking_rod.toml"
    path.write_text(SHRINKING_ROD)
    return path


def _own(system, c: float, **options):
    """Member c's own run: its trajectory, or the SimulationError that stopped it."""
    try:
        return C.simulate(system, T_END, parameters={"c": c}, method="dopri", rtol=1e-8, atol=1e-10,
                          max_steps=MAX_STEPS, outputs=[], compiled=False, **options)
    except C.SimulationError as error:
        return error


def _collapse(message: str) -> tuple[float, float, np.ndarray]:
    """(t*, the time of the last good state, the bob's position there) named by a collapse."""
    t_star = float(re.search(rf"towards t\* ≈ ({NUMBER}) s", message).group(1))
    last = float(re.search(rf"the last good state is at t = ({NUMBER}) s", message).group(1))
    at = re.search(rf"particle 'bob' at \(({NUMBER}), ({NUMBER}), ({NUMBER})\) m", message)
    return t_star, last, np.array([float(at.group(i)) for i in (1, 2, 3)])


def test_a_collapsing_member_stops_as_its_own_run_and_the_others_equal_theirs(scene):
    """The member c = 1.25 stops just short of t* = 0.8 s, at its own run's last good state and
    step count, naming t* and the blow-up in its own run's words; its attempts are a few
    thousand, as its own run's (the batch used to spend its whole step budget). The
    others' states are bit for bit those of the batch without it, within 1e-12 m of their own
    runs, and on their rods of length 1 − c t_end."""
    system = C.load_scene(scene).system
    ens = C.simulate_many(system, T_END, {"c": C_VALUES}, rtol=1e-8, atol=1e-10, compiled=False,
                          max_steps=MAX_STEPS)
    assert ens.status == ("completed", "completed", "step size collapsed", "completed")
    message = ens.messages[COLLAPSING]
    assert message.startswith("the step size collapsed: the mean step fell from ")
    assert "(a finite-time blow-up: no number of steps reaches t*); likely cause: forces that blow up" \
        in message
    t_star, last, bob = _collapse(message)
    assert abs(t_star - T_STAR) < 1e-4 and T_STAR - 1e-3 < last < T_STAR
    assert np.all(np.isnan(ens.x[COLLAPSING]))  # (no output time before the stop but t_end)

    alone = _own(system, C_VALUES[COLLAPSING])  # every step kept: the state it reached is its last
    assert isinstance(alone, C.SimulationError)
    own_message = str(alone)
    assert own_message == f"the run stopped early: {message}"  # the same windows, state and words
    own_steps = alone.trajectory.stats["steps"]
    own_attempts = own_steps + alone.trajectory.stats["rejected"]
    t_last = alone.trajectory.t[-1]
    assert abs(last - t_last) < 1e-6  # (printed to 6 digits)
    # the last good state (printed to 4 digits) is on the rod, of length 1 − c t there: a few
    # tenths of a millimetre
    assert abs(np.linalg.norm(bob) / (1 - C_VALUES[COLLAPSING] * t_last) - 1) < 1e-3
    assert int(ens.steps[COLLAPSING]) == own_steps
    attempts = int(ens.steps[COLLAPSING] + ens.rejected[COLLAPSING])
    assert attempts <= 2 * own_attempts and attempts < 10_000

    others = [j for j in range(len(C_VALUES)) if j != COLLAPSING]
    without = C.simulate_many(system, T_END, {"c": [C_VALUES[j] for j in others]}, rtol=1e-8, atol=1e-10,
                              compiled=False, max_steps=MAX_STEPS)
    assert without.status == ("completed",) * 3
    np.testing.assert_array_equal(without.x, ens.x[others])
    np.testing.assert_array_equal(without.v, ens.v[others])
    np.testing.assert_array_equal(without.steps, ens.steps[others])
    for j in others:
        own = _own(system, C_VALUES[j], t_eval=[T_END])
        np.testing.assert_allclose(ens.x[j, -1], own.x[-1], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ens.v[j, -1], own.v[-1], rtol=0, atol=1e-12)
        assert ens.steps[j] == own.stats["steps"]
        assert abs(np.linalg.norm(ens.x[j, -1, 0]) - (1 - C_VALUES[j] * T_END)) < 1e-12


def test_output_times_move_the_windows_not_the_verdict(scene):
    """With output times every 0.1 s the batch's calls end at them, as its own run's do, but
    the two split the steps between them differently (its own run chains fewer attempts to
    land on them): the windows end a few steps apart, and both still stop within a millimetre
    of simulated time of t*, with a few thousand steps, naming it to 1e-4 s."""
    system = C.load_scene(scene).system
    t_eval = np.linspace(0.0, T_END, 16)
    ens = C.simulate_many(system, T_END, {"c": C_VALUES}, t_eval=t_eval, rtol=1e-8, atol=1e-10,
                          compiled=False, max_steps=MAX_STEPS)
    assert ens.status[COLLAPSING] == "step size collapsed"
    assert all(ens.status[j] == "completed" for j in range(len(C_VALUES)) if j != COLLAPSING)
    t_star, last, _ = _collapse(ens.messages[COLLAPSING])
    assert abs(t_star - T_STAR) < 1e-4 and T_STAR - 1e-3 < last < T_STAR
    before = t_eval < last
    assert np.all(np.isfinite(ens.x[COLLAPSING, before])) and np.all(np.isnan(ens.x[COLLAPSING, ~before]))
    # the samples it kept are its own run's
    alone = _own(system, C_VALUES[COLLAPSING], t_eval=t_eval)
    kept = alone.trajectory
    np.testing.assert_allclose(ens.x[COLLAPSING, :len(kept.t)], kept.x, rtol=0, atol=1e-12)
    own_t_star = float(re.search(rf"towards t\* ≈ ({NUMBER}) s", str(alone)).group(1))
    assert abs(own_t_star - t_star) < 1e-4
    assert int(ens.steps[COLLAPSING]) < 2 * kept.stats["steps"] and int(ens.steps[COLLAPSING]) < 10_000


def test_ctrl_c_still_stops_a_batch_with_a_collapsing_member_at_the_next_call(scene):
    """Ctrl-C during the batch (SIGINT sent from the progress callback after the third call):
    the batch stops at its next check and returns, raising nothing; the collapsing member,
    still short of its collapse, is "interrupted" after those three calls of 64 attempts."""
    system = C.load_scene(scene).system
    calls = []

    def progress(fraction: float) -> None:
        calls.append(fraction)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGINT)

    ens = C.simulate_many(system, T_END, {"c": C_VALUES}, rtol=1e-8, atol=1e-10, compiled=False,
                          max_steps=MAX_STEPS, progress=progress)
    assert len(calls) == 3
    assert ens.status[COLLAPSING] == "interrupted" and ens.messages[COLLAPSING] == ""
    assert ens.steps[COLLAPSING] + ens.rejected[COLLAPSING] == 3 * 64
    assert ens.stats["interrupted"]  # (it was read after the watch had forgotten it: always False)
    # the members that had reached t_end when Ctrl-C came are complete: their end state is
    # kept (it was NaN, "interrupted") and is their own run's
    for k, c in enumerate(C_VALUES):
        if k == COLLAPSING:
            continue
        assert ens.status[k] == "completed"
        own = _own(system, c)
        np.testing.assert_allclose(ens.x[k, -1].ravel(), np.ravel(own.x[-1]), atol=1e-12)


def test_a_sweep_row_of_a_collapsing_member_carries_its_reason(scene, tmp_path, capsys):
    """The batched sweep over c: the collapsing row's status is its own run's sentence (t*, the
    blow-up, its last good state just before t*), the others are ordinary rows whose end
    positions equal their own runs' at the batch's output times, and the sweep exits 0 with
    the count of failed runs on stderr."""
    code = main(["sweep", str(scene), "--vary", f"parameters.c={C_VALUES}", "--out", str(tmp_path), "--quiet",
                 "--scheduler", "sequential"])
    assert code == 0
    assert "1 of 4 runs failed" in capsys.readouterr().err
    rows = list(csv.DictReader(open(tmp_path / "summary.csv")))
    assert [r["path"] for r in rows] == ["batched"] * 4
    status = rows[COLLAPSING]["status"]
    assert status.startswith("the step size collapsed: the mean step fell from ")
    assert "likely cause: forces that blow up" in status and rows[COLLAPSING]["x_bob"] == ""
    t_star, last, _ = _collapse(status)
    assert abs(t_star - T_STAR) < 1e-4 and T_STAR - 1e-3 < last < T_STAR
    system = C.load_scene(scene).system
    for j, row in enumerate(rows):
        if j == COLLAPSING:
            continue
        c = float(row["parameters.c"])
        own = _own(system, c, t_eval=np.linspace(0.0, T_END, 21))
        assert row["status"] == "ok"
        assert abs(float(row["x_bob"]) - own.x[-1, 0, 0]) < 1e-12
        assert abs(float(row["y_bob"]) - own.x[-1, 0, 1]) < 1e-12
        assert abs(np.hypot(float(row["x_bob"]), float(row["y_bob"])) - (1 - c * T_END)) < 1e-10
