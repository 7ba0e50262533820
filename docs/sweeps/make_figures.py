"""Regenerate the figures of docs/sweeps.md (run from the repository root).

    PYTHONPATH=. python docs/sweeps/make_figures.py [--scheduler tcp://HOST:PORT]

1. kapitza_map.png: the 12 x 12 Kapitza stability sweep (scenarios/kapitza_sweep.toml) with
   the analytic boundary a^2 nu^2 = 2 g l; prints the agreement count and the timing.
2. double_pendulum_divergence.png: 16 starts of the double pendulum within 1e-9 m of each
   other (random design with --samples 16), distance from the first member against time.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from constrained.run.trajectory import Trajectory  # noqa: E402
from constrained.sweeps.sweep import cell_edges, sweep  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


def kapitza(scheduler, out: Path) -> None:
    started = time.perf_counter()
    r = sweep(ROOT / "scenarios/kapitza_sweep.toml",
              ["parameters.a=lin(0.002, 0.02, 12)", "parameters.nu=lin(20, 240, 12)"],
              summary=["min:up=y_bob - a*cos(nu*t)"], boundary="a**2*nu**2 - 2*g*l",
              scheduler=scheduler, out_dir=out / "kapitza", progress=True)
    wall = time.perf_counter() - started
    g, l = 9.81, 0.1
    A, N = r.specs[0].values, r.specs[1].values
    ea, en = cell_edges(A), cell_edges(N)
    up = r.column("up").reshape(len(A), len(N))
    crossed = disagree = 0
    for i, a in enumerate(A):
        for j, nu in enumerate(N):
            corners = [aa**2 * nn**2 - 2 * g * l for aa in ea[i:i + 2] for nn in en[j:j + 2]]
            if min(corners) < 0 < max(corners):
                crossed += 1
                disagree_here = (up[i, j] > 0) != (a * a * nu * nu > 2 * g * l)
                print(f"  boundary cell a={a:.4g} nu={nu:.4g}: {'stable' if up[i, j] > 0 else 'falls'}"
                      f"{' (differs from the threshold at the centre)' if disagree_here else ''}")
                continue
            disagree += (up[i, j] > 0) != (a * a * nu * nu > 2 * g * l)
    print(f"kapitza: {r.total} runs on {r.workers} workers in {wall:.1f} s; {crossed} cells crossed by the "
          f"boundary, {disagree} disagreements elsewhere")
    shutil.copyfile(r.out_dir / "sweep.png", HERE / "kapitza_map.png")


def double_pendulum(scheduler, out: Path) -> None:
    started = time.perf_counter()
    r = sweep(ROOT / "scenarios/double_pendulum.toml",
              ["particles.p2.position[0]=normal(1.5077695709, 5e-10)",
               "particles.p2.position[1]=normal(1.2172904521, 5e-10)"],
              samples=16, seed=1, save_trajectories=True, scheduler=scheduler,
              overrides=["simulate.t_end=20", "simulate.output_dt=0.01", "simulate.rtol=1e-12",
                         "simulate.atol=1e-12"],
              out_dir=out / "double_pendulum", progress=True, figure=False)
    wall = time.perf_counter() - started
    trajs = [Trajectory.load(r.out_dir / "runs" / f"{row['run_id']}.npz") for row in r.rows]
    t = trajs[0].t
    ref = trajs[0].x.reshape(len(t), -1)
    start_spread = max(np.linalg.norm(tr.x[0].ravel() - ref[0]) for tr in trajs[1:])
    fig, ax = plt.subplots(figsize=(6.4, 4.4), constrained_layout=True)
    d = np.array([np.linalg.norm(tr.x.reshape(len(t), -1) - ref, axis=1) for tr in trajs[1:]])
    for row in d:
        ax.semilogy(t, row, lw=0.7, alpha=0.6)
    med = np.median(d, axis=0)
    ax.semilogy(t, med, "k", lw=2, label="median of the 15 distances")
    k = (t > 1.0) & (med < 1e-2)
    lam = np.polyfit(t[k], np.log(med[k]), 1)[0]
    ax.semilogy(t[k], np.exp(np.polyval(np.polyfit(t[k], np.log(med[k]), 1), t[k])), "r--",
                label=f"fit: growth rate {lam:.2f} 1/s")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("|x_i(t) - x_0(t)| (m)")
    ax.set_title(f"double pendulum: 16 starts within {start_spread:.1g} m (rtol 1e-12)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(HERE / "double_pendulum_divergence.png", dpi=120)
    print(f"double pendulum: {r.total} runs on {r.workers} workers in {wall:.1f} s; start spread "
          f"{start_spread:.2g} m, growth rate {lam:.2f} 1/s, distance reaches 0.1 m at "
          f"t = {t[np.argmax(med > 0.1)]:.1f} s")


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--scheduler", default=None)
    p.add_argument("--out", default="out/docs_sweeps")
    args = p.parse_args()
    kapitza(args.scheduler, Path(args.out))
    double_pendulum(args.scheduler, Path(args.out))
