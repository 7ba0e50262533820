"""Ensembles: variants per second, side by side in one process (issue 17).

    python benchmarks/ensemble.py [--n 1000 10000] [--out docs/performance/ensemble]

The planar double pendulum of ``scenarios/double_pendulum_parametric.toml`` to t = 2 s, with
masses, lengths and start angles drawn at random per variant (m ∈ [0.5, 2] kg, l ∈ [0.5,
1.5] m, θ ∈ [1.5, 2.5] rad, at rest). Target: every variant's end position within 1e-6 m of
a reference (``simulate_many`` at rtol 1e-12 on the first 200 variants). Runners:

- ``simulate_many`` (dopri DOP853 mapped over the variants, compiled, rtol 5e-8);
- ``simulate`` in a Python loop (one call per variant, the Model passed back in with the
  variant's parameters: nothing is rebuilt);
- Exudyn's kinematic tree + DOPRI5 in a Python loop (built and solved per variant);
- hand-written CasADi loops on the angle ODE, folded and mapped over the variants, compiled:
  classical RK4 with fixed steps (the fewest that meet 1e-6), and the ideal the issue names —
  DOPRI5 with each variant's own adaptive step and error control (SciPy's controller), 64
  attempts a call, called until every variant is done, at the loosest rtol that meets 1e-6.

Each timing includes everything after the first (warm-up) call: starts, steps, outputs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import constrained as C  # noqa: E402
from constrained.codegen import compiled as compiled_evaluation  # noqa: E402

SCENE = ROOT / "scenarios" / "double_pendulum_parametric.toml"
T_END, TARGET, G = 2.0, 1e-6, 9.81


def draw(n: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"m1": rng.uniform(0.5, 2, n), "m2": rng.uniform(0.5, 2, n), "l1": rng.uniform(0.5, 1.5, n),
            "l2": rng.uniform(0.5, 1.5, n), "th1": rng.uniform(1.5, 2.5, n), "th2": rng.uniform(1.5, 2.5, n)}


def end_positions(th1, th2, l1, l2) -> np.ndarray:
    """(n, 2, 2) bob positions from absolute angles (from the downward vertical)."""
    p1 = np.stack([l1 * np.sin(th1), -l1 * np.cos(th1)], axis=-1)
    return np.stack([p1, p1 + np.stack([l2 * np.sin(th2), -l2 * np.cos(th2)], axis=-1)], axis=1)


def _angle_ode():
    y, p = ca.SX.sym("y", 4), ca.SX.sym("p", 4)
    th1, th2, w1, w2 = ca.vertsplit(y)
    m1, m2, l1, l2 = ca.vertsplit(p)
    d = th1 - th2
    den = 2 * m1 + m2 - m2 * ca.cos(2 * d)
    a1 = (-G * (2 * m1 + m2) * ca.sin(th1) - m2 * G * ca.sin(th1 - 2 * th2)
          - 2 * ca.sin(d) * m2 * (w2**2 * l2 + w1**2 * l1 * ca.cos(d))) / (l1 * den)
    a2 = (2 * ca.sin(d) * (w1**2 * l1 * (m1 + m2) + G * (m1 + m2) * ca.cos(th1)
                           + w2**2 * l2 * m2 * ca.cos(d)) / (l2 * den))
    return ca.Function("f", [y, p], [ca.vertcat(w1, w2, a1, a2)])


def hand_mapped_rk4(steps: int, n: int):
    """y = (θ1, θ2, ω1, ω2), p = (m1, m2, l1, l2), RK4 with fixed steps folded ``steps``
    times, mapped over n variants, compiled."""
    f = _angle_ode()
    y, p = ca.SX.sym("y", 4), ca.SX.sym("p", 4)
    h = T_END / steps
    k1 = f(y, p)
    k2 = f(y + h / 2 * k1, p)
    k3 = f(y + h / 2 * k2, p)
    k4 = f(y + h * k3, p)
    step = ca.Function("rk4", [y, p], [y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    Y, Pm = ca.MX.sym("y", 4), ca.MX.sym("p", 4)
    folded = ca.Function("run", [Y, Pm], [step.fold(steps)(Y, ca.repmat(Pm, 1, steps))])
    return compiled_evaluation.compile_function(folded.map(n))


class HandMappedDopri5:
    """The issue's ideal: per column s = (θ1, θ2, ω1, ω2, t, h), p = (m1, m2, l1, l2); one
    DOPRI5 attempt (SciPy's RK45 tableau, error norm and step controller) skipped once t =
    T_END, folded ``attempts`` times, mapped over n columns, compiled; called until done."""

    def __init__(self, rtol: float, n: int, attempts: int = 64, first_step: float = 1e-3):
        from scipy.integrate import RK45

        f = _angle_ode()
        S, p = ca.SX.sym("s", 6), ca.SX.sym("p", 4)
        y, t = S[:4], S[4]
        h = ca.fmin(S[5], T_END - t)
        K = []
        for i in range(6):
            K.append(f(y + h * sum((RK45.A[i][j] * K[j] for j in range(i)), ca.SX.zeros(4)), p))
        y_new = y + h * sum(RK45.B[j] * K[j] for j in range(6))
        K.append(f(y_new, p))
        err = h * sum(RK45.E[j] * K[j] for j in range(7))
        scale = rtol * 1e-2 + rtol * ca.fmax(ca.fabs(y), ca.fabs(y_new))
        norm = ca.sqrt(ca.sumsqr(err / scale) / 4)
        factor = ca.fmin(10, ca.fmax(0.2, 0.9 * norm ** (-0.2)))
        new = ca.if_else(norm < 1, ca.vertcat(y_new, t + h, h * factor), ca.vertcat(y, t, h * factor))
        step = ca.Function("attempt", [S, p], [ca.if_else(t >= T_END, S, new)])
        Sm, Pm = ca.MX.sym("s", 6), ca.MX.sym("p", 4)
        folded = ca.Function("attempts", [Sm, Pm], [step.fold(attempts)(Sm, ca.repmat(Pm, 1, attempts))])
        self.call = compiled_evaluation.compile_function(folded.map(n))
        self.n, self.first_step = n, first_step

    def __call__(self, th1, th2, pm) -> np.ndarray:
        s = np.stack([th1, th2, np.zeros(self.n), np.zeros(self.n), np.zeros(self.n),
                      np.full(self.n, self.first_step)])
        while np.min(s[4]) < T_END:
            s = np.asarray(self.call(s, pm), float)
        return s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--loop-n", type=int, default=300, help="variants for the per-variant loops")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    scene = C.load_scene(SCENE)
    model = C.assemble(scene.system)
    rows = []

    def reference(table) -> np.ndarray:
        """End positions (k, 2, 2) of the table's first 200 variants at rtol 1e-12."""
        first = {k: v[:200] for k, v in table.items()}
        run = C.simulate_many(scene.system, T_END, first, rtol=1e-12, atol=1e-14, model=model)
        return run.x[:, -1, :, :2]

    def error_of(x, ref_x):
        return float(np.max(np.abs(x[:len(ref_x)] - ref_x)))

    # the ideal's step count: the fewest (of a doubling ladder) that meet the target
    probe = {k: v[:200] for k, v in draw(200, seed=1).items()}
    probe_ref = reference(probe)
    steps = 250
    while True:
        ideal = hand_mapped_rk4(steps, 200)
        y0 = np.stack([probe["th1"], probe["th2"], np.zeros(200), np.zeros(200)])
        out = np.asarray(ideal(y0, np.stack([probe["m1"], probe["m2"], probe["l1"], probe["l2"]])), float)
        ideal_error = error_of(end_positions(out[0], out[1], probe["l1"], probe["l2"]), probe_ref)
        if ideal_error <= TARGET or steps > 64000:
            break
        steps *= 2
    pm_probe = np.stack([probe["m1"], probe["m2"], probe["l1"], probe["l2"]])
    for dopri5_rtol in (1e-7, 3e-8, 1e-8, 3e-9, 1e-9, 1e-10):
        s = HandMappedDopri5(dopri5_rtol, 200)(probe["th1"], probe["th2"], pm_probe)
        if error_of(end_positions(s[0], s[1], probe["l1"], probe["l2"]), probe_ref) <= TARGET:
            break
    for n in args.n:
        table = draw(n)
        ref_x = reference(table)
        # simulate_many
        C.simulate_many(scene.system, T_END, table, rtol=5e-8, atol=5e-10, model=model, threads=1)
        started = time.perf_counter()
        ens = C.simulate_many(scene.system, T_END, table, rtol=5e-8, atol=5e-10, model=model, threads=1)
        wall = time.perf_counter() - started
        rows.append({"runner": "constrained simulate_many (dopri, compiled, threads=1)", "variants": n,
                     "per_s": n / wall, "error": error_of(ens.x[:, -1, :, :2], ref_x),
                     "failed": int((~ens.ok).sum())})
        # the hand-mapped ideal
        ideal = hand_mapped_rk4(steps, n)
        y0 = np.stack([table["th1"], table["th2"], np.zeros(n), np.zeros(n)])
        pm = np.stack([table["m1"], table["m2"], table["l1"], table["l2"]])
        ideal(y0, pm)
        started = time.perf_counter()
        out = np.asarray(ideal(y0, pm), float)
        wall = time.perf_counter() - started
        x = end_positions(out[0], out[1], table["l1"], table["l2"])
        rows.append({"runner": f"hand-mapped CasADi RK4, {steps} fixed steps, compiled", "variants": n,
                     "per_s": n / wall, "error": error_of(x, ref_x), "failed": 0})
        # the ideal: hand-mapped adaptive DOPRI5
        ideal = HandMappedDopri5(dopri5_rtol, n)
        ideal(table["th1"], table["th2"], pm)
        started = time.perf_counter()
        s = ideal(table["th1"], table["th2"], pm)
        wall = time.perf_counter() - started
        x = end_positions(s[0], s[1], table["l1"], table["l2"])
        rows.append({"runner": f"hand-mapped CasADi DOPRI5, adaptive, rtol {dopri5_rtol:g}, compiled (ideal)",
                     "variants": n, "per_s": n / wall, "error": error_of(x, ref_x), "failed": 0})
        # simulate_many as called by default: threads for the cores of this machine
        kw2 = dict(rtol=5e-8, atol=5e-10, model=model)
        C.simulate_many(scene.system, T_END, table, **kw2)
        started = time.perf_counter()
        ens = C.simulate_many(scene.system, T_END, table, **kw2)
        wall = time.perf_counter() - started
        rows.append({"runner": f"constrained simulate_many (dopri, compiled, default: "
                               f"threads={ens.stats['threads']})", "variants": n,
                     "per_s": n / wall, "error": error_of(ens.x[:, -1, :, :2], ref_x),
                     "failed": int((~ens.ok).sum())})
    # the loops, on fewer variants
    n = args.loop_n
    table = draw(n)
    ref_x = reference(table)
    kw = dict(rtol=5e-8, atol=5e-10, t_eval=[0.0, T_END], outputs=set(), model=model)
    C.simulate(scene.system, T_END, **kw)
    started = time.perf_counter()
    xs = []
    for k in range(n):
        values = {name: float(v[k]) for name, v in table.items()}
        tr = C.simulate(scene.system, T_END, parameters=values, **kw)
        xs.append(tr.x[-1][:, :2])
    wall = time.perf_counter() - started
    rows.append({"runner": "constrained simulate, Python loop", "variants": n, "per_s": n / wall,
                 "error": error_of(np.array(xs), ref_x), "failed": 0})
    try:
        sys.path.insert(0, str(ROOT / "benchmarks"))
        import peers
        from fresh_call import exudyn_call  # the kinematic tree with a mass and a length

        def exudyn_variant(k):
            problem = peers.Problem("double", 2, (float(table["th1"][k]), float(table["th2"][k])), (0.0, 0.0),
                                    T_END, TARGET)
            return exudyn_call(problem, 1e-7, float(table["m1"][k]), float(table["l2"][k]))

        exudyn_variant(0)
        started = time.perf_counter()
        for k in range(n):
            exudyn_variant(k)
        wall = time.perf_counter() - started
        rows.append({"runner": "Exudyn tree + DOPRI5, Python loop (m1, l2, angles vary; m2 = l1 = 1)",
                     "variants": n, "per_s": n / wall, "error": None, "failed": 0})
    except ImportError:
        pass
    ideal_rate = {r["variants"]: r["per_s"] for r in rows if "(ideal)" in r["runner"]}
    lines = ["| runner | variants | variants/s | vs the ideal | max end error (first 200) |",
             "|---|---|---|---|---|"]
    for r in rows:
        base = ideal_rate.get(r["variants"]) or max(ideal_rate.values())
        err = "—" if r["error"] is None else f"{r['error']:.1e}"
        lines.append(f"| {r['runner']} | {r['variants']} | {r['per_s']:.0f} | {r['per_s'] / base:.2f}× "
                     f"| {err} |")
    table_md = "\n".join(lines)
    print(table_md)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "ensemble.md").write_text(table_md + "\n")
        (args.out / "ensemble.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
