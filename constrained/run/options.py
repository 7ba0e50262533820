"""THE map from a scene's ``[simulate]`` settings to the options of one run.

The CLI's ``run``, sweeps and ``cross_check`` all build their runs here, so a setting means
the same everywhere and its default is written once (``scene.SIMULATE_DEFAULTS``). Which
options a method takes is read from its declaration (``Solver.OPTIONS``, ``Solver.BASES``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError
from ..solvers import DEFAULT_METHOD, METHODS


def method_options(method: str) -> tuple[str, ...]:
    """The keyword options ``method`` declares (``()`` for an unknown method)."""
    cls = METHODS.get(method)
    return () if cls is None else tuple(cls.OPTIONS)


def time_grid(t_start: float, t_end: float, *, output_dt=None, samples=None) -> np.ndarray | None:
    """Output times: every ``output_dt`` from t_start (t_end included), or ``samples`` points,
    or None (the method's own steps)."""
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
    """Everything ``simulate`` needs besides the system, for one run.

    ``method_options`` holds only options the method declares (``base`` is dropped for a
    method that takes none). ``simulate_kwargs()`` is the keyword set for ``simulate``.
    """

    method: str
    t_end: float
    t_start: float = 0.0
    rtol: float = 1e-8
    atol: float = 1e-10
    dt: float | None = None
    t_eval: np.ndarray | None = field(default=None, compare=False)
    outputs: frozenset[str] | None = None
    max_initial_correction: float = 1e-3
    compiled: bool | str = "auto"
    rest_speed: float | None = None
    max_steps: int | None = None
    method_options: Mapping[str, Any] = field(default_factory=dict)

    def simulate_kwargs(self) -> dict:
        extra = {k: v for k, v in (("rest_speed", self.rest_speed), ("max_steps", self.max_steps))
                 if v is not None}
        return {"method": self.method, "rtol": self.rtol, "atol": self.atol, "dt": self.dt,
                "t_start": self.t_start, "t_eval": self.t_eval, "outputs": self.outputs,
                "max_initial_correction": self.max_initial_correction, "compiled": self.compiled,
                **extra, **self.method_options}


def from_settings(settings: Mapping[str, Any], *, outputs: Iterable[str] | None = None,
                  scene=None, compiled: bool | str | None = None, **overrides) -> RunOptions:
    """RunOptions from a scene's ``[simulate]`` settings (``scene.settings``).

    ``overrides`` replace settings (``t_end``, ``rtol``, ``t_eval`` …; a method option such as
    ``base`` or ``alpha`` goes to the method when it declares it). ``compiled`` replaces the
    scene's setting (sweeps pass False/True). ``scene`` is needed for method ``reduced``,
    whose generalized coordinates come from the scene's ``[reduced]`` section.
    """
    s = {**settings, **{k: v for k, v in overrides.items() if k in settings or k == "t_eval"}}
    extra = {k: v for k, v in overrides.items() if k not in settings and k != "t_eval"}
    method = s.get("method", DEFAULT_METHOD)
    if method not in METHODS:
        raise InputError(f"unknown method {method!r} (choose from {', '.join(sorted(METHODS))})",
                         where="simulate.method")
    if s.get("t_end") is None:
        raise InputError("no end time: give t_end in [simulate] or as an argument", where="simulate.t_end")
    t_start, t_end = float(s.get("t_start") or 0.0), float(s["t_end"])
    t_eval = s.get("t_eval")
    if t_eval is None:
        t_eval = time_grid(t_start, t_end, output_dt=s.get("output_dt"), samples=s.get("samples"))
    declared = method_options(method)
    options = {k: v for k, v in extra.items() if k in declared}
    unknown = sorted(set(extra) - set(declared))
    if unknown:
        raise InputError(f"method '{method}' does not take the option(s) {', '.join(unknown)}")
    if "base" in declared and "base" not in options and s.get("base") is not None:
        options["base"] = s["base"]
    if method == "reduced" and "reduced_model" not in options:
        if scene is None or getattr(scene, "reduced", None) is None:
            raise InputError("method 'reduced' needs generalized coordinates: give the scene a [reduced] "
                             "section (coordinates, initial, rates, map)", where="simulate.method")
        from .reduced import ReducedModel

        options["reduced_model"] = ReducedModel.from_scene(scene)
    return RunOptions(
        method=method, t_end=t_end, t_start=t_start, rtol=float(s.get("rtol", 1e-8)),
        atol=float(s.get("atol", 1e-10)), dt=s.get("dt"), t_eval=t_eval,
        outputs=None if outputs is None else frozenset(outputs),
        max_initial_correction=float(s.get("max_initial_correction", 1e-3)),
        compiled=s.get("compiled", "auto") if compiled is None else compiled,
        rest_speed=s.get("rest_speed"), max_steps=s.get("max_steps"),
        method_options=options,
    )


def from_scene(scene, *, outputs: Iterable[str] | None = None, compiled: bool | str | None = None,
               **overrides) -> RunOptions:
    """RunOptions of ``scene`` with its own ``[simulate]`` settings and ``overrides``."""
    return from_settings(scene.settings, outputs=outputs, scene=scene, compiled=compiled, **overrides)
