"""A batch member whose damping coefficient is negative is refused as its own run is
(docs/hard-cases.md §13, docs/ensembles.md). ``simulate`` refuses a coefficient given by a
formula of the parameters and t (``coefficient = "b"``) that is negative or not finite at any
instant of the run (R = ½ c |v|² with c < 0 is an energy source); ``simulate_many`` used to run
such a member all the same, and a sweep over b reported it as an ordinary row. Now the member is
not run, its status is "negative damping" and its message is its own run's, word for word, while
the others finish exactly as in a batch without it.

Closed forms: for a bob of mass 1 on a rod with a Rayleigh function R = ½ c |v|², the energy
E = ½ |v|² + g y changes at dE/dt = −2R = −c |v|², so E(t) − E(0) = −∫ c |v|² dt; with c ≥ 0 it
never grows."""

from __future__ import annotations

import csv

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.model.effects import Damping

G = 9.81
TH0 = 0.6
T_END = 2.0
T_EVAL = np.linspace(0.0, T_END, 201)
TOL = {"rtol": 1e-10, "atol": 1e-12, "compiled": False}
#: coefficient = "b": b < 0 is refused (members 0 and 1), b = 0 runs undamped, b > 0 dissipates.
B = [-0.2, -0.01, 0.0, 0.1, 0.3]
NEGATIVE = (0, 1)
#: coefficient = "b + 0.15 sin(20 t)": its lowest value over a span holding a trough of the sine
#: (20 t = 3π/2 + 2kπ, first at t = 0.2356 s) is b − 0.15, so over [0, 2] s the members with
#: b < 0.15 are refused: 0.1 (negative for 0.084 s of each 0.314 s period, where
#: sin(20 t) < −2/3) and 0.149 (for 0.0116 s of each, where sin(20 t) < −0.9933). Over [0, 0.2] s
#: the sine reaches only sin(4) = −0.757 (at t = 0.2): only b < 0.15 · 0.757 = 0.1135 is refused.
B_SINE = [0.1, 0.149, 0.151, 0.2, 0.3]
SINE = "b + 0.15*sin(20*t)"


def pendulum(coefficient="b", **parameters) -> C.System:
    """A bob of 1 kg on a rod of length L from the origin, released at rest at TH0 from the
    downward vertical, under gravity, with damping of the given coefficient."""
    s = C.System(name="damped pendulum", parameters={"b": 0.1, "L": 1.0, **parameters})
    s.add_particle("bob", 1.0, [f"L*sin({TH0})", f"-L*cos({TH0})", 0.0], [0.0, 0.0, 0.0])
    s.add(C.Distance("bob", point=[0, 0, 0], length="L"), C.Gravity([0, -G, 0]), C.Damping(coefficient))
    return s


