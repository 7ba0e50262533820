"""A sweep's figure: a column against one varied key, or a map over two (with the zero
contour of a boundary formula), and the axis labels with units.

``save_sweep_figure(result, path)`` reads a SweepResult (``specs``, ``rows``, ``columns``,
``column(name)``); formulas are parsed by :mod:`constrained.expressions`, never evaluated.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..model import expressions
from ..run.trajectory import atomic_write
from ..scene.load import apply_overrides
from .design import load_raw


def cell_edges(values: Sequence[float], log: bool = False) -> np.ndarray:
    """Edges of the cells around grid values: midpoints (geometric when ``log``), outer half cells."""
    v = np.asarray(values, float)
    if len(v) == 1:
        return np.array([v[0] * 0.9, v[0] * 1.1]) if log else np.array([v[0] - 0.5, v[0] + 0.5])
    w = np.log(v) if log else v
    mid = 0.5 * (w[1:] + w[:-1])
    edges = np.concatenate([[w[0] - (mid[0] - w[0])], mid, [w[-1] + (w[-1] - mid[-1])]])
    return np.exp(edges) if log else edges


def boundary_function(formula: str, axes: Sequence[str], parameters: dict[str, float]):
    """A vectorized f(*axis arrays) from a formula in the axis names and parameters (no eval)."""
    import casadi as ca

    syms = {n: ca.SX.sym(n) for n in axes}
    names = {**{k: float(v) for k, v in parameters.items()}, **syms}
    expr = ca.SX(expressions.parse(formula, names, where="--boundary"))
    fun = ca.Function("boundary", [syms[n] for n in axes], [expr])

    def f(*arrays):
        shape = np.shape(arrays[0])
        flat = [np.asarray(a, float).ravel()[None, :] for a in arrays]
        return np.asarray(fun.map(flat[0].shape[1])(*flat)).reshape(shape)

    return f


#: units of the scene keys a sweep can vary, by the key's last name (parameters: [scene] units)
KEY_UNITS = {"t_end": "s", "t_start": "s", "dt": "s", "output_dt": "s", "mass": "kg", "position": "m",
             "velocity": "m/s", "length": "m", "rest": "m", "offset": "m", "point": "m", "k": "N/m",
             "coefficient": "N·s/m", "g": "m/s²", "charge": "C"}


#: The summary table's own columns: what each means and its unit (x_P: a coordinate of P at t_end).
_TABLE_COLUMN = re.compile(r"(?:(min|max)_)?(v?[xyz])_(\w+)")
_TABLE_UNITS = {"t_final": ("t_final", "s"), "energy_drift": ("energy drift max |E − E0|", "J"),
                "max_constraint_residual": ("max constraint residual", "m"),
                "max_velocity_residual": ("max velocity residual", "m/s")}


def axis_label(key: str, units: dict | None = None) -> str:
    """``"a [m]"`` for ``parameters.a`` with ``units = {a = "m"}``; known keys get their SI unit
    (``particles.p1.mass [kg]``); a summary column is looked up in ``units`` by its name, and the
    table's own columns say what they are (``min_y_bob`` → ``smallest y of bob over the run [m]``)."""
    units = units or {}
    if "." not in key and key not in units:
        if key in _TABLE_UNITS:
            return f"{_TABLE_UNITS[key][0]} [{_TABLE_UNITS[key][1]}]"
        m = _TABLE_COLUMN.fullmatch(key)
        if m:
            extreme, coordinate, particle = m.groups()
            when = {"min": "smallest {} of {} over the run", "max": "largest {} of {} over the run",
                    None: "{} of {} at t_end"}[extreme].format(coordinate, particle)
            return f"{when} [{'m/s' if coordinate.startswith('v') else 'm'}]"
    parts = re.split(r"[.\[\]]+", key.strip("."))
    names = [p for p in parts if p and not p.isdigit()]
    last = names[-1] if names else key
    if key.startswith("parameters."):
        unit = units.get(last)
        return f"{last} [{unit}]" if unit else f"{last} (parameter)"
    unit = units.get(key) or (KEY_UNITS.get(last) if "." in key else None)
    return f"{key} [{unit}]" if unit else key


def default_column(result, summaries: Sequence[str] = ()) -> tuple[str | None, str]:
    """``(column, why)``: what sweep.png shows without ``--plot`` — the first ``--summary``
    column; else the position coordinate of the table (at t_end, or smallest or largest over
    the run) that varies most across the runs, in metres: what the varied keys change most in
    the motion. Never a measure of the runs' accuracy (energy drift, residuals): energy is not
    even conserved in a driven or damped scene."""
    named = [c for c in summaries if c in result.columns]
    if named:
        return named[0], ""
    spread = {}
    for c in result.columns:
        m = _TABLE_COLUMN.fullmatch(c)
        if m and not m.group(2).startswith("v"):
            z = result.column(c)
            if z.dtype != object and np.isfinite(z).sum() > 1:
                spread[c] = float(np.nanmax(z) - np.nanmin(z))
    if not spread:
        return None, ""
    best = max(spread, key=spread.get)  # the first of equals: columns are in particle order
    return best, "the coordinate that varies most; --plot COLUMN to choose"


