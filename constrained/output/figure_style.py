"""What every figure shares: an Agg figure, particle and constraint names, colours, legends,
the time axis with the run's events marked, and the plane of a planar motion."""

from __future__ import annotations

import dataclasses

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from ..errors import InputError
from ..run.trajectory import QUANTITIES, Trajectory

#: Legends list at most this many entries, then "…".
MAX_LEGEND = 12
#: Relative tolerance of the planarity test (distance to the plane / size of the motion).
PLANAR_RTOL = 1e-9
AXES = "xyz"


def new_figure(size=(7.0, 4.5)) -> Figure:
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def particle_names(traj: Trajectory) -> list[str]:
    n = traj.x.shape[1]
    names = list(traj.particle_names or [])
    return names if len(names) == n else [f"particle {i}" for i in range(n)]


def constraint_labels(traj: Trajectory, count: int) -> list[str]:
    labels = list(traj.constraint_labels or [])
    return labels if len(labels) == count else [f"constraint {k}" for k in range(count)]


def colour(i: int) -> str:
    return f"C{i % 10}"


#: From this many curves a figure draws them as one collection (LineCollection) with one
#: scatter for each kind of marker: one artist per curve took 4 s for a 3,000-bead rope's paths.
MANY_CURVES = 64


def curves(ax, paths: np.ndarray, *, lw: float = 1.5, ends: bool = False, alpha: float = 1.0) -> list:
    """Draw the curves ``paths`` (n, T, 2) — or (n, T, 3) on 3D axes — in the colours
    ``colour(i)``, with a start circle and an end square each when ``ends``; return one legend
    handle per curve (a proxy line of its colour where the curves are one collection)."""
    paths = np.asarray(paths, float)
    n, three_d = len(paths), paths.shape[-1] == 3
    if n < MANY_CURVES:
        handles = []
        for i, p in enumerate(paths):
            (line,) = ax.plot(*p.T, color=colour(i), lw=lw, alpha=alpha)
            if ends:
                ax.plot(*p[0][:, None], "o", color=colour(i), ms=7, mfc="white", mew=1.8)
                ax.plot(*p[-1][:, None], "s", color=colour(i), ms=6)
            handles.append(line)
        return handles
    colours = [colour(i) for i in range(n)]
    if three_d:
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        ax.add_collection3d(Line3DCollection(paths, colors=colours, linewidths=lw, alpha=alpha))
    else:
        from matplotlib.collections import LineCollection

        ax.add_collection(LineCollection(paths, colors=colours, linewidths=lw, alpha=alpha))
    finite = paths.reshape(-1, paths.shape[-1])
    finite = finite[np.all(np.isfinite(finite), axis=1)]
    if len(finite):  # (a collection does not move the data limits)
        if three_d:
            ax.auto_scale_xyz(finite[:, 0], finite[:, 1], finite[:, 2])
        else:
            ax.update_datalim(finite)
            ax.autoscale_view()
    if ends:
        ax.scatter(*paths[:, 0].T, marker="o", s=49, facecolors="white", edgecolors=colours, linewidths=1.8)
        ax.scatter(*paths[:, -1].T, marker="s", s=36, c=colours)
    return [Line2D([], [], color=c, lw=lw) for c in colours[:MAX_LEGEND]] + [None] * (n - MAX_LEGEND)


def legend(ax, handles: list, labels: list[str], **kwargs) -> None:
    """Legend with at most MAX_LEGEND entries; the rest is summed up as "… (k more)"."""
    if not handles:
        return
    if len(handles) > MAX_LEGEND:
        more = len(handles) - MAX_LEGEND
        handles = [*handles[:MAX_LEGEND], Line2D([], [], linestyle="none")]
        labels = [*labels[:MAX_LEGEND], f"… ({more} more)"]
    if len(handles) > 4:  # many entries would hide the curves: put the legend outside
        kwargs = {**kwargs, "loc": "upper left", "bbox_to_anchor": (1.01, 1.0)}
    ax.legend(handles, labels, fontsize="small", **kwargs)


def need(traj: Trajectory, name: str, what: str) -> np.ndarray:
    value = getattr(traj, name)
    if value is None:
        raise InputError(
            f"this trajectory has no {what}: run the simulation with '{name}' among the "
            f"requested quantities to plot it"
        )
    return np.asarray(value, dtype=float)


#: Events marked in one figure at most (a settling ball has many; the first ones tell).
MAX_MARKED_EVENTS = 60
#: Line colours of the event kinds (user events: grey).
EVENT_COLOURS = {"release": "tab:red", "contact": "tab:green", "impact": "tab:purple"}


