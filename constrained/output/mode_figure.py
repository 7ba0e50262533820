"""The mode-shapes figure: the state at rest and each mode's extreme displacements, one panel
per mode (constrained.modes; the animation of one mode is a Trajectory drawn by
constrained.animation and the viewer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..run.trajectory import Trajectory, atomic_write
from .animation import links
from .figure_style import motion_plane, new_figure

#: Panels drawn at most (the lowest modes).
MAX_PANELS = 6


def _plane(points: np.ndarray) -> tuple[np.ndarray, tuple[str, str]]:
    """(basis (2, 3), labels): the motion's plane, or the two axes along which it spreads most."""
    found = motion_plane(points)
    if found is not None:
        return found[1], found[2]
    spread = np.ptp(points.reshape(-1, 3), axis=0)
    keep = sorted(np.argsort(spread)[-2:].tolist())
    return np.eye(3)[keep], ("xyz"[keep[0]], "xyz"[keep[1]])


def mode_shapes_figure(x: np.ndarray, shapes: np.ndarray, titles: list[str], *, system=None,
                       names: list[str] | None = None, amplitude: float | None = None):
    """x (N, 3) the state at rest; shapes (k, N, 3) complex displacements; titles (k,)."""
    x = np.asarray(x, float)
    shapes = np.asarray(shapes)[:MAX_PANELS]
    k = len(shapes)
    size = max(float(np.max(np.ptp(x, axis=0))), float(np.max(np.linalg.norm(x, axis=1))), 1e-3)
    A = 0.06 * size if amplitude is None else amplitude
    traj = Trajectory(t=np.zeros(1), x=x[None], v=np.zeros_like(x)[None], particle_names=list(names or []))
    pairs, anchors = links(system, traj) if system is not None else ([], [])
    cloud = np.concatenate([x[None], x[None] + A * shapes.real, x[None] - A * shapes.real]) if k else x[None]
    basis, labels = _plane(np.concatenate([cloud.reshape(-1, 3), *[p[None] for _, p, _ in anchors]]))
    cols = min(k, 3) or 1
    rows = max(1, -(-k // cols))
    fig = new_figure((3.4 * cols, 3.2 * rows + 0.4))
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False).ravel())
    for ax in axes[k:]:
        ax.set_visible(False)

    def draw(ax, pos, colour, style, label=None):
        p = pos @ basis.T
        for i, j in pairs:
            ax.plot(p[[i, j], 0], p[[i, j], 1], style, color=colour, lw=1.2)
        for i, point, _ in anchors:
            q = point @ basis.T
            ax.plot([q[0], p[i, 0]], [q[1], p[i, 1]], style, color=colour, lw=1.2)
            ax.plot(q[0], q[1], "^", color="k", ms=6)
        ax.plot(p[:, 0], p[:, 1], "o", color=colour, ms=4, label=label)

    for ax, shape, title in zip(axes, shapes, titles, strict=False):
        draw(ax, x, "0.3", "-", "at rest")
        draw(ax, x + A * shape.real, "C0", "--", "+ shape")
        draw(ax, x - A * shape.real, "C3", ":", "− shape")
        ax.set_title(title, fontsize="small")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{labels[0]} [m]", fontsize="small")
        ax.set_ylabel(f"{labels[1]} [m]", fontsize="small")
        ax.tick_params(labelsize="x-small")
    if k:
        axes[0].legend(fontsize="x-small", loc="best")
    return fig


def save_mode_shapes(x, shapes, titles, path, *, system=None, names=None) -> Path:
    """Draw ``mode_shapes_figure`` and save it as PNG, atomically."""
    fig = mode_shapes_figure(x, shapes, titles, system=system, names=names)
    atomic_write(Path(path), lambda f: fig.savefig(f, format="png", dpi=110))
    return Path(path)
