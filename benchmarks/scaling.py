"""Scaling in N: build time, simulation time and peak memory of the planar N-link chain.

Each (N, method) runs in its own subprocess so that peak memory (``ru_maxrss``) is that
run's alone; "model memory" is that peak minus the process's peak right after the imports.
Unit masses and links, start bent at 0.5 rad, 1 s. Methods are ``constrained`` method names,
``a:b`` meaning method a with base b (``projection`` = SciPy-stepped DOP853, ``dopri`` =
the CasADi-stepped DOP853). The error is measured against a run at rtol 1e-12 for
N ≤ ``--error-up-to``. One-time costs (compilation) are paid by a warm-up run and reported
as "setup".

    python benchmarks/scaling.py [--n 8 16 32 64 128 256 512 1000] [--methods dopri projection]
        [--compiled auto|false|true] [--rtol 1e-6] [--repeats 3] [--out docs/performance]

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
sys.path.insert(0, {root!r} + "/benchmarks")
import numpy as np
import constrained as C
from peers import chain  # the planar N-link chain every benchmark uses
baseline_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

n, rtol, compiled, reference, method = {n}, {rtol}, {compiled!r}, {reference}, {method!r}
compiled = {{"true": True, "false": False}}.get(compiled, compiled)
method, _, base = method.partition(":")
extra = {{"base": base}} if base else {{}}
t0 = time.perf_counter()
model = C.assemble(chain(n))
build = time.perf_counter() - t0
t0 = time.perf_counter()  # warm-up: pays one-time costs (compilation, the step loop's graph)
C.simulate(chain(n), 1e-3, model=model, method=method, compiled=compiled, outputs=set(), **extra)
setup = time.perf_counter() - t0
t0 = time.perf_counter()
tr = C.simulate(chain(n), 1.0, model=model, method=method, rtol=rtol, atol=rtol * 1e-2,
                t_eval=[0.0, 1.0], outputs=set(), compiled=compiled, **extra)
total = time.perf_counter() - t0
err = None
if reference:
    ref = C.simulate(chain(n), 1.0, rtol=1e-12, atol=1e-14, t_eval=[0.0, 1.0], outputs=set(),
                     compiled=False)
    err = float(np.max(np.abs(ref.x[-1] - tr.x[-1])))
peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(dict(n=n, method={method!r}, build=build, setup=setup, run=tr.stats["wall_time_s"],
                      total=total, err=err, nfev=tr.stats["nfev"], steps=tr.stats["steps"],
                      evaluation=tr.stats["evaluation"], maxrss_mb=peak_mb,
                      model_mb=peak_mb - baseline_mb)))
"""


def measure(n, rtol, compiled, reference, method="projection") -> dict:
    code = CHILD.format(root=str(ROOT), n=n, rtol=rtol, compiled=compiled, reference=reference,
                        method=method)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[8, 16, 32, 64, 128, 256, 512, 1000])
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--compiled", default="auto")
    parser.add_argument("--methods", nargs="+", default=["dopri", "projection"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--error-up-to", type=int, default=64)
    parser.add_argument("--out", default=str(ROOT / "docs" / "performance"))
    parser.add_argument("--plot-only", action="store_true", help="redraw the figure from scaling.json")
    args = parser.parse_args()
    if args.plot_only:
        plot(json.loads((Path(args.out) / "scaling.json").read_text()), Path(args.out), args.rtol)
        return
    rows = []
    lines = ["| method | N | build [s] | setup [s] | simulation [s] | simulate() total [s] | steps | rhs "
             "| error vs rtol 1e-12 | peak RSS [MB] | model memory [MB] | evaluation |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for n in args.n:
        for method in args.methods:  # methods alternate at each N
            runs = [measure(n, args.rtol, args.compiled, reference=(k == 0 and n <= args.error_up_to),
                            method=method) for k in range(args.repeats)]
            keys = ("build", "setup", "run", "total", "maxrss_mb", "model_mb")
            med = {key: statistics.median(r[key] for r in runs) for key in keys}
            err = runs[0]["err"]
            row = dict(runs[0], **med)
            rows.append(row)
            line = (f"| {method} | {n} | {med['build']:.3f} | {med['setup']:.3f} | {med['run']:.3f} | "
                    f"{med['total']:.3f} | {row['steps']} | {row['nfev']} | "
                    f"{'—' if err is None else f'{err:.1e}'} | {med['maxrss_mb']:.0f} | "
                    f"{med['model_mb']:.0f} | {row['evaluation']} |")
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
    fig = Figure(figsize=(10, 4))
    ax1, ax2 = fig.subplots(1, 2)
    methods = list(dict.fromkeys(r.get("method", "projection") for r in rows))
    for k, method in enumerate(methods):
        mine = [r for r in rows if r.get("method", "projection") == method]
        ns = [r["n"] for r in mine]
        ax1.loglog(ns, [r["run"] for r in mine], "s-", color=f"C{k}",
                   label=f"{method}: simulation (1 s, rtol {rtol:g})")
        if k == 0:
            ax1.loglog(ns, [r["build"] for r in mine], "o--", color="gray", label="model build")
            ax1.loglog(ns, [mine[-1]["run"] * n / ns[-1] for n in ns], "k:", label="∝ N")
        ax2.loglog(ns, [max(r.get("model_mb", r["maxrss_mb"]), 0.1) for r in mine], "s-", color=f"C{k}",
                   label=f"{method}: peak RSS above the imports")
        if k == 0 and mine[-1].get("model_mb", 0) > 0:
            ax2.loglog(ns, [mine[-1]["model_mb"] * n / ns[-1] for n in ns], "k:", label="∝ N")
    ax1.set_xlabel("N (links)")
    ax1.set_ylabel("wall time [s]")
    ax1.legend(fontsize=8)
    ax1.grid(True, which="both", alpha=0.3)
    ax2.set_xlabel("N (links)")
    ax2.set_ylabel("memory [MB]")
    ax2.legend(fontsize=8)
    ax2.grid(True, which="both", alpha=0.3)
    fig.suptitle("planar N-link chain, Cartesian coordinates with multipliers")
    fig.tight_layout()
    fig.savefig(out / "scaling.png", dpi=110)
    print(f"wrote {out / 'scaling.png'}")


if __name__ == "__main__":
    main()
