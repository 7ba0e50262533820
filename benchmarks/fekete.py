"""The Fekete problem of the IVP Test Set: constrained against a hand-vectorized NumPy version.

Problem (Test Set for IVP Solvers, F. Mazzia, C. Magherini, Bari, ``fekete.f``; after
Bendtsen & Thomsen, IMM-DTU 1999; https://archimede.dm.uniba.it/~testset/): 20 points
p_i on the unit sphere move, with unit mass and damping, towards the configuration that
maximizes the product of their mutual distances (elliptic Fekete points):

    p_i'' = g_i − α p_i' + 2 λ_i p_i,   g_i = Σ_{j≠i} (p_i − p_j) / |p_i − p_j|²,   α = 0.5,
    0 = |p_i|² − 1,                      t ∈ [0, 1000].

The test set integrates it as a stabilized index-2 DAE of size 160 (p, q = p', λ, and μ
with p' = q + 2 μ p, 0 = 2 p·q); μ = 0 on the exact solution. The start is four latitude
rings (3, 7, 6, 4 points) at rest. The reference at t = 1000 is the test set's ``solut``.
The definition, the start and the reference were read from two independent ports of
``fekete.f``: SciML/SciMLBenchmarks.jl ``benchmarks/DAE/fekete.jmd`` (and its rendered
output SciML/SciMLBenchmarksOutput ``markdown/DAE/fekete.md``, which also prints the
first start values), and a MATLAB driver of MEBDF for the same problem (``FEKETE``,
with ``INIT``, ``F_EVAL`` and ``SOLN``); both agree digit for digit.

In ``constrained`` (``fekete_system``): 20 particles of mass 1, one ``Surface`` row
x² + y² + z² − 1 = 0 per particle (J = 2 p_iᵀ, so the multipliers are the test set's λ_i,
→ −(N − 1)/4 = −4.75 at rest), ``Central`` V(r) = −log r for each of the 190 pairs
(−∂V/∂p_i is the test set's g_i) and ``Damping(0.5)`` (R = ½ α Σ|v_i|², force −α v_i).
There is no scene file: a ``central`` entry covers one pair (190 entries would be needed),
and a single ``potential`` formula over all pairs is about 10,100 characters with these
particle names, over the formula parser's 10,000-character limit.

The NumPy peer is the index-1 form in (p, q) with λ_i in closed form from the acceleration-
level constraint, λ_i = −(|q_i|² + p_i·(g_i − α q_i)) / (2 |p_i|²), integrated by SciPy's
DOP853 without projection (so |p_i|² − 1 drifts).

Every runner does the same run (t = 0 → 1000, output at 1000) at each rtol with
atol = rtol × ``--atol-factor``; the runners alternate within each repeat and the table
gives medians. ``--methods`` lists constrained methods, ``a:b`` meaning method a with
``base="b"``; a name the installed package rejects is skipped with its message.

    python benchmarks/fekete.py [--methods dopri,projection,projection:CVODES,idas]
        [--rtols 1e-10 1e-11] [--atol-factor 1e-2] [--repeats 3] [--json PATH] [--md PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import constrained as C  # noqa: E402
from constrained.errors import InputError  # noqa: E402
from constrained.manifold.manifold import Manifold  # noqa: E402

N = 20
ALPHA = 0.5
T_END = 1000.0
DEFAULT_METHODS = "dopri,projection,projection:CVODES,idas"
SOURCES = [
    "IVP Test Set, problem FEKETE (fekete.f, subroutines init/feval/solut): "
    "https://archimede.dm.uniba.it/~testset/",
    "SciML/SciMLBenchmarks.jl benchmarks/DAE/fekete.jmd (port of fekete.f, REFSOL from solut)",
    "SciML/SciMLBenchmarksOutput markdown/DAE/fekete.md (same, with the printed start values)",
    "MATLAB MEBDF driver FEKETE (INIT, F_EVAL, SOLN): same equations, start and reference",
]

#: The test set's reference solution at t = 1000 (``solut``), positions y(1..60) as (20, 3).
REFERENCE_POSITIONS = np.array([
    [-0.4070263380333202, 0.3463758772791802, 0.8451942450030429],
    [0.7752934752521549e-01, -0.2628662719972299, 0.9617122871829146],
    [0.7100577833343567, 0.1212948055586120, 0.6936177005172217],
    [0.2348267744557627, 0.7449277976923311, 0.6244509285956391],
    [-0.4341114738782885, 0.8785430442262876, 0.1992720444237660],
    [-0.9515059600312596, 0.2203508762787005, 0.2146669498274008],
    [-0.6385191643609878, -0.4310833259390688, 0.6375425027722121],
    [-0.1464175087914336, -0.9380871635228862, 0.3139337298744690],
    [0.5666974065069942, -0.6739221885076542, 0.4740073135462156],
    [0.9843259538440293, -0.1696995357819996, -0.4800504290609090e-01],
    [0.1464175087914331, 0.9380871635228875, -0.3139337298744656],
    [-0.7092757549979014, 0.5264062637139616, -0.4688542938854929],
    [-0.8665731819284478, -0.4813878059756024, -0.1315929352982178],
    [-0.2347897778700538, -0.8594340408013130, -0.4541441287957579],
    [0.5530976940074118, -0.7674370265615124, -0.3242273140037833],
    [0.7711050969896927, 0.6357041816577034, 0.3573685519777001e-01],
    [0.7103951209379591, 0.2403570431280519, -0.6614886725910596],
    [-0.3038208738735660e-01, 0.4501923293640461, -0.8924145871442046],
    [-0.5772996158107093, -0.1766763414971813, -0.7971892020969544],
    [0.2414481766969039, -0.3416456818373135, -0.9082846503446250],
])
#: Velocities y(61..120) of the reference: all below 3e-16 in magnitude, i.e. zero; the
#: error reported for velocities is max |v| at t = 1000.
REFERENCE_SPEED_BOUND = 3e-16
#: λ_i of the reference, y(121..140): −4.75 to within one unit in the last printed digit.
#: It is −(N − 1)/4 exactly at rest on the unit sphere, since p_i·g_i = (N − 1)/2 there.
REFERENCE_MULTIPLIER = -4.75


def initial_positions() -> np.ndarray:
    """The test set's start (``init``): rings of 3, 7, 6, 4 points at latitudes β (radians),
    longitudes α = 2π k/n + offset, p = (cos α cos β, sin α cos β, sin β); shape (20, 3).

    k runs 1..n in the first three rings but 0..3 in the last (``2*pi*(i-17)/4`` for
    i = 17..20): the same four points, but the order fixes which particle ends where."""
    rings = [(3, 1, np.pi / 13, 3 * np.pi / 8), (7, 1, np.pi / 29, np.pi / 8),
             (6, 1, np.pi / 7, -2 * np.pi / 15), (4, 0, np.pi / 17, -3 * np.pi / 10)]
    points = []
    for count, first, offset, beta in rings:
        for k in range(first, first + count):
            a = 2 * np.pi * k / count + offset
            points.append([np.cos(a) * np.cos(beta), np.sin(a) * np.cos(beta), np.sin(beta)])
    return np.array(points)


def names() -> list[str]:
    return [f"p{i + 1}" for i in range(N)]


def fekete_system(alpha: float = ALPHA) -> C.System:
    """The Fekete problem as a constrained System (start at rest, see the module docstring)."""
    s = C.System(name="Fekete problem (IVP Test Set)")
    labels = names()
    for name, p in zip(labels, initial_positions(), strict=True):
        s.add_particle(name, 1.0, p)
    s.add(C.Surface(labels, "x**2 + y**2 + z**2 - 1", name="unit sphere"))
    for i in range(N):
        for j in range(i + 1, N):
            s.add(C.Central(labels[i], labels[j], expr="-log(r)", name=f"log repulsion {i + 1}-{j + 1}"))
    s.add(C.Damping(alpha, name=f"damping {alpha:g}"))
    return s


# --- the NumPy index-1 peer ---------------------------------------------------------------------
def repulsion(p: np.ndarray) -> np.ndarray:
    """g_i = Σ_{j≠i} (p_i − p_j)/|p_i − p_j|², shape (N, 3)."""
    d = p[:, None, :] - p[None, :, :]
    r2 = np.einsum("ijk,ijk->ij", d, d)
    np.fill_diagonal(r2, np.inf)
    return np.einsum("ijk,ij->ik", d, 1.0 / r2)


def numpy_multipliers(p: np.ndarray, q: np.ndarray, alpha: float = ALPHA) -> np.ndarray:
    """λ_i from d²/dt² (|p_i|² − 1) = 2|q_i|² + 2 p_i·q_i' = 0 with q_i' = g_i − α q_i + 2 λ_i p_i."""
    f = repulsion(p) - alpha * q
    return -(np.einsum("ik,ik->i", q, q) + np.einsum("ik,ik->i", p, f)) / (2 * np.einsum("ik,ik->i", p, p))


def numpy_rhs(t, y, alpha: float = ALPHA):
    """(p', q') of the index-1 ODE, y = (p, q) flat."""
    p, q = y[: 3 * N].reshape(N, 3), y[3 * N:].reshape(N, 3)
    f = repulsion(p) - alpha * q
    lam = -(np.einsum("ik,ik->i", q, q) + np.einsum("ik,ik->i", p, f)) / (2 * np.einsum("ik,ik->i", p, p))
    return np.concatenate([y[3 * N:], (f + 2 * lam[:, None] * p).ravel()])


def run_numpy(rtol: float, atol: float, t_end: float = T_END, alpha: float = ALPHA) -> dict:
    """The NumPy index-1 version with SciPy DOP853; final state, λ and the wall time."""
    y0 = np.concatenate([initial_positions().ravel(), np.zeros(3 * N)])
    start = time.perf_counter()
    sol = solve_ivp(numpy_rhs, (0.0, t_end), y0, method="DOP853", rtol=rtol, atol=atol,
                    t_eval=[t_end], args=(alpha,))
    wall = time.perf_counter() - start
    if sol.status != 0:
        raise RuntimeError(f"solve_ivp failed: {sol.message}")
    p, q = sol.y[: 3 * N, -1].reshape(N, 3), sol.y[3 * N:, -1].reshape(N, 3)
    return {"wall": wall, "solver_wall": wall, "x": p, "v": q, "lam": numpy_multipliers(p, q, alpha),
            "nfev": int(sol.nfev), "steps": None}


def run_constrained(system: C.System, model, method: str, options: dict, rtol: float, atol: float,
                    t_end: float = T_END) -> dict:
    """One ``constrained.run.simulate`` run with output at 0 and t_end only; λ at the end after timing."""
    start = time.perf_counter()
    tr = C.simulate(system, t_end, method=method, rtol=rtol, atol=atol, t_eval=[0.0, t_end],
                    outputs=set(), model=model, **options)
    wall = time.perf_counter() - start
    x, v = tr.x[-1], tr.v[-1]
    _, lam = Manifold(model).accelerations(x.ravel(), v.ravel(), float(tr.t[-1]))
    return {"wall": wall, "solver_wall": float(tr.stats["wall_time_s"]), "x": x, "v": v, "lam": lam,
            "nfev": tr.stats.get("nfev"), "steps": tr.stats.get("steps")}


# --- measures ------------------------------------------------------------------------------------
def tangential_force(p: np.ndarray) -> np.ndarray:
    """The part of g_i tangent to the sphere at p_i/|p_i|: zero at an equilibrium, (N, 3)."""
    g = repulsion(p)
    n = p / np.linalg.norm(p, axis=1, keepdims=True)
    return g - np.einsum("ik,ik->i", g, n)[:, None] * n


def errors(x, v, lam) -> dict:
    """Errors against the published reference at t = 1000, and the final constraint residual."""
    x = np.asarray(x).reshape(N, 3)
    return {
        "position_error": float(np.max(np.abs(x - REFERENCE_POSITIONS))),
        "max_speed": float(np.max(np.abs(v))),
        "multiplier_error": float(np.max(np.abs(np.asarray(lam) - REFERENCE_MULTIPLIER))),
        "sphere_residual": float(np.max(np.abs(np.einsum("ik,ik->i", x, x) - 1.0))),
        "tangential_force": float(np.max(np.linalg.norm(tangential_force(x), axis=1))),
    }


def parse_methods(text: str) -> list[tuple[str, str, dict]]:
    """'projection,projection:CVODES,idas' -> [(label, method, options)]."""
    out = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        method, _, base = item.partition(":")
        out.append((f"constrained {item}", method, {"base": base} if base else {}))
    return out


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)  # mkstemp's 0600 would stick to the final file
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default=DEFAULT_METHODS,
                        help=f"constrained methods, comma-separated, a:b = method a with base b "
                             f"(default {DEFAULT_METHODS})")
    parser.add_argument("--rtols", type=float, nargs="+", default=[1e-10, 1e-11])
    parser.add_argument("--atol-factor", type=float, default=1e-2, help="atol = rtol × this (1e-2)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--t-end", type=float, default=T_END,
                        help="end time (the reference is at 1000 only; other values are for smoke runs)")
    parser.add_argument("--json", type=Path, help="write all results as JSON (atomically)")
    parser.add_argument("--md", type=Path, help="write the markdown report (atomically)")
    args = parser.parse_args(argv)

    lines: list[str] = []

    def emit(text: str = "") -> None:
        print(text, flush=True)
        lines.append(text)

    system = fekete_system()
    model = C.assemble(system)
    runners: dict[str, tuple] = {"NumPy index-1 + DOP853": ("numpy", None, None)}
    skipped: dict[str, str] = {}
    for label, method, options in parse_methods(args.methods):
        try:  # warm-up, also pays one-time costs; an unknown method or base is skipped
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                run_constrained(system, model, method, options, 1e-6, 1e-8, t_end=1.0)
        except InputError as exc:
            skipped[label] = _first_line(exc)
            print(f"skipped {label}: {skipped[label]}", flush=True)
            continue
        runners[label] = ("constrained", method, options)
    run_numpy(1e-6, 1e-8, t_end=1.0)

    command = "python benchmarks/fekete.py " + " ".join(sys.argv[1:] if argv is None else argv)
    emit(f"# Fekete problem (IVP Test Set), t = 0 → {args.t_end:g}, {N} points, α = {ALPHA}")
    emit()
    emit(f"`{command.strip()}` — {args.repeats} repeats alternating between runners, medians; "
         f"atol = rtol × {args.atol_factor:g}. Python {platform.python_version()}, "
         f"{platform.machine()}, {os.cpu_count()} cores.")
    emit()
    emit("Errors against the test set's published reference at t = 1000: positions (max |Δp| over "
         "60 components), speeds (max |v|; the reference's are < 3e-16), multipliers "
         "(max |λ_i + 4.75|); |p|²−1 is the sphere residual at the end, "
         "F_tan the largest tangential repulsion (0 at an equilibrium). "
         "Wall time: the whole `simulate()` call (model assembled once beforehand) or "
         "`solve_ivp`; solver: `stats['wall_time_s']`; ratio: median wall over the fastest "
         "median wall at the same rtol.")
    if args.t_end != T_END:
        emit()
        emit(f"**t_end = {args.t_end:g} is not the reference time {T_END:g}: the errors below are "
             "distances to the t = 1000 state, not integration errors.**")
    emit()
    emit("| rtol | runner | median wall [s] | solver [s] | ratio | position error | max speed "
         "| λ error | \\|p\\|²−1 | F_tan | nfev | steps | warnings |")
    emit("|---|---|---|---|---|---|---|---|---|---|---|---|---|")

    rows = []
    for rtol in args.rtols:
        atol = rtol * args.atol_factor
        walls = {k: [] for k in runners}
        solver_walls = {k: [] for k in runners}
        last: dict[str, dict] = {}
        caught: dict[str, set] = {k: set() for k in runners}
        failed: dict[str, str] = {}
        for _ in range(args.repeats):
            for label, (kind, method, options) in runners.items():
                if label in failed:
                    continue
                with warnings.catch_warnings(record=True) as seen:
                    warnings.simplefilter("always")
                    try:
                        if kind == "numpy":
                            res = run_numpy(rtol, atol, t_end=args.t_end)
                        else:
                            res = run_constrained(system, model, method, options, rtol, atol, args.t_end)
                    except Exception as exc:  # a failed run is reported, the others go on
                        failed[label] = _first_line(exc)
                        continue
                caught[label].update(type(w.message).__name__ for w in seen)
                walls[label].append(res["wall"])
                solver_walls[label].append(res["solver_wall"])
                last[label] = res
        medians = {k: statistics.median(v) for k, v in walls.items() if v}
        best = min(medians.values()) if medians else float("nan")
        for label in runners:
            if label in failed:
                rows.append({"rtol": rtol, "atol": atol, "runner": label, "failed": failed[label]})
                emit(f"| {rtol:g} | {label} | failed: {failed[label][:120]} | | | | | | | | | | |")
                continue
            res = last[label]
            err = errors(res["x"], res["v"], res["lam"])
            row = {"rtol": rtol, "atol": atol, "runner": label, "wall_median_s": medians[label],
                   "walls_s": walls[label], "solver_wall_median_s": statistics.median(solver_walls[label]),
                   "ratio_to_fastest": medians[label] / best, "nfev": res["nfev"], "steps": res["steps"],
                   "warnings": sorted(caught[label]), **err}
            rows.append(row)
            steps = "" if res["steps"] is None else str(res["steps"])
            emit(f"| {rtol:g} | {label} | {row['wall_median_s']:.3f} | {row['solver_wall_median_s']:.3f} "
                 f"| {row['ratio_to_fastest']:.2f}× | {err['position_error']:.1e} | {err['max_speed']:.1e} "
                 f"| {err['multiplier_error']:.1e} | {err['sphere_residual']:.1e} "
                 f"| {err['tangential_force']:.1e} | {res['nfev']} | {steps} "
                 f"| {', '.join(row['warnings'])} |")
    if skipped:
        emit()
    for label, why in skipped.items():
        rows.append({"runner": label, "skipped": why})
        emit(f"- skipped {label}: {why}")
    emit()
    emit("Notes: the reference is itself only about 3e-12 accurate (when this benchmark was "
         "written, `projection` runs from rtol 1e-8 to 1e-12 all differed from it by 2.3–2.7e-12), "
         "so position errors at that level are ties. The NumPy version has no projection: "
         "|p|²−1 and p·q drift and are never pulled back, which sets its error floor. "
         "Near the equilibrium the explicit methods' steps are limited by stability, not accuracy "
         "(hence DOP853's StiffnessWarning, and nfev that barely changes with rtol).")
    emit()
    emit("Sources of the definition, start and reference:")
    emit()
    for source in SOURCES:
        emit(f"- {source}")

    if args.md:
        _atomic_write(args.md, "\n".join(lines) + "\n")
    if args.json:
        payload = {
            "problem": "fekete", "n_points": N, "alpha": ALPHA, "t_end": args.t_end,
            "command": command.strip(), "methods": args.methods, "rtols": args.rtols,
            "atol_factor": args.atol_factor, "repeats": args.repeats, "sources": SOURCES,
            "reference": {"positions": REFERENCE_POSITIONS.tolist(), "speed_bound": REFERENCE_SPEED_BOUND,
                          "multiplier": REFERENCE_MULTIPLIER},
            "machine": {"python": platform.python_version(), "machine": platform.machine(),
                        "cpus": os.cpu_count()},
            "rows": rows,
        }
        _atomic_write(args.json, json.dumps(payload, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
