"""Ensembles and sweeps on physics nobody here chose (session 15, docs/hard-cases.md §15):
members that differ wildly, start off their constraints by different amounts, fall into a
singularity, are stiff, chaotic, or bounce — each checked against a closed form or against
its own ``simulate``."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import ellipj, ellipk

import constrained as C
from constrained.cli.main import main
from constrained.solvers.stiffness import StiffnessWarning

G = 9.81
PARAMETRIC = Path(__file__).resolve().parent.parent / "scenarios" / "double_pendulum_parametric.toml"

PENDULUM = """
[parameters]
g = 9.81
l = 1.0
m = 1.0
th0 = 0.2
d = 0.0          # how far the start lies outside the rod (m)

[[particles]]
name = "bob"
mass = "m"
position = ["(l + d)*sin(th0)", "-(l + d)*cos(th0)", 0.0]

[[constraints]]
name = "rod"
type = "distance"
a = "bob"
point = [0.0, 0.0, 0.0]
length = "l"

[[constraints]]
type = "plane"
particles = ["bob"]
normal = [0.0, 0.0, 1.0]

[[effects]]
type = "gravity"
g = [0.0, "-g", 0.0]

[simulate]
t_end = 1.0
rtol = 1e-10
atol = 1e-12
"""

FALL = """
[parameters]
r0 = 1.0
k = 1.0
[[particles]]
name = "p"
mass = 1.0
position = ["r0", 0, 0]
[[constraints]]
type = "plane"
particles = ["p"]
normal = [0, 0, 1]
[[effects]]
type = "central"
a = "p"
point = [0.0, 0.0, 0.0]
expr = "-k/r"
"""

SPRING = """
[parameters]
k = 4.0
[[particles]]
name = "m"
mass = 1.0
position = [1.0, 0.0, 0.0]
velocity = [0.0, 1.0, 0.0]
[[constraints]]
type = "plane"
particles = ["m"]
normal = [0.0, 0.0, 1.0]
[[effects]]
type = "spring"
a = "m"
point = [0, 0, 0]
k = "k"
rest = 1.0
[simulate]
t_end = 10.0
max_steps = 3000
"""

BALL = """
[parameters]
h = 1.0
[[particles]]
name = "ball"
mass = 1.0
position = [0, "h", 0]
[[constraints]]
type = "plane"
particles = ["ball"]
normal = [0, 1, 0]
unilateral = true
restitution = 0.5
[[effects]]
type = "gravity"
g = [0, -9.81, 0]
[simulate]
t_end = 0.6
rtol = 1e-10
atol = 1e-12
"""


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("unfriendly")
    paths = {}
    for name, text in (("pendulum", PENDULUM), ("fall", FALL), ("spring", SPRING), ("ball", BALL)):
        paths[name] = root / f"{name}.toml"
        paths[name].write_text(text)
    return paths


@pytest.fixture(scope="module")
def pendulum(scenes):
    system = C.load_scene(scenes["pendulum"]).system
    return system, C.assemble(system)


def _pendulum_exact(l: float, t: np.ndarray, th0: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Released at rest from th0: θ(t) = 2 arcsin(k sn(K(k) − ω t; k)), k = sin(th0/2), ω = √(g/l)."""
    k = math.sin(th0 / 2)
    sn = ellipj(ellipk(k ** 2) - math.sqrt(G / l) * t, k ** 2)[0]
    th = 2 * np.arcsin(k * sn)
    return l * np.sin(th), -l * np.cos(th)