def energy(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """E = ½ m |v|² + m g y of the bob (m = 1) at every sample."""
    return 0.5 * np.sum(v[..., 0, :] ** 2, axis=-1) + G * x[..., 0, 1]


def simpson(values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """∫ values dt from t[0] to every second sample (composite Simpson, even spacing)."""
    h = t[1] - t[0]
    pieces = h / 3 * (values[0:-2:2] + 4 * values[1:-1:2] + values[2::2])
    return np.concatenate([[0.0], np.cumsum(pieces)])


def own_run(system, b: float, t_end: float = T_END, t_eval=T_EVAL):
    """Member b's own run: its trajectory, or the InputError refusing it."""
    try:
        return C.simulate(system, t_end, parameters={"b": b}, method="dopri", t_eval=t_eval, **TOL)
    except C.InputError as error:
        return error


@pytest.fixture(scope="module")
def plain():
    system = pendulum()
    return system, C.assemble(system)


def test_negative_members_are_refused_in_their_own_runs_words(plain):
    """b = −0.2 and −0.01 are refused with their own ``simulate``'s InputError text; b = 0, 0.1,
    0.3 equal their own runs to 1e-12 (bit for bit a batch without the refused members) and lose
    energy at dE/dt = −b |v|²: E(t) − E(0) = −b ∫ |v|² dt."""
    system, model = plain
    ens = C.simulate_many(system, T_END, {"b": B}, t_eval=T_EVAL, model=model, **TOL)
    without = C.simulate_many(system, T_END, {"b": [b for k, b in enumerate(B) if k not in NEGATIVE]},
                              t_eval=T_EVAL, model=model, **TOL)
    kept = [k for k in range(len(B)) if k not in NEGATIVE]
    assert np.array_equal(ens.x[kept], without.x) and np.array_equal(ens.v[kept], without.v)
    assert np.array_equal(ens.steps[kept], without.steps)
    for k, b in enumerate(B):
        own = own_run(system, b)
        if k in NEGATIVE:
            assert isinstance(own, C.InputError) and "energy source" in str(own)
            assert ens.status[k] == "negative damping" and ens.messages[k] == str(own)
            assert f"is {b:g} N·s/m at t = 0 s" in ens.messages[k]
            assert np.all(np.isnan(ens.x[k])) and ens.steps[k] == 0 and np.isnan(ens.corrections[k])
            continue
        assert ens.status[k] == "completed" and ens.messages[k] == ""
        np.testing.assert_allclose(ens.x[k], own.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(ens.v[k], own.v, rtol=0, atol=1e-12)
        E = energy(ens.x[k], ens.v[k])
        np.testing.assert_allclose(E, own.energy, rtol=0, atol=1e-11)
        speed2 = np.sum(ens.v[k, :, 0] ** 2, axis=-1)
        loss = -b * simpson(speed2, T_EVAL)
        np.testing.assert_allclose(E[::2] - E[0], loss, rtol=0, atol=1e-6 * max(abs(loss[-1]), 1e-3))
        assert np.all(np.diff(E) <= 1e-10)  # never gains energy
        if b > 0:
            assert E[-1] - E[0] < -0.1 * b  # and loses a measurable amount
        assert np.max(np.abs(np.linalg.norm(ens.x[k, :, 0], axis=-1) - 1.0)) < 1e-12  # the rod holds


def test_a_formula_that_dips_briefly_refuses_only_the_members_it_dips_for(plain):
    """b + 0.15 sin(20 t): over [0, 2] s members b = 0.1 and 0.149 are refused, naming the
    lowest value b − 0.15 at a trough of the sine, as their own runs; over [0, 0.2] s only b = 0.1,
    at t = 0.2 s with 0.1 + 0.15 sin(4). Every member run dissipates at dE/dt = −c(t) |v|²."""
    system = pendulum(SINE)
    model = C.assemble(system)
    for t_end, refused in ((T_END, (0, 1)), (0.2, (0,))):
        t_eval = np.linspace(0.0, t_end, 201)
        ens = C.simulate_many(system, t_end, {"b": B_SINE}, t_eval=t_eval, model=model, **TOL)
        for k, b in enumerate(B_SINE):
            own = own_run(system, b, t_end, t_eval)
            if k in refused:
                assert isinstance(own, C.InputError)
                assert ens.status[k] == "negative damping" and ens.messages[k] == str(own)
                t_low = float(ens.messages[k].split("at t = ")[1].split(" s")[0])
                value = float(ens.messages[k].split(" is ")[1].split(" N·s/m")[0])
                if t_end == T_END:  # a trough: 20 t = 3π/2 + 2kπ, c = b − 0.15
                    phase = (20 * t_low - 1.5 * np.pi) / (2 * np.pi)
                    assert abs(phase - round(phase)) < 1e-4 and value == pytest.approx(b - 0.15, rel=1e-5)
                else:  # the end of the span, before the first trough
                    assert t_low == pytest.approx(0.2, abs=1e-5)
                    assert value == pytest.approx(b + 0.15 * np.sin(4.0), rel=1e-5)
                continue
            assert ens.status[k] == "completed", (t_end, b, ens.messages[k])
            np.testing.assert_allclose(ens.x[k], own.x, rtol=0, atol=1e-12)
            E = energy(ens.x[k], ens.v[k])
            c = b + 0.15 * np.sin(20 * t_eval)
            assert np.all(c >= 0)
            loss = -simpson(c * np.sum(ens.v[k, :, 0] ** 2, axis=-1), t_eval)
            np.testing.assert_allclose(E[::2] - E[0], loss, rtol=0, atol=1e-6 * abs(loss[-1]))
            assert np.all(np.diff(E) <= 1e-10) and E[-1] < E[0]


def test_members_sharing_the_values_the_formula_names_share_one_check(monkeypatch):
    """24 members, b ∈ {−0.05, 0.2} × 12 rod lengths: the coefficient names b only, so two checks
    decide all 24 (one per value of b); the 12 with b = −0.05 are refused, the others keep their
    rods and lose energy. A plain coefficient, and a system without damping, make no check."""
    calls = []
    refusal = Damping.refusal

    def counted(self, values, t0, t_end):
        calls.append(values["b"])
        return refusal(self, values, t0, t_end)

    monkeypatch.setattr(Damping, "refusal", counted)
    lengths = np.linspace(0.5, 1.6, 12)
    table = {"b": np.repeat([-0.05, 0.2], 12), "L": np.tile(lengths, 2)}
    ens = C.simulate_many(pendulum(), 1.0, table, t_eval=[0.0, 1.0], **TOL)
    assert sorted(calls) == [-0.05, 0.2]
    assert ens.status == ("negative damping",) * 12 + ("completed",) * 12
    assert len(set(ens.messages[:12])) == 1 and "is -0.05 N·s/m at t = 0 s" in ens.messages[0]
    np.testing.assert_allclose(np.linalg.norm(ens.x[12:, -1, 0], axis=-1), lengths, rtol=0, atol=1e-12)
    E = energy(ens.x[12:], ens.v[12:])
    assert np.all(E[:, 1] < E[:, 0])
    # a plain coefficient is checked when the effect is made, not per member
    calls.clear()
    plain = C.System(name="plain", parameters={"L": 1.0})
    plain.add_particle("bob", 1.0, [f"L*sin({TH0})", f"-L*cos({TH0})", 0.0], [0.0, 0.0, 0.0])
    plain.add(C.Distance("bob", point=[0, 0, 0], length="L"), C.Gravity([0, -G, 0]), C.Damping(0.2))
    flat = C.simulate_many(plain, 1.0, {"L": lengths}, t_eval=[0.0, 1.0], **TOL)
    assert calls == [] and all(s == "completed" for s in flat.status)
    np.testing.assert_allclose(flat.x, ens.x[12:], rtol=0, atol=1e-12)  # c = 0.2 either way


SCENE = """
[parameters]
b = 0.1

[[particles]]
name = "bob"
mass = 1.0
position = [0.5646424733950354, -0.8253356149096783, 0.0]
velocity = [0.0, 0.0, 0.0]

[[constraints]]
name = "rod"
type = "distance"
a = "bob"
point = [0.0, 0.0, 0.0]
length = 1.0

[[effects]]
type = "gravity"
g = [0.0, -9.81, 0.0]

[[effects]]
type = "damping"
coefficient = "b"

[simulate]
t_end = 1.0
rtol = 1e-10
atol = 1e-12
samples = 21
"""


def test_a_sweep_over_b_gives_the_negative_rows_their_refusal(tmp_path, capsys):
    """``constrained sweep`` over b on the batched path: the rows b < 0 carry their own run's
    refusal — the same status as the per-run path's rows — and no numbers; the others equal their
    own runs and the per-run rows (the same 21 output times), their energy drift grows with b (0
    for b = 0); exit status 0 with the count of failed
    runs on stderr (docs/sweeps.md: a failed run is a row, the sweep goes on)."""
    scene = tmp_path / "damped.toml"
    scene.write_text(SCENE)
    values = "parameters.b=[-0.2, -0.01, 0.0, 0.1, 0.3]"
    tables = {}
    for path, extra in (("batched", []), ("per-run", ["--per-run"])):
        out = tmp_path / path
        code = main(["sweep", str(scene), "--vary", values, "--out", str(out), "--quiet",
                     "--scheduler", "sequential", *extra])
        assert code == 0
        assert "2 of 5 runs failed" in capsys.readouterr().err
        tables[path] = list(csv.DictReader(open(out / "summary.csv")))
    rows, per_run = tables["batched"], tables["per-run"]
    assert [r["path"] for r in rows] == ["batched"] * 5 and [r["path"] for r in per_run] == ["per-run"] * 5
    system = C.load_scene(scene).system
    drift = []
    for k, b in enumerate(B):
        own = own_run(system, b, 1.0, np.linspace(0.0, 1.0, 21))
        if k in NEGATIVE:
            words = " ".join(str(own).split())
            assert rows[k]["status"] == per_run[k]["status"] == words and "energy source" in words
            assert rows[k]["x_bob"] == "" and rows[k]["energy_drift"] == ""
            continue
        assert rows[k]["status"] == per_run[k]["status"] == "ok"
        assert abs(float(rows[k]["x_bob"]) - own.x[-1, 0, 0]) < 1e-12
        assert abs(float(rows[k]["x_bob"]) - float(per_run[k]["x_bob"])) < 1e-12
        drift.append(float(rows[k]["energy_drift"]))
    assert drift[0] < 1e-8 < drift[1] < drift[2]  # b = 0 conserves; more damping, more loss
