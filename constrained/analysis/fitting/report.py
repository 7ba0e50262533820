"""Reporting a fit: its JSON and CSV, the observables along the fitted run, the figures
(data against the fitted curve, residuals against time)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from ...manifold.manifold import Manifold
from ...model.structure import Model
from ...run.trajectory import Trajectory, atomic_write
from .fit import FitResult
from .observables import observables

__all__ = ["observable_series", "save_fit_figures", "write_fit_csv", "write_fit_json"]


def write_fit_json(result: FitResult, path) -> Path:
    """``result.to_dict()`` as JSON, atomically."""
    text = json.dumps(result.to_dict(), indent=2)
    atomic_write(Path(path), lambda f: f.write(text.encode("utf-8")))
    return Path(path)


def write_fit_csv(result: FitResult, path) -> Path:
    """One row per measurement time: t, then for each output its data, fitted value and residual."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["t", *[f"{k}_{n}" for n in result.outputs for k in ("data", "fitted", "residual")]])
    for i, t in enumerate(result.t):
        row = [repr(float(t))]
        for j in range(len(result.outputs)):
            row += [repr(float(v)) if np.isfinite(v) else "" for v in
                    (result.data[i, j], result.fitted[i, j], result.residuals[i, j])]
        w.writerow(row)
    atomic_write(Path(path), lambda f: f.write(buf.getvalue().encode("utf-8")))
    return Path(path)


def observable_series(model: Model, traj: Trajectory, formulas) -> np.ndarray:
    """(T, k) the observables ``formulas`` along ``traj`` (accelerations and constraint forces
    from the KKT system at each sample)."""
    obs = observables(model, formulas)
    manifold = Manifold(model)
    n = len(traj.t)
    X, V = traj.x.reshape(n, -1), traj.v.reshape(n, -1)
    A = np.array([manifold.accelerations(X[i], V[i], float(traj.t[i]))[0] for i in range(n)])
    p = np.repeat(model.parameter_vector[:, None], n, axis=1)
    return np.asarray(obs.function.map(n)(X.T, V.T, A.T, np.asarray(traj.t)[None, :], p), float).T


def save_fit_figures(result: FitResult, fit_path, residuals_path, curve=None) -> list[Path]:
    """``fit_path``: each output's data (dots) and the fitted model (a line: ``curve`` = (t, y
    (T, k)) along the fitted run when given, else the fitted values); ``residuals_path``: the
    residuals against time, with the ±1 σ band (the σ given, or estimated from the residuals)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    k = len(result.outputs)
    t_line, y_line = curve if curve is not None else (result.t, result.fitted)
    written = []
    for path, residuals in ((fit_path, False), (residuals_path, True)):
        fig = Figure(figsize=(7.0, 1.0 + 2.0 * k), layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(k, 1, sharex=True, squeeze=False)[:, 0]
        for j, (ax, name) in enumerate(zip(axes, result.outputs, strict=True)):
            if residuals:
                r = result.residuals[:, j]
                band = float(np.sqrt(np.nanmean(r * r)))
                ax.axhspan(-band, band, color="0.9", label=f"±{band:.3g} (rms)")
                ax.axhline(0.0, color="0.5", lw=0.8)
                ax.plot(result.t, r, ".", ms=3, color="C3", label="data − fit")
                ax.set_ylabel(f"residual {name}", fontsize="small")
            else:
                ax.plot(result.t, result.data[:, j], ".", ms=3, color="C0", label="data")
                ax.plot(t_line, y_line[:, j], "-", lw=1.2, color="C1", label="fitted model")
                ax.set_ylabel(name, fontsize="small")
            ax.legend(fontsize="small", loc="upper right")
        axes[-1].set_xlabel("t [s]")
        values = ", ".join(f"{n} = {e:.6g} ± {s:.2g}" for n, e, s in
                           zip(result.names, result.estimates, result.standard_errors, strict=True))
        fig.suptitle(("residuals: " if residuals else "fit: ") + values, fontsize="medium")
        atomic_write(Path(path), lambda f, fig=fig: fig.savefig(f, format="png", dpi=110))
        written.append(Path(path))
    return written
