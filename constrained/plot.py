"""Figures of a Trajectory: paths, energy drift, residuals, constraint forces, multipliers, phase,
and an animation (GIF through matplotlib's PillowWriter; also MP4 when ffmpeg is on PATH).

Every ``*_figure`` function returns a :class:`matplotlib.figure.Figure` drawn on an Agg canvas;
pyplot and its global state are never touched, so this works headless and in threads.
``save_figures`` writes several of them as PNG files, each atomically.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the "3d" projection)

from .errors import InputError
from .trajectory import Trajectory, atomic_write

#: Legends list at most this many entries, then "…".
MAX_LEGEND = 12
#: Relative tolerance of the planarity test (distance to the plane / size of the motion).
PLANAR_RTOL = 1e-9
_AXES = "xyz"


def _figure(size=(7.0, 4.5)) -> Figure:
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _names(traj: Trajectory) -> list[str]:
    n = traj.x.shape[1]
    names = list(traj.particle_names or [])
    return names if len(names) == n else [f"particle {i}" for i in range(n)]


def _labels(traj: Trajectory, count: int) -> list[str]:
    labels = list(traj.constraint_labels or [])
    return labels if len(labels) == count else [f"constraint {k}" for k in range(count)]


def _colour(i: int) -> str:
    return f"C{i % 10}"


def _legend(ax, handles: list, labels: list[str], **kwargs) -> None:
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


def _need(traj: Trajectory, name: str, what: str) -> np.ndarray:
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


def _time_axis(ax, traj: Trajectory | None = None) -> None:
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
        return origin, np.eye(3)[keep], (_AXES[keep[0]], _AXES[keep[1]])
    _, _, vt = np.linalg.svd(c, full_matrices=False)
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


def _fmt_vec(v: np.ndarray) -> str:
    v = np.where(np.abs(v) < 5e-4, 0.0, v)
    return "(" + ", ".join(f"{c:.3g}" for c in v) + ")"


def trajectory_figure(traj: Trajectory) -> Figure:
    """Particle paths, drawn in 2D when the motion is planar and in 3D otherwise.

    Each path starts at a circle and ends at a square; the legend names the particles.
    """
    x = np.asarray(traj.x, dtype=float)
    names = _names(traj)
    plane = motion_plane(x)
    fig = _figure((7.0, 6.0))
    handles = []
    if plane is not None:
        origin, basis, (a, b) = plane
        ax = fig.add_subplot()
        coordinate_plane = a != "u"
        # coordinate planes keep the raw coordinates; a general plane is centred at the origin
        shift = np.zeros(3) if coordinate_plane else origin
        q = (x - shift) @ basis.T  # (T, N, 2)
        for i in range(len(names)):
            (line,) = ax.plot(q[:, i, 0], q[:, i, 1], color=_colour(i), lw=1.5)
            ax.plot(*q[0, i], "o", color=_colour(i), ms=7, mfc="white", mew=1.8)
            ax.plot(*q[-1, i], "s", color=_colour(i), ms=6)
            handles.append(line)
        for e in traj.events[:MAX_MARKED_EVENTS]:
            at = (np.asarray(e.x, float) - shift) @ basis.T
            ax.plot(at[:, 0], at[:, 1], "x", color=EVENT_COLOURS.get(e.kind, "0.45"), ms=7, mew=1.6)
        ax.set_xlabel(f"{a} [m]")
        ax.set_ylabel(f"{b} [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        if coordinate_plane:
            k = next(c for c in _AXES if c not in (a, b))
            where = f"planar motion in {a}–{b} plane ({k} = {origin[_AXES.index(k)]:.4g} m)"
        else:
            where = (
                f"planar motion; u = {_fmt_vec(basis[0])}, v = {_fmt_vec(basis[1])}, "
                f"origin {_fmt_vec(origin)} m"
            )
        ax.set_title(f"Particle paths\n{where}", fontsize="medium")
    else:
        ax = fig.add_subplot(projection="3d")
        for i in range(len(names)):
            p = x[:, i]
            (line,) = ax.plot(p[:, 0], p[:, 1], p[:, 2], color=_colour(i), lw=1.5)
            ax.plot(*p[0][:, None], "o", color=_colour(i), ms=7, mfc="white", mew=1.8)
            ax.plot(*p[-1][:, None], "s", color=_colour(i), ms=6)
            handles.append(line)
        for e in traj.events[:MAX_MARKED_EVENTS]:
            at = np.asarray(e.x, float)
            ax.plot(at[:, 0], at[:, 1], at[:, 2], "x", color=EVENT_COLOURS.get(e.kind, "0.45"), ms=7, mew=1.6)
        ax.set_xlabel("x [m]", labelpad=10)
        ax.set_ylabel("y [m]", labelpad=10)
        ax.set_zlabel("z [m]", labelpad=12)
        finite = x.reshape(-1, 3)[np.all(np.isfinite(x.reshape(-1, 3)), axis=1)]
        if len(finite):
            span = np.ptp(finite, axis=0)
            # a thin axis keeps a readable depth (its ticks would collide otherwise)
            # zoom < 1 leaves room for the axis labels (the z label is cut off at 1)
            ax.set_box_aspect(np.maximum(span, 0.25 * max(span.max(), 1e-12)), zoom=0.82)
        from matplotlib.ticker import MaxNLocator

        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_major_locator(MaxNLocator(5))
        ax.set_title("Particle paths (3D)", fontsize="medium")
    markers = [
        Line2D([], [], marker="o", color="0.3", mfc="white", mew=1.8, linestyle="none"),
        Line2D([], [], marker="s", color="0.3", linestyle="none"),
    ]
    words = ["start", "end"]
    if traj.events:
        markers.append(Line2D([], [], marker="x", color="0.3", mew=1.6, linestyle="none"))
        kinds = dict.fromkeys(e.kind for e in traj.events[:MAX_MARKED_EVENTS])
        words.append(f"events ({', '.join(kinds)})")
    _legend(ax, handles, names, loc="upper left")
    _legend_markers(ax, markers, words)
    return fig


def _legend_markers(ax, markers, words=("start", "end")) -> None:
    """A second legend for the start/end (and event) markers, kept beside the particle legend."""
    first = ax.get_legend()
    ax.legend(markers, list(words), fontsize="small", loc="lower right")
    if first is not None:
        ax.add_artist(first)


# ------------------------------------------------------------------------ time series figures


#: model terms (``Trajectory.info["active_terms"]``) that make E = T + V change physically,
#: with the words for them
NOT_CONSERVING = {
    "rheonomic": "moving (rheonomic) constraints",
    "time_dependent_forces": "time-dependent forces",
    "dissipation": "damping",
    "applied_force": "applied forces",
}


def driving_terms(traj: Trajectory) -> list[str]:
    """What keeps the energy of this run from being conserved (empty for a free scene)."""
    active = set(traj.info.get("active_terms", ()) if traj.info else ())
    words = [words for term, words in NOT_CONSERVING.items() if term in active]
    if any(e.energy_lost > 0 for e in getattr(traj, "events", ())):
        words.append("impacts")
    return words


def energy_figure(traj: Trajectory) -> Figure:
    """E(t) − E(0) in joules; E(0) is given in the title. Called "drift" only where E is
    conserved: a driven or damped scene's title says what changes E (the energy is not a
    check of the integration there)."""
    energy = _need(traj, "energy", "energy")
    t = np.asarray(traj.t, dtype=float)
    e0 = energy[0]
    drift = energy - e0
    fig = _figure()
    ax = fig.add_subplot()
    ax.plot(t, drift, color="C0", lw=1.5)
    ax.axhline(0.0, color="0.5", lw=0.8, ls="--")
    _time_axis(ax, traj)
    ax.set_ylabel("E(t) − E(0) [J]")
    finite = drift[np.isfinite(drift)]
    worst = float(np.max(np.abs(finite))) if len(finite) else float("nan")
    rel = f" (relative {worst / abs(e0):.2e})" if e0 != 0 and np.isfinite(e0) else ""
    driven = driving_terms(traj)
    if driven:
        title = (f"Energy change (E(0) = {e0:.6g} J): not conserved here, by physics\n"
                 f"{' and '.join(driven)} change E; max |E − E(0)| = {worst:.3g} J")
    else:
        title = f"Energy drift (E(0) = {e0:.6g} J)\nmax |E − E(0)| = {worst:.3g} J{rel}"
    ax.set_title(title, fontsize="medium")
    return fig


def _floor_positive(values: list[np.ndarray]) -> float:
    """A floor for log plots: a decade below the smallest positive value (1e-16 if none)."""
    positive = np.concatenate([v[np.isfinite(v) & (v > 0)] for v in values] or [np.empty(0)])
    return float(positive.min()) / 10 if len(positive) else 1e-16


def residual_figure(traj: Trajectory) -> Figure:
    """Constraint residual max|f| [m] and velocity residual max|J v + f_t| [m/s], log scale."""
    panels = [
        (name, np.abs(np.asarray(value, dtype=float)))
        for name, value in (
            ("constraint_residual", traj.constraint_residual),
            ("velocity_residual", traj.velocity_residual),
        )
        if value is not None
    ]
    if not panels:
        raise InputError(
            "this trajectory has no constraint or velocity residual: run the simulation with "
            "'constraint_residual' or 'velocity_residual' among the requested quantities"
        )
    t = np.asarray(traj.t, dtype=float)
    text = {
        "constraint_residual": ("Position-level constraint residual", "max$_k$ |f$_k$| [m]", "C3"),
        "velocity_residual": (
            "Velocity-level constraint residual",
            "max$_k$ |(J v + ∂f/∂t)$_k$| [m/s]",
            "C4",
        ),
    }
    fig = _figure((7.0, 3.0 * len(panels) + 0.5))
    axes = fig.subplots(len(panels), 1, squeeze=False)[:, 0]
    for ax, (name, value) in zip(axes, panels, strict=True):
        title, ylabel, colour = text[name]
        floor = _floor_positive([value])
        zeros = int(np.count_nonzero(value == 0))
        ax.semilogy(t, np.maximum(value, floor), color=colour, lw=1.2)
        _time_axis(ax, traj)
        ax.set_ylabel(ylabel)
        finite = value[np.isfinite(value)]
        if not len(finite):
            worst = "no finite values"
        elif finite.max() == 0:
            worst = "identically zero"
        else:
            worst = f"max {finite.max():.2e}"
        # the note on exact zeros goes in the title: inside the axes it would cover the curve
        note = f"\n{zeros} exact zero{'s' if zeros > 1 else ''} drawn at {floor:.0e}" if zeros else ""
        ax.set_title(f"{title} ({worst}){note}", fontsize="medium")
    return fig


def constraint_forces_figure(traj: Trajectory) -> Figure:
    """Magnitude of the total constraint force on each particle, |F_con,i|(t) in newtons."""
    forces = _need(traj, "constraint_forces", "constraint forces")
    t = np.asarray(traj.t, dtype=float)
    magnitude = np.linalg.norm(forces, axis=2)
    names = _names(traj)
    fig = _figure()
    ax = fig.add_subplot()
    handles = [
        ax.plot(t, magnitude[:, i], color=_colour(i), lw=1.3)[0] for i in range(len(names))
    ]
    _time_axis(ax, traj)
    ax.set_ylabel("|F$_{con}$| [N]")
    ax.set_ylim(bottom=0.0)
    ax.set_title("Constraint force on each particle", fontsize="medium")
    _legend(ax, handles, names, loc="best")
    return fig


def multipliers_figure(traj: Trajectory) -> Figure:
    """Each Lagrange multiplier λ_k(t); the legend names the constraint rows."""
    lam = _need(traj, "multipliers", "multipliers")
    lam = lam.reshape(len(lam), -1)
    t = np.asarray(traj.t, dtype=float)
    labels = _labels(traj, lam.shape[1])
    fig = _figure()
    ax = fig.add_subplot()
    handles = [ax.plot(t, lam[:, k], color=_colour(k), lw=1.3)[0] for k in range(lam.shape[1])]
    ax.axhline(0.0, color="0.5", lw=0.8, ls="--")
    _time_axis(ax, traj)
    ax.set_ylabel("λ [N] (for constraints f in m)")
    rows = f"{lam.shape[1]} constraint row{'s' if lam.shape[1] != 1 else ''}"
    ax.set_title(f"Lagrange multipliers ({rows})", fontsize="medium")
    _legend(ax, handles, labels, loc="best")
    return fig


def principal_coordinate(traj: Trajectory) -> tuple[np.ndarray, np.ndarray, float]:
    """``(s, ds/dt, share)``: positions projected on their first principal direction.

    PCA over the flattened configurations x(t) ∈ R^{3N}; ``share`` is the fraction of the
    position variance that direction carries (1 for a rigid one-degree-of-freedom line
    motion, close to 1 for small oscillations).
    """
    x = np.asarray(traj.x, dtype=float).reshape(len(traj.t), -1)
    v = np.asarray(traj.v, dtype=float).reshape(len(traj.t), -1)
    c = x - x.mean(axis=0)
    _, sing, vt = np.linalg.svd(c, full_matrices=False)
    direction = vt[0]
    if direction[np.argmax(np.abs(direction))] < 0:
        direction = -direction
    total = float(np.sum(sing**2))
    share = float(sing[0] ** 2 / total) if total > 0 else 1.0
    return c @ direction, v @ direction, share


def phase_figure(traj: Trajectory) -> Figure:
    """Phase portrait (s, ds/dt) of a one-degree-of-freedom scene along the principal coordinate."""
    s, ds, share = principal_coordinate(traj)
    fig = _figure((6.0, 5.5))
    ax = fig.add_subplot()
    ax.plot(s, ds, color="C0", lw=1.2)
    ax.plot(s[0], ds[0], "o", color="C0", ms=7, mfc="white", mew=1.8, label="start")
    ax.plot(s[-1], ds[-1], "s", color="C0", ms=6, label="end")
    ax.axhline(0.0, color="0.6", lw=0.6)
    ax.axvline(0.0, color="0.6", lw=0.6)
    ax.grid(True, alpha=0.3)
    ax.set_xlabel("s [m]")
    ax.set_ylabel("ds/dt [m/s]")
    ax.set_title(
        "Phase portrait\ns = principal coordinate (positions projected on their first\n"
        f"principal direction, which carries {100 * share:.1f}% of the position variance)"
        + ("\ncaution: the motion is not well described by a single coordinate"
           if share < 0.9 else ""),
        fontsize="medium",
    )
    ax.legend(fontsize="small", loc="best")
    return fig


# ------------------------------------------------------------------------------- animation

#: Most frames an animation gets (the trajectory is resampled uniformly in time).
MAX_FRAMES = 120


def _links(system, traj: Trajectory) -> tuple[list[tuple[int, int]], list[tuple[int, np.ndarray, float | None]]]:  # noqa: E501
    """Rods to draw: (i, j) particle pairs and (i, point, length) rods to fixed pivots, from
    ``system`` when given, else from the sketch the run stored in ``traj.info``."""
    if system is not None:
        from .system import sketch

        found = sketch(system)
    else:
        found = (traj.info or {}).get("sketch") or {"rods": [], "anchors": []}
    n = traj.x.shape[1]
    pairs = [(int(i), int(j)) for i, j in found["rods"] if i < n and j < n]
    anchors = [(int(i), np.asarray(p, dtype=float), length) for i, p, length in found["anchors"] if i < n]
    return pairs, anchors


def _resample(t: np.ndarray, data: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Linear interpolation of (T, ...) samples at ``times``."""
    flat = data.reshape(len(t), -1)
    out = np.stack([np.interp(times, t, flat[:, k]) for k in range(flat.shape[1])], axis=1)
    return out.reshape((len(times), *data.shape[1:]))