def test_lengths_from_1_mm_to_100_m_and_masses_from_1_g_to_1_t_each_keep_their_own_accuracy(pendulum):
    """Periods from 63 ms to 20 s in one batch: every member meets the elliptic closed form to
    a relative 1e-8 of its own length (32 swings of the 1 mm one) and takes exactly the steps
    of its own run — no shared step size."""
    system, model = pendulum
    L, M = np.logspace(-3, 2, 6), np.logspace(-3, 3, 6)
    t_eval = np.linspace(0.25, 2.0, 8)
    ens = C.simulate_many(system, 2.0, {"l": L, "m": M}, t_eval=t_eval, rtol=1e-10, atol=1e-12, model=model,
                          compiled=False)
    assert ens.ok.all()
    for i, l in enumerate(L):
        x, y = _pendulum_exact(l, t_eval)
        assert np.max(np.abs(ens.x[i, :, 0, 0] - x)) < 1e-8 * l
        assert np.max(np.abs(ens.x[i, :, 0, 1] - y)) < 1e-8 * l
    assert ens.steps[0] > 10 * ens.steps[-1]  # the short pendulum took its own, many more steps
    alone = C.simulate(system, 2.0, model=model, parameters={"l": L[0], "m": M[0]}, method="dopri",
                       rtol=1e-10, atol=1e-12, t_eval=t_eval, outputs=[], compiled=False)
    np.testing.assert_allclose(ens.x[0], alone.x, rtol=0, atol=1e-15)
    assert alone.stats["steps"] == ens.steps[0]


def test_starts_off_the_rod_are_judged_by_each_members_own_size(pendulum):
    """A start d outside the rod is moved radially by |d| (the nearest point of the circle).
    The limit is max_initial_correction × the member's own size: 1 mm pendulum 0.3 mm off is
    refused, as its own run refuses it (it used to be projected: the limit was taken from
    the default system, floored at 1 m); a 100 m one 5 cm off is projected, as its own run
    projects it (it used to be refused)."""
    system, model = pendulum
    L, D = np.array([1e-3, 100.0, 1.0]), np.array([3e-4, 0.05, 1e-4])
    ens = C.simulate_many(system, 0.5, {"l": L, "d": D}, rtol=1e-10, atol=1e-12, model=model, compiled=False)
    assert ens.status == ("inconsistent start", "completed", "completed")
    with pytest.raises(C.InconsistentStateError) as refused:
        C.simulate(system, 0.5, model=model, parameters={"l": 1e-3, "d": 3e-4}, method="dopri")
    assert ens.messages[0] == f"inconsistent start: {refused.value}"
    assert "more than the allowed 0.001 × system size" in ens.messages[0]
    assert np.isnan(ens.corrections[0])
    np.testing.assert_allclose(ens.corrections[1:], D[1:], rtol=1e-9)
    for i in (1, 2):  # on the rod, then the pendulum released from th0 on a rod of length l
        x, y = _pendulum_exact(L[i], np.array([0.5]))
        assert abs(ens.x[i, -1, 0, 0] - x[0]) < 1e-8 * L[i] and abs(ens.x[i, -1, 0, 1] - y[0]) < 1e-8 * L[i]
        assert abs(np.linalg.norm(ens.x[i, -1, 0]) - L[i]) < 1e-12 * L[i]


def test_a_rod_of_length_zero_or_negative_fails_alone_with_its_own_reason(pendulum):
    """l = 0: the rod's gradient is undefined at the anchor; l = −1: no position satisfies it.
    Each member says so in its own run's words (they used to read "inconsistent start" and
    "projection failed ... reduce rtol"); the others finish on their closed form."""
    system, model = pendulum
    L = [1.0, 0.0, -1.0, 2.0]
    ens = C.simulate_many(system, 1.0, {"l": L}, rtol=1e-10, atol=1e-12, model=model, compiled=False)
    assert ens.status == ("completed", "inconsistent start", "inconsistent start", "completed")
    for i in (1, 2):
        with pytest.raises(C.InconsistentStateError) as refused:
            C.simulate(system, 1.0, model=model, parameters={"l": L[i]}, method="dopri")
        assert ens.messages[i] == f"inconsistent start: {refused.value}"
    assert "rod of length 0" in ens.messages[1] and "cannot all be satisfied" in ens.messages[2]
    for i in (0, 3):
        x, y = _pendulum_exact(L[i], np.array([1.0]))
        assert abs(ens.x[i, -1, 0, 0] - x[0]) < 1e-8 and abs(ens.x[i, -1, 0, 1] - y[0]) < 1e-8


