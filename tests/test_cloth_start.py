"""A flat cloth pinned at two corners (issue 26, item 6): the edge between the pins is a taut
straight chain of rods at exactly the pins' distance; gravity across the cloth would bend it,
which it allows only by stretching. Every method refuses that start in one sentence naming the
edge's rods and the fix; the same cloth pinned at two diagonal corners (slack everywhere) runs."""

from __future__ import annotations

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main

G = 9.81
LINK = 0.05  # 5 cm, 10 g per particle


def cloth(n: int, pins: str = "edge") -> C.System:
    s = C.System(name=f"cloth {n}x{n}")
    for i in range(n):
        for j in range(n):
            s.add_particle(f"p{i}_{j}", 0.01, [i * LINK, j * LINK, 0.0])
    for i in range(n):
        for j in range(n):
            if i + 1 < n:
                s.add(C.Distance(f"p{i}_{j}", f"p{i + 1}_{j}", length=LINK))
            if j + 1 < n:
                s.add(C.Distance(f"p{i}_{j}", f"p{i}_{j + 1}", length=LINK))
    far = (n - 1, 0) if pins == "edge" else (n - 1, n - 1)
    s.add(C.Pin("p0_0", [0, 0, 0]), C.Pin(f"p{far[0]}_{far[1]}", [far[0] * LINK, far[1] * LINK, 0.0]))
    s.add(C.Gravity([0, 0, -G]))
    return s


METHODS = ["dopri", "projection", "baumgarte", "rattle", "idas", "ggl", "pantelides"]


@pytest.mark.parametrize("method", METHODS)
def test_a_flat_cloth_pinned_at_two_corners_of_an_edge_is_refused_naming_the_edge(method):
    settings = {"dt": 1e-3} if method == "rattle" else {}
    with pytest.raises(C.InconsistentStateError) as refused:
        C.simulate(cloth(8), 0.5, method=method, **settings)
    message = str(refused.value)
    assert "taut, self-stressed" in message and "slack" in message
    named = message.split("the constraints ")[1].split(" form")[0]
    assert "p0_0–p1_0" in named and "p1_0–p2_0" in named  # the edge between the pins
    assert "_1" not in named.replace("p1_0", "")  # and nothing off the edge


def test_the_command_refuses_the_20x20_cloth_with_exit_status_2(tmp_path, capsys):
    n = 20
    lines = []
    for i in range(n):
        for j in range(n):
            lines.append(f'[[particles]]\nname = "p{i}_{j}"\nmass = 0.01\n'
                         f"position = [{i * LINK}, {j * LINK}, 0.0]\n")
    for i in range(n):
        for j in range(n):
            for di, dj in ((1, 0), (0, 1)):
                if i + di < n and j + dj < n:
                    lines.append(f'[[constraints]]\ntype = "distance"\na = "p{i}_{j}"\n'
                                 f'b = "p{i + di}_{j + dj}"\nlength = {LINK}\n')
    lines.append('[[constraints]]\ntype = "pin"\na = "p0_0"\npoint = [0.0, 0.0, 0.0]\n')
    lines.append(f'[[constraints]]\ntype = "pin"\na = "p{n - 1}_0"\npoint = [{(n - 1) * LINK}, 0.0, 0.0]\n')
    lines.append('[[effects]]\ntype = "gravity"\ng = [0.0, 0.0, -9.81]\n[simulate]\nt_end = 0.5\n')
    scene = tmp_path / "cloth.toml"
    scene.write_text("\n".join(lines))
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "taut, self-stressed" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_the_same_cloth_pinned_at_two_diagonal_corners_runs():
    """No straight path joins the pins at their distance: every part has slack. The cloth
    falls (the far corners drop), the rods hold to round-off and the energy is kept."""
    system = cloth(8, pins="diagonal")
    tr = C.simulate(system, 0.3, t_eval=np.linspace(0.0, 0.3, 7), rtol=1e-10, atol=1e-12)
    assert np.max(tr.constraint_residual) < 1e-12
    assert tr.x[-1, :, 2].min() < -0.1  # the free corners swing down
    scale = 64 * 0.01 * G * 0.1
    assert np.max(np.abs(tr.energy - tr.energy[0])) < 1e-8 * scale


@pytest.mark.parametrize("method", ["dopri", "rattle"])
def test_a_failed_run_keeps_the_steps_before_it_and_names_the_edge(method):
    """The same cloth with gravity along the pinned edge: the rest of the cloth, once swinging,
    pulls the taut edge sideways, which no motion allows, and dopri's projection fails a few
    hundredths of a second in (rattle: its Newton fails). Before, dopri dropped the whole
    chained call, so the run reported its last good state at t = 0, and both gave a generic
    cause; now the steps before the failing one are kept (the error's trajectory ends next to
    the failure, on the constraints, with the cloth moving) and the cause is diagnosed there."""
    system = cloth(6)
    system.effects[:] = [e for e in system.effects if not isinstance(e, C.Gravity)]
    system.add(C.Gravity([-G, 0.0, 0.0]))
    with pytest.raises(C.SimulationError, match="the run stopped early") as failed:
        C.simulate(system, 0.5, method=method, outputs={"constraint_residual"},
                   **({"dt": 1e-3} if method == "rattle" else {}))
    tr = failed.value.trajectory
    assert tr is not None and tr.t[-1] > 0 and np.max(tr.constraint_residual) < 1e-6
    if method == "dopri":  # (dopri accepts states up to PROJECTION_FAIL)
        near = float(str(failed.value).split("near t = ")[1].split(" s")[0])
        assert 0.5 * near < tr.t[-1] < near  # the failing step started there
        assert np.max(np.abs(tr.v[-1])) > 0.05  # swinging: steps were kept, not only the start
    # the diagnosis, at that state, names the edge between the pins (its rods and the pins' x
    # rows: nearly dependent once bent by round-off), not a generic cause
    cause = str(failed.value).split("likely cause:")[1]
    assert "p0_0–p1_0" in cause and "p4_0–p5_0" in cause and "pin p0_0" in cause
