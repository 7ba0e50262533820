"""What accuracy costs on a fine rope: dopri (explicit, DOP853) against rodas (linearly implicit,
RODAS), work against precision (issue 28, goal 2).

The rope (a physical discretization): N links of 1 cm, a 10 g bead at the end of each, hung
from the origin by its first link, released horizontal and at rest, in the plane z = 0,
gravity 9.81 m/s², no damping; T = 1 s. A taut fine rope carries transverse waves of
thousands of rad/s: dopri's steps are held near its stability limit (h·ρ ≈ 5) whatever the
tolerance, rodas's follow the accuracy asked (one sparse LU of the banded KKT matrix per step).

Error of a run: the largest distance between a bead's position at T and the reference's (m).
Reference: dopri at rtol = atol = 1e-11 (printed beside it: rodas at 1e-10, their difference).
Each (method, rtol) runs ``--repeats`` times in alternation on a built model (compiled step
loops warm), the median CPU and wall time of the ``simulate`` call kept; steps, rejected
steps, and time per step are reported. Measure on a quiet machine.

    python benchmarks/rope_work_precision.py                     # N = 1,000
    python benchmarks/rope_work_precision.py --n 200 1000 10000 --rtols 1e-3 1e-4 1e-6 --repeats 1
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

LINK, MASS, G, T_END = 0.01, 0.01, 9.81, 1.0


def rope(n: int):
    import constrained as C

    s = C.System(name=f"rope of {n} links of 1 cm")
    for i in range(n):
        s.add_particle(f"p{i}", MASS, [(i + 1) * LINK, 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=LINK))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=LINK))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -G, 0]))
    return s


def run(system, model, method: str, rtol: float):
    import constrained as C

    cpu, wall = time.process_time(), time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # dopri's stiffness warning: the point of the comparison
        tr = C.simulate(system, T_END, model=model, method=method, rtol=rtol, atol=rtol * 1e-2,
                        t_eval=[0.0, T_END], outputs=set())
    return (time.process_time() - cpu, time.perf_counter() - wall, tr.x[-1], int(tr.stats["steps"]),
            int(tr.stats.get("rejected", 0)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[1000])
    ap.add_argument("--rtols", type=float, nargs="+", default=[1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8])
    ap.add_argument("--methods", default="dopri,rodas")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    import constrained as C

    for n in args.n:
        system = rope(n)
        model = C.assemble(system)
        ref = run(system, model, "dopri", 1e-11)
        check = run(system, model, "rodas", 1e-10)
        apart = np.max(np.linalg.norm(check[2] - ref[2], axis=1))
        print(f"\n## {n} links of 1 cm, T = {T_END} s (reference: dopri at 1e-11, {ref[3]} steps; "
              f"rodas at 1e-10 differs from it by {apart:.1e} m)\n")
        settings = [(m, r) for m in args.methods.split(",") for r in args.rtols]
        for method, rtol in settings:
            run(system, model, method, rtol)  # warm: compiled loops, built functions
        results = {k: [] for k in settings}
        for _ in range(args.repeats):
            for k in settings:
                results[k].append(run(system, model, *k))
        print("| method | rtol | error (m) | CPU s | wall s | steps (rejected) | CPU ms per step |")
        print("|---|---|---|---|---|---|---|")
        for (method, rtol), runs in results.items():
            cpu, wall = statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)
            error = float(np.max(np.linalg.norm(runs[0][2] - ref[2], axis=1)))
            steps, rejected = runs[0][3], runs[0][4]
            print(f"| {method} | {rtol:g} | {error:.1e} | {cpu:.3f} | {wall:.3f} | {steps} ({rejected}) "
                  f"| {1e3 * cpu / max(steps + rejected, 1):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
