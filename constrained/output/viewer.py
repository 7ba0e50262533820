"""viewer.html: one self-contained interactive page of a run (``constrained view``).

The page needs no network: the data travel inside it as JSON and base64 arrays, and
``viewer_template.html`` (package data) draws them with plain canvas and inline JavaScript.
Python does the heavy lifting so that the page stays small and smooth on any run:

- frames are picked uniformly in time, at most ``MAX_FRAMES`` and at most
  ``MAX_POINT_FRAMES`` (frames × particles); positions and forces are stored as int16
  quantized to their range (a 1/65534 of the size of the motion);
- the time series (energy, constraint residual, every multiplier) are reduced to a
  min/max envelope of at most ``MAX_SERIES_POINTS`` points each, and all multipliers
  together to at most ``MAX_SERIES_VALUES`` numbers, so spikes survive decimation;
- with the scene's System the constraints are evaluated at the frame times (output/shapes.py):
  rods and strings (distance constraints, also to a fixed or moving anchor), pins moving with
  t, planes as patches and surfaces and curves as clouds of points on them, found by Newton
  projection of a grid around the motion. Custom constraints are listed, not drawn.
"""

from __future__ import annotations

import base64
import html
import json
import math
import re
import warnings
from importlib import resources
from pathlib import Path

import numpy as np

from ..errors import InputError, listed
from ..model.effects import Gravity
from ..run.trajectory import Trajectory, atomic_write
from .shapes import shapes

__all__ = ["viewer_page", "write_viewer", "MAX_FRAMES", "MAX_POINT_FRAMES"]

#: Most frames a page carries (the screen cannot show more along a slider).
MAX_FRAMES = 2000
#: Most frames × particles a page carries (bounds the page size for big systems).
MAX_POINT_FRAMES = 400_000
#: Fewest frames a page carries when the run has them (big systems trade frames for particles).
MIN_FRAMES = 100
#: Most points of one time series (a min/max envelope: half as many buckets).
MAX_SERIES_POINTS = 2000
#: Events listed (and marked) on the page at most.
MAX_EVENTS = 200
#: Most numbers of all multiplier series together.
MAX_SERIES_VALUES = 400_000
#: How far above the level a 3-D motion is first seen from (radians; drag to turn).
ELEVATION = math.radians(25.0)
_TEMPLATE = "viewer_template.html"


# --------------------------------------------------------------------------------- encoding


def _b64(a: np.ndarray, dtype) -> str:
    little = np.ascontiguousarray(a, dtype=np.dtype(dtype).newbyteorder("<"))
    return base64.b64encode(little.tobytes()).decode()


def _f32(a) -> str:
    return _b64(np.asarray(a, dtype=float), np.float32)


def _quantize(a: np.ndarray, lo: np.ndarray, step: np.ndarray) -> str:
    """int16 codes of ``(a - lo) / step - 32767``; NaN (and ±inf) become −32768."""
    q = np.round((a - lo) / step) - 32767.0
    q = np.where(np.isfinite(q), np.clip(q, -32767, 32767), -32768)
    return _b64(q, np.int16)


# --------------------------------------------------------------------------------- decimation


