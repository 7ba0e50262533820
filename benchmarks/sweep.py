"""`constrained sweep` as a whole command against an in-process Exudyn loop (issue 17).

    python benchmarks/sweep.py --variants 2000 --out docs/performance/sweep

The planar double pendulum of ``benchmarks/scenes/double_pendulum_sweep.toml`` to t = 2 s,
with both masses (U[0.5, 2] kg), both rod lengths (U[0.5, 1.5] m) and both start angles
(U[1.5, 2.5] rad, at rest) drawn at random per variant (seed 0). Every runner gets the same
variants; each one's end positions are checked against a DOP853 reference (SciPy's
``solve_ivp`` on the pendulum's angle ODE at rtol 1e-12, an independent route) on the first
``--check`` variants, and must be within 1e-6 m. Runners:

- ``constrained sweep SCENE --design variants.csv --out DIR`` in a subprocess: the whole
  command, from the interpreter's start to the summary files written (imports, scene, the
  batched chunks, chunk files, summary.csv/.parquet, the figure). Run twice: the first run
  may compile the batched step loop (the C compiler's output is cached on disk), the second
  finds it in the cache — the timing reported is the second unless ``--cold``;
- ``simulate_many`` called from Python on the same table (the batched API; no files);
- Exudyn's kinematic tree + DOPRI5 in a Python loop in this process (a tree built and solved
  per variant; the loop only, after the tolerance search), at the loosest of ``--exudyn-rtol``
  that meets 1e-6 m on the checked variants;
- hand-written CasADi loops of benchmarks/ensemble.py on the angle ODE, folded, mapped over
  the variants, compiled: RK4 with the fewest fixed steps that meet 1e-6, and the ideal —
  DOPRI5 with each variant's own adaptive steps at the loosest rtol that meets 1e-6.

Numbers depend on the machine and its load: rerun on a quiet machine before quoting them.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ensemble import HandMappedDopri5, end_positions, hand_mapped_rk4  # noqa: E402

import constrained as C  # noqa: E402

SCENE = ROOT / "benchmarks" / "scenes" / "double_pendulum_sweep.toml"
T_END, TARGET, G = 2.0, 1e-6, 9.81
NAMES = ("m1", "m2", "l1", "l2", "th1", "th2")


def draw(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"m1": rng.uniform(0.5, 2, n), "m2": rng.uniform(0.5, 2, n), "l1": rng.uniform(0.5, 1.5, n),
            "l2": rng.uniform(0.5, 1.5, n), "th1": rng.uniform(1.5, 2.5, n), "th2": rng.uniform(1.5, 2.5, n)}


def write_design(path: Path, table: dict) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([f"parameters.{k}" for k in NAMES])
        for row in zip(*(table[k] for k in NAMES), strict=True):
            w.writerow([repr(float(v)) for v in row])


def angle_rhs(m1, m2, l1, l2):
    def f(_t, y):
        th1, th2, w1, w2 = y
        d = th1 - th2
        den = 2 * m1 + m2 - m2 * np.cos(2 * d)
        a1 = (-G * (2 * m1 + m2) * np.sin(th1) - m2 * G * np.sin(th1 - 2 * th2)
              - 2 * np.sin(d) * m2 * (w2**2 * l2 + w1**2 * l1 * np.cos(d))) / (l1 * den)
        a2 = (2 * np.sin(d) * (w1**2 * l1 * (m1 + m2) + G * (m1 + m2) * np.cos(th1)
                               + w2**2 * l2 * m2 * np.cos(d))) / (l2 * den)
        return [w1, w2, a1, a2]
    return f


def reference(table: dict, count: int) -> np.ndarray:
    """End positions (count, 2, 2) by SciPy's DOP853 on the angle ODE at rtol 1e-12."""
    from scipy.integrate import solve_ivp

    out = []
    for k in range(count):
        m1, m2, l1, l2, th1, th2 = (float(table[n][k]) for n in NAMES)
        sol = solve_ivp(angle_rhs(m1, m2, l1, l2), (0.0, T_END), [th1, th2, 0.0, 0.0], method="DOP853",
                        rtol=1e-12, atol=1e-12)
        out.append(_positions(sol.y[0, -1], sol.y[1, -1], l1, l2))
    return np.array(out)


