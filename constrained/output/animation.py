"""The animation of a Trajectory: particles, rods, the curves and surfaces the scene holds its
particles on, and (optionally) constraint forces frame by frame, written as a GIF (and an MP4
when ffmpeg is on PATH).

Playback: each frame lasts (t_end − t_start) / frames of simulated time, rounded to the GIF's
10 ms, so the GIF plays in real time; where that would need frames shorter than
``MIN_FRAME_MS`` (short runs) or longer than ``MAX_FRAME_MS`` (long ones) the frame time is
clipped and the figure says how much faster or slower than real time it plays.

Force arrows are scaled per frame: the longest arrow of each frame is ``ARROW_SHARE`` of the
picture's size, and the title gives its magnitude in newtons, so forces show in every frame
(a run's one large force, at an impact, would otherwise shrink all others to nothing). They
are drawn above the particles.

Writing: the static parts are drawn once; each frame only redraws what moves (blitting) and is
mapped to one palette for the whole GIF (output/gif.py) instead of being quantized anew.
"""

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

from ..run.trajectory import Trajectory, file_mode
from .figure_style import MANY_CURVES, MAX_LEGEND, colour, curves, legend, motion_plane, particle_names

#: Most frames an animation gets (the trajectory is resampled uniformly in time).
MAX_FRAMES = 120
#: Shortest and longest time a GIF frame is shown [ms] (browsers show frames under 20 ms slowly).
MIN_FRAME_MS, MAX_FRAME_MS = 20, 200
#: The longest force arrow of a frame, as a share of the picture's size.
ARROW_SHARE = 0.25
#: Animation size: inches and dots per inch of a frame (640 × 600 px).
ANIMATION_SIZE, ANIMATION_DPI = (6.4, 6.0), 100


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


def playback(span: float, max_frames: int, samples: int) -> tuple[int, int]:
    """``(frames, frame_ms)``: how many frames and how long each is shown [ms] — the simulated
    time per frame (real time) in the GIF's steps of 10 ms, within [MIN_FRAME_MS,
    MAX_FRAME_MS], at most ``max_frames`` and at most the run's ``samples``."""
    n = int(max(2, min(max_frames, samples)))
    real = int(10 * np.ceil(100.0 * span / (n - 1) - 1e-9))  # ms per frame for real time, at n frames
    if MIN_FRAME_MS <= real <= MAX_FRAME_MS:  # real time: the frame count that fills the span
        return int(max(2, min(n, round(1000.0 * span / real) + 1))), real
    return n, int(np.clip(real, MIN_FRAME_MS, MAX_FRAME_MS))


def speed_note(span: float, n_frames: int, frame_ms: float) -> str:
    """What the figure says about its speed: "real time", or how much slower or faster."""
    speed = span / max((n_frames - 1) * frame_ms / 1000.0, 1e-300)
    if abs(speed - 1.0) <= 0.02:
        return "plays in real time"
    return f"plays at {speed:.3g}× real time ({'slowed' if speed < 1 else 'sped up'})"


