"""THE map from a scene's ``[simulate]`` settings to the options of one run.

``Scene.run()`` (and through it ``constrained run``) builds its runs here, so a setting means
the same everywhere. The names follow the solver-core plan (docs/architecture.md):
``from_scene(scene, outputs=...)`` gives a frozen ``RunOptions`` whose ``simulate_kwargs()``
is the keyword set of ``simulate``. NumPy and the solvers are imported when a function needs
them, not when this module is imported.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from .errors import InputError

__all__ = ["RunOptions", "from_scene", "from_settings", "takes_option", "time_grid"]


def takes_option(method: str, option: str) -> bool:
    """Whether the solver of ``method`` accepts the keyword ``option`` (e.g. ``base``)."""
    import inspect

    from .solvers import METHODS

    cls = METHODS.get(method)
    return cls is not None and option in inspect.signature(cls.__init__).parameters


def time_grid(t_start: float, t_end: float, *, output_dt=None, samples=None):
    """Output times: every ``output_dt`` from t_start (t_end included), or ``samples`` points,
    or None (the method's own steps)."""
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


@dataclass(frozen=True)
class RunOptions:
    """Everything ``simulate`` needs besides the system, for one run; ``simulate_kwargs()``
    is the keyword set for ``simulate``."""

    method: str
    t_end: float
    t_start: float = 0.0
    rtol: float = 1e-8
    atol: float = 1e-10
    dt: float | None = None
    t_eval: Any = field(default=None, compare=False)
    outputs: frozenset[str] | None = None
    max_initial_correction: float = 1e-3
    compiled: bool | str = "auto"
    method_options: Mapping[str, Any] = field(default_factory=dict)

    def simulate_kwargs(self) -> dict:
        return {"method": self.method, "rtol": self.rtol, "atol": self.atol, "dt": self.dt,
                "t_start": self.t_start, "t_eval": self.t_eval, "outputs": self.outputs,
                "max_initial_correction": self.max_initial_correction, "compiled": self.compiled,
                **self.method_options}


def from_settings(settings: Mapping[str, Any], *, outputs: Iterable[str] | None = None,
                  scene=None, compiled: bool | str | None = None) -> RunOptions:
    """RunOptions from a scene's ``[simulate]`` settings (``scene.settings``); ``scene`` is
    needed for method ``reduced`` (its ``[reduced]`` coordinates)."""
    s = dict(settings)
    method = s.get("method", "projection")
    if s.get("t_end") is None:
        raise InputError("no end time: give t_end in [simulate] or override simulate.t_end",
                         where="simulate.t_end")
    t_start, t_end = float(s.get("t_start") or 0.0), float(s["t_end"])
    options: dict[str, Any] = {}
    if s.get("base") is not None and takes_option(method, "base"):
        options["base"] = s["base"]
    if method == "reduced":
        if scene is None or getattr(scene, "reduced", None) is None:
            raise InputError("method 'reduced' needs generalized coordinates: give the scene a [reduced] "
                             "section (coordinates, initial, rates, map)", where="simulate.method")
        from .reduced import ReducedModel

        options["reduced_model"] = ReducedModel.from_scene(scene)
    return RunOptions(
        method=method, t_end=t_end, t_start=t_start, rtol=float(s.get("rtol", 1e-8)),
        atol=float(s.get("atol", 1e-10)), dt=s.get("dt"),
        t_eval=time_grid(t_start, t_end, output_dt=s.get("output_dt"), samples=s.get("samples")),
        outputs=None if outputs is None else frozenset(outputs),
        max_initial_correction=float(s.get("max_initial_correction", 1e-3)),
        compiled=s.get("compiled", "auto") if compiled is None else compiled,
        method_options=options,
    )


def from_scene(scene, *, outputs: Iterable[str] | None = None,
               compiled: bool | str | None = None) -> RunOptions:
    """RunOptions of ``scene`` with its own ``[simulate]`` settings."""
    return from_settings(scene.settings, outputs=outputs, scene=scene, compiled=compiled)
