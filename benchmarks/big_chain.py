"""Issues 16 and 28: ``constrained run`` of a large model as a whole command, on physical
discretizations, with the per-step cost against this machine's floor measured in the same run.

Scenes (written by this script as TOML, released at rest, default method ``dopri``, no
figures: ``plots = []``; the default quantities — multipliers, constraint forces, energy,
constraint residual — on the default output grid, every accepted step):

- ``--n N`` (default): the rope of issue 28, N particles of ``--mass`` kg (default 0.01 kg) on
  rods of ``--link`` m (default 0.01 m: 1 cm) released horizontal at (i + 1)·link along x:
  the first on a rod to the fixed point (0, 0, 0), each next on a rod to the one before; all
  in the plane z = 0 (one ``plane`` constraint); gravity (0, −9.81, 0); 1 s at rtol = atol =
  1e-6. A taut fine rope is stiff (its transverse waves): dopri's steps are set by stability,
  and the run says so (StiffnessWarning). ``--link 1 --mass 1 --atol 1e-8`` is the old,
  favourable chain of issue 16 (1 m links, 1 kg: a 10 km chain that barely moves in 1 s).
- ``--cloth K``: a K × K cloth of 1 cm squares (rods on the grid's edges, shear springs of
  0.5 N/m on both diagonals of each square), 1.5e-5 kg per particle (a 150 g/m² cotton), lying
  flat in z = 0 and pinned at two diagonally opposite corners, gravity (0, 0, −9.81) across
  it; 0.5 s at rtol = atol = 1e-6. (Two corners of one edge are refused on purpose: that edge
  is a taut straight chain, docs/hard-cases.md.)

Each run is one subprocess ``/usr/bin/time -v python -m constrained.cli run SCENE --out DIR``:
its wall time is everything a user waits for (interpreter start, imports, reading and checking
the scene, assembly, the start, the run, post-processing, trajectory.npz, the printed report)
and its peak memory is ``Maximum resident set size`` of that process; the minimum over
``--repeats`` is reported (the machine is shared).

``--breakdown`` runs the same steps once more in one instrumented process (BREAKDOWN below):
the wall and CPU time and the peak RSS after each stage, and the machine's floor measured in
that process at the model's sizes — a daxpy y += a·x over the 3N coordinates, SciPy's CSR
product J y (J: C × 3N) and A λ (A = J M⁻¹ Jᵀ: C × C), the fastest of many repeats in CPU time
— against which dopri's CPU time per attempted step is put:

    floor per step = 14 (4 t(J y) + 3 t(A λ) + 5 t(axpy)) + 2 K t(axpy)

14 KKT solves per DOP853 step (11 stages, the first-same-as-last acceleration, two projection
solves), each at least evaluating J and γ, forming A, factorizing it, solving with it, J M⁻¹F
and Jᵀλ (each one pass over J or A) and five vector updates; K the nonzero coefficients of the
tableau's stage sums and error estimates, each an update of x and of v. It is a streaming
bound (every pass touches its matrix once, at SciPy's speed), not a flop count.

    python benchmarks/big_chain.py [--n 100 1000 10000] [--cloth 100] [--repeats 2] [--quiet]
        [--breakdown] [--samples K] [--json FILE] [--write-only DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Cloth: 1 cm squares, a 150 g/m² cotton (1.5e-5 kg per particle), shear springs of 0.5 N/m on
#: both diagonals of every square (a cotton's in-plane shear stiffness, about 1 N/m; without them
#: the rods alone are a mechanism whose free corners fold flat into a dead-centre configuration:
#: the 100 × 100 cloth reached one at t = 0.245 s).
CLOTH_LINK, CLOTH_MASS, CLOTH_SHEAR = 0.01, 1.5e-5, 0.5


def chain_scene(n: int, *, t_end: float = 1.0, rtol: float = 1e-6, atol: float = 1e-6,
                samples: int | None = None, link: float = 0.01, mass: float = 0.01) -> str:
    """The TOML text of the N-link planar chain released horizontal (links of ``link`` m,
    particles of ``mass`` kg: the rope of issue 28 is 1 cm and 10 g)."""
    lines = [
        f"# {n}-link planar chain of {link:g} m links and {mass:g} kg particles released horizontal "
        "(benchmarks/big_chain.py)",
        "[scene]", f'name = "{n}-link chain, horizontal"', "",
    ]
    for i in range(n):
        lines += ["[[particles]]", f'name = "p{i}"', f"mass = {mass!r}",
                  f"position = [{(i + 1) * link!r}, 0.0, 0.0]", ""]
    lines += ["[[constraints]]", 'type = "distance"', 'a = "p0"', "point = [0.0, 0.0, 0.0]",
              f"length = {link!r}", ""]
    for i in range(1, n):
        lines += ["[[constraints]]", 'type = "distance"', f'a = "p{i - 1}"', f'b = "p{i}"',
                  f"length = {link!r}", ""]
    names = ", ".join(f'"p{i}"' for i in range(n))
    lines += ["[[constraints]]", 'type = "plane"', f"particles = [{names}]",
              "normal = [0.0, 0.0, 1.0]", "offset = 0.0", ""]
    lines += ["[[effects]]", 'type = "gravity"', "g = [0.0, -9.81, 0.0]", ""]
    lines += ["[simulate]", f"t_end = {t_end}", f"rtol = {rtol}", f"atol = {atol}"]
    if samples:
        lines.append(f"samples = {samples}")
    lines += ["", "[outputs]", "plots = []", ""]
    return "\n".join(lines)


def cloth_scene(k: int, *, t_end: float = 0.5, rtol: float = 1e-6, atol: float = 1e-6,
                samples: int | None = None, link: float = CLOTH_LINK, mass: float = CLOTH_MASS) -> str:
    """The TOML text of a k × k cloth lying flat in z = 0, pinned at two diagonally opposite
    corners, gravity across it."""
    lines = [f"# {k} x {k} cloth of {link:g} m squares and {mass:g} kg particles, pinned at two "
             "diagonal corners, released flat (benchmarks/big_chain.py)",
             "[scene]", f'name = "{k}x{k} cloth, two diagonal corners"', ""]
    for i in range(k):
        for j in range(k):
            lines += ["[[particles]]", f'name = "p{i}_{j}"', f"mass = {mass!r}",
                      f"position = [{i * link!r}, {j * link!r}, 0.0]", ""]
    for i in range(k):
        for j in range(k):
            for di, dj in ((1, 0), (0, 1)):
                if i + di < k and j + dj < k:
                    lines += ["[[constraints]]", 'type = "distance"', f'a = "p{i}_{j}"',
                              f'b = "p{i + di}_{j + dj}"', f"length = {link!r}", ""]
    for i in range(k - 1):  # shear springs on both diagonals of every square
        for j in range(k - 1):
            for (a, b) in (((i, j), (i + 1, j + 1)), ((i + 1, j), (i, j + 1))):
                lines += ["[[effects]]", 'type = "spring"', f'a = "p{a[0]}_{a[1]}"', f'b = "p{b[0]}_{b[1]}"',
                          f"k = {CLOTH_SHEAR!r}", f"rest = {link * 2 ** 0.5!r}", ""]
    far = (k - 1) * link
    lines += ["[[constraints]]", 'type = "pin"', 'a = "p0_0"', "point = [0.0, 0.0, 0.0]", "",
              "[[constraints]]", 'type = "pin"', f'a = "p{k - 1}_{k - 1}"',
              f"point = [{far!r}, {far!r}, 0.0]", ""]
    lines += ["[[effects]]", 'type = "gravity"', "g = [0.0, 0.0, -9.81]", ""]
    lines += ["[simulate]", f"t_end = {t_end}", f"rtol = {rtol}", f"atol = {atol}"]
    if samples:
        lines.append(f"samples = {samples}")
    lines += ["", "[outputs]", "plots = []", ""]
    return "\n".join(lines)


#: Seconds one run may take (``--timeout``); a longer one is killed and reported as unfinished.
TIMEOUT = [900.0]


def _run_within(cmd: list[str], env: dict, cwd: Path) -> subprocess.CompletedProcess | None:
    """``cmd`` run to its end, or None when it takes more than TIMEOUT: then it is killed with
    every process it started (its own session: /usr/bin/time's child too)."""
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=cwd,
                          start_new_session=True) as proc:
        try:
            out, err = proc.communicate(timeout=TIMEOUT[0])
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            return None
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def run_once(scene: Path, out: Path, *, quiet: bool, code: Path = ROOT) -> dict:
    """One ``constrained run`` in a fresh process under /usr/bin/time -v, with the package at
    ``code`` (this checkout, or ``--before``'s)."""
    env = dict(os.environ, PYTHONPATH=str(code) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "constrained.cli", "run", str(scene),
           "--out", str(out)] + (["--quiet"] if quiet else [])
    t0 = time.perf_counter()
    proc = _run_within(cmd, env, code)
    if proc is None:  # (killed: said in the table, not waited for)
        print(f"{scene.name}: did not finish in {TIMEOUT[0]:g} s (--timeout)", file=sys.stderr)
        return dict(wall_s=math.inf, cpu_s=math.inf, peak_rss_mb=math.nan, stdout="", samples=None)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
    cpu = sum(float(re.search(rf"{k} time \(seconds\): ([\d.]+)", proc.stderr).group(1))
              for k in ("User", "System"))
    samples = re.search(r"(\d+) samples", proc.stdout)
    return dict(wall_s=wall, cpu_s=cpu, peak_rss_mb=rss_kb / 1024, stdout=proc.stdout,
                samples=int(samples.group(1)) if samples else None)


