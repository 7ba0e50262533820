"""``rodas``: the linearly implicit Rosenbrock method (RODAS, order 4) on the index-1 DAE
(constrained/solvers/rodas.py, issue 28): its order against the double pendulum's
high-precision reference, steps set by accuracy where dopri's are set by stability (a stiff
spring chain, steps counted), a fine rope's energy kept to its tolerance, and the driver's
contract (output times, dense output, events, redundant rows, moving constraints)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import DP_REF_T2, double_pendulum

import constrained as C
from constrained.errors import InputError
from constrained.solvers import METHODS
from constrained.solvers.tableaus.rodas4 import RODAS4


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))


def test_rodas_is_a_method_of_the_driver():
    assert METHODS["rodas"].order == 4 and not METHODS["rodas"].explicit
    with pytest.raises(InputError, match="does not take the option"):
        C.simulate(double_pendulum(), 0.1, method="rodas", base="DOP853")


def test_the_tableau_is_stiffly_accurate_and_of_order_4_on_a_linear_problem():
    """On y' = λy with the exact Jacobian each stage solves (1/γ − z) U_i = z (1 + Σ a_ij U_j)
    + Σ c_ij U_j (z = hλ): the step's factor R(z) agrees with exp(z) to O(z⁵) and vanishes
    at z → −∞ (L-stable); the embedded estimate U_6 is O(z⁴)."""
    def factor(z):
        U = []
        for i in range(6):
            arg = 1 + sum(RODAS4.A[i, j] * U[j] for j in range(i))
            U.append((z * arg + sum(RODAS4.C[i, j] * U[j] for j in range(i))) / (1 / RODAS4.gamma - z))
        return 1 + sum(RODAS4.A[5, j] * U[j] for j in range(5)) + U[5], U[5]

    for z in (1e-2, 2e-2):
        assert abs(factor(z)[0] - np.exp(z)) < 0.02 * z ** 5
        assert abs(factor(z)[1]) < 0.1 * z ** 4
    assert abs(factor(-1e9)[0]) < 1e-7


def test_order_4_on_the_double_pendulum():
    """Errors at t = 2 s against the 30-digit reference: log(error) against log(steps) falls
    with slope about −4; the tightest run is good to 1e-8 m."""
    steps, errors = [], []
    for rtol in (1e-5, 1e-6, 1e-7, 1e-8, 1e-9):
        tr = C.simulate(double_pendulum(), 2.0, method="rodas", rtol=rtol, atol=rtol * 1e-2, outputs=set(),
                        t_eval=[0.0, 2.0])
        steps.append(tr.stats["steps"])
        errors.append(float(np.max(np.abs(tr.x[-1, :, :2] - DP_REF_T2))))
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert -5.0 < slope < -3.4, (steps, errors, slope)
    assert errors[-1] < 1e-8


def stiff_chain(k=1e6, c=60.0, n=8, m=0.01, link=0.02, rod=0.5) -> C.System:
    """A chain of n beads of 10 and 13 g on stiff damped springs (k, c between neighbours),
    the first on a 0.5 m rod to the origin, in a plane, released horizontal under gravity:
    the springs' modes (10⁴ rad/s, damped) are far faster than the swing (a few rad/s)."""
    s = C.System(name="stiff spring chain")
    for i in range(n):
        s.add_particle(f"p{i}", m * (1 + 0.3 * (i % 2)), [rod + i * link, 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=rod), C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]),
          C.Gravity([0, -9.81, 0]))
    for i in range(1, n):
        s.add(C.Spring(f"p{i - 1}", f"p{i}", k=k, rest=link), C.Damping(c, a=f"p{i - 1}", b=f"p{i}"))
    return s


