"""Compiled evaluation against CasADi's virtual machine, measured side by side.

Runs each case alternately in both modes (``repeats`` times each, after one warm-up run
that also pays the one-time compilation), and prints a markdown table of median wall
times and their ratio, plus the one-time compile cost measured with an empty cache.

    python benchmarks/compiled_vs_vm.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from peers import chain  # noqa: E402  (the planar N-link chain every benchmark uses)

import constrained as C  # noqa: E402


def double_pendulum() -> C.System:
    s = C.System(name="double pendulum")
    s.add_particle("p1", 1.0, [np.sin(2.0), -np.cos(2.0), 0.0])
    s.add_particle("p2", 1.0, [np.sin(2.0) + np.sin(2.5), -np.cos(2.0) - np.cos(2.5), 0.0])
    s.add(C.Distance("p1", point=[0, 0, 0], length=1.0), C.Distance("p1", "p2", length=1.0),
          C.Plane(["p1", "p2"], [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    return s


CASES = [
    ("rattle, double pendulum, 100 s, dt 1e-3", double_pendulum, 100.0, dict(method="rattle", dt=1e-3)),
    ("rattle, 20-link chain, 2 s, dt 1e-3", lambda: chain(20), 2.0, dict(method="rattle", dt=1e-3)),
    ("projection, 40-link chain, 1 s, rtol 1e-8", lambda: chain(40), 1.0, dict(rtol=1e-8, atol=1e-10)),
    ("dopri, double pendulum, 2 s, rtol 1e-10", double_pendulum, 2.0,
     dict(method="dopri", rtol=1e-10, atol=1e-12)),
    ("dopri, 256-link chain, 1 s, rtol 1e-6", lambda: chain(256), 1.0,
     dict(method="dopri", rtol=1e-6, atol=1e-8)),
]


def run(system, t_end, settings, compiled):
    tr = C.simulate(system, t_end, compiled=compiled, t_eval=[0.0, t_end], outputs=set(), **settings)
    return tr.stats["wall_time_s"], tr.x[-1], tr.stats.get("evaluation")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print("| case | virtual machine [s] | compiled [s] | speed-up | max difference | one-time compile [s] |")
    print("|---|---|---|---|---|---|")
    for label, make, t_end, settings in CASES:
        with tempfile.TemporaryDirectory() as cache:
            os.environ["CONSTRAINED_CACHE"] = cache
            start = time.perf_counter()
            run(make(), t_end, settings, True)  # warm-up, pays the compilation
            first = time.perf_counter() - start
            vm_times, c_times = [], []
            for _ in range(args.repeats):  # alternate, so drifts in machine load hit both
                t_vm, x_vm, _ = run(make(), t_end, settings, False)
                t_c, x_c, how = run(make(), t_end, settings, True)
                vm_times.append(t_vm)
                c_times.append(t_c)
            assert how == "compiled", how
            vm, cm = statistics.median(vm_times), statistics.median(c_times)
            compile_cost = max(first - cm, 0.0)
            print(f"| {label} | {vm:.3f} | {cm:.3f} | {vm / cm:.2f}× | "
                  f"{np.max(np.abs(x_vm - x_c)):.1e} | {compile_cost:.2f} |")


if __name__ == "__main__":
    main()
