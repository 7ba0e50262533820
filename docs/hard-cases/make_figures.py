"""Figures of docs/hard-cases.md: constraint residual and energy over time for each hard scene
(plus the conditioning of J M⁻¹ Jᵀ for the singular-configuration cases).

    PYTHONPATH=. python docs/hard-cases/make_figures.py
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import constrained as C
from constrained.manifold import diagnostics
from constrained.output.plot import driving_terms

ROOT = Path(__file__).resolve().parents[2]
HARD = ROOT / "scenarios" / "hard"
OUT = Path(__file__).resolve().parent

#: scene -> (t_end, extra simulate keywords)
CASES = {
    "redundant_cube": (2.0, {}),
    "redundant_plane_triangle": (3.0, {}),
    "redundant_closed_chain": (3.0, {}),
    "fourbar_toggle": (2.0, {}),
    "fourbar_limit": (3.0, {}),
    "slider_crank_dead_centre": (5.0, {}),
    "stretched_chain": (1.5, {}),
    "stiff_axle": (1.0, {}),
    "double_pendulum_1000s": (1000.0, {"t_eval": np.linspace(0, 1000, 2001)}),
    "kapitza_threshold": (1.5, {}),
    "bead_hoop_damped": (40.0, {}),
    "extreme_mass_ratio": (3.0, {}),
    "blowup_attractive": (2.0, {}),
}
CONDITIONING = ("fourbar_toggle", "fourbar_limit", "slider_crank_dead_centre", "stretched_chain")


def simulate(name, t_end, extra):
    sc = C.load_scene(HARD / f"{name}.toml")
    s = sc.settings
    kw = {"rtol": s["rtol"], "atol": s["atol"], "base": s["base"], **extra}
    kw.setdefault("t_eval", np.arange(0.0, t_end + 1e-9, s["output_dt"] or t_end / 400))
    note = ""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tr = C.simulate(sc.system, t_end, **kw)
    except C.SimulationError as exc:
        tr, note = exc.trajectory, "stopped: " + str(exc).split(";")[0]
    return sc, tr, note


def figure(name, sc, tr, note):
    cond = name in CONDITIONING
    fig = Figure(figsize=(7.5, 6.6 if cond else 4.6))
    FigureCanvasAgg(fig)
    axes = fig.subplots(3 if cond else 2, 1, sharex=True)
    zeros = int(np.count_nonzero(tr.constraint_residual == 0))
    res = np.maximum(tr.constraint_residual, 1e-17)
    axes[0].semilogy(tr.t, res, lw=0.8)
    axes[0].set_ylabel("max |f| (m)")
    if zeros:
        plural = "s" if zeros > 1 else ""
        axes[0].set_title(f"constraint residual ({zeros} exact zero{plural} drawn at 1e-17)", fontsize=8)
    e = tr.energy
    axes[1].plot(tr.t, e - e[0], lw=0.8)
    axes[1].set_ylabel("E − E(0) (J)")
    driven = driving_terms(tr)
    axes[1].set_title("energy: changed by physics here (" + " and ".join(driven) + "), not a drift"
                      if driven else "energy drift (E is conserved by this scene)", fontsize=8)
    if cond:
        c = diagnostics.conditioning(C.assemble(sc.system), tr)
        axes[2].semilogy(c.t, c.cond, lw=0.8, label="cond(J M⁻¹ Jᵀ)")
        axes[2].semilogy(c.t, 1 / np.maximum(c.sigma_min, 1e-300), lw=0.8,
                         label="1 / σ_min(J row-normalized)")
        axes[2].legend(fontsize=7)
        axes[2].set_ylabel("conditioning")
    axes[-1].set_xlabel("t (s)")
    fig.suptitle(f"{sc.name}" + (f"\n{note}" if note else ""), fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / f"{name}.png", dpi=90)


def main():
    for name, (t_end, extra) in CASES.items():
        sc, tr, note = simulate(name, t_end, extra)
        figure(name, sc, tr, note)
        print(name, len(tr.t), note)


if __name__ == "__main__":
    main()