#: Animation size: inches and dots per inch of a frame (640 × 600 px).
ANIMATION_SIZE, ANIMATION_DPI = (6.4, 6.0), 100


def _animation_parts(traj: Trajectory, system, forces: bool, max_frames: int):
    """``(fig, draw, n_frames)``: the figure with its static parts, and ``draw(k)`` which sets
    frame k and returns the artists that change."""
    t = np.asarray(traj.t, dtype=float)
    names = _names(traj)
    n_frames = int(max(2, min(max_frames, len(t))))
    times = np.linspace(t[0], t[-1], n_frames)
    x_all = np.asarray(traj.x, dtype=float)
    x = _resample(t, x_all, times)
    f = None
    if forces and traj.constraint_forces is not None:
        f = _resample(t, np.asarray(traj.constraint_forces, dtype=float), times)
    pairs, anchors = _links(system, traj)
    plane = motion_plane(x_all)
    # a fixed layout: the constrained-layout engine would re-run on every frame
    fig = Figure(figsize=ANIMATION_SIZE)
    FigureCanvasAgg(fig)
    if plane is not None:
        fig.subplots_adjust(left=0.12, right=0.97, bottom=0.2, top=0.93)
        origin, basis, (a, b) = plane
        shift = np.zeros(3) if a != "u" else origin
        project = lambda p: (np.asarray(p) - shift) @ basis.T  # noqa: E731
        ax = fig.add_subplot()
        ax.set_xlabel(f"{a} [m]")
        ax.set_ylabel(f"{b} [m]")
        ax.set_aspect("equal", adjustable="box")
        dim = 2
    else:
        fig.subplots_adjust(left=0.02, right=0.95, bottom=0.04, top=0.95)
        project = np.asarray
        ax = fig.add_subplot(projection="3d")
        ax.set_xlabel("x [m]", labelpad=8)
        ax.set_ylabel("y [m]", labelpad=8)
        ax.set_zlabel("z [m]", labelpad=8)
        dim = 3
    q = project(x)  # (F, N, dim)
    path = project(x_all)
    pts = path.reshape(-1, dim)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    anchor_q = [project(p) for _, p, _ in anchors]
    if anchor_q:
        pts = np.vstack([pts, *anchor_q])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    size = float(max(np.max(hi - lo), 1e-9))
    pad = 0.12 * size
    scale = 0.0
    if f is not None:
        fq = f @ basis.T if dim == 2 else f  # forces are directions: no shift
        biggest = float(np.max(np.linalg.norm(fq, axis=-1))) if fq.size else 0.0
        scale = 0.25 * size / biggest if biggest > 0 else 0.0
    limits = [(lo[k] - pad, hi[k] + pad) for k in range(dim)]
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    if dim == 3:
        ax.set_zlim(*limits[2])
        ax.set_box_aspect([max(h - l_, 0.05 * size) for l_, h in limits], zoom=0.85)
    else:
        ax.grid(True, alpha=0.3)
    # the whole path, faint: the curve or surface the constraints hold each particle to shows up
    for i in range(len(names)):
        ax.plot(*[path[:, i, k] for k in range(dim)], color=_colour(i), lw=0.6, alpha=0.25)
    if dim == 2:  # a rod to a fixed pivot: the circle it holds its particle on, dashed
        from matplotlib.patches import Circle

        for (_, point, length), pq in zip(anchors, anchor_q, strict=True):
            in_plane = plane is not None and abs(np.dot(point - plane[0], np.cross(*plane[1]))) < 1e-9 * size
            if length and in_plane:
                ax.add_patch(Circle(tuple(pq), length, fill=False, ls="--", lw=0.8, color="0.6"))
    else:  # in 3-D the sphere a rod to a fixed pivot holds its particle on, as a faint wireframe
        u, w = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
        for _, point, length in anchors:
            if not length:
                continue
            sphere = [point[0] + length * np.cos(u) * np.sin(w), point[1] + length * np.sin(u) * np.sin(w),
                      point[2] + length * np.cos(w)]
            inside = np.all([(c >= lo_ - 1e-9) & (c <= hi_ + 1e-9)
                             for c, (lo_, hi_) in zip(sphere, limits, strict=True)], axis=0)
            ax.plot_wireframe(*[np.where(inside, c, np.nan) for c in sphere], color="0.7", lw=0.4, alpha=0.6)
    trail_len = max(1, n_frames // 4)
    trails, dots = [], []
    for i in range(len(names)):
        (trail,) = ax.plot(*([[]] * dim), color=_colour(i), lw=1.2, alpha=0.7)
        (dot,) = ax.plot(*([[]] * dim), "o", color=_colour(i), ms=9, label=names[i])
        trails.append(trail)
        dots.append(dot)
    rods = [ax.plot(*([[]] * dim), color="0.25", lw=2.0)[0] for _ in pairs + anchors]
    for p in anchor_q:
        ax.plot(*[[c] for c in p], "k^", ms=8)
    arrows = []
    title = ax.set_title("", fontsize="medium")
    handles = list(dots)
    labels = list(names)
    if scale:
        handles.append(Line2D([], [], color="C3", lw=2))
        labels.append(f"constraint force (arrow 1 m = {1 / scale:.3g} N)")
    if dim == 2:  # below the axes: inside, it would cover the pivot or the path
        ax.legend(handles[:MAX_LEGEND], labels[:MAX_LEGEND], fontsize="small", loc="upper center",
                  bbox_to_anchor=(0.5, -0.1), ncol=min(3, len(handles)), frameon=False)
    else:
        _legend(ax, handles, labels, loc="upper right")

    def set_line(line, pts_):
        pts_ = np.asarray(pts_).reshape(-1, dim)
        if dim == 2:
            line.set_data(pts_[:, 0], pts_[:, 1])
        else:
            line.set_data_3d(pts_[:, 0], pts_[:, 1], pts_[:, 2])

    def draw(k: int):
        for a_ in arrows:
            a_.remove()
        arrows.clear()
        for i in range(len(names)):
            set_line(trails[i], q[max(0, k - trail_len) : k + 1, i])
            set_line(dots[i], q[k, i])
        for rod, (i, j) in zip(rods, pairs, strict=False):
            set_line(rod, np.stack([q[k, i], q[k, j]]))
        for rod, (i, _, _), p in zip(rods[len(pairs):], anchors, anchor_q, strict=True):
            set_line(rod, np.stack([p, q[k, i]]))
        if scale:
            vec = (f[k] @ basis.T if dim == 2 else f[k]) * scale
            if dim == 2:
                arrows.append(ax.quiver(q[k, :, 0], q[k, :, 1], vec[:, 0], vec[:, 1], color="C3",
                                        angles="xy", scale_units="xy", scale=1, width=0.005))
            else:
                arrows.append(ax.quiver(q[k, :, 0], q[k, :, 1], q[k, :, 2], vec[:, 0], vec[:, 1],
                                        vec[:, 2], color="C3"))
        title.set_text(f"t = {times[k]:.3f} s")
        return [*trails, *rods, *dots, *arrows, title]

    return fig, draw, n_frames


def animation_figure(traj: Trajectory, *, system=None, forces: bool = True, max_frames: int = MAX_FRAMES):
    """``(fig, FuncAnimation)``: particles, their trails and faint full paths, rods and the
    circles rods to fixed pivots hold their particles on (from ``system``, or from the sketch a
    run stores in the trajectory), and constraint-force arrows (when ``forces`` and the
    trajectory has them), in 2D for planar motion, else 3D. Frames are uniform in time, at most
    ``max_frames``."""
    from matplotlib.animation import FuncAnimation

    fig, draw, n_frames = _animation_parts(traj, system, forces, max_frames)
    anim = FuncAnimation(fig, draw, frames=n_frames, blit=False)
    return fig, anim


def _gif(fig, draw, n_frames: int, path: Path, fps: int, progress=None) -> None:
    """Write the frames as a GIF: the static parts are drawn once, each frame only redraws the
    artists that move (several times faster than a full redraw per frame)."""
    from PIL import Image

    canvas = fig.canvas
    for artist in draw(0):
        artist.set_animated(True)
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    frames = []
    for k in range(n_frames):
        canvas.restore_region(background)
        for artist in draw(k):
            artist.set_animated(True)
            if hasattr(artist, "do_3d_projection"):
                artist.do_3d_projection()
            fig.draw_artist(artist)
        rgba = np.asarray(canvas.buffer_rgba())
        frames.append(Image.fromarray(rgba[..., :3].copy()).quantize(colors=128, dither=Image.Dither.NONE))
        if progress is not None:
            progress(k, n_frames)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:],
                       duration=int(round(1000 / fps)), loop=0)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_animation(traj: Trajectory, path, *, system=None, forces: bool = True, fps: int = 15,
                   dpi: int = ANIMATION_DPI, max_frames: int = MAX_FRAMES, progress=None) -> list[Path]:
    """Write ``path`` (GIF) and, when ffmpeg is on PATH, the same as ``.mp4``.

    ``progress(fraction)`` is called after each frame written (fractions add up to 1)."""
    from matplotlib.animation import FFMpegWriter

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, draw, n_frames = _animation_parts(traj, system, forces, max_frames)
    fig.set_dpi(dpi)
    video = shutil.which("ffmpeg") is not None
    targets = 2 if video else 1
    callback = None
    if progress is not None:
        callback = lambda _i, n: progress(1.0 / (n * targets))  # noqa: E731
    _gif(fig, draw, n_frames, path, fps, callback)
    written = [path]
    if video:
        from matplotlib.animation import FuncAnimation

        for artist in fig.findobj():
            if hasattr(artist, "set_animated"):
                artist.set_animated(False)
        anim = FuncAnimation(fig, draw, frames=n_frames, blit=False)
        target = path.with_suffix(".mp4")
        fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=target.suffix, dir=target.parent)
        os.close(fd)
        try:
            anim.save(tmp, writer=FFMpegWriter(fps=fps), dpi=dpi, progress_callback=callback)
            os.replace(tmp, target)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        written.append(target)
    return written


