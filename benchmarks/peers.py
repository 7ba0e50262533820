"""constrained against peers on the planar N-link chain, side by side in one run, alternating.

Peers: a hand-vectorized NumPy baseline written here (angles θ_i, unit masses and links,
M(θ) θ'' = −C(θ) θ'² − g c sin θ solved densely, SciPy DOP853). Other peers (sympy's
LagrangesMethod, pydy, exudyn, mujoco) are reported as skipped when not installed, and are
not implemented here yet (issue 9). The error is the largest end-position difference
against a constrained run at rtol 1e-12.

    python benchmarks/peers.py [--n 8 32 128 256] [--repeats 5]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import constrained as C  # noqa: E402

G, BEND, T_END = 9.81, 0.5, 1.0


def chain(n: int) -> C.System:
    s = C.System(name=f"{n}-link chain")
    for i in range(n):
        s.add_particle(f"p{i}", 1.0, [(i + 1) * np.sin(BEND), -(i + 1) * np.cos(BEND), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=1.0))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=1.0))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -G, 0]))
    return s


def numpy_chain(n: int, rtol: float):
    """Angles from the vertical; c_ij = n − max(i, j) particles hang below both links."""
    idx = np.arange(n)
    c = n - np.maximum.outer(idx, idx)
    ci = n - idx

    def rhs(t, y):
        th, w = y[:n], y[n:]
        d = th[:, None] - th[None, :]
        M = c * np.cos(d)
        b = -(c * np.sin(d)) @ (w * w) - G * ci * np.sin(th)
        return np.concatenate([w, np.linalg.solve(M, b)])

    y0 = np.concatenate([np.full(n, BEND), np.zeros(n)])
    start = time.perf_counter()
    sol = solve_ivp(rhs, (0.0, T_END), y0, method="DOP853", rtol=rtol, atol=rtol * 1e-2, t_eval=[T_END])
    wall = time.perf_counter() - start
    th = sol.y[:n, -1]
    pos = np.stack([np.cumsum(np.sin(th)), -np.cumsum(np.cos(th)), np.zeros(n)], axis=1)
    return wall, pos.ravel()


def constrained_chain(n: int, rtol: float, model):
    tr = C.simulate(chain(n), T_END, model=model, rtol=rtol, atol=rtol * 1e-2, t_eval=[0.0, T_END],
                    outputs=set())
    return tr.stats["wall_time_s"], tr.x[-1].ravel()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[8, 32, 128, 256])
    parser.add_argument("--rtols", type=float, nargs="+", default=[1e-6, 1e-8])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    for name in ("sympy", "pydy", "exudyn", "mujoco"):
        found = importlib.util.find_spec(name) is not None
        why = "installed, but not implemented in this script yet" if found else "not installed"
        print(f"peer {name}: {why} — skipped")
    print("\n| N | rtol | peer | median wall [s] | error [m] | ratio to fastest |")
    print("|---|---|---|---|---|---|")
    for n in args.n:
        model = C.assemble(chain(n))
        ref = C.simulate(chain(n), T_END, rtol=1e-12, atol=1e-14, t_eval=[0.0, T_END], outputs=set(),
                         compiled=False).x[-1].ravel()
        constrained_chain(n, 1e-3, model)  # warm-up, pays any one-time compilation
        for rtol in args.rtols:
            times = {"constrained projection+DOP853": [], "NumPy angles+DOP853": []}
            errs = {}
            for _ in range(args.repeats):  # alternate so that load drifts hit both
                for label in times:
                    if label.startswith("constrained"):
                        wall, pos = constrained_chain(n, rtol, model)
                    else:
                        wall, pos = numpy_chain(n, rtol)
                    times[label].append(wall)
                    errs[label] = float(np.max(np.abs(pos - ref)))
            med = {k: statistics.median(v) for k, v in times.items()}
            best = min(med.values())
            for label, m in med.items():
                print(f"| {n} | {rtol:g} | {label} | {m:.4f} | {errs[label]:.1e} | {m / best:.2f}× |",
                      flush=True)


if __name__ == "__main__":
    main()
