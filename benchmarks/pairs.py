"""Issue 28's pair-force goals: ``constrained run`` of a Lennard-Jones cluster, as a whole command,
all pairs and with a cutoff.

The scene (written by this script as TOML; physical units): N beads of 1 g on a cubic lattice
at the pair potential's minimum distance 2^(1/6) σ (jittered by 0.02 σ), moving at about
2 cm/s (zero total momentum: a warm, self-bound droplet, no container), with
V(r) = 4ε((σ/r)¹² − (σ/r)⁶), σ = 1 cm, ε = 1e-6 J, ``pairwise`` over every pair (``--cutoff``
none) or with a cutoff (shifted to second order at r_c, a neighbour list of skin 0.1 r_c).
``--t-end`` (the LJ time σ √(m/ε) is 0.32 s) at rtol 1e-6 (atol 1e-8) with the default method
(dopri), two output samples, no figures, the default quantities.

Goals (issue 28): N = 1,000 all pairs, whole run ≤ 30 s; N = 10,000 with a cutoff of 2.5 σ,
≤ 10 s per 1,000 steps. Each run is one subprocess ``/usr/bin/time -v python -m
constrained.cli run SCENE --out DIR``: wall time of everything (imports, scene, assembly,
the compile of the step loop on a cold cache, the run, post-processing, the report) and peak
RSS; the solver's own time and its steps come from the trajectory's stats, and "per 1,000
steps" is the solver's wall time over its accepted steps × 1,000. A second run shows the warm
cache (the compiled step loop found on disk). Measure on a quiet machine.

    python benchmarks/pairs.py                                  # N = 1,000, all pairs
    python benchmarks/pairs.py --n 10000 --cutoff 0.025 --t-end 0.1
        [--compiled auto|true|false] [--repeats 2] [--write-only DIR] [--method rattle --dt 0.001]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MASS, SIGMA, EPSILON, SPEED = 0.001, 0.01, 1e-6, 0.02
SPACING = 2 ** (1 / 6) * SIGMA


def cluster_scene(n: int, *, cutoff: float | None, t_end: float, compiled: str = "auto",
                  seed: int = 3, method: str | None = None, dt: float | None = None) -> str:
    rng = np.random.default_rng(seed)
    side = math.ceil(n ** (1 / 3))
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    x = (grid - (side - 1) / 2) * SPACING + rng.normal(0, 0.02 * SPACING, (n, 3))
    v = rng.normal(0, SPEED / math.sqrt(3), (n, 3))
    v -= v.mean(axis=0)
    cut = f", cutoff {cutoff} m" if cutoff else ", all pairs"
    lines = [f"# a Lennard-Jones cluster of {n} beads{cut} (benchmarks/pairs.py)",
             "[scene]", f'name = "LJ cluster of {n}{cut}"', "",
             "[parameters]", f"eps = {EPSILON}", f"sig = {SIGMA}", ""]
    for i in range(n):
        lines += ["[[particles]]", f'name = "g{i}"', f"mass = {MASS}",
                  f"position = [{float(x[i, 0])!r}, {float(x[i, 1])!r}, {float(x[i, 2])!r}]",
                  f"velocity = [{float(v[i, 0])!r}, {float(v[i, 1])!r}, {float(v[i, 2])!r}]", ""]
    lines += ["[[effects]]", 'type = "pairwise"', 'expr = "4*eps*((sig/r)**12 - (sig/r)**6)"']
    if cutoff:
        lines.append(f"cutoff = {cutoff}")
    lines += ["", "[simulate]", f"t_end = {t_end}", "rtol = 1e-6", "atol = 1e-8", "samples = 2",
              f"compiled = {compiled}" if compiled != "auto" else "",
              f'method = "{method}"' if method else "", f"dt = {dt!r}" if dt else "",
              "", "[outputs]", "plots = []", ""]
    return "\n".join(lines)


def run_once(scene: Path, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "constrained.cli", "run", str(scene),
           "--out", str(out)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
    cpu = sum(float(re.search(rf"{k} time \(seconds\): ([\d.]+)", proc.stderr).group(1))
              for k in ("User", "System"))
    stats = _stats(out / "trajectory.npz")
    return dict(wall_s=wall, cpu_s=cpu, peak_rss_mb=rss_kb / 1024, **stats)


def _stats(path: Path) -> dict:
    sys.path.insert(0, str(ROOT))
    from constrained.run.trajectory import Trajectory

    stats = Trajectory.load(path).stats
    steps = int(stats.get("steps", 0))
    solver = float(stats.get("wall_time_s", float("nan")))
    return dict(steps=steps, rejected=int(stats.get("rejected", 0)), solver_s=solver,
                setup_s=float(stats.get("setup_time_s", float("nan"))), evaluation=stats.get("evaluation"),
                per_1000_steps_s=solver / steps * 1000 if steps else float("nan"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[1000])
    ap.add_argument("--cutoff", type=float, default=None, help="m (default: every pair)")
    ap.add_argument("--t-end", type=float, default=1.0)
    ap.add_argument("--compiled", default="auto", choices=["auto", "true", "false"])
    ap.add_argument("--method", help="[simulate] method (default: the default, dopri); e.g. rattle")
    ap.add_argument("--dt", type=float, help="[simulate] dt for a fixed-step method (rattle: e.g. 0.001 s)")
    ap.add_argument("--repeats", type=int, default=2, help="the first on a cold compile cache")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--write-only", type=Path, metavar="DIR")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.n:
            text = cluster_scene(n, cutoff=args.cutoff, t_end=args.t_end, compiled=args.compiled,
                                 method=args.method, dt=args.dt)
            if args.write_only:
                args.write_only.mkdir(parents=True, exist_ok=True)
                (args.write_only / f"cluster{n}.toml").write_text(text)
                continue
            scene = Path(tmp) / f"cluster{n}.toml"
            scene.write_text(text)
            os.environ["CONSTRAINED_CACHE"] = str(Path(tmp) / "cache")  # the first run compiles
            for k in range(args.repeats):
                row = dict(n=n, cache="cold" if k == 0 else "warm", **run_once(scene, Path(tmp) / f"out{n}"))
                rows.append(row)
                print(f"N = {n} ({row['cache']}): {row['wall_s']:.2f} s wall, {row['cpu_s']:.2f} s CPU, "
                      f"{row['peak_rss_mb']:.0f} MB, {row['steps']} steps", file=sys.stderr)
    if args.write_only:
        return 0
    what = f"cutoff {args.cutoff} m" if args.cutoff else "all pairs"
    how = f"{args.method} at dt {args.dt:g} s" if args.dt else f"{args.method or 'dopri'} at rtol 1e-6"
    print(f"Lennard-Jones cluster, {what}, t_end {args.t_end} s, {how}, compiled = {args.compiled}\n")
    print("| N | cache | whole run wall s | CPU s | peak RSS MB | steps (rejected) | solver s | setup s "
          "| solver s per 1,000 steps | evaluation |\n|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['n']:,} | {r['cache']} | {r['wall_s']:.2f} | {r['cpu_s']:.2f} | {r['peak_rss_mb']:.0f} "
              f"| {r['steps']} ({r['rejected']}) | {r['solver_s']:.2f} | {r['setup_s']:.2f} "
              f"| {r['per_1000_steps_s']:.2f} | {r['evaluation']} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
