from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import constrained as C

ROOT = Path(__file__).resolve().parents[1]


def pytest_addoption(parser):
    parser.addoption("--all", action="store_true", default=False,
                     help="also run the tests marked slow (every docs block, Ctrl-C of every method, "
                          "the browser, scene fuzzing): what .ci/run runs")


def pytest_collection_modifyitems(config, items):
    """The developer's loop leaves the slow tests out (deselected, not skipped); ``--all`` or
    ``-m slow`` runs them."""
    if config.getoption("--all") or config.getoption("-m"):
        return
    slow = [item for item in items if item.get_closest_marker("slow")]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if not item.get_closest_marker("slow")]
SCENARIOS = ROOT / "scenarios"
#: The high-precision double-pendulum reference (30-digit arithmetic, good to < 1e-12): the
#: one copy every test reads.
REFERENCE = Path(__file__).resolve().parent / "reference" / "double_pendulum.md"


def _reference() -> tuple[dict[float, np.ndarray], float]:
    """Positions (2, 2) [[x1, y1], [x2, y2]] by time, and the energy, from REFERENCE."""
    text = REFERENCE.read_text(encoding="utf-8").replace("\u2212", "-")
    positions = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[0].endswith(" s"):
            positions[float(cells[0][:-2])] = np.array([float(c) for c in cells[1:]]).reshape(2, 2)
    energy = float(text.split("Energy (kinetic + m g y):")[1].split("J")[0])
    return positions, energy


DP_REF, DP_ENERGY = _reference()
#: Positions at t = 2 s, where the start's chaos has grown perturbations only about 3-fold.
DP_REF_T2 = DP_REF[2.0]


#: A particle pushed by a force that blows up (exp(exp(5 t))): every method must stop early.
BLOWUP_TOML = """\
[[particles]]
name = "p"
mass = 1.0
position = [0.0, 0.0, 0.0]

[[effects]]
type = "force"
particle = "p"
expr = ["exp(exp(5*t))", "0", "0"]

[simulate]
t_end = 3.0
"""


def pendulum_toml(t_end: float, position=(0.0, -1.0, 0.0), velocity=(1.0, 0.0, 0.0)) -> str:
    """A small scene file: a 1 kg bob on a 1 m rod from the origin, gravity along −y."""
    moving = f"velocity = [{', '.join(map(str, map(float, velocity)))}]\n" if velocity is not None else ""
    return (f'[scene]\nname = "pendulum"\n\n[[particles]]\nname = "bob"\nmass = 1.0\n'
            f"position = [{', '.join(map(str, map(float, position)))}]\n{moving}\n"
            '[[constraints]]\ntype = "distance"\na = "bob"\npoint = [0.0, 0.0, 0.0]\nlength = 1.0\n\n'
            '[[effects]]\ntype = "gravity"\ng = [0.0, -9.81, 0.0]\n\n'
            f"[simulate]\nt_end = {t_end}\n")


def planar_pendulum(theta0: float, omega0: float = 0.0, *, m=1.0, l=1.0, g=9.81) -> C.System:
    """A particle on a rod of length l from the origin, in the plane z = 0, gravity along −y."""
    s = C.System(name="pendulum")
    s.add_particle("bob", m, [l * np.sin(theta0), -l * np.cos(theta0), 0.0],
                   [l * omega0 * np.cos(theta0), l * omega0 * np.sin(theta0), 0.0])
    s.add(C.Distance("bob", point=[0, 0, 0], length=l), C.Plane("bob", [0, 0, 1]),
          C.Gravity([0, -g, 0]))
    return s


def double_pendulum(th1: float = 2.0, th2: float = 2.5) -> C.System:
    """The DESIGN.md double pendulum started from the exact angles."""
    s = C.System(name="double pendulum")
    s.add_particle("p1", 1.0, [np.sin(th1), -np.cos(th1), 0.0])
    s.add_particle("p2", 1.0, [np.sin(th1) + np.sin(th2), -np.cos(th1) - np.cos(th2), 0.0])
    s.add(C.Distance("p1", point=[0, 0, 0], length=1.0), C.Distance("p1", "p2", length=1.0),
          C.Plane(["p1", "p2"], [0, 0, 1], 0.0), C.Gravity([0, -9.81, 0]))
    return s


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
