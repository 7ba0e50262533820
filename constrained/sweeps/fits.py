"""Many fits of one scene: one per data set (trials, cameras, noise draws), in this process or
on Dask.

Each data set is one task: the scene's text, the --set overrides and the measurements go to
the worker, which reads the scene, fits (constrained.fitting.fit) and returns one row — the
estimates, their standard errors, χ², the degrees of freedom, and the status (``converged``,
``not converged: …`` or the error that stopped it). A failing fit is a row with its error;
the others go on. ``scheduler`` as for sweeps (constrained.execute): "sequential" (here),
"local" (a local Dask cluster), "tcp://HOST:PORT", or a ``distributed.Client``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..analysis.fitting.fit import fit
from ..analysis.fitting.measurements import Measurements, read_measurements
from ..errors import ConstrainedError, InputError
from ..scene.load import SceneError, apply_overrides, build_scene
from .design import load_raw
from .execute import _client

__all__ = ["FitSweep", "fit_sweep"]


@dataclass(frozen=True)
class FitSweep:
    """``rows``: one dict per data set, in the order given (``data``, ``status``, and per
    fitted parameter NAME its ``NAME`` estimate and ``se_NAME``; ``chi2``, ``dof``,
    ``reduced_chi2``, ``nfev``); ``where``: what ran them."""

    parameters: tuple[str, ...]
    rows: list[dict] = field(default_factory=list)
    where: str = "in-process"

    @property
    def failed(self) -> int:
        return sum(1 for r in self.rows if r["status"] != "converged")

    def estimates(self) -> np.ndarray:
        """(data sets, parameters), NaN where a fit failed."""
        return np.array([[r.get(n, math.nan) for n in self.parameters] for r in self.rows], float)

    def standard_errors(self) -> np.ndarray:
        return np.array([[r.get(f"se_{n}", math.nan) for n in self.parameters] for r in self.rows], float)


def _fit_task(task: dict) -> dict:
    """One fit (on a worker or here): the row of its data set."""
    row = {"data": task["label"], "status": "converged"}
    try:
        raw = apply_overrides(load_raw(task["scene_text"], task["file"]), list(task["overrides"]),
                              file=task["file"])
        scene = build_scene(raw, path=task["file"])
        data = Measurements(**task["data"])
        result = fit(scene.system, data, task["parameters"], t_start=scene.settings["t_start"],
                     **task["options"])
    except (ConstrainedError, SceneError) as exc:
        return {**row, "status": f"error: {' '.join(str(exc).split())}"}
    for name, estimate, se in zip(result.names, result.estimates, result.standard_errors, strict=True):
        row[name], row[f"se_{name}"] = float(estimate), float(se)
    row.update(chi2=result.chi2, dof=result.dof, reduced_chi2=result.reduced_chi2, nfev=result.nfev)
    if not result.success:
        row["status"] = f"not converged: {result.message}"
    return row


def _data(item, k: int) -> tuple[str, dict]:
    """(label, Measurements fields) of a data set: a CSV path or Measurements."""
    if isinstance(item, str | Path):
        item = read_measurements(item)
    if not isinstance(item, Measurements):
        raise InputError(f"data set {k} must be a CSV file or Measurements, got {type(item).__name__}",
                         where="datasets")
    return item.source if item.source != "data" else f"data set {k}", {
        "t": item.t, "names": item.names, "values": item.values, "sigma": item.sigma, "source": item.source}


def fit_sweep(scene_path, datasets: Iterable, parameters: Sequence[str], *, overrides: Sequence[str] = (),
              scheduler="sequential", workers: int | None = None, **options: Mapping) -> FitSweep:
    """Fit ``parameters`` of the scene at ``scene_path`` to each of ``datasets`` (CSV paths or
    Measurements), one task each (see the module); ``options`` go to ``fit`` (observables,
    start, bounds, sigma, rtol, atol, max_nfev)."""
    path = Path(scene_path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SceneError(f"cannot read the file ({exc.strerror or exc})", file=str(path)) from None
    names = [parameters] if isinstance(parameters, str) else list(parameters)
    tasks = []
    for k, item in enumerate(datasets):
        label, data = _data(item, k)
        tasks.append({"scene_text": text, "file": str(path), "overrides": list(overrides), "label": label,
                      "data": data, "parameters": names, "options": dict(options)})
    if not tasks:
        raise InputError("no data set to fit", where="datasets")
    if scheduler == "sequential":
        return FitSweep(tuple(names), [_fit_task(t) for t in tasks], "in-process")
    client, close = _client(scheduler, workers)
    try:
        futures = client.map(_fit_task, tasks, pure=False)
        rows = client.gather(futures)
        n = len(client.scheduler_info().get("workers", {}))
    finally:
        close()
    return FitSweep(tuple(names), list(rows), f"Dask ({n} worker(s))")