def test_stiff_spring_chain_takes_steps_set_by_accuracy():
    """At rtol 1e-5 both methods meet the tolerance (against dopri at 1e-10), dopri with about
    ten times the steps: its steps are held to the springs' stability limit, rodas's are not."""
    system = stiff_chain()
    model = C.assemble(system)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # dopri's end-of-run stiffness warning
        ref = C.simulate(system, 1.0, model=model, rtol=1e-10, atol=1e-12, outputs=set(), t_eval=[0, 1],
                         compiled=False)
        runs = {method: C.simulate(system, 1.0, model=model, method=method, rtol=1e-5, atol=1e-7,
                                   outputs=set(), t_eval=[0, 1]) for method in ("dopri", "rodas")}
    size = np.abs(ref.x[-1]).max()
    for method, tr in runs.items():
        assert np.abs(tr.x[-1] - ref.x[-1]).max() < 1e-4 * size, method
    assert runs["dopri"].stats["steps"] > 8 * runs["rodas"].stats["steps"], \
        {m: tr.stats["steps"] for m, tr in runs.items()}


def rope(n: int = 200, link: float = 0.01, mass: float = 0.01) -> C.System:
    """n links of 1 cm and 10 g beads from the origin, released horizontal, in a plane, gravity."""
    s = C.System(name=f"rope of {n} links of {link} m")
    for i in range(n):
        s.add_particle(f"p{i}", mass, [(i + 1) * link, 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=link))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=link))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    return s


def test_fine_rope_keeps_its_energy_to_the_tolerance():
    """200 links of 1 cm, 10 g each, released horizontal (no damping): 0.3 s of the fall (the
    rope's end has dropped by 0.44 m) at rtol 1e-6. The energy (0 at the start) stays within
    rtol of the energies exchanged (m g Δy of the rope, ~2 J); the constraints to round-off."""
    system = rope()
    tr = C.simulate(system, 0.3, method="rodas", rtol=1e-6, atol=1e-8, t_eval=np.linspace(0, 0.3, 7),
                    outputs={"energy", "constraint_residual"})
    assert tr.info["stop"] == "completed"
    exchanged = np.max(np.abs(9.81 * np.einsum("n,tn->t", system.masses, tr.x[:, :, 1])))
    assert exchanged > 1.0
    assert np.max(np.abs(tr.energy - tr.energy[0])) < 1e-6 * exchanged
    assert np.max(tr.constraint_residual) < 1e-12


def test_output_times_dense_output_and_events():
    """A pendulum: 40 output times (the driver's dense output, projected) agree with landed
    ones; an event (the bob crossing x = 0 downwards… upwards) is located to round-off."""
    system = double_pendulum()
    t_eval = np.linspace(0, 1.0, 40)
    dense = C.simulate(system, 1.0, method="rodas", rtol=1e-9, atol=1e-11, t_eval=t_eval,
                       outputs={"constraint_residual"})
    landed = [C.simulate(system, float(t), method="rodas", rtol=1e-9, atol=1e-11, t_eval=[0, float(t)],
                         outputs=set()).x[-1] for t in t_eval[[7, 23, 39]]]
    np.testing.assert_allclose(dense.x[[7, 23, 39]], np.array(landed), atol=1e-7)
    assert np.max(dense.constraint_residual) < 1e-12
    event = C.Event("p1 crosses x = 0", lambda t, x, v: x[0], direction=0, terminal=True)
    tr = C.simulate(system, 2.0, method="rodas", rtol=1e-9, atol=1e-11, events=[event], outputs=set())
    assert abs(tr.x[-1, 0, 0]) < 1e-10 and tr.t[-1] < 2.0


@pytest.mark.parametrize("scene", ["rigid_tetrahedron", "kapitza_pendulum", "fekete"])
def test_redundant_rows_moving_anchors_and_surfaces(scene):
    """Redundant rows (the tetrahedron's), a driven anchor (rheonomic: ∂f/∂t terms), surface
    constraints: rodas agrees with dopri at tight tolerances."""
    s = C.load_scene(f"scenarios/{scene}.toml")
    t_end = min(float(s.settings.get("t_end") or 1.0), 0.25)
    a = C.simulate(s.system, t_end, method="rodas", rtol=1e-9, atol=1e-11, outputs=set(), t_eval=[0, t_end])
    b = C.simulate(s.system, t_end, method="dopri", rtol=1e-11, atol=1e-13, outputs=set(), t_eval=[0, t_end],
                   compiled=False)
    assert np.abs(a.x[-1] - b.x[-1]).max() < 1e-6 * max(1.0, np.abs(b.x[-1]).max())
