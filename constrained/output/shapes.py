"""The constraints of a scene as shapes to draw, evaluated at the frame times of a picture.

One item per constraint (a dict, JSON-ready but for NumPy arrays of what moves):

- ``rod``: a distance constraint, particle ``a`` to particle ``b`` or to a ``point``;
- ``pin``: particle ``a`` held at a ``point``;
- ``plane``: a square patch around the motion, 4 corners;
- ``surface`` / ``curve``: a cloud of points on g(x, y, z, t) = 0 (a curve: g1 = g2 = 0) near
  the motion, found by Newton projection of a grid; one cloud per distinct formula
  (``same_as`` names the first item with it), at ``CLOUD_KEYS`` key times when it moves;
- ``undrawn``: a custom constraint (a formula in every coordinate has no picture).

A point is ``{"fixed": [x, y, z]}`` or ``{"moving": (frames, 3) array}``. The viewer page
(output/viewer.py) encodes the arrays; the animation (output/animation.py) draws them.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..errors import InputError
from ..model.constraints import Curve, Custom, Distance, Pin, Plane, Surface
from ..model.symbols import Symbols

#: Most points of a surface or curve cloud, and most key times of a moving one.
CLOUD_POINTS = 700
CLOUD_KEYS = 40
#: Most distinct surface and curve formulas drawn (each costs a Newton projection and page space).
MAX_CLOUDS = 12
_GRID = 14  # seeds per axis of the Newton projection onto surfaces and curves


def shapes(system, names: list[str], times: np.ndarray, x: np.ndarray) -> list[dict]:
    """The items of every constraint of ``system`` at ``times`` around the motion ``x``."""
    found = Shapes(system, names, times, x)
    for c in system.constraints:
        found.add(c)
    return found.items


def _time_vector(fn: ca.Function, times: np.ndarray) -> np.ndarray:
    """(len(times), k) values of a CasADi function of t returning k numbers."""
    out = fn.map(len(times))(times.reshape(1, -1))
    return np.asarray(out, dtype=float).T


class Shapes:
    """The constraints of a System, evaluated at the frame ``times`` around the motion ``x``
    (frames × N × 3): ``add(constraint)`` appends one item to ``items`` (see the module doc);
    arrays that move with t are (times or key times) × numbers float arrays."""

    def __init__(self, system, names: list[str], times: np.ndarray, x: np.ndarray):
        self.s = Symbols(system)
        self.names = {n: k for k, n in enumerate(names)}
        self.times = times
        finite = x.reshape(-1, 3)
        finite = finite[np.all(np.isfinite(finite), axis=1)]
        self.lo = finite.min(axis=0) if len(finite) else np.zeros(3)
        self.hi = finite.max(axis=0) if len(finite) else np.zeros(3)
        self.size = float(max(np.max(self.hi - self.lo), 1e-3))
        self.centre = 0.5 * (self.lo + self.hi)
        self.items: list[dict] = []
        self._clouds: dict[tuple, dict] = {}  # one cloud per distinct formula (a chain repeats them)

    def particle(self, name, where) -> int:
        if name not in self.names:
            raise InputError(f"names particle {name!r}, which the trajectory does not have", where=where)
        return self.names[name]

    def point(self, entries, where) -> dict:
        """A point of t: fixed ``[x, y, z]`` or per frame (base64 float32, frames × 3)."""
        vec = self.s.point(entries, where)
        fn = ca.Function("p", [self.s.t], [vec])
        if not ca.depends_on(vec, self.s.t):
            return {"fixed": [float(v) for v in np.asarray(fn(0.0)).ravel()]}
        return {"moving": _time_vector(fn, self.times)}

    def add(self, c) -> None:
        where = c.where or c.label
        label = c.label
        if isinstance(c, Distance):
            item = {"kind": "rod", "label": label, "a": self.particle(c.a, where)}
            if c.b is not None:
                item["b"] = self.particle(c.b, where)
            else:
                item["point"] = self.point(c.point, where)
            self.items.append(item)
        elif isinstance(c, Pin):
            self.items.append({"kind": "pin", "label": label, "a": self.particle(c.a, where),
                               "point": self.point(c.point, where)})
        elif isinstance(c, Plane):
            self.items.append({"kind": "plane", "label": label, **self.plane(c, where)})
        elif isinstance(c, Surface | Curve):
            exprs = [c.expr] if isinstance(c, Surface) else c.exprs
            self.items.append({"kind": "surface" if isinstance(c, Surface) else "curve",
                               "label": label, **self.cloud(exprs, where)})
        else:  # Custom, or a constraint class this page does not know
            kind = ("custom" if isinstance(c, Custom) else "velocity constraint"
                    if getattr(c, "level", "") == "velocity" else type(c).__name__.lower())
            self.items.append({"kind": "undrawn", "label": f"{label} ({kind}: not drawn)"})

    def plane(self, c: Plane, where) -> dict:
        """The plane as a square patch around the motion: 4 corners, fixed or per frame."""
        s = self.s
        n = s.point(c.normal, f"{where}.normal")
        d = s.time_function(c.offset, f"{where}.offset")
        fn = ca.Function("n", [s.t], [ca.vertcat(n, d)])
        moving = ca.depends_on(ca.vertcat(n, d), s.t)
        nd = _time_vector(fn, self.times if moving else np.zeros(1))
        corners = np.array([self._square(row[:3], row[3]) for row in nd])  # (K, 4, 3)
        if moving:
            return {"moving": corners.reshape(len(corners), 12)}
        return {"fixed": corners[0].tolist()}

    def _square(self, normal, offset) -> np.ndarray:
        norm = float(np.linalg.norm(normal))
        if not np.isfinite(norm) or norm == 0:
            return np.full((4, 3), np.nan)
        n = normal / norm
        centre = self.centre - (n @ self.centre - offset / norm) * n
        u = np.cross(n, np.eye(3)[np.argmin(np.abs(n))])
        u /= np.linalg.norm(u)
        w = np.cross(n, u)
        h = 0.75 * self.size
        return np.array([centre + h * (su * u + sw * w) for su, sw in ((-1, -1), (1, -1), (1, 1), (-1, 1))])

    def cloud(self, exprs: list[str], where) -> dict:
        """Points on g_k(x, y, z, t) = 0 near the motion (Newton from a grid), per key time."""
        key = tuple(str(e) for e in exprs)
        if key in self._clouds:
            return {"same_as": self._clouds[key]["index"]}
        if len(self._clouds) >= MAX_CLOUDS:
            return {"points": [], "note": f"not drawn: only the first {MAX_CLOUDS} distinct formulas are"}
        self._clouds[key] = {"index": len(self.items)}
        return self._cloud(exprs, where)

    def _cloud(self, exprs: list[str], where) -> dict:
        s = self.s
        p = ca.SX.sym("p", 3)
        g = ca.vertcat(*[s.parse_field(e, f"{where}.expr", p) for e in exprs])
        J = ca.jacobian(g, p)
        step = p - J.T @ ca.solve(J @ J.T + 1e-14 * ca.SX.eye(g.numel()), g)
        newton = ca.Function("newton", [p, s.t], [step, ca.norm_inf(g)])
        moving = ca.depends_on(g, s.t)
        lo, hi = self.lo - 0.3 * self.size, self.hi + 0.3 * self.size
        axes = [np.linspace(lo[k], hi[k], _GRID) if hi[k] > lo[k] else np.array([lo[k]]) for k in range(3)]
        seeds = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).T
        mapped = newton.map(seeds.shape[1])
        if moving:
            count = min(CLOUD_KEYS, len(self.times))
            keys = np.unique(np.linspace(0, len(self.times) - 1, count).astype(int))
        else:
            keys = np.array([0])
        clouds = []
        for k in keys:
            clouds.append(self._project(mapped, seeds, float(self.times[k]), lo, hi))
        count = max(len(c) for c in clouds)
        if count == 0:
            return {"points": [], "note": "no points found near the motion"}
        if not moving:
            return {"points": np.round(clouds[0], 6).tolist()}
        # equal counts per key (NaN padding) so the page can index one flat array
        padded = np.full((len(keys), count, 3), np.nan)
        for j, c in enumerate(clouds):
            padded[j, : len(c)] = c
        return {"keys": keys.tolist(), "count": count, "moving": padded.reshape(len(keys), -1)}

    def _project(self, newton, seeds, t, lo, hi) -> np.ndarray:
        pts = seeds
        with np.errstate(all="ignore"):
            for _ in range(12):
                step, _res = newton(pts, t)
                pts = np.asarray(step, dtype=float)
            res = np.asarray(newton(pts, t)[1], dtype=float).ravel()
        pts = pts.T
        ok = np.isfinite(res) & (res < 1e-6 * self.size) & np.all((pts >= lo) & (pts <= hi), axis=1)
        pts = pts[ok]
        if len(pts) == 0:
            return pts
        cells = np.round((pts - lo) / (self.size / 80)).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        pts = pts[np.sort(first)]
        if len(pts) > CLOUD_POINTS:
            pts = pts[np.linspace(0, len(pts) - 1, CLOUD_POINTS).astype(int)]
        return pts