def action_figure(traj: Trajectory) -> Figure:
    """The cumulative action S(t) = ∫ L dt along the run (L = T − V − U)."""
    if traj.action is None:
        raise InputError("this trajectory has no action: ask for the quantity 'action'")
    fig = Figure(figsize=(7, 4))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(traj.t, traj.action, color="C0")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("S(t) = ∫ L dt [J·s]")
    ax.set_title(f"Action along the run: S(t_end) = {traj.action[-1]:.6g} J·s\n(L = T − V − U; "
                 "damping and applied forces have no Lagrangian)", fontsize=10)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------- saving

FIGURES: dict[str, Callable[[Trajectory], Figure]] = {
    "trajectory": trajectory_figure,
    "energy": energy_figure,
    "constraint_residual": residual_figure,
    "constraint_forces": constraint_forces_figure,
    "multipliers": multipliers_figure,
    "phase": phase_figure,
    "action": action_figure,
}
#: Every kind ``save_figures`` knows: the PNG figures and the animation (animation.gif).
KINDS = (*FIGURES, "animation")


def save_figures(
    traj: Trajectory, kinds: Iterable[str], out_dir, *, dpi: int = 120, system=None, progress=None,
    parallel: bool = False,
) -> list[Path]:
    """Write ``out_dir/<kind>.png`` for each kind (atomically) and return the paths.

    The kind ``"animation"`` writes ``out_dir/animation.gif`` (and ``.mp4`` with ffmpeg); rods
    are drawn when ``system`` (the scene's System) is given. ``progress(amount)``, when given,
    is told 1 per kind written (the animation in fractions, frame by frame). ``parallel``:
    draw the PNG figures in forked worker processes (one per core), the animation here.
    """
    kinds = [kinds] if isinstance(kinds, str) else list(kinds)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise InputError(
            f"unknown figure kind(s) {', '.join(map(repr, unknown))}; "
            f"allowed: {', '.join(KINDS)}"
        )
    out_dir = Path(out_dir)
    pngs = [k for k in kinds if k != "animation"]
    if parallel and len(pngs) > 1 and _fork_context() is not None:
        return _save_in_parallel(traj, kinds, pngs, out_dir, dpi=dpi, system=system, progress=progress)
    paths = []
    for kind in kinds:
        if kind == "animation":
            paths.extend(save_animation(traj, out_dir / "animation.gif", system=system,
                                        progress=progress))
            continue
        fig = FIGURES[kind](traj)
        path = out_dir / f"{kind}.png"
        atomic_write(path, lambda f, fig=fig: fig.savefig(f, format="png", dpi=dpi))
        paths.append(path)
        if progress is not None:
            progress(1.0)
    return paths