def frame_indices(t: np.ndarray, n_particles: int, point_frames: int = MAX_POINT_FRAMES) -> np.ndarray:
    """Sample indices of the frames: uniform in time, at most the budgets above allow."""
    n = len(t)
    budget = max(MIN_FRAMES, point_frames // max(n_particles, 1))
    count = min(MAX_FRAMES, budget)
    if n <= count:
        return np.arange(n)
    times = np.linspace(t[0], t[-1], count)
    idx = np.clip(np.searchsorted(t, times), 0, n - 1)
    return np.unique(idx)


def envelope(t: np.ndarray, y: np.ndarray, points: int) -> tuple[np.ndarray, np.ndarray]:
    """``(times, values)`` of at most ``points`` samples keeping each bucket's min and max.

    ``y`` is (T,) or (T, C); columns share the times. NaN is ignored inside a bucket.
    """
    y = np.asarray(y)
    y = y.astype(np.result_type(y.dtype, np.float32), copy=False)  # float32 stays float32
    n = len(t)
    if n <= points:
        return np.asarray(t, dtype=float), y
    buckets = max(1, points // 2)
    starts = np.linspace(0, n, buckets + 1).astype(int)[:-1]
    ends = np.append(starts[1:], n) - 1
    with np.errstate(invalid="ignore"):
        lo = np.fmin.reduceat(y, starts, axis=0)
        hi = np.fmax.reduceat(y, starts, axis=0)
    times = np.empty(2 * buckets)
    times[0::2], times[1::2] = t[starts], t[ends]
    values = np.empty((2 * buckets, *y.shape[1:]))
    values[0::2], values[1::2] = lo, hi
    return times, values


# --------------------------------------------------------------------------------- view


def view_basis(x: np.ndarray, up=None) -> tuple[np.ndarray, list[str], bool]:
    """Initial view: rows (right, up, towards the viewer), their axis names, planar or not.

    A planar motion is seen face-on (a coordinate plane with its own axes when it lies in
    one), turned so that ``up`` (against gravity; default +z) points up the screen; a
    level plane is seen from above. A 3-D motion is seen along the normal of its best-fit
    plane, raised ``ELEVATION`` above the level, ``up`` up the screen.
    """
    p = x.reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 2:
        p = np.vstack([p, np.zeros((2, 3))])
    spread = np.ptp(p, axis=0)
    size = float(max(spread.max(), 1e-300))
    flat = [k for k in range(3) if spread[k] <= 1e-9 * size]
    if flat and up is None:  # a coordinate plane: its own axes, x right, then y or z up
        k = flat[-1]
        keep = [j for j in range(3) if j != k]
        basis = np.eye(3)[[*keep, k]]
        if k == 1:  # y = const: x right, z up, looking along +y keeps a right-handed frame
            basis[2] *= -1
        return basis, ["xyz"[j] for j in (*keep, k)], True
    c = p - p.mean(axis=0)
    c = np.vstack([c[:: max(1, len(c) // 20000)], np.zeros((max(0, 3 - len(c)), 3))])  # (3 directions)
    _, sv, vt = np.linalg.svd(c, full_matrices=False)
    normal = np.eye(3)[flat[-1]] if flat else vt[2]
    planar = bool(flat) or bool(sv[2] <= 1e-9 * max(sv[0], 1e-300))
    ref = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
    ref = ref / np.linalg.norm(ref)
    in_plane = ref - (ref @ normal) * normal
    level = np.linalg.norm(in_plane) <= 0.3
    if planar and not level:  # up lies (mostly) in the plane of the motion: look along its normal
        upv = in_plane / np.linalg.norm(in_plane)
        towards = normal if normal @ np.array([1.0, -1.0, 1.0]) >= 0 else -normal
    elif planar:  # a level plane: look down on it from above
        towards = ref
        upv = np.cross(towards, vt[0])
        if np.linalg.norm(upv) < 1e-6:
            upv = np.cross(towards, np.eye(3)[np.argmin(np.abs(towards))])
        upv /= np.linalg.norm(upv)
    else:  # 3-D: along the best-fit plane's normal, from ELEVATION above the level
        h = normal - (normal @ ref) * ref
        if np.linalg.norm(h) < 0.3:  # a level best-fit plane: a default azimuth
            h = np.array([0.5, -0.866, 0.0]) - (np.array([0.5, -0.866, 0.0]) @ ref) * ref
            if np.linalg.norm(h) < 1e-6:
                h = np.cross(ref, np.eye(3)[np.argmin(np.abs(ref))])
        h /= np.linalg.norm(h)
        if h @ np.array([1.0, -1.0, 1.0]) < 0:
            h = -h
        towards = math.cos(ELEVATION) * h + math.sin(ELEVATION) * ref
        upv = ref - (ref @ towards) * towards
        upv /= np.linalg.norm(upv)
    right = np.cross(upv, towards)
    right /= np.linalg.norm(right)
    basis = np.array([right, np.cross(towards, right), towards])
    names = ["u", "v", "w"]
    for r, row in enumerate(basis):  # name the rows after coordinate axes when they are ones
        k = int(np.argmax(np.abs(row)))
        if abs(row[k]) > 1 - 1e-12:
            names[r] = "xyz"[k]
    return basis, names, planar


def _nice(x: float) -> float:
    """1, 2 or 5 times a power of ten, near ``x`` from below."""
    e = 10.0 ** math.floor(math.log10(x))
    m = x / e
    return (5.0 if m >= 5 else 2.0 if m >= 2 else 1.0) * e


def floor_grid(x: np.ndarray, basis: np.ndarray, planar: bool, up=None) -> dict:
    """The picture's grid and axes, in world coordinates (the page projects them like the rest).

    Planar motion: graph paper in the plane of the motion (``basis`` rows 0 and 1). 3-D
    motion: a floor, the level plane (perpendicular to ``up``, default +z) at the lowest point
    of the motion. Lines every ``step`` metres (1, 2 or 5 × 10^k, about six across) over the
    motion's extent, rounded out to whole steps; ``axes``: the grid's lines through the origin, named
    after the coordinate they measure; ``ticks``: the coordinate values along two edges.
    """
    p = x.reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    p = p[:: max(1, len(p) // 20000)] if len(p) else np.zeros((1, 3))
    if planar:
        e1, e2, normal = basis[0], basis[1], basis[2]
        level = float(np.median(p @ normal))
    else:
        normal = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float) / np.linalg.norm(up)
        k = int(np.argmax(np.abs(normal)))
        if abs(normal[k]) > 1 - 1e-9:  # level with two coordinate axes
            e1, e2 = np.eye(3)[(k + 1) % 3], np.eye(3)[(k + 2) % 3]
        else:
            e1 = np.cross(normal, basis[2])
            e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-9 else basis[0]
            e2 = np.cross(normal, e1)
        level = float(np.min(p @ normal))
    a, b = p @ e1, p @ e2
    size = max(float(np.ptp(a)), float(np.ptp(b)), float(np.ptp(p @ normal)), 1e-3)
    step = _nice(size / 5)
    lo_a, hi_a = math.floor(a.min() / step - 1e-9), math.ceil(a.max() / step + 1e-9)
    lo_b, hi_b = math.floor(b.min() / step - 1e-9), math.ceil(b.max() / step + 1e-9)

    def at(u, v):
        return [round(float(c), 9) for c in u * e1 + v * e2 + level * normal]

    def name(e):  # the coordinate a direction measures, and its sign
        j = int(np.argmax(np.abs(e)))
        return ("xyz"[j], float(np.sign(e[j]))) if abs(e[j]) > 1 - 1e-9 else (None, 1.0)

    (n1, s1), (n2, s2) = name(e1), name(e2)
    us, vs = np.arange(lo_a, hi_a + 1) * step, np.arange(lo_b, hi_b + 1) * step
    lines = [[at(u, vs[0]), at(u, vs[-1])] for u in us] + [[at(us[0], v), at(us[-1], v)] for v in vs]
    axes = []
    if us[0] < 0 < us[-1] and n2:
        axes.append([at(0.0, vs[0]), at(0.0, vs[-1]), n2 if s2 > 0 else f"−{n2}"])
    if vs[0] < 0 < vs[-1] and n1:
        axes.append([at(us[0], 0.0), at(us[-1], 0.0), n1 if s1 > 0 else f"−{n1}"])
    every = max(1, len(us) // 6)
    ticks = [[at(u, vs[0] - 0.35 * step), f"{s1 * u + 0.0:.6g}"] for u in us[::every]]
    ticks += [[at(us[0] - 0.35 * step, v), f"{s2 * v + 0.0:.6g}"] for v in vs[1::max(1, len(vs) // 6)]]
    names = [[at(us[-1] + 0.5 * step, vs[0]), f"{n1 or 'u'} [m]"],
             [at(us[0], vs[-1] + 0.5 * step), f"{n2 or 'v'} [m]"]]
    return {"lines": lines, "axes": axes, "ticks": ticks, "names": names, "step": step,
            "normal": [float(c) for c in normal]}


def up_direction(system) -> np.ndarray | None:
    """Against the scene's uniform gravity, when it has one with constant numbers."""
    for e in getattr(system, "effects", ()):
        if isinstance(e, Gravity):
            try:
                g = np.array([float(v) for v in e.g])
            except (TypeError, ValueError):
                continue
            if np.linalg.norm(g) > 0:
                return -g / np.linalg.norm(g)
    return None


def _check_scene(system, names: list[str], n: int) -> None:
    scene_names = [p.name for p in system.particles]
    if len(scene_names) != n or (names and scene_names != names):
        have = listed(names, 6) if names else f"{n} particles"
        differ = next((k for k, (a, b) in enumerate(zip(scene_names, names, strict=False)) if a != b), None)
        where = (f"; the first to differ is number {differ + 1}: {scene_names[differ]!r} against "
                 f"{names[differ]!r}" if differ is not None else "")
        raise InputError(
            f"the scene's particles ({listed(scene_names, 6) or 'none'}) are not the run's "
            f"({have}){where}: give the scene the run was made from"
        )



# --------------------------------------------------------------------------------- page


def page_data(traj: Trajectory, *, system=None, title: str = "",
              point_frames: int = MAX_POINT_FRAMES) -> dict:
    """Everything the page draws, decimated and encoded (JSON-ready)."""
    t = np.asarray(traj.t, dtype=float)
    x = np.asarray(traj.x)  # maybe float32 and big: converted after decimation only
    if t.ndim != 1 or x.ndim != 3 or x.shape[0] != len(t) or x.shape[2] != 3 or len(t) == 0:
        raise InputError(f"the trajectory's arrays do not fit: t {t.shape}, x {x.shape} "
                         "(expected t (T,), x (T, N, 3), T > 0)")
    n = x.shape[1]
    names = list(traj.particle_names or [])
    if system is not None:  # before any work: the scene must be the run's
        _check_scene(system, names, n)
        names = [p.name for p in system.particles]
    names = names if len(names) == n else [f"particle {i}" for i in range(n)]
    idx = frame_indices(t, n, point_frames)
    times, xf = t[idx], np.asarray(x[idx], dtype=float)
    up = up_direction(system) if system is not None else None
    basis, axes, planar = view_basis(xf, up)
    with warnings.catch_warnings():  # an axis that is NaN throughout: drawn nowhere
        warnings.simplefilter("ignore", RuntimeWarning)
        lo, hi = np.nanmin(xf, axis=(0, 1)), np.nanmax(xf, axis=(0, 1))
    lo, hi = np.where(np.isfinite(lo), lo, 0.0), np.where(np.isfinite(hi), hi, 0.0)
    step = np.maximum((hi - lo) / 65534.0, 1e-12)
    data: dict = {
        "title": title, "names": names, "n": n, "frames": len(idx), "samples": len(t),
        "t": _f32(times), "t0": float(t[0]), "t1": float(t[-1]),
        "x": {"lo": lo.tolist(), "step": step.tolist(), "q": _quantize(xf, lo, step)},
        "view": {"basis": basis.tolist(), "axes": axes, "planar": planar},
        "grid": floor_grid(xf, basis, planar, up),
        "series": {},
    }
    if traj.constraint_forces is not None:
        data.update(_forces(np.asarray(np.asarray(traj.constraint_forces)[idx], dtype=float)))
    for name in ("energy", "constraint_residual"):
        y = getattr(traj, name)
        if y is not None and len(y) == len(t):
            y = np.asarray(y, dtype=float)
            if name == "energy":  # drawn as E − E(t0), subtracted here before float32 rounding
                finite = y[np.isfinite(y)]
                e0 = float(finite[0]) if finite.size else 0.0
                y = y - e0
            tt, yy = envelope(t, y, MAX_SERIES_POINTS)
            data["series"][name] = {"t": _f32(tt), "y": _f32(yy)}
            if name == "energy":
                data["series"][name]["e0"] = e0
    lam = traj.multipliers
    if lam is not None and lam.ndim == 2 and len(lam) == len(t) and lam.shape[1] > 0:
        c = lam.shape[1]
        points = int(np.clip(MAX_SERIES_VALUES // c, 100, MAX_SERIES_POINTS))
        tt, yy = envelope(t, lam, points)
        labels = list(traj.constraint_labels or [])
        labels = labels if len(labels) == c else [f"multiplier {k}" for k in range(c)]
        data["series"]["multipliers"] = {"t": _f32(tt), "y": _f32(yy.T), "count": c, "labels": labels}
    events = list(getattr(traj, "events", None) or [])
    if events:  # the list under the picture and the marks in the panels (the first ones tell)
        data["events"] = [{"t": float(e.t), "kind": e.kind, "text": e.describe()}
                          for e in events[:MAX_EVENTS]]
        data["events_total"] = len(events)
    if system is not None:
        data["constraints"] = _encoded(shapes(system, names, times, xf))
    return data


def _forces(f: np.ndarray) -> dict:
    """The constraint forces of the frames (F, N, 3), quantized per frame: int16 codes of
    f / (frame's largest component) and that scale, so that a frame of small forces keeps its
    digits beside a run's one large force; ``norm``: each frame's largest |F| (the page scales
    the arrows of a frame by it). Empty when there are none."""
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a frame that is NaN throughout
        frame = np.nan_to_num(np.nanmax(np.abs(f), axis=(1, 2)), nan=0.0, posinf=0.0)
        norm = np.nan_to_num(np.nanmax(np.linalg.norm(f, axis=-1), axis=1), nan=0.0, posinf=0.0)
    if not np.any(frame > 0):
        return {}
    unit = np.where(frame > 0, frame, 1.0) / 32767.0  # newtons per code, per frame
    codes = np.round(f / unit[:, None, None])
    codes = np.where(np.isfinite(codes), np.clip(codes, -32767, 32767), -32768)
    return {"forces": {"unit": _f32(unit), "q": _b64(codes, np.int16), "norm": _f32(norm),
                       "max": float(norm.max())}}


def viewer_page(traj: Trajectory, *, system=None, title: str = "",
                point_frames: int = MAX_POINT_FRAMES) -> str:
    """The HTML text of the viewer of ``traj`` (constraints drawn when ``system`` is given)."""
    data = page_data(traj, system=system, title=title, point_frames=point_frames)
    blob = json.dumps(_finite(data), separators=(",", ":"), allow_nan=False, default=_plain)
    blob = blob.replace("</", "<\\/")  # never closes the <script> element holding it
    template = resources.files(__package__).joinpath(_TEMPLATE).read_text(encoding="utf-8")
    heading = html.escape(title or "constrained run")
    fill = {"__TITLE__": heading, "__DATA__": blob}  # one pass: neither can create the other
    return re.sub("__TITLE__|__DATA__", lambda m: fill[m.group(0)], template)


def _finite(value):
    """JSON has no NaN: a non-finite number (a formula undefined at some t) becomes null."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float | np.floating) and not math.isfinite(value):
        return None
    return value


def _encoded(value):
    """The arrays of what moves with t (shapes.py) as base64 float32, the rest as it is."""
    if isinstance(value, dict):
        return {k: _encoded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_encoded(v) for v in value]
    return _f32(value) if isinstance(value, np.ndarray) else value


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON: {type(value).__name__}")


#: Frames × particles of the viewer inside a notebook cell (the notebook file keeps it).
INLINE_POINT_FRAMES = 60_000


def inline_viewer(traj: Trajectory, *, system=None, title: str = "", height: int = 600) -> str:
    """The viewer as an ``<iframe>`` for a notebook cell (Jupyter's ``_repr_html_``): the page
    of ``viewer_page`` with fewer frames for big systems (``INLINE_POINT_FRAMES``)."""
    page = viewer_page(traj, system=system, title=title, point_frames=INLINE_POINT_FRAMES)
    return (f'<iframe srcdoc="{html.escape(page, quote=True)}" style="width:100%;height:{int(height)}px;'
            'border:1px solid #d9dce3" title="constrained viewer"></iframe>')


def write_viewer(traj: Trajectory, path, *, system=None, title: str = "") -> Path:
    """Write the viewer page to ``path`` atomically; returns the path."""
    text = viewer_page(traj, system=system, title=title)
    path = Path(path)
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))
    return path


def load_run(path) -> Trajectory:
    """The trajectory in ``path`` (a trajectory.npz, or a folder holding one), or an InputError."""
    path = Path(path)
    if path.is_dir():
        path = path / "trajectory.npz"
    if not path.is_file():
        raise InputError(f"view: no such file {path} (give a trajectory.npz written by 'run')")
    try:
        traj = Trajectory.load(path)
    except InputError as exc:
        raise InputError(f"view: {exc}") from None
    except Exception as exc:  # a truncated or foreign file: zip, zlib, pickle or JSON errors
        raise InputError(f"view: cannot read {path} as a trajectory ({type(exc).__name__}: {exc})") from None
    x = np.asarray(traj.x)
    if x.ndim != 3 or x.shape[-1] != 3 or len(traj.t) != len(x) or len(x) == 0:
        raise InputError(f"view: {path}: x has shape {x.shape} for {len(traj.t)} times "
                         "(expected (T, N, 3), T > 0)")
    if not math.isfinite(float(traj.t[0])) or not math.isfinite(float(traj.t[-1])):
        raise InputError(f"view: {path}: the times are not finite")
    return traj



def view_command(results, *, scene=None, out=None) -> Path:
    """``constrained view``: read RUN, write the page; bad input is an InputError.

    ``scene`` is a loaded Scene (or None: the page shows what the trajectory alone allows).
    """
    traj = load_run(results)
    run = Path(results)
    target = Path(out) if out else (run if run.is_dir() else run.parent) / "viewer.html"
    if target.is_dir():
        raise InputError(f"view: --out {target} is a directory; give the name of the page to write")
    blocking = next((d for d in target.parents if d.exists() and not d.is_dir()), None)
    if blocking is not None:  # (mkdir's own words, "File exists", named the wrong cause)
        raise InputError(f"view: cannot write {target}: {blocking} is a file, not a folder; give an --out "
                         "in a folder, or move the file")
    system = scene.system if scene is not None else None
    file = run / "trajectory.npz" if run.is_dir() else run
    title = (scene.name if scene is not None else "") or f"{file.parent.name}/{file.name}".lstrip("/")
    try:
        return write_viewer(traj, target, system=system, title=title)
    except OSError as exc:
        raise InputError(f"view: cannot write {target}: {exc.strerror or exc}") from None
    except InputError as exc:  # the scene does not fit the run, or a formula cannot be drawn
        where = f"scene file {scene.path}" if scene is not None else str(file)
        raise InputError(f"view: {where} with {file}: {exc}") from None