def test_a_member_that_falls_into_the_centre_stops_alone_at_t_star(scenes):
    """V = −k/r from rest at r0: the fall reaches r = 0 at t* = (π/2) √(r0³ / 2k) (1.1107 s for
    r0 = 1) and no step gets past it; r0 = 2, 3 are still falling at t = 2 s, on the cycloid
    r = r0 cos²η, t = √(r0³ / 2k) (η + sin η cos η)."""
    system = C.load_scene(scenes["fall"]).system
    ens = C.simulate_many(system, 2.0, {"r0": [1.0, 2.0, 3.0]}, rtol=1e-10, atol=1e-12, compiled=False)
    assert ens.status == ("step size collapsed", "completed", "completed")
    t_star = math.pi / 2 * math.sqrt(1 / 2)
    stopped = float(ens.messages[0].split("t = ")[1].split(" s")[0])
    assert abs(stopped - t_star) < 1e-4
    assert "forces that blow up" in ens.messages[0] and "particle 'p'" in ens.messages[0]
    assert np.all(np.isnan(ens.x[0, -1]))
    for i, r0 in ((1, 2.0), (2, 3.0)):
        scale = math.sqrt(r0 ** 3 / 2)
        eta = brentq(lambda e, s=scale: s * (e + math.sin(e) * math.cos(e)) - 2.0, 0, math.pi / 2)
        assert abs(ens.x[i, -1, 0, 0] - r0 * math.cos(eta) ** 2) < 1e-8


def test_chaotic_members_a_nanoradian_apart_each_equal_their_own_run():
    """Double pendulum, th1 = 2 + j·1e-9: the members' end states spread a thousand times
    beyond 1e-9 (the motion is chaotic), yet each equals its own simulate far closer than its
    neighbour — batching changes the answer less than a 1e-12 rad change of the start would
    (the starts' projections differ in round-off, which the motion amplifies alike) — and
    each keeps its energy."""
    scene = C.load_scene(PARAMETRIC)
    system, model = scene.system, C.assemble(scene.system)
    th1 = 2.0 + 1e-9 * np.arange(3)
    ens = C.simulate_many(system, 6.0, {"th1": th1}, rtol=1e-10, atol=1e-12, model=model, compiled=False)
    assert ens.ok.all()
    spread = np.max(np.abs(ens.x[1, -1] - ens.x[0, -1]))
    assert spread > 1e-6  # a nanoradian grew by a thousand at least
    energy = model.parametric("energy")
    for j in range(3):
        alone = C.simulate(system, 6.0, model=model, parameters={"th1": th1[j]}, method="dopri", rtol=1e-10,
                           atol=1e-12, t_eval=[6.0], outputs=[], compiled=False)
        assert np.max(np.abs(ens.x[j, -1] - alone.x[-1])) < 1e-3 * spread
        p = np.array(model.with_parameters({"th1": th1[j]}).parameter_vector, float)
        x0 = np.array(system.with_parameters({"th1": th1[j]}).positions, float).ravel()
        e0 = float(energy(x0, np.zeros(6), 0.0, p))
        e1 = float(energy(ens.x[j, -1].ravel(), ens.v[j, -1].ravel(), 6.0, p))
        assert abs(e1 - e0) < 1e-7