def animation_parts(traj: Trajectory, system, forces: bool, max_frames: int, frame_ms: float | None = None):
    """``(fig, draw, n_frames)``: the figure with its static parts, and ``draw(k)`` which sets
    frame k and returns the artists that change. ``frame_ms``: how long a frame is shown
    (default: real time, see ``playback``); the figure says the resulting speed."""
    t = np.asarray(traj.t, dtype=float)
    names = particle_names(traj)
    span = float(t[-1] - t[0])
    n_frames, chosen_ms = playback(span, max_frames, len(t))
    frame_ms = chosen_ms if frame_ms is None else frame_ms
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
        fig.subplots_adjust(left=0.12, right=0.97, bottom=0.2, top=0.9)
        origin, basis, (a, b) = plane
        shift = np.zeros(3) if a != "u" else origin
        project = lambda p: (np.asarray(p) - shift) @ basis.T  # noqa: E731
        ax = fig.add_subplot()
        ax.set_xlabel(f"{a} [m]")
        ax.set_ylabel(f"{b} [m]")
        ax.set_aspect("equal", adjustable="box")
        dim = 2
    else:
        fig.subplots_adjust(left=0.02, right=0.95, bottom=0.04, top=0.92)
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
    limits = [(lo[k] - pad, hi[k] + pad) for k in range(dim)]
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    if dim == 3:
        ax.set_zlim(*limits[2])
        ax.set_box_aspect([max(h - l_, 0.05 * size) for l_, h in limits], zoom=0.85)
    else:
        ax.grid(True, alpha=0.3)
    # the whole path, faint (limits kept: they are set above)
    limits_now = (ax.get_xlim(), ax.get_ylim(), ax.get_zlim() if dim == 3 else None)
    curves(ax, path.transpose(1, 0, 2), lw=0.6, alpha=0.25)
    ax.set_xlim(*limits_now[0])
    ax.set_ylim(*limits_now[1])
    if dim == 3:
        ax.set_zlim(*limits_now[2])
    _draw_pivot_circles(ax, dim, plane, anchors, anchor_q, size, limits)
    moving_clouds, cloud_artists = (_draw_clouds(ax, system, names, times, x, plane, project, dim, size)
                                    if system is not None else ([], []))
    trail_len = max(1, n_frames // 4)
    # one trail and one dot artist per particle; from MANY_CURVES particles one per colour, the
    # particles of a colour drawn as one line broken by NaN (and the rods as one): a frame of a
    # 3,000-bead rope updated 9,000 artists (51 s for the GIF)
    many = len(names) >= MANY_CURVES
    groups = ([np.arange(c, len(names), 10) for c in range(10)] if many
              else [np.array([i]) for i in range(len(names))])
    trails, dots = [], []
    for g in groups:
        (trail,) = ax.plot(*([[]] * dim), color=colour(int(g[0])), lw=1.2, alpha=0.7)
        (dot,) = ax.plot(*([[]] * dim), "o", color=colour(int(g[0])), ms=8, alpha=0.9, linestyle="none",
                         label=names[int(g[0])], zorder=3)
        trails.append(trail)
        dots.append(dot)
    if many:  # legend entries: a proxy per particle named (the artists are per colour)
        named = [Line2D([], [], marker="o", color=colour(i), ms=8, alpha=0.9, linestyle="none")
                 for i in range(MAX_LEGEND)]
        dots_legend = named + [None] * (len(names) - MAX_LEGEND)
    else:
        dots_legend = dots
    rods = ([ax.plot(*([[]] * dim), color="0.25", lw=2.0)[0]] if many and pairs + anchors
            else [ax.plot(*([[]] * dim), color="0.25", lw=2.0)[0] for _ in pairs + anchors])
    rod_ends = np.array([(i, j) for i, j in pairs] + [(i, -1 - a) for a, (i, _, _) in enumerate(anchors)],
                        dtype=int).reshape(-1, 2)
    for p in anchor_q:
        ax.plot(*[[c] for c in p], "k^", ms=8)
    fq = None if f is None else (f @ basis.T if dim == 2 else f)  # forces are directions: no shift
    longest = None if fq is None else np.max(np.linalg.norm(fq, axis=-1), axis=1)  # per frame
    arrows_on = longest is not None and bool(np.any(longest > 0))
    title = ax.set_title("", fontsize="medium")
    # drawn once (static): the GIF's speed, bottom left
    fig.text(0.01, 0.01, f"GIF {speed_note(span, n_frames, frame_ms)}", fontsize="small", color="0.3")
    handles, labels = [*dots_legend, *cloud_artists], [*names, *(a.get_label() for a in cloud_artists)]
    if arrows_on:
        handles.append(Line2D([], [], color="C3", lw=2))
        labels.append("constraint force (arrows scaled per frame)")
    if dim == 2:  # below the axes: inside, it would cover the pivot or the path
        ax.legend(handles[:MAX_LEGEND], labels[:MAX_LEGEND], fontsize="small", loc="upper center",
                  bbox_to_anchor=(0.5, -0.1), ncol=min(3, len(handles)), frameon=False)
    elif len(handles) > 4:  # legend()'s place for many entries, right of the axes, is outside
        # this fixed frame: the figure's top left corner instead, which the 3-D box leaves free
        if len(handles) > MAX_LEGEND:
            more = len(handles) - MAX_LEGEND
            handles = [*handles[:MAX_LEGEND], Line2D([], [], linestyle="none")]
            labels = [*labels[:MAX_LEGEND], f"… ({more} more)"]
        labels = [text if len(text) <= 44 else text[:43] + "…" for text in labels]
        fig.legend(handles, labels, fontsize="small", loc="upper left", bbox_to_anchor=(0.005, 0.995),
                   frameon=False)
        title = ax.set_title("", fontsize="medium", loc="right")  # (beside it, not under it)
    else:
        legend(ax, handles, labels, loc="upper right")
    arrows = []
    quiver = None
    if arrows_on and dim == 2:  # one quiver, its arrows moved frame by frame, above the particles
        quiver = ax.quiver(q[0, :, 0], q[0, :, 1], np.zeros(len(names)), np.zeros(len(names)), color="C3",
                           angles="xy", scale_units="xy", scale=1, width=0.006, zorder=5)
    floor = 1e-9 * float(np.max(longest)) if arrows_on else 0.0

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
        recent = q[max(0, k - trail_len) : k + 1]  # (L, N, dim)
        for g, trail, dot in zip(groups, trails, dots, strict=True):
            set_line(trail, _broken(recent[:, g].transpose(1, 0, 2)))
            set_line(dot, q[k, g])
        if many and len(rod_ends):
            ends = np.vstack([q[k], np.asarray(anchor_q[::-1], float).reshape(-1, dim)])  # anchor a: -1 - a
            set_line(rods[0], _broken(ends[rod_ends]))
        elif not many:
            for rod, (i, j) in zip(rods, pairs, strict=False):
                set_line(rod, np.stack([q[k, i], q[k, j]]))
            for rod, (i, _, _), p in zip(rods[len(pairs):], anchors, anchor_q, strict=True):
                set_line(rod, np.stack([p, q[k, i]]))
        changed = [cloud.show(k) for cloud in moving_clouds]
        text = f"t = {times[k]:.3f} s"
        if arrows_on:
            big = float(longest[k])
            vec = fq[k] * (ARROW_SHARE * size / big) if big > floor else np.zeros_like(fq[k])
            text += f"\nlongest force arrow: {big:.3g} N" if big > floor else "\nno constraint force now"
            if dim == 2:
                quiver.set_offsets(q[k])
                quiver.set_UVC(vec[:, 0], vec[:, 1])
            else:
                arrows.append(ax.quiver(q[k, :, 0], q[k, :, 1], q[k, :, 2], vec[:, 0], vec[:, 1], vec[:, 2],
                                        color="C3", zorder=5, lw=2, arrow_length_ratio=0.2))
        title.set_text(text)
        return [*changed, *trails, *rods, *dots, *([quiver] if quiver is not None else []), *arrows, title]

    return fig, draw, n_frames


def _broken(lines: np.ndarray) -> np.ndarray:
    """The polylines ``lines`` (n, L, dim) as one array of points with a NaN row after each,
    which a Line2D draws as n separate pieces."""
    n, _, dim = lines.shape
    return np.concatenate([lines, np.full((n, 1, dim), np.nan)], axis=1).reshape(-1, dim)


def _draw_pivot_circles(ax, dim, plane, anchors, anchor_q, size, limits) -> None:
    """A rod to a fixed pivot: the circle (2-D, dashed) or sphere (3-D, faint wireframe) it
    holds its particle on."""
    if dim == 2:
        from matplotlib.patches import Circle

        for (_, point, length), pq in zip(anchors, anchor_q, strict=True):
            in_plane = plane is not None and abs(np.dot(point - plane[0], np.cross(*plane[1]))) < 1e-9 * size
            if length and in_plane:
                ax.add_patch(Circle(tuple(pq), length, fill=False, ls="--", lw=0.8, color="0.6"))
        return
    u, w = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
    for _, point, length in anchors:
        if not length:
            continue
        sphere = [point[0] + length * np.cos(u) * np.sin(w), point[1] + length * np.sin(u) * np.sin(w),
                  point[2] + length * np.cos(w)]
        inside = np.all([(c >= lo_ - 1e-9) & (c <= hi_ + 1e-9)
                         for c, (lo_, hi_) in zip(sphere, limits, strict=True)], axis=0)
        ax.plot_wireframe(*[np.where(inside, c, np.nan) for c in sphere], color="0.7", lw=0.4, alpha=0.6)


class _MovingCloud:
    """A curve or surface that moves with t: its points at the key time nearest each frame."""

    def __init__(self, artist, keys, points, dim):
        self.artist, self.keys, self.points, self.dim = artist, np.asarray(keys), points, dim

    def show(self, k: int):
        pts = self.points[int(np.argmin(np.abs(self.keys - k)))]
        if self.dim == 2:
            self.artist.set_data(pts[:, 0], pts[:, 1])
        else:
            self.artist.set_data_3d(pts[:, 0], pts[:, 1], pts[:, 2])
        return self.artist


def _draw_clouds(ax, system, names, times, x, plane, project, dim, size):
    """The curves and surfaces the scene's constraints hold particles on (output/shapes.py: points
    on them near the motion), as small dots; in a planar picture only the points in its plane
    (where a surface meets it). Returns the moving ones (redrawn each frame) and every artist."""
    from ..model.constraints import Curve, Surface
    from .shapes import Shapes

    moving, artists = [], []
    wanted = [c for c in system.constraints if isinstance(c, Curve | Surface)]
    if not wanted:  # (a big chain of rods: nothing to evaluate)
        return moving, artists
    found = Shapes(system, names, times, x)
    for c in wanted:
        found.add(c)
    seen = 0
    for item in found.items:
        if item.get("kind") not in ("curve", "surface") or "same_as" in item:
            continue
        style = dict(ls="none", marker=".", ms=2.5 if item["kind"] == "curve" else 1.5,
                     color="tab:purple" if item["kind"] == "curve" else f"C{(4 + seen) % 10}",
                     alpha=0.55 if item["kind"] == "curve" else 0.3, zorder=1)
        seen += 1
        if "points" in item:
            clouds = [np.asarray(item["points"], dtype=float).reshape(-1, 3)]
        elif "moving" in item:
            clouds = list(np.asarray(item["moving"], dtype=float).reshape(len(item["keys"]), -1, 3))
        else:
            continue
        kept = []
        for pts in clouds:
            pts = pts[np.all(np.isfinite(pts), axis=1)]
            if plane is not None:  # the points in the picture's plane
                normal = np.cross(*plane[1])
                pts = pts[np.abs((pts - plane[0]) @ normal) <= 0.01 * size]
            kept.append(np.asarray(project(pts)).reshape(-1, dim))
        label = f"{item['kind']}: {item['label']}"
        artist = ax.plot(*[kept[0][:, j] for j in range(dim)], label=label, **style)[0]
        artists.append(artist)
        if "moving" in item:
            moving.append(_MovingCloud(artist, item["keys"], kept, dim))
    return moving, artists


def animation_figure(traj: Trajectory, *, system=None, forces: bool = True, max_frames: int = MAX_FRAMES):
    """``(fig, FuncAnimation)``: particles, their trails and faint full paths, rods and the
    circles rods to fixed pivots hold their particles on (from ``system``, or from the sketch a
    run stores in the trajectory), the curves and surfaces of the scene's constraints (with
    ``system``), and constraint-force arrows scaled per frame (when ``forces`` and the
    trajectory has them), in 2D for planar motion, else 3D. Frames are uniform in time, at most
    ``max_frames``, each shown for the simulated time it spans (real time, within limits)."""
    from matplotlib.animation import FuncAnimation

    fig, draw, n_frames = animation_parts(traj, system, forces, max_frames)
    _, frame_ms = playback(float(traj.t[-1] - traj.t[0]), max_frames, len(traj.t))
    anim = FuncAnimation(fig, draw, frames=n_frames, blit=False, interval=frame_ms)
    return fig, anim


def _frames(fig, draw, n_frames: int, progress=None, sink=None) -> tuple[list[np.ndarray], np.ndarray]:
    """Draw every frame by blitting; ``(indexed frames, palette)`` for the GIF. ``sink(rgb)``,
    when given, also receives each frame's (H, W, 3) uint8 pixels (the MP4)."""
    from .gif import PaletteMap, palette_from

    canvas = fig.canvas
    for artist in draw(0):
        artist.set_animated(True)
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)

    def render(k: int) -> np.ndarray:
        canvas.restore_region(background)
        for artist in draw(k):
            artist.set_animated(True)
            if hasattr(artist, "do_3d_projection"):
                artist.do_3d_projection()
            fig.draw_artist(artist)
        return np.asarray(canvas.buffer_rgba())

    # the palette from a few frames spread over the run (the colours of every artist in them)
    samples = sorted({0, n_frames // 3, (2 * n_frames) // 3, n_frames - 1})
    mapping = PaletteMap(palette_from([render(k)[..., :3].copy() for k in samples]))
    frames = []
    for k in range(n_frames):
        rgba = render(k)
        frames.append(mapping(rgba))
        if sink is not None:
            sink(rgba[..., :3])
        if progress is not None:
            progress(k, n_frames)
    return frames, mapping.palette


def save_animation(traj: Trajectory, path, *, system=None, forces: bool = True, fps: float | None = None,
                   dpi: int = ANIMATION_DPI, max_frames: int = MAX_FRAMES, progress=None) -> list[Path]:
    """Write ``path`` (GIF) and, when ffmpeg is on PATH, the same as ``.mp4``.

    ``fps``: frames per second of the file (default: real time, see ``playback``).
    ``progress(fraction)`` is called after each frame written (fractions add up to 1)."""
    from .gif import write_gif

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _, frame_ms = playback(float(traj.t[-1] - traj.t[0]), max_frames, len(traj.t))
    frame_ms = frame_ms if fps is None else 1000.0 / fps
    fig, draw, n_frames = animation_parts(traj, system, forces, max_frames, frame_ms=frame_ms)
    fig.set_dpi(dpi)
    callback = None
    if progress is not None:
        callback = lambda _i, n_: progress(1.0 / n_)  # noqa: E731
    video = _Video(path.with_suffix(".mp4"), fig, 1000.0 / frame_ms) if shutil.which("ffmpeg") else None
    try:
        frames, palette = _frames(fig, draw, n_frames, callback, sink=video.write if video else None)
        write_gif(path, frames, palette, int(round(frame_ms)))
        written = [path]
        if video is not None:
            written.append(video.close())
    finally:
        if video is not None:
            video.abort()
    return written


class _Video:
    """An MP4 written by ffmpeg from raw RGB frames piped to it (the frames the GIF is made of)."""

    def __init__(self, target: Path, fig, fps: float):
        import subprocess

        width, height = fig.canvas.get_width_height()
        self.target, self.done = target, False
        fd, self.tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=target.suffix, dir=target.parent)
        os.close(fd)
        self.proc = subprocess.Popen(
            ["ffmpeg", "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s",
             f"{width}x{height}", "-r", f"{fps:.6g}", "-i", "-", "-an", "-vcodec", "libx264", "-pix_fmt",
             "yuv420p", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", self.tmp],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def write(self, rgb: np.ndarray) -> None:
        self.proc.stdin.write(np.ascontiguousarray(rgb, dtype=np.uint8).tobytes())

    def close(self) -> Path:
        self.proc.stdin.close()
        err = self.proc.stderr.read().decode("utf-8", "replace")
        if self.proc.wait() != 0:
            raise RuntimeError(f"ffmpeg could not write {self.target}: {err.strip()[-300:]}")
        os.chmod(self.tmp, file_mode())
        os.replace(self.tmp, self.target)
        self.done = True
        return self.target

    def abort(self) -> None:
        if self.done:
            return
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        if os.path.exists(self.tmp):
            os.unlink(self.tmp)