#: The stages of ``constrained run`` in one process: what the CLI does (constrained/cli/run.py
#: _run), with the library's stage functions wrapped to time them; then the floor. Prints JSON.
BREAKDOWN = r"""
import json, resource, sys, time
t00, c00 = time.perf_counter(), time.process_time()
stages = []
def peak(): return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
def mark(name, t0, c0): stages.append((name, time.perf_counter() - t0, time.process_time() - c0, peak()))
import numpy as np
from pathlib import Path
import constrained.cli.run as cli  # what `constrained run` imports before it reads the scene
import constrained.solvers
import constrained.run.simulate
from constrained.scene.load import load_scene
simulate_module = sys.modules["constrained.run.simulate"]
def wrap(module, name, label):
    original = getattr(module, name)
    def timed(*a, **k):
        t0, c0 = time.perf_counter(), time.process_time()
        out = original(*a, **k)
        mark(label, t0, c0)
        return out
    setattr(module, name, timed)
for name, label in (("assemble", "assemble"), ("consistent_start", "start (projection, redundancy)"),
                    ("trajectory_from", "post-processing")):
    wrap(simulate_module, name, label)
run = {}
driver = sys.modules["constrained.solvers.driver"]
original_integrate = driver.integrate
def integrate(stepper, *a, **k):
    t0, c0 = time.perf_counter(), time.process_time()
    out = original_integrate(stepper, *a, **k)
    run.update(wall=time.perf_counter() - t0, cpu=time.process_time() - c0, model=stepper.model,
               attempts=int(stepper.stats.get("steps", 0)) + int(stepper.stats.get("rejected", 0)),
               tableau=getattr(stepper, "tableau", None))
    mark("the run (stepping)", t0, c0)
    return out
driver.integrate = integrate
mark("imports", t00, c00)
t0, c0 = time.perf_counter(), time.process_time()
scene = load_scene(sys.argv[1])
mark("read and check the scene", t0, c0)
quantities = cli._contract_quantities(scene.outputs["quantities"])
t0, c0 = time.perf_counter(), time.process_time()
loaded = getattr(scene, "loaded_model", lambda: None)()  # as the CLI: the Structure built at load
mark("the loaded model", t0, c0)
t0, c0 = time.perf_counter(), time.process_time(); result = scene.run(quantities=quantities, model=loaded)
mark("scene.run (all of the above)", t0, c0)
tr = result.trajectory
stages.append(("  of which building the step loop", tr.stats["setup_time_s"], None, None))
t0, c0 = time.perf_counter(), time.process_time()
tr.save(Path(sys.argv[2]) / "trajectory.npz", quantities=quantities)
mark("write trajectory.npz", t0, c0)
t0, c0 = time.perf_counter(), time.process_time()
dof = tr.info.get("degrees_of_freedom")
dof = cli._degrees_of_freedom(scene) if dof is None else dof
mark("report (DOF)", t0, c0)
mark("total", t00, c00)

# the floor, at the model's sizes, in this process
import scipy.sparse as sp
from constrained.manifold.manifold import sparse_jacobian
model = run["model"]
x0 = np.asarray(scene.system.positions, float).ravel()
J = sparse_jacobian(model)(x0, 0.0)
r, c = J.sparsity().get_triplet()
J = sp.csr_matrix((np.asarray(J.nonzeros()).ravel(), (r, c)), shape=J.shape)
A = (J @ sp.diags(model.inverse_masses) @ J.T).tocsr()
def best(f, repeats=200):
    f()
    out = []
    for _ in range(5):
        c0 = time.process_time()
        for _ in range(repeats):
            f()
        out.append((time.process_time() - c0) / repeats)
    return min(out)
x, y = np.random.rand(J.shape[1]), np.random.rand(J.shape[1])
lam = np.random.rand(J.shape[0])
t_axpy = best(lambda: y.__iadd__(0.5 * x))
t_J, t_A = best(lambda: J @ x), best(lambda: A @ lam)
tab = run["tableau"]
K = 0 if tab is None else int(np.count_nonzero(tab.A) + np.count_nonzero(tab.B)
                              + sum(np.count_nonzero(e) for e in tab.E))
floor_step = 14 * (4 * t_J + 3 * t_A + 5 * t_axpy) + 2 * K * t_axpy
per_step = run["cpu"] / max(run["attempts"], 1)
floor = dict(t_axpy=t_axpy, t_J=t_J, t_A=t_A, nnz_J=J.nnz, nnz_A=A.nnz, K=K, floor_step=floor_step,
             step_cpu=per_step, attempts=run["attempts"], particles=model.n_particles,
             ratio=per_step / floor_step)
print(json.dumps(dict(stages=stages, dof=dof, floor=floor)))
"""