def _fork_context():
    """The multiprocessing "fork" context where there is one (not on Windows), else None."""
    import multiprocessing

    try:
        return multiprocessing.get_context("fork")
    except ValueError:
        return None


def _save_one(traj: Trajectory, kind: str, out_dir: Path, dpi: int) -> Path:
    fig = FIGURES[kind](traj)
    path = out_dir / f"{kind}.png"
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=dpi))
    return path


def _save_in_parallel(traj, kinds, pngs, out_dir, *, dpi, system, progress) -> list[Path]:
    """``save_figures`` with the PNGs drawn in forked processes (matplotlib is already imported
    here, so a worker starts in milliseconds) while this process writes the animation."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    workers = max(1, min(len(pngs), os.cpu_count() or 1))
    done: dict[str, Path] = {}
    with ProcessPoolExecutor(workers, mp_context=_fork_context()) as pool:
        futures = {pool.submit(_save_one, traj, kind, out_dir, dpi): kind for kind in pngs}
        animation = []
        if "animation" in kinds:
            animation = save_animation(traj, out_dir / "animation.gif", system=system, progress=progress)
        for future in as_completed(futures):
            done[futures[future]] = future.result()
            if progress is not None:
                progress(1.0)
    paths = []
    for kind in kinds:
        paths.extend(animation if kind == "animation" else [done[kind]])
    return paths