def test_a_stiff_member_stops_at_the_step_budget_with_the_stiffness_watchs_advice(scenes):
    """k = 1e10 N/m on 1 kg, barely stretched: period 2π/√k = 6.28e-5 s; within 3000 steps it
    reaches about t = 3000 × (a fraction of that period), and the member's message is the
    stiffness watch's (a rigid link: replace it by a distance constraint), as its own run's is.
    The soft member keeps its angular momentum x vy − y vx = 1 and energy v²/2 + k (r − 1)²/2 = 1/2."""
    system = C.load_scene(scenes["spring"]).system
    ens = C.simulate_many(system, 10.0, {"k": [4.0, 1e10]}, max_steps=3000, rtol=1e-10, atol=1e-12,
                          compiled=False)
    assert ens.status == ("completed", "step limit")
    message = ens.messages[1]
    assert message.startswith("more than max_steps = 3000 steps")
    assert "likely cause: stiffness" in message and "period 2π/ω = 6.28e-05 s" in message
    assert 'type = "distance"' in message
    with pytest.raises(C.SimulationError) as alone, pytest.warns(StiffnessWarning):
        C.simulate(system, 10.0, parameters={"k": 1e10}, method="dopri", max_steps=3000, compiled=False)
    assert "likely cause: stiffness" in str(alone.value)
    (x, y, _), (vx, vy, _) = ens.x[0, -1, 0], ens.v[0, -1, 0]
    assert abs(x * vy - y * vx - 1.0) < 1e-6
    assert abs((vx ** 2 + vy ** 2) / 2 + 4.0 * (math.hypot(x, y) - 1.0) ** 2 / 2 - 0.5) < 1e-6


def test_one_sided_contacts_are_refused_by_simulate_many_and_swept_per_run_exactly(scenes, tmp_path):
    """simulate_many has no event handling: a ball on a floor is refused by name (it used to hold
    the floor two-sided, so every drop was an "inconsistent start"). The sweep runs it per run:
    from h, the ball lands at t1 = √(2h/g) and leaves at e·g·t1 (e = 0.5); at t = 0.6 s both
    are in the first rebound, y = u (t − t1) − g (t − t1)² / 2."""
    system = C.load_scene(scenes["ball"]).system
    with pytest.raises(C.InputError, match="one-sided constraint.*event handling"):
        C.simulate_many(system, 0.6, {"h": [0.5, 1.0]})
    code = main(["sweep", str(scenes["ball"]), "--vary", "parameters.h=[0.5, 1.0]", "--out", str(tmp_path),
                 "--quiet", "--scheduler", "sequential"])
    assert code == 0
    rows = list(csv.DictReader(open(tmp_path / "summary.csv")))
    for row in rows:
        h = float(row["parameters.h"])
        t1 = math.sqrt(2 * h / G)
        s = 0.6 - t1
        assert row["status"] == "ok" and row["path"] == "per-run"
        assert abs(float(row["y_ball"]) - (0.5 * G * t1 * s - G * s ** 2 / 2)) < 1e-7


def test_sweep_rows_say_why_in_their_own_runs_words(scenes, tmp_path):
    """A batched sweep over l with a rod of length 0 and a stiff-spring sweep: the failed rows
    carry their own reasons (the undefined rod; the stiffness watch's advice, within the
    scene's max_steps, now passed to the batch), the others their closed forms."""
    code = main(["sweep", str(scenes["pendulum"]), "--vary", "parameters.l=[1.0, 0.0, 4.0]", "--out",
                 str(tmp_path / "l"), "--quiet", "--scheduler", "sequential"])
    assert code == 0
    rows = list(csv.DictReader(open(tmp_path / "l" / "summary.csv")))
    assert [r["path"] for r in rows] == ["batched"] * 3
    assert "rod of length 0" in rows[1]["status"] and "constraint 'rod'" in rows[1]["status"]
    for row in (rows[0], rows[2]):
        l = float(row["parameters.l"])
        x, y = _pendulum_exact(l, np.array([1.0]))
        assert row["status"] == "ok" and abs(float(row["x_bob"]) - x[0]) < 1e-8
        # energy at t_end is that of the release: drift far below m g l (1 - cos th0)
        assert float(row["energy_drift"]) < 1e-9 * G * l * (1 - math.cos(0.2))
    code = main(["sweep", str(scenes["spring"]), "--vary", "parameters.k=[4.0, 1e10]", "--out",
                 str(tmp_path / "k"), "--quiet", "--scheduler", "sequential"])
    rows = list(csv.DictReader(open(tmp_path / "k" / "summary.csv")))
    assert rows[0]["status"] == "ok" and rows[1]["path"] == "batched"
    assert rows[1]["status"].startswith("more than max_steps = 3000 steps")
    assert "likely cause: stiffness" in rows[1]["status"]
