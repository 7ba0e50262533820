"""The map from a scene's ``[simulate]`` settings to a run: ``simulate`` keyword arguments,
output times, and :class:`RunResult` (what ``Scene.run()`` returns, ``constrained run`` uses).

One place for it, used by the CLI, ``sweep`` and the Python API, so that a scene runs the
same way everywhere. Importing this module is cheap (NumPy, CasADi and the solvers are
imported when a function needs them).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

__all__ = ["RunResult", "simulate_kwargs", "takes_base", "time_grid"]


def time_grid(t_start: float, t_end: float, *, output_dt=None, samples=None):
    """Output times: every ``output_dt`` from t_start (t_end included), or ``samples`` points;
    None when neither is given (the solver's own steps)."""
    import numpy as np

    if samples is not None:
        return np.linspace(t_start, t_end, int(samples))
    if output_dt is None:
        return None
    n = int(np.floor((t_end - t_start) / output_dt + 1e-9))
    grid = t_start + output_dt * np.arange(n + 1)
    if t_end - grid[-1] > 1e-9 * max(1.0, abs(t_end)):
        grid = np.append(grid, t_end)
    else:
        grid[-1] = t_end
    return grid


def takes_base(method: str) -> bool:
    """Whether the solver of ``method`` accepts a ``base`` integrator option."""
    import inspect

    from .solvers import METHODS

    cls = METHODS.get(method)
    return cls is not None and "base" in inspect.signature(cls.__init__).parameters


def simulate_kwargs(scene, outputs: Iterable[str]) -> dict:
    """Keyword arguments of ``constrained.simulate`` for ``scene.settings`` ([simulate]),
    computing ``outputs`` (trajectory quantity names besides t, x, v)."""
    s = scene.settings
    kwargs = dict(
        method=s["method"],
        rtol=s["rtol"],
        atol=s["atol"],
        dt=s["dt"],
        t_start=s["t_start"],
        t_eval=time_grid(s["t_start"], s["t_end"], output_dt=s["output_dt"], samples=s["samples"]),
        outputs=set(outputs),
        max_initial_correction=s["max_initial_correction"],
        compiled=s["compiled"],
    )
    if takes_base(s["method"]):
        kwargs["base"] = s["base"]
    if s["method"] == "reduced":
        from .reduced import ReducedModel

        kwargs["reduced_model"] = ReducedModel.from_scene(scene)
    return kwargs


@dataclass
class RunResult:
    """A scene run with its own settings: the Trajectory and the scene's ``[expect]`` results.

    ``ok`` is True when every check passes (and when the scene has none); ``failed`` lists the
    checks that did not; ``report()`` is the one-line-per-check text ``constrained run`` prints.
    """

    scene: object
    trajectory: object
    expectations: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(r.ok for r in self.expectations)

    @property
    def failed(self) -> list:
        return [r for r in self.expectations if not r.ok]

    def report(self) -> str:
        n, bad = len(self.expectations), len(self.failed)
        lines = [f"expect: {n - bad} of {n} checks pass"]
        lines += ["  " + r.line for r in self.expectations]
        return "\n".join(lines)

    def __iter__(self):  # traj, checks = scene.run()
        return iter((self.trajectory, self.expectations))

    def __repr__(self) -> str:
        n, bad = len(self.expectations), len(self.failed)
        return (f"RunResult({getattr(self.scene, 'name', '?')!r}, {len(self.trajectory.t)} samples, "
                f"expect {n - bad}/{n} pass)")
