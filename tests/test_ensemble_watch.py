"""The stiffness watch inside batches (docs/hard-cases.md §15): a member whose steps a stiff
spring holds down is stopped on its own share of the batch's clock, in its own run's words,
while the others finish exactly as their own runs; a member that fails inside a chunk of
attempts stops at its last good attempt, where its own run stops.

The clocks are fakes that advance a fixed TICK per read: nothing here is timed."""

from __future__ import annotations

import csv
import math
import re
from types import SimpleNamespace

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.run.variants.watch import MemberWatch
from constrained.solvers import stiffness

G = 9.81
#: A bob on a rod of 1 m, a bead of 10 g hanging from it on a spring of rest length 0.1 m.
PENDULUM_SPRING = """
[parameters]
k = 10.0
th0 = 0.3

[[particles]]
name = "bob"
mass = 1.0
position = ["sin(th0)", "-cos(th0)", 0.0]

[[particles]]
name = "bead"
mass = 0.01
position = ["sin(th0)", "-cos(th0) - 0.1", 0.0]

[[constraints]]
name = "rod"
type = "distance"
a = "bob"
point = [0.0, 0.0, 0.0]
length = 1.0

[[constraints]]
type = "plane"
particles = ["bob", "bead"]
normal = [0.0, 0.0, 1.0]

[[effects]]
type = "gravity"
g = [0.0, -9.81, 0.0]

[[effects]]
name = "coil"
type = "spring"
a = "bob"
b = "bead"
k = "k"
rest = 0.1

[simulate]
t_end = 2.0
rtol = 1e-8
atol = 1e-10
"""
#: A bob on a rod of 1 m circling at 1 rad/s in the plane x = 0, which jumps to x = 2 at t = T:
#: no position on the rod lies there.
SLOT_JUMP = """
[parameters]
T = 1.0
[[particles]]
name = "bob"
mass = 1.0
position = [0.0, 1.0, 0.0]
velocity = [0.0, 0.0, 1.0]
[[constraints]]
name = "rod"
type = "distance"
a = "bob"
point = [0.0, 0.0, 0.0]
length = 1.0
[[constraints]]
name = "slot"
type = "plane"
particles = ["bob"]
normal = [1.0, 0.0, 0.0]
offset = "2*floor(t/T)"
"""
K = [10.0, 20.0, 1e9, 40.0]
STIFF = 2
T_END = 2.0
#: Seconds a fake clock advances per read.
TICK = 0.05


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        self.now += TICK
        return self.now


@pytest.fixture
def fake_clocks(monkeypatch):
    """The batch's clock and the single run's watch clock, both fakes."""
    monkeypatch.setattr(MemberWatch, "clock", staticmethod(FakeClock()))
    monkeypatch.setattr(stiffness, "time", SimpleNamespace(perf_counter=FakeClock()))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("watch") / "pendulum_spring.toml"
    path.write_text(PENDULUM_SPRING)
    return path


def _energy(x: np.ndarray, v: np.ndarray, k: float) -> float:
    """½ Σ m |v|² + Σ m g y + ½ k (|x_bob − x_bead| − 0.1)²."""
    m = np.array([1.0, 0.01])
    stretch = np.linalg.norm(x[0] - x[1]) - 0.1
    return float(0.5 * m @ np.sum(v ** 2, axis=1) + G * m @ x[:, 1] + 0.5 * k * stretch ** 2)


def _when_independent(message: str) -> str:
    """The watch's sentence without what depends on when it looked (the time, the steps so
    far, the stretch there) and without simulate's note of its last output: the spring, its
    period, and the advice."""
    cause = message[message.index("likely cause"):].split("; the last good state is at")[0]
    return cause[:cause.index("; dopri took")] + cause[cause.index(" m of 0.1 m:"):]