def breakdown(scene: Path, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = _run_within([sys.executable, "-c", BREAKDOWN, str(scene), str(out)], env, ROOT)
    if proc is None:
        return None
    if proc.returncode:
        raise RuntimeError(f"the instrumented run failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def scene_text(args, n: int | None = None, cloth: int | None = None) -> str:
    span = {} if args.t_end is None else {"t_end": args.t_end}
    if cloth:
        text = cloth_scene(cloth, samples=args.samples, rtol=args.rtol, atol=args.atol, **span)
    else:
        text = chain_scene(n, samples=args.samples, link=args.link, mass=args.mass, rtol=args.rtol,
                           atol=args.atol, **span)
    return text.replace("[simulate]\n", f'[simulate]\nmethod = "{args.method}"\n') if args.method else text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="*", default=None, help="rope sizes (default 1000 3000 10000)")
    ap.add_argument("--cloth", type=int, nargs="*", default=[], help="cloth sides (100: 10,000 particles)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--quiet", action="store_true", help="pass --quiet (no printed report)")
    ap.add_argument("--samples", type=int,
                    help="output samples (default: the accepted steps, thinned on a large model)")
    ap.add_argument("--link", type=float, default=0.01, help="rope link length (m); issue 16's chain: 1")
    ap.add_argument("--mass", type=float, default=0.01, help="rope particle mass (kg); issue 16's chain: 1")
    ap.add_argument("--rtol", type=float, default=1e-6)
    ap.add_argument("--atol", type=float, default=1e-6, help="(issue 16's chain: 1e-8)")
    ap.add_argument("--method", help="[simulate] method (default: the default method)")
    ap.add_argument("--t-end", type=float,
                    help="simulated time (default: the rope's 1 s, the cloth's 0.5 s); 0.0005 leaves the "
                         "fixed cost of a call (reading, assembling, start checks, the step loop, output)")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--write-only", type=Path, metavar="DIR", help="only write the scenes into DIR")
    ap.add_argument("--breakdown", action="store_true", help="time the stages and the floor in one more run")
    ap.add_argument("--before", type=Path, metavar="DIR",
                    help="also run every case with the package of another checkout (e.g. `git archive "
                         "main | tar -x -C DIR`), alternating with this one: before/after in one run")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds one run may take (then killed)")
    args = ap.parse_args(argv)
    TIMEOUT[0] = args.timeout
    ropes = args.n if args.n is not None else ([] if args.cloth else [1000, 3000, 10000])
    cases = [(f"rope{n}", dict(n=n)) for n in ropes] + [(f"cloth{k}", dict(cloth=k)) for k in args.cloth]

    if args.write_only:
        args.write_only.mkdir(parents=True, exist_ok=True)
        for name, case in cases:
            (args.write_only / f"{name}.toml").write_text(scene_text(args, **case))
        return 0
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, case in cases:
            scene = Path(tmp) / f"{name}.toml"
            scene.write_text(scene_text(args, **case))
            codes = {"now": ROOT, **({"before": args.before.resolve()} if args.before else {})}
            runs = {k: [] for k in codes}
            for _ in range(args.repeats):  # the versions alternate
                for label, code in codes.items():
                    runs[label].append(run_once(scene, Path(tmp) / f"out_{name}_{label}", quiet=args.quiet,
                                                code=code))
            particles = case.get("n") or case["cloth"] ** 2
            row = dict(case=name, particles=particles,
                       breakdown=breakdown(scene, Path(tmp) / f"stages_{name}") if args.breakdown else None)
            for label, done in runs.items():
                best = min(done, key=lambda r: r["wall_s"])
                row[label] = dict(wall_s=best["wall_s"], cpu_s=best["cpu_s"],
                                  peak_rss_mb=min(r["peak_rss_mb"] for r in done),
                                  walls=[r["wall_s"] for r in done], samples=best["samples"])
                walls = ", ".join(f"{r['wall_s']:.2f}" for r in done)
                rss = row[label]["peak_rss_mb"]
                print(f"{name} ({label}): {best['wall_s']:.2f} s wall, {best['cpu_s']:.2f} s CPU "
                      f"(runs {walls}), peak RSS {rss:.0f} MB, {best['samples']} samples", file=sys.stderr)
                if not args.quiet:
                    print(best["stdout"], file=sys.stderr)
            results.append(row)
    labels = ["before", "now"] if args.before else ["now"]
    print("| scene | particles | " + " | ".join(f"{k}: wall (s) | {k}: CPU (s) | {k}: peak RSS (MB)"
                                                for k in labels) + " | samples |")
    print("|---|---|" + "---|---|---|" * len(labels) + "---|")
    for r in results:
        cells = " | ".join(f"{r[k]['wall_s']:.2f} | {r[k]['cpu_s']:.2f} | {r[k]['peak_rss_mb']:.0f}"
                           for k in labels)
        print(f"| {r['case']} | {r['particles']:,} | {cells} | {r['now']['samples']} |")
    for r in results:
        b = r["breakdown"]
        if not b:
            continue
        print(f"\n{r['case']}, one instrumented run:\n")
        print("| stage | wall (s) | CPU (s) | peak RSS after (MB) |\n|---|---|---|---|")
        for name, seconds, cpu, mb in b["stages"]:
            print(f"| {name} | {seconds:.2f} | {'' if cpu is None else f'{cpu:.2f}'} | "
                  f"{'' if mb is None else f'{mb:.0f}'} |")
        wall = {name: seconds for name, seconds, _, _ in b["stages"]}
        if "total" in wall and "the run (stepping)" in wall:
            print(f"\nfixed cost (the whole command but its stepping): "
                  f"{wall['total'] - wall['the run (stepping)']:.2f} s wall (issue 28's goal: ≤ 1 s)")
        f = b["floor"]
        per_particle = 1e6 * f["step_cpu"] / f["particles"]
        print(f"\nper attempted step: {1e3 * f['step_cpu']:.2f} ms CPU ({per_particle:.2f} µs per "
              f"particle-step, {f['attempts']} attempts); floor {1e3 * f['floor_step']:.2f} ms (axpy over 3N "
              f"{1e6 * f['t_axpy']:.1f} µs, J y {1e6 * f['t_J']:.1f} µs with {f['nnz_J']:,} nonzeros, "
              f"A λ {1e6 * f['t_A']:.1f} µs with {f['nnz_A']:,}; K = {f['K']}): "
              f"**{f['ratio']:.1f}× the floor**")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(dict(quiet=args.quiet, samples=args.samples, results=results),
                                        indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
