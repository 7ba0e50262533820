"""Figures of a Trajectory: paths, energy drift, residuals, constraint forces, multipliers, phase,
and an animation (GIF through matplotlib's PillowWriter; also MP4 when ffmpeg is on PATH).

Every ``*_figure`` function returns a :class:`matplotlib.figure.Figure` drawn on an Agg canvas;
pyplot and its global state are never touched, so this works headless and in threads.
``save_figures`` writes several of them as PNG files, each atomically.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the "3d" projection)

from ..errors import InputError
from ..run.trajectory import Trajectory, atomic_write
from .animation import save_animation
from .figure_style import (
    AXES,
    EVENT_COLOURS,
    MAX_MARKED_EVENTS,
    constraint_labels,
    curves,
    finite_samples,
    fmt_vec,
    legend,
    motion_plane,
    need,
    new_figure,
    particle_names,
    time_axis,
)


def trajectory_figure(traj: Trajectory) -> Figure:
    """Particle paths, drawn in 2D when the motion is planar and in 3D otherwise.

    Each path starts at a circle and ends at a square; the legend names the particles.
    """
    x = np.asarray(traj.x, dtype=float)
    names = particle_names(traj)
    plane = motion_plane(x)
    fig = new_figure((7.0, 6.0))
    handles = []
    if plane is not None:
        origin, basis, (a, b) = plane
        ax = fig.add_subplot()
        coordinate_plane = a != "u"
        # coordinate planes keep the raw coordinates; a general plane is centred at the origin
        shift = np.zeros(3) if coordinate_plane else origin
        q = (x - shift) @ basis.T  # (T, N, 2)
        handles = curves(ax, q.transpose(1, 0, 2), ends=True)
        for e in traj.events[:MAX_MARKED_EVENTS]:
            at = (np.asarray(e.x, float) - shift) @ basis.T
            ax.plot(at[:, 0], at[:, 1], "x", color=EVENT_COLOURS.get(e.kind, "0.45"), ms=7, mew=1.6)
        ax.set_xlabel(f"{a} [m]")
        ax.set_ylabel(f"{b} [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        if coordinate_plane:
            k = next(c for c in AXES if c not in (a, b))
            where = f"planar motion in {a}–{b} plane ({k} = {origin[AXES.index(k)]:.4g} m)"
        else:
            where = (
                f"planar motion; u = {fmt_vec(basis[0])}, v = {fmt_vec(basis[1])}, "
                f"origin {fmt_vec(origin)} m"
            )
        ax.set_title(f"Particle paths\n{where}", fontsize="medium")
    else:
        ax = fig.add_subplot(projection="3d")
        handles = curves(ax, x.transpose(1, 0, 2), ends=True)
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
    legend(ax, handles, names, loc="upper left")
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
    energy = need(traj, "energy", "energy")
    t = np.asarray(traj.t, dtype=float)
    e0 = energy[0]
    drift = energy - e0
    fig = new_figure()
    ax = fig.add_subplot()
    ax.plot(t, drift, color="C0", lw=1.5)
    ax.axhline(0.0, color="0.5", lw=0.8, ls="--")
    time_axis(ax, traj)
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
    fig = new_figure((7.0, 3.0 * len(panels) + 0.5))
    axes = fig.subplots(len(panels), 1, squeeze=False)[:, 0]
    for ax, (name, value) in zip(axes, panels, strict=True):
        title, ylabel, colour = text[name]
        floor = _floor_positive([value])
        zeros = int(np.count_nonzero(value == 0))
        ax.semilogy(t, np.maximum(value, floor), color=colour, lw=1.2)
        time_axis(ax, traj)
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


def _refuse_without_constraints(traj: Trajectory, what: str) -> None:
    """An InputError for a system without constraints, whose figure of ``what`` would be empty
    (``constrained plot`` lists it as skipped)."""
    lam = traj.multipliers
    if lam is not None and np.asarray(lam).size == 0:
        raise InputError(f"the system has no constraints: no {what} to draw")


def constraint_forces_figure(traj: Trajectory) -> Figure:
    """Magnitude of the total constraint force on each particle, |F_con,i|(t) in newtons."""
    forces = need(traj, "constraint_forces", "constraint forces")
    _refuse_without_constraints(traj, "constraint forces")
    t = np.asarray(traj.t, dtype=float)
    magnitude = np.linalg.norm(forces, axis=2)
    names = particle_names(traj)
    fig = new_figure()
    ax = fig.add_subplot()
    handles = curves(ax, np.stack(np.broadcast_arrays(t[None, :], magnitude.T), axis=-1), lw=1.3)
    time_axis(ax, traj)
    ax.set_ylabel("|F$_{con}$| [N]")
    ax.set_ylim(bottom=0.0)
    ax.set_title("Constraint force on each particle", fontsize="medium")
    legend(ax, handles, names, loc="best")
    return fig


def multipliers_figure(traj: Trajectory) -> Figure:
    """Each Lagrange multiplier λ_k(t); the legend names the constraint rows."""
    lam = need(traj, "multipliers", "multipliers")
    _refuse_without_constraints(traj, "multipliers")
    lam = lam.reshape(len(lam), -1)
    t = np.asarray(traj.t, dtype=float)
    labels = constraint_labels(traj, lam.shape[1])
    fig = new_figure()
    ax = fig.add_subplot()
    handles = curves(ax, np.stack(np.broadcast_arrays(t[None, :], lam.T), axis=-1), lw=1.3)
    ax.axhline(0.0, color="0.5", lw=0.8, ls="--")
    time_axis(ax, traj)
    ax.set_ylabel("λ [N] (for constraints f in m)")
    rows = f"{lam.shape[1]} constraint row{'s' if lam.shape[1] != 1 else ''}"
    ax.set_title(f"Lagrange multipliers ({rows})", fontsize="medium")
    legend(ax, handles, labels, loc="best")
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
    # shares of the singular values, not of their squares: positions of 1e300 m (a hand-made
    # file) would overflow the squares and print NumPy's RuntimeWarnings into plot's output
    top = float(sing[0]) if sing.size else 0.0
    share = float(np.sum((sing / top) ** 2)) if top > 0 and np.isfinite(top) else 0.0
    share = 1.0 / share if share > 0 and np.isfinite(share) else 1.0
    return c @ direction, v @ direction, share


def phase_figure(traj: Trajectory) -> Figure:
    """Phase portrait (s, ds/dt) of a one-degree-of-freedom scene along the principal coordinate."""
    s, ds, share = principal_coordinate(traj)
    fig = new_figure((6.0, 5.5))
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
    Samples whose positions or velocities are not finite are left out (``finite_samples``).
    """
    kinds = [kinds] if isinstance(kinds, str) else list(kinds)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise InputError(
            f"unknown figure kind(s) {', '.join(map(repr, unknown))}; "
            f"allowed: {', '.join(KINDS)}"
        )
    out_dir = Path(out_dir)
    traj, _ = finite_samples(traj)  # (what cannot be drawn is left out, not a crash)
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
