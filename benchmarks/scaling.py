"""Scaling in N: build time, simulation time and peak memory of the planar N-link chain.

Each (N, variant) runs in its own subprocess so that peak memory (``ru_maxrss``) is that
run's alone. Unit masses and links, start bent at 0.5 rad, 1 s, ``projection`` + DOP853.
The error is measured against a run at rtol 1e-12 for N ≤ ``--error-up-to``.

    python benchmarks/scaling.py [--n 8 16 32 64 128 256 512 1000] [--compiled auto|false]
        [--rtol 1e-6] [--repeats 3] [--out docs/performance]

Writes a markdown table to stdout (and ``scaling.md``) and a log-log figure ``scaling.png``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, resource, sys, time
sys.path.insert(0, {root!r})
import numpy as np
import constrained as C

def chain(n):
    s = C.System(name=f"{{n}}-link chain")
    for i in range(n):
        s.add_particle(f"p{{i}}", 1.0, [(i + 1) * np.sin(0.5), -(i + 1) * np.cos(0.5), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=1.0))
    for i in range(1, n):
        s.add(C.Distance(f"p{{i - 1}}", f"p{{i}}", length=1.0))
    s.add(C.Plane([f"p{{i}}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    return s

n, rtol, compiled, reference = {n}, {rtol}, {compiled!r}, {reference}
compiled = {{"true": True, "false": False}}.get(compiled, compiled)
t0 = time.perf_counter()
model = C.assemble(chain(n))
build = time.perf_counter() - t0
if compiled is not False:  # pay the one-time compilation outside the timed run
    C.simulate(chain(n), 1e-3, model=model, compiled=compiled, outputs=set())
t0 = time.perf_counter()
tr = C.simulate(chain(n), 1.0, model=model, rtol=rtol, atol=rtol * 1e-2, t_eval=[0.0, 1.0],
                outputs=set(), compiled=compiled)
total = time.perf_counter() - t0
err = None
if reference:
    ref = C.simulate(chain(n), 1.0, rtol=1e-12, atol=1e-14, t_eval=[0.0, 1.0], outputs=set(),
                     compiled=False)
    err = float(np.max(np.abs(ref.x[-1] - tr.x[-1])))
print(json.dumps(dict(n=n, build=build, run=tr.stats["wall_time_s"], total=total, err=err,
                      nfev=tr.stats["nfev"], steps=tr.stats["steps"], evaluation=tr.stats["evaluation"],
                      maxrss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)))
"""


def measure(n, rtol, compiled, reference) -> dict:
    code = CHILD.format(root=str(ROOT), n=n, rtol=rtol, compiled=compiled, reference=reference)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[8, 16, 32, 64, 128, 256, 512, 1000])
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--compiled", default="auto")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--error-up-to", type=int, default=64)
    parser.add_argument("--out", default=str(ROOT / "docs" / "performance"))
    parser.add_argument("--plot-only", action="store_true", help="redraw the figure from scaling.json")
    args = parser.parse_args()
    if args.plot_only:
        plot(json.loads((Path(args.out) / "scaling.json").read_text()), Path(args.out), args.rtol)
        return
    rows = []
    lines = ["| N | build [s] | simulation [s] | simulate() total [s] | steps | rhs | error vs rtol 1e-12 "
             "| peak RSS [MB] | evaluation |", "|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for n in args.n:
        runs = [measure(n, args.rtol, args.compiled, reference=(k == 0 and n <= args.error_up_to))
                for k in range(args.repeats)]
        med = {key: statistics.median(r[key] for r in runs) for key in ("build", "run", "total", "maxrss_mb")}
        err = runs[0]["err"]
        row = dict(runs[0], **med)
        rows.append(row)
        line = (f"| {n} | {med['build']:.3f} | {med['run']:.3f} | {med['total']:.3f} | {row['steps']} | "
                f"{row['nfev']} | {'—' if err is None else f'{err:.1e}'} | {med['maxrss_mb']:.0f} | "
                f"{row['evaluation']} |")
        lines.append(line)
        print(line, flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scaling.md").write_text("\n".join(lines) + "\n")
    (out / "scaling.json").write_text(json.dumps(rows, indent=1))
    plot(rows, out, args.rtol)


def plot(rows, out: Path, rtol: float) -> None:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib not installed: no figure")
        return
    ns = [r["n"] for r in rows]
    fig = Figure(figsize=(9, 4))
    ax1, ax2 = fig.subplots(1, 2)
    ax1.loglog(ns, [r["build"] for r in rows], "o-", label="model build")
    ax1.loglog(ns, [r["run"] for r in rows], "s-", label=f"simulation (1 s, rtol {rtol:g})")
    ax1.loglog(ns, [rows[-1]["run"] * n / ns[-1] for n in ns], "k:", label="∝ N")
    ax1.set_xlabel("N (links)")
    ax1.set_ylabel("wall time [s]")
    ax1.legend()
    ax1.grid(True, which="both", alpha=0.3)
    ax2.loglog(ns, [r["maxrss_mb"] for r in rows], "o-", label="peak RSS of the process")
    ax2.set_xlabel("N (links)")
    ax2.set_ylabel("memory [MB]")
    ax2.legend()
    ax2.grid(True, which="both", alpha=0.3)
    fig.suptitle("planar N-link chain, projection + DOP853")
    fig.tight_layout()
    fig.savefig(out / "scaling.png", dpi=110)
    print(f"wrote {out / 'scaling.png'}")


if __name__ == "__main__":
    main()
