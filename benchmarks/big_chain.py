"""Issue 16's scale goal: ``constrained run`` of an N-link planar chain, as a whole command.

The scene (written by this script as TOML): N unit masses at (i + 1, 0, 0), i.e. the chain
released horizontal and at rest; the first on a 1 m rod to the fixed point (0, 0, 0), each
next on a 1 m rod to the one before; all in the plane z = 0 (one ``plane`` constraint);
gravity (0, −9.81, 0). 1 s at rtol 1e-6 (atol 1e-8 = rtol·1e-2, as in every benchmark here)
with the default method (dopri). No figures (``plots = []``); the default quantities
(multipliers, constraint forces, energy, constraint residual) and the default output grid
(every accepted step) unless ``--samples`` is given.

Each run is one subprocess ``/usr/bin/time -v python -m constrained.cli run SCENE --out DIR``:
its wall time is everything a user waits for (interpreter start, imports, scene loading and
checks, assembly, the start, the run, post-processing, trajectory.npz, the printed report:
DOF, energy drift, residuals) and its peak memory is ``Maximum resident set size`` of that
process. The minimum over ``--repeats`` is reported (the machine is shared).
``--breakdown`` runs the same steps once more in one instrumented process (BREAKDOWN below)
and reports the wall time and the peak RSS after each stage.

    python benchmarks/big_chain.py [--n 1000 3000 10000] [--repeats 2] [--quiet] [--breakdown]
        [--samples K] [--json docs/performance/scale/scale.json] [--write-only DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def chain_scene(n: int, *, t_end: float = 1.0, rtol: float = 1e-6, atol: float = 1e-8,
                samples: int | None = None, link: float = 1.0, mass: float = 1.0) -> str:
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


def run_once(scene: Path, out: Path, *, quiet: bool) -> dict:
    """One ``constrained run`` in a fresh process under /usr/bin/time -v."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "constrained.cli", "run", str(scene),
           "--out", str(out)] + (["--quiet"] if quiet else [])
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
    samples = re.search(r"(\d+) samples", proc.stdout)
    return dict(wall_s=wall, peak_rss_mb=rss_kb / 1024, stdout=proc.stdout,
                samples=int(samples.group(1)) if samples else None)


#: The stages of ``constrained run`` in one process: what the CLI does (constrained/cli_run.py
#: _run), with the library's stage functions wrapped to time them. Prints JSON.
BREAKDOWN = r"""
import json, resource, sys, time
t00 = time.perf_counter()
stages = []
def peak(): return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
def mark(name, t0): stages.append((name, time.perf_counter() - t0, peak()))
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
        t0 = time.perf_counter(); out = original(*a, **k); mark(label, t0); return out
    setattr(module, name, timed)
for name, label in (("assemble", "assemble"), ("consistent_start", "start (projection)"),
                    ("trajectory_from", "post-processing")):
    wrap(simulate_module, name, label)
mark("imports", t00)
t0 = time.perf_counter(); scene = load_scene(sys.argv[1]); mark("load scene (parse, validate)", t0)
quantities = cli._contract_quantities(scene.outputs["quantities"])
t0 = time.perf_counter(); result = scene.run(quantities=quantities)
mark("scene.run (all)", t0)
tr = result.trajectory
stages.append(("  solver setup (build step loop)", tr.stats["setup_time_s"], None))
stages.append(("  solver run", tr.stats["wall_time_s"], None))
t0 = time.perf_counter()
tr.save(Path(sys.argv[2]) / "trajectory.npz", quantities=quantities)
mark("write trajectory.npz", t0)
t0 = time.perf_counter()
dof = tr.info.get("degrees_of_freedom")
dof = cli._degrees_of_freedom(scene) if dof is None else dof
mark("report (DOF)", t0)
mark("total", t00)
print(json.dumps(dict(stages=stages, dof=dof)))
"""


def breakdown(scene: Path, out: Path) -> list:
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", BREAKDOWN, str(scene), str(out)], capture_output=True,
                          text=True, env=env, cwd=ROOT)
    if proc.returncode:
        raise RuntimeError(f"the instrumented run failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])["stages"]


def scene_text(args, n: int) -> str:
    text = chain_scene(n, samples=args.samples, link=args.link, mass=args.mass, rtol=args.rtol,
                       atol=args.atol)
    return text.replace("[simulate]\n", f'[simulate]\nmethod = "{args.method}"\n') if args.method else text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[1000, 3000, 10000])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--quiet", action="store_true", help="pass --quiet (no printed report)")
    ap.add_argument("--samples", type=int, help="output samples (default: every accepted step)")
    ap.add_argument("--link", type=float, default=1.0, help="link length (m); the rope of issue 28: 0.01")
    ap.add_argument("--mass", type=float, default=1.0, help="particle mass (kg); the rope of issue 28: 0.01")
    ap.add_argument("--rtol", type=float, default=1e-6)
    ap.add_argument("--atol", type=float, default=1e-8, help="(the rope of issue 28: 1e-6)")
    ap.add_argument("--method", help="[simulate] method (default: the default method)")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--write-only", type=Path, metavar="DIR", help="only write the scenes into DIR")
    ap.add_argument("--breakdown", action="store_true", help="time the stages in one more run")
    args = ap.parse_args(argv)

    if args.write_only:
        args.write_only.mkdir(parents=True, exist_ok=True)
        for n in args.n:
            (args.write_only / f"chain{n}.toml").write_text(scene_text(args, n))
        return 0
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.n:
            scene = Path(tmp) / f"chain{n}.toml"
            scene.write_text(scene_text(args, n))
            runs = [run_once(scene, Path(tmp) / f"out{n}", quiet=args.quiet) for _ in range(args.repeats)]
            best = min(runs, key=lambda r: r["wall_s"])
            row = dict(n=n, wall_s=best["wall_s"], peak_rss_mb=min(r["peak_rss_mb"] for r in runs),
                       walls=[r["wall_s"] for r in runs], samples=best["samples"],
                       stages=breakdown(scene, Path(tmp) / f"stages{n}") if args.breakdown else [])
            results.append(row)
            print(f"N = {n}: {row['wall_s']:.2f} s (runs {', '.join(f'{w:.2f}' for w in row['walls'])}), "
                  f"peak RSS {row['peak_rss_mb']:.0f} MB, {row['samples']} samples", file=sys.stderr)
            if not args.quiet:
                print(best["stdout"], file=sys.stderr)
    print("| N | wall (s) | peak RSS (MB) | samples |")
    print("|---|---|---|---|")
    for r in results:
        print(f"| {r['n']:,} | {r['wall_s']:.2f} | {r['peak_rss_mb']:.0f} | {r['samples']} |")
    for r in results:
        if r["stages"]:
            print(f"\nN = {r['n']:,}, one instrumented run:\n")
            print("| stage | s | peak RSS after (MB) |\n|---|---|---|")
            for name, seconds, mb in r["stages"]:
                print(f"| {name} | {seconds:.2f} | {'' if mb is None else f'{mb:.0f}'} |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(dict(quiet=args.quiet, samples=args.samples, results=results),
                                        indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