def save_sweep_figure(result, path, *, column: str | None = None, boundary: str | None = None,
                      scene_text: str | None = None, file: str = "scene", overrides=(),
                      summaries: Sequence[str] = ()) -> Path | None:
    """1-D: ``column`` (default: ``default_column``) against the parameter; 2-D grid: a map,
    with the zero contour of ``boundary``. None (nothing drawn, matplotlib not even imported)
    when not one or two keys vary."""
    specs = [s for s in result.specs if len(set(map(repr, s.values))) > 1 or s.random]
    if len(specs) not in (1, 2):
        return None
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    why = ""
    if column is None:
        column, why = default_column(result, summaries)
    if column is None or column not in result.columns or len(specs) not in (1, 2):
        return None
    z = result.column(column)
    if z.dtype == object:
        return None
    if any(not all(isinstance(v, int | float) for v in (s.values or (0.0,))) for s in specs):
        return None
    units = {}
    if scene_text is not None:
        scene_table = load_raw(scene_text, file).get("scene", {})
        units = scene_table.get("units", {}) if isinstance(scene_table, dict) else {}
    fig, ax = plt.subplots(figsize=(6.4, 4.8), constrained_layout=True)
    if len(specs) == 1:
        s = specs[0]
        x = np.asarray(result.column(s.key), float)
        order = np.argsort(x)
        ax.plot(x[order], z[order], "o-", ms=3)
        ax.set_xlabel(axis_label(s.key, units))
        ax.set_ylabel(axis_label(column, units))
        if s.log:
            ax.set_xscale("log")
        ax.grid(True, alpha=0.3)
    else:
        sx, sy = specs[1], specs[0]  # the second key across, the first up
        if sx.scattered or sy.scattered:
            xs = np.asarray(result.column(sx.key), float)
            ys = np.asarray(result.column(sy.key), float)
            im = ax.scatter(xs, ys, c=z, cmap="viridis", s=20)
            gx = np.linspace(xs.min(), xs.max(), 200)
            gy = np.linspace(ys.min(), ys.max(), 200)
        else:
            Z = np.full((len(sy.values), len(sx.values)), np.nan)
            jx = {v: j for j, v in enumerate(sx.values)}
            iy = {v: i for i, v in enumerate(sy.values)}
            for x_, y_, val in zip(result.column(sx.key), result.column(sy.key), z, strict=True):
                Z[iy[y_], jx[x_]] = val
            ex, ey = cell_edges(sx.values, sx.log), cell_edges(sy.values, sy.log)
            finite = Z[np.isfinite(Z)]
            norm = None
            if finite.size and finite.min() < 0 < finite.max():
                norm = TwoSlopeNorm(0.0, finite.min(), finite.max())
            im = ax.pcolormesh(ex, ey, Z, cmap="RdBu" if norm is not None else "viridis", norm=norm,
                               shading="flat")
            gx = np.geomspace(ex[0], ex[-1], 400) if sx.log else np.linspace(ex[0], ex[-1], 400)
            gy = np.geomspace(ey[0], ey[-1], 400) if sy.log else np.linspace(ey[0], ey[-1], 400)
        fig.colorbar(im, ax=ax, label=axis_label(column, units))
        if boundary:
            params = {}
            if scene_text is not None:
                raw = apply_overrides(load_raw(scene_text, file), list(overrides), file=file)
                params = {k: v for k, v in raw.get("parameters", {}).items() if isinstance(v, int | float)}
            fb = boundary_function(boundary, [sx.name, sy.name], params)
            GX, GY = np.meshgrid(gx, gy)
            ax.contour(GX, GY, fb(GX, GY), levels=[0.0], colors="k", linewidths=1.5)
            ax.plot([], [], "k-", label=f"{boundary} = 0")
            ax.legend(loc="upper right", fontsize=8)
        ax.set_xlabel(axis_label(sx.key, units))
        ax.set_ylabel(axis_label(sy.key, units))
        if sx.log:
            ax.set_xscale("log")
        if sy.log:
            ax.set_yscale("log")
    ax.set_title(f"sweep: {column} ({result.finished} runs)" + (f"\n({why})" if why else ""), fontsize=10)
    path = Path(path)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=120))
    plt.close(fig)
    return path