def time_axis(ax, traj: Trajectory | None = None) -> None:
    """The time axis; the instants of the run's events (``traj.events``) as thin dashed lines,
    coloured by kind, with the kinds in a small legend."""
    ax.set_xlabel("t [s]")
    ax.grid(True, alpha=0.3)
    events = list(getattr(traj, "events", None) or [])[:MAX_MARKED_EVENTS]
    if not events:
        return
    kinds = {}
    for e in events:
        colour = EVENT_COLOURS.get(e.kind, "0.45")
        ax.axvline(e.t, color=colour, lw=0.8, ls="--", alpha=0.7, zorder=0)
        kinds.setdefault(e.kind, colour)
    from matplotlib.legend import Legend

    # an artist of its own: the figure's own legend, made later, does not replace it
    ax.add_artist(Legend(ax, [Line2D([], [], color=c, lw=0.8, ls="--") for c in kinds.values()], list(kinds),
                         fontsize="x-small", loc="lower left", title="events", title_fontsize="x-small"))


# --------------------------------------------------------------------------------- planarity


def motion_plane(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[str, str]] | None:
    """The plane holding every position of ``x`` (shape (..., 3)), or None if there is none.

    Returns ``(origin, basis, labels)``: plane coordinates are ``(p - origin) @ basis.T``
    (``basis`` is 2×3, orthonormal rows). When the plane is a coordinate plane (e.g.
    z = const) the basis is the two other unit axes and labels are their names ("x", "y");
    otherwise the basis is the two principal directions and labels are ("u", "v").
    "In the plane" means within ``PLANAR_RTOL`` times the size of the motion.
    """
    p = np.asarray(x, dtype=float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) == 0:
        return None
    origin = p.mean(axis=0)
    c = p - origin
    size = float(np.max(np.ptp(p, axis=0)))
    tol = PLANAR_RTOL * size
    spread = np.ptp(p, axis=0)
    flat = [k for k in range(3) if spread[k] <= tol]
    if flat:
        k = flat[-1]  # prefer z = const, then y = const, then x = const
        keep = [j for j in range(3) if j != k]
        return origin, np.eye(3)[keep], (AXES[keep[0]], AXES[keep[1]])
    # (fewer than 3 points: zero rows complete the SVD's three directions without moving them)
    _, _, vt = np.linalg.svd(np.vstack([c, np.zeros((max(0, 3 - len(c)), 3))]), full_matrices=False)
    normal = vt[2]
    if np.max(np.abs(c @ normal)) > tol:
        return None
    basis = vt[:2].copy()
    for row in basis:  # deterministic orientation: largest component positive
        if row[np.argmax(np.abs(row))] < 0:
            row *= -1
    if np.dot(np.cross(basis[0], basis[1]), normal) < 0:
        normal = -normal
    return origin, basis, ("u", "v")


def fmt_vec(v: np.ndarray) -> str:
    v = np.where(np.abs(v) < 5e-4, 0.0, v)
    return "(" + ", ".join(f"{c:.3g}" for c in v) + ")"


def finite_samples(traj: Trajectory) -> tuple[Trajectory, int]:
    """``(traj, 0)``, or the trajectory without its samples whose time, positions or velocities
    are not finite (a damaged or hand-made file) and how many were left out; InputError when
    no sample is left to draw."""
    n = len(traj.t)
    if n == 0:  # (np.reshape of an empty x to (0, -1) would raise)
        raise InputError("the trajectory has no samples: nothing to draw")
    ok = (np.isfinite(np.asarray(traj.t, float)) & np.all(np.isfinite(np.reshape(traj.x, (n, -1))), axis=1)
          & np.all(np.isfinite(np.reshape(traj.v, (n, -1))), axis=1))
    if ok.all():
        return traj, 0
    if not ok.any():
        raise InputError(f"none of the trajectory's {n} samples has finite positions and velocities: "
                         "nothing to draw")
    cut = {name: None if getattr(traj, name) is None else np.asarray(getattr(traj, name))[ok]
           for name in ("t", "x", "v", *QUANTITIES)}
    return dataclasses.replace(traj, **cut), int(n - ok.sum())


def nonfinite_quantities(traj: Trajectory) -> list[tuple[str, int, int]]:
    """``(name, samples not finite, samples)`` of each saved quantity (energy, multipliers, ...)
    with values that are not finite at some sample: ``plot`` says so, as it does of positions."""
    found = []
    for name in QUANTITIES:
        values = getattr(traj, name, None)
        if values is None or not len(traj.t) or np.asarray(values).size == 0:
            continue
        rows = np.reshape(np.asarray(values, float), (len(traj.t), -1))
        bad = int(np.sum(~np.all(np.isfinite(rows), axis=1)))
        if bad:
            found.append((name, bad, len(traj.t)))
    return found