def test_a_stiff_member_is_stopped_on_its_share_of_the_clock_and_the_others_equal_their_own_runs(
        scene, fake_clocks):
    """k = 1e9 N/m on the 10 g bead (reduced mass μ = 0.0099 kg): period 2π/√(k/μ) = 1.98e-5 s,
    1e5 periods in 2 s; dopri is held to steps below it, about 5e5 steps to t_end. Its own
    ``simulate`` is stopped by the stiffness watch; in the batch it used to run on, since the
    watch did not run there. Now it is stopped early, with its own run's reason and advice, and
    the soft members (k = 10, 20, 40 N/m) end where their own runs end and keep their energy."""
    system = C.load_scene(scene).system
    t_eval = [1.0, T_END]
    ens = C.simulate_many(system, T_END, {"k": K}, t_eval=t_eval, rtol=1e-8, atol=1e-10, compiled=False)
    assert ens.status == ("completed", "completed", "stiff", "completed")
    message = ens.messages[STIFF]
    stopped = float(re.match(r"the steps follow a fast oscillation at t = (\S+) s; likely cause: stiffness",
                             message).group(1))
    period = 2 * math.pi / math.sqrt(K[STIFF] / (1.0 * 0.01 / 1.01))
    steps = int(ens.steps[STIFF])
    assert stopped < 0.05 * T_END and steps < 100_000  # long before t_end and the 20,000,000 budget
    assert stopped / steps <= period  # held down by the oscillation
    assert f"dopri took {steps} steps" in message and "period 2π/ω = 1.98e-05 s" in message
    assert 'type = "distance", a = "bob", b = "bead", length = 0.1' in message
    assert np.all(np.isnan(ens.x[STIFF]))
    with pytest.raises(C.SimulationError) as alone:
        C.simulate(system, T_END, parameters={"k": K[STIFF]}, method="dopri", rtol=1e-8, atol=1e-10,
                   t_eval=t_eval, outputs=[], compiled=False)
    assert "the steps follow a fast oscillation at t = " in str(alone.value)
    assert _when_independent(message) == _when_independent(str(alone.value))

    soft = [j for j in range(len(K)) if j != STIFF]
    without = C.simulate_many(system, T_END, {"k": [K[j] for j in soft]}, t_eval=t_eval, rtol=1e-8,
                              atol=1e-10, compiled=False)
    np.testing.assert_array_equal(without.x, ens.x[soft])
    np.testing.assert_array_equal(without.steps, ens.steps[soft])
    x0 = np.array(system.with_parameters({"k": 10.0}).positions, float)
    for j in soft:
        own = C.simulate(system, T_END, parameters={"k": K[j]}, method="dopri", rtol=1e-8, atol=1e-10,
                         t_eval=t_eval, outputs=[], compiled=False)
        np.testing.assert_allclose(ens.x[j], own.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(ens.v[j], own.v, rtol=0, atol=1e-11)
        assert ens.steps[j] == own.stats["steps"]
        e0 = _energy(x0, np.zeros((2, 3)), K[j])
        assert abs(_energy(ens.x[j, -1], ens.v[j, -1], K[j]) - e0) < 1e-7
        assert abs(np.linalg.norm(ens.x[j, -1, 0]) - 1.0) < 1e-12  # on the rod


def test_a_sweep_row_of_a_stiff_member_carries_the_watchs_reason(scene, fake_clocks, tmp_path, capsys):
    """The batched sweep of the same four springs: the stiff row's status is the watch's
    sentence, the others' end positions equal their own runs' at the batch's output times, and
    the sweep exits 0 with the count of failed runs on stderr (docs/sweeps.md)."""
    code = main(["sweep", str(scene), "--vary", f"parameters.k={K}", "--out", str(tmp_path), "--quiet",
                 "--scheduler", "sequential"])
    assert code == 0
    assert "1 of 4 runs failed" in capsys.readouterr().err
    rows = list(csv.DictReader(open(tmp_path / "summary.csv")))
    assert [r["path"] for r in rows] == ["batched"] * 4
    status = rows[STIFF]["status"]
    assert status.startswith("the steps follow a fast oscillation at t = ")
    assert "spring 'coil'" in status and 'type = "distance", a = "bob", b = "bead"' in status
    system = C.load_scene(scene).system
    for j, row in enumerate(rows):
        if j == STIFF:
            continue
        own = C.simulate(system, T_END, parameters={"k": float(row["parameters.k"])}, method="dopri",
                         rtol=1e-8, atol=1e-10, t_eval=np.linspace(0.0, T_END, 21), outputs=[],
                         compiled=False)
        assert row["status"] == "ok"
        assert abs(float(row["x_bead"]) - own.x[-1, 1, 0]) < 1e-12
        assert abs(float(row["y_bob"]) - own.x[-1, 0, 1]) < 1e-12


def test_a_member_that_fails_inside_a_chunk_stops_at_its_last_good_step_as_its_own_run(tmp_path):
    """The slot x = 2 floor(t/T) leaves the rod at t = T: the step across T cannot be projected.
    Each such member stops at its last step before T — the time and step count of its own
    run's last good state — not at the start of the chunk of 64 attempts in which it failed
    (here t = 0). The member with T = 30 circles on: (0, cos t, sin t)."""
    path = tmp_path / "slot.toml"
    path.write_text(SLOT_JUMP)
    system = C.load_scene(path).system
    periods = [1.0, 2.0, 3.0, 30.0]
    ens = C.simulate_many(system, 4.0, {"T": periods}, rtol=1e-8, atol=1e-10, compiled=False)
    assert ens.status == ("projection failed",) * 3 + ("completed",)
    for j, T in enumerate(periods[:3]):
        stopped = float(re.search(r"near t = (\S+) s", ens.messages[j]).group(1))
        with pytest.raises(C.SimulationError) as alone:
            C.simulate(system, 4.0, parameters={"T": T}, method="dopri", rtol=1e-8, atol=1e-10, outputs=[],
                       compiled=False)
        last = alone.value.trajectory
        assert 0.5 * T < stopped < T and abs(stopped - last.t[-1]) < 1e-6 * T
        assert ens.steps[j] == len(last.t) - 1  # every accepted step is a sample of the own run
    np.testing.assert_allclose(ens.x[3, -1, 0], [0.0, math.cos(4.0), math.sin(4.0)], atol=1e-8)