def sweep_command(design: Path, out: Path, env: dict) -> tuple[float, np.ndarray, str]:
    """(wall seconds of the whole command, end positions (n, 2, 2), its 'ran ...' lines)."""
    args = [sys.executable, "-m", "constrained.cli", "sweep", str(SCENE), "--design", str(design),
            "--out", str(out)]
    started = time.perf_counter()
    proc = subprocess.run(args, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - started
    if proc.returncode != 0:
        raise SystemExit(f"constrained sweep failed ({proc.returncode}):\n{proc.stderr}")
    said = "\n".join(line for line in proc.stdout.splitlines()
                     if line.startswith(("sweep:", "paths:", "ran")))
    with open(out / "summary.csv") as f:
        rows = list(csv.DictReader(f))
    failed = [r["status"] for r in rows if r["status"] != "ok"]
    if failed:
        raise SystemExit(f"{len(failed)} variants of the sweep failed, e.g.: {failed[0]}")
    xy = np.array([[[float(r[f"{a}_{p}"]) for a in "xy"] for p in ("p1", "p2")] for r in rows])
    return wall, xy, said


def exudyn_variant(m1, m2, l1, l2, th1, th2, rtol):
    """End positions (2, 2) of Exudyn's kinematic tree (point masses) with DOPRI5."""
    import exudyn as exu
    from exudyn.itemInterface import NodeGenericODE2, ObjectKinematicTree

    sc = exu.SystemContainer()
    mbs = sc.AddSystem()
    node = mbs.AddNode(NodeGenericODE2(referenceCoordinates=[0.0, 0.0], initialCoordinates=[th1, th2 - th1],
                                       initialCoordinates_t=[0.0, 0.0], numberOfODE2Coordinates=2))
    mbs.AddObject(ObjectKinematicTree(
        nodeNumber=node, jointTypes=[exu.JointType.RevoluteZ] * 2, linkParents=[-1, 0],
        jointTransformations=exu.Matrix3DList([np.eye(3)] * 2),
        jointOffsets=exu.Vector3DList([[0.0, 0.0, 0.0], [0.0, -l1, 0.0]]),
        linkInertiasCOM=exu.Matrix3DList([np.zeros((3, 3))] * 2),
        linkCOMs=exu.Vector3DList([[0.0, -l1, 0.0], [0.0, -l2, 0.0]]), linkMasses=[m1, m2],
        gravity=[0.0, -G, 0.0]))
    mbs.Assemble()
    s = exu.SimulationSettings()
    s.timeIntegration.endTime = T_END
    s.timeIntegration.verboseMode = 0
    s.solution.file.write = False
    s.solution.sensors.active = False
    s.show.computationTime = False
    s.show.statistics = False
    ti = s.timeIntegration
    ti.automaticStepSize = True
    ti.relativeTolerance, ti.absoluteTolerance = rtol, rtol * 1e-2
    ti.numberOfSteps = 10
    exu.SolveDynamic(mbs, s, solverType=exu.DynamicSolverType.DOPRI5)
    q = np.asarray(mbs.GetNodeOutput(node, exu.OutputVariableType.Coordinates), float)
    return _positions(q[0], q[0] + q[1], l1, l2)


def _positions(th1: float, th2: float, l1: float, l2: float) -> np.ndarray:
    """(2, 2) bob positions [[x1, y1], [x2, y2]] of one variant (end_positions on arrays)."""
    return end_positions(np.array([th1]), np.array([th2]), np.array([l1]), np.array([l2]))[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", type=int, default=2000)
    parser.add_argument("--check", type=int, default=200, help="variants checked against the reference")
    parser.add_argument("--exudyn-rtol", type=float, nargs="+", default=[1e-7, 5e-8, 2e-8, 1e-8, 5e-9],
                        help="Exudyn's tolerances to try: the loosest that meets 1e-6 m is timed")
    parser.add_argument("--cold", action="store_true",
                        help="report the first sweep run (with an empty compile cache) instead of the second")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    n = args.variants
    table = draw(n)
    check = min(args.check, n)
    ref = reference(table, check)
    rows = []

    def add(runner, per_s, xy, note=""):
        err = float(np.max(np.abs(np.asarray(xy)[:check] - ref)))
        rows.append({"runner": runner, "variants": n, "per_s": per_s, "error": err, "note": note})
        print(f"{runner}: {per_s:.0f} variants/s, max end error {err:.1e} m {note}", flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        design = tmp / "variants.csv"
        write_design(design, table)
        env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        if args.cold:
            env["CONSTRAINED_CACHE"] = str(tmp / "cache")
        first, xy, said = sweep_command(design, tmp / "first", env)
        wall = first
        if not args.cold:
            wall, xy, said = sweep_command(design, tmp / "second", env)
        add("constrained sweep (whole command)", n / wall, xy,
            f"{wall:.2f} s incl. start-up; first run {first:.2f} s; " + said.replace("\n", "; "))
        empty = time.perf_counter()
        subprocess.run([sys.executable, "-c", "pass"], check=True)
        interpreter = time.perf_counter() - empty
        rows[-1]["interpreter_s"] = interpreter
    # the batched API from Python (warm: the step loop built and compiled by a first call)
    scene = C.load_scene(SCENE)
    model = C.assemble(scene.system)
    kw = dict(rtol=scene.settings["rtol"], atol=scene.settings["atol"], model=model)
    C.simulate_many(scene.system, T_END, {k: v[:50] for k, v in table.items()}, **kw)
    started = time.perf_counter()
    ens = C.simulate_many(scene.system, T_END, table, **kw)
    wall = time.perf_counter() - started
    add("constrained simulate_many (Python, warm)", n / wall, ens.x[:, -1, :, :2])
    # Exudyn in a Python loop
    try:
        import exudyn  # noqa: F401
    except ImportError:
        print("Exudyn not installed (pip install -e .[bench]): no Exudyn row")
    else:
        params = [tuple(float(table[k][i]) for k in NAMES) for i in range(n)]
        for rtol in args.exudyn_rtol:  # the loosest tolerance that meets the target on the checked variants
            checked = np.array([exudyn_variant(*p, rtol) for p in params[:check]])
            if np.max(np.abs(checked - ref)) <= TARGET:
                break
        started = time.perf_counter()
        xy = [exudyn_variant(*p, rtol) for p in params]
        wall = time.perf_counter() - started
        add(f"Exudyn tree + DOPRI5 rtol {rtol:g}, Python loop", n / wall, xy)
    # the ideal: the fewest RK4 steps (of a doubling ladder) that meet the target on the checked variants
    steps = 250
    pm = np.stack([table["m1"], table["m2"], table["l1"], table["l2"]])
    y0 = np.stack([table["th1"], table["th2"], np.zeros(n), np.zeros(n)])
    while True:
        ideal = hand_mapped_rk4(steps, n)
        ideal(y0, pm)
        started = time.perf_counter()
        out = np.asarray(ideal(y0, pm), float)
        wall = time.perf_counter() - started
        xy = end_positions(out[0], out[1], table["l1"], table["l2"])
        if np.max(np.abs(xy[:check] - ref)) <= TARGET or steps > 64000:
            break
        steps *= 2
    add(f"hand-mapped CasADi RK4, {steps} fixed steps, compiled", n / wall, xy)
    for rtol in (1e-7, 3e-8, 1e-8, 3e-9, 1e-9, 1e-10):  # the ideal: adaptive DOPRI5, loosest rtol that meets
        ideal = HandMappedDopri5(rtol, n)
        ideal(table["th1"], table["th2"], pm)
        started = time.perf_counter()
        out = ideal(table["th1"], table["th2"], pm)
        wall = time.perf_counter() - started
        xy = end_positions(out[0], out[1], table["l1"], table["l2"])
        if np.max(np.abs(xy[:check] - ref)) <= TARGET:
            break
    add(f"hand-mapped CasADi DOPRI5, adaptive, rtol {rtol:g}, compiled (ideal)", n / wall, xy)
    exu = next((r["per_s"] for r in rows if r["runner"].startswith("Exudyn")), None)
    ideal_rate = rows[-1]["per_s"]
    lines = ["| runner | variants | variants/s | vs Exudyn loop | vs the ideal | max end error (first "
             f"{check}) |", "|---|---|---|---|---|---|"]
    for r in rows:
        vs_exu = f"{r['per_s'] / exu:.2f}×" if exu else "—"
        lines.append(f"| {r['runner']} | {r['variants']} | {r['per_s']:.0f} | {vs_exu} | "
                     f"{r['per_s'] / ideal_rate:.2f}× | {r['error']:.1e} |")
    sweep_row = rows[0]
    lines += ["", f"constrained sweep: {sweep_row['note']}",
              f"(an empty interpreter starts in {sweep_row['interpreter_s']:.2f} s on this machine)",
              f"load average at the end: {', '.join(f'{x:.1f}' for x in os.getloadavg())} on "
              f"{os.cpu_count()} cores"]
    text = "\n".join(lines)
    print(text)
    if any(r["error"] > TARGET for r in rows):
        print(f"WARNING: a runner misses the {TARGET:g} m target")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "sweep.md").write_text(text + "\n")
        (args.out / "sweep.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
