"""Compile time of dopri's compiled step loop against the size of the model, mapped and not.

For each N, the planar N-link chain (benchmarks/peers.py ``chain``: unit masses and links, a
plane, gravity), with ``--pairs`` the same chain with an all-pairs potential V = Σ −k/r_ij,
and with ``--varied`` a chain whose every length and mass is a different number (the numbers
become data of one kernel), each run in a fresh process with an empty compile cache:

- ``assemble``: the Structure (parsing, differentiation);
- ``first call``: the first ``simulate`` (1 ms of motion): the step loop's CasADi graph, its C
  code generated and compiled (``compile``, timed around ``compiled._build``: code generation
  plus the C compiler), the consistent start;
- ``C source``: the size of the generated C file;
- ``run``: the compiled loop simulating 1 s at rtol 1e-6 (atol 1e-8), fastest of ``--repeats``,
  the two builds run alternately in the same process (each on its own Structure).

``mapped`` is the build of constrained.mapped (repeated rows and terms as one kernel each,
applied with CasADi ``map``; the default from ``mapped.MAPPED_FROM`` coordinates), ``unrolled``
the Structure's one SX graph (the default below), each forced here at every N (the unrolled
one up to ``--unrolled-up-to`` links).

    python benchmarks/compile_time.py [--n 16 64 256 1000] [--pairs 16 32 64] [--varied 256] [--repeats 5]
        [--unrolled-up-to 256] [--out docs/performance/compile_time]
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, os, sys, time
sys.path.insert(0, {root!r})
sys.path.insert(0, {root!r} + "/benchmarks")
os.environ["CONSTRAINED_CACHE"] = {cache!r}
import casadi as ca
import numpy as np
import constrained as C
from constrained.codegen import compiled
from constrained.manifold import mapped
from peers import chain

n, kind, builds, repeats = {n}, {kind!r}, {builds!r}, {repeats}


def system():
    if kind == "varied":  # every link's length and every mass a different number
        s = C.System(name=f"varied {{n}}-link chain")
        reach = np.cumsum(1.0 + 0.001 * np.arange(n))
        for i in range(n):
            s.add_particle(f"p{{i}}", 1.0 + 0.01 * i, [reach[i] * np.sin(0.5), -reach[i] * np.cos(0.5), 0.0])
        s.add(C.Distance("p0", point=[0, 0, 0], length=1.0))
        for i in range(1, n):
            s.add(C.Distance(f"p{{i - 1}}", f"p{{i}}", length=1.0 + 0.001 * i))
        s.add(C.Plane([f"p{{i}}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -9.81, 0]))
        return s
    s = chain(n)
    if kind == "pairs":
        s.add(C.Pairwise("-0.05/r"))
    return s


seen = dict(compile=0.0, source=0)
original = compiled._build


def timed(functions, *args, **kwargs):
    cg = ca.CodeGenerator("size.c", {{"with_header": False}})
    for f in functions:
        cg.add(f)
    seen["source"] += len(cg.dump())
    start = time.perf_counter()
    try:
        return original(functions, *args, **kwargs)
    finally:
        seen["compile"] += time.perf_counter() - start


compiled._build = timed
rows, models = {{}}, {{}}
for build in builds:  # each its own Structure, so each its own step loop
    mapped.MAPPED_FROM = 0 if build == "mapped" else 10 ** 9
    seen.update(compile=0.0, source=0)
    start = time.perf_counter()
    models[build] = C.assemble(system(), reuse=False)
    assemble = time.perf_counter() - start
    start = time.perf_counter()
    C.simulate(system(), 1e-3, model=models[build], method="dopri", compiled=True, outputs=set())
    rows[build] = dict(n=n, kind=kind, build=build, assemble=assemble, first=time.perf_counter() - start,
                       compile=seen["compile"], source_kb=seen["source"] / 1024, runs=[])
for _ in range(repeats):  # alternately, so that the machine's load hits both alike
    for build in builds:
        tr = C.simulate(system(), 1.0, model=models[build], method="dopri", rtol=1e-6, atol=1e-8,
                        t_eval=[0.0, 1.0], outputs=set(), compiled=True)
        rows[build]["runs"].append(tr.stats["wall_time_s"])
        rows[build].update(steps=tr.stats["steps"], evaluation=tr.stats["evaluation"],
                           end=tr.x[-1].ravel().tolist())
for row in rows.values():
    row["run"] = min(row["runs"])
print(json.dumps(list(rows.values())))
"""


MODELS = {"chain": "chain", "pairs": "chain + all pairs", "varied": "chain, lengths and masses varied"}


def measure(n: int, kind: str, builds: tuple, repeats: int) -> list[dict]:
    with tempfile.TemporaryDirectory() as cache:
        code = CHILD.format(root=str(ROOT), cache=cache, n=n, kind=kind, builds=builds, repeats=repeats)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=7200)
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="*", default=[16, 64, 256, 1000])
    parser.add_argument("--pairs", type=int, nargs="*", default=[16, 32, 64])
    parser.add_argument("--varied", type=int, nargs="*", default=[256])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--unrolled-up-to", type=int, default=256)
    parser.add_argument("--out", default=str(ROOT / "docs" / "performance" / "compile_time"))
    args = parser.parse_args()
    lines = ["| model | N | build | assemble [s] | first call [s] | compile [s] | C source [KB] "
             "| run, 1 s [ms] | steps | max end difference |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    rows = []
    cases = ([(n, "chain") for n in args.n] + [(n, "pairs") for n in args.pairs]
             + [(n, "varied") for n in args.varied])
    for n, kind in cases:
        builds = ("mapped", "unrolled") if n <= args.unrolled_up_to else ("mapped",)
        measured = measure(n, kind, builds, args.repeats)
        for row in measured:
            rows.append(row)
            diff = "—" if row["build"] == "mapped" else \
                f"{max(abs(a - b) for a, b in zip(row['end'], measured[0]['end'], strict=True)):.1e}"
            model = MODELS[kind]
            line = (f"| {model} | {n} | {row['build']} | {row['assemble']:.3f} | {row['first']:.2f} | "
                    f"{row['compile']:.2f} | {row['source_kb']:.0f} | {row['run'] * 1e3:.2f} | "
                    f"{row['steps']} | {diff} |")
            lines.append(line)
            print(line, flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    header = (f"`python benchmarks/compile_time.py {' '.join(sys.argv[1:])}` on {platform.machine()}, "
              f"{time.strftime('%Y-%m-%d')}; each N a fresh process with an empty compile cache. The machine "
              "(2 cores) was shared with other jobs: compile times vary by up to 2x between runs.\n\n")
    (out / "compile_time.md").write_text(header + "\n".join(lines) + "\n")
    kept = [{k: v for k, v in row.items() if k != "end"} for row in rows]
    (out / "compile_time.json").write_text(json.dumps(kept, indent=1))


if __name__ == "__main__":
    main()
