"""The animation of a Trajectory: particles, rods and (optionally) constraint forces frame by
frame, written as a GIF through matplotlib's PillowWriter (and an MP4 when ffmpeg is on PATH)."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the "3d" projection)

from ..run.trajectory import Trajectory, _umask
from .figure_style import MAX_LEGEND, colour, legend, motion_plane, particle_names

#: Most frames an animation gets (the trajectory is resampled uniformly in time).
MAX_FRAMES = 120


def links(system, traj: Trajectory) -> tuple[list[tuple[int, int]], list[tuple[int, np.ndarray, float | None]]]:  # noqa: E501
    """Rods to draw: (i, j) particle pairs and (i, point, length) rods to fixed pivots, from
    ``system`` when given, else from the sketch the run stored in ``traj.info``."""
    if system is not None:
        from ..model.system import sketch

        found = sketch(system)
    else:
        found = (traj.info or {}).get("sketch") or {"rods": [], "anchors": []}
    n = traj.x.shape[1]
    pairs = [(int(i), int(j)) for i, j in found["rods"] if i < n and j < n]
    anchors = [(int(i), np.asarray(p, dtype=float), length) for i, p, length in found["anchors"] if i < n]
    return pairs, anchors


def resample(t: np.ndarray, data: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Linear interpolation of (T, ...) samples at ``times``."""
    flat = data.reshape(len(t), -1)
    out = np.stack([np.interp(times, t, flat[:, k]) for k in range(flat.shape[1])], axis=1)
    return out.reshape((len(times), *data.shape[1:]))


#: Animation size: inches and dots per inch of a frame (640 × 600 px).
ANIMATION_SIZE, ANIMATION_DPI = (6.4, 6.0), 100


def animation_parts(traj: Trajectory, system, forces: bool, max_frames: int):
    """``(fig, draw, n_frames)``: the figure with its static parts, and ``draw(k)`` which sets
    frame k and returns the artists that change."""
    t = np.asarray(traj.t, dtype=float)
    names = particle_names(traj)
    n_frames = int(max(2, min(max_frames, len(t))))
    times = np.linspace(t[0], t[-1], n_frames)
    x_all = np.asarray(traj.x, dtype=float)
    x = resample(t, x_all, times)
    f = None
    if forces and traj.constraint_forces is not None:
        f = resample(t, np.asarray(traj.constraint_forces, dtype=float), times)
    pairs, anchors = links(system, traj)
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
        ax.plot(*[path[:, i, k] for k in range(dim)], color=colour(i), lw=0.6, alpha=0.25)
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
        (trail,) = ax.plot(*([[]] * dim), color=colour(i), lw=1.2, alpha=0.7)
        (dot,) = ax.plot(*([[]] * dim), "o", color=colour(i), ms=9, label=names[i])
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
        legend(ax, handles, labels, loc="upper right")

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

    fig, draw, n_frames = animation_parts(traj, system, forces, max_frames)
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
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the mode open() would
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and str(exc.filename or "") != str(path):  # name the user's file
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        raise


def save_animation(traj: Trajectory, path, *, system=None, forces: bool = True, fps: int = 15,
                   dpi: int = ANIMATION_DPI, max_frames: int = MAX_FRAMES, progress=None) -> list[Path]:
    """Write ``path`` (GIF) and, when ffmpeg is on PATH, the same as ``.mp4``.

    ``progress(fraction)`` is called after each frame written (fractions add up to 1)."""
    from matplotlib.animation import FFMpegWriter

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, draw, n_frames = animation_parts(traj, system, forces, max_frames)
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
            os.chmod(tmp, 0o666 & ~_umask())
            os.replace(tmp, target)
        except BaseException as exc:
            if os.path.exists(tmp):
                os.unlink(tmp)
            if isinstance(exc.__context__, KeyboardInterrupt):  # Ctrl-C ended ffmpeg too: matplotlib
                raise KeyboardInterrupt from None  # reports its exit status instead of the interrupt
            if isinstance(exc, OSError) and str(exc.filename or "") != str(target):
                raise OSError(exc.errno, exc.strerror or str(exc), str(target)) from None
            raise
        written.append(target)
    return written
