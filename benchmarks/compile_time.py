"""Compile time of dopri's compiled step loop against the size of the model, mapped and not.

For each N, the planar N-link chain (benchmarks/peers.py ``chain``: unit masses and links, a
plane, gravity) and, with ``--pairs``, the same chain with an all-pairs potential V = Σ −k/r_ij
run in a fresh process with an empty compile cache:

- ``assemble``: the Structure (parsing, differentiation);
- ``first call``: the first ``simulate`` (1 ms of motion): the step loop's CasADi graph, its C
  code generated and compiled (``compile``, timed around ``compiled._build``: code generation
  plus the C compiler), the consistent start;
- ``C source``: the size of the generated C file;
- ``run``: the compiled loop simulating 1 s at rtol 1e-6 (atol 1e-8), fastest of ``--repeats``.

``mapped`` is the build of constrained.mapped (repeated rows and terms as one kernel each,
applied with CasADi ``map``; the default from ``mapped.MAPPED_FROM`` coordinates), ``unrolled``
the Structure's one SX graph (the default below), each forced here at every N (the unrolled
one up to ``--unrolled-up-to`` links).

    python benchmarks/compile_time.py [--n 16 64 256 1000] [--pairs 16 32 64] [--repeats 5]
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
import constrained as C
from constrained import compiled, mapped
from peers import chain

n, pairs, build_kind, repeats = {n}, {pairs}, {build!r}, {repeats}
mapped.MAPPED_FROM = 0 if build_kind == "mapped" else 10 ** 9


def system():
    s = chain(n)
    if pairs:
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
start = time.perf_counter()
model = C.assemble(system())
assemble = time.perf_counter() - start
start = time.perf_counter()
C.simulate(system(), 1e-3, model=model, method="dopri", compiled=True, outputs=set())
first = time.perf_counter() - start
runs = []
for _ in range(repeats):
    tr = C.simulate(system(), 1.0, model=model, method="dopri", rtol=1e-6, atol=1e-8,
                    t_eval=[0.0, 1.0], outputs=set(), compiled=True)
    runs.append(tr.stats["wall_time_s"])
print(json.dumps(dict(n=n, pairs=pairs, build=build_kind, assemble=assemble, first=first,
                      compile=seen["compile"], source_kb=seen["source"] / 1024, run=min(runs),
                      steps=tr.stats["steps"], evaluation=tr.stats["evaluation"],
                      end=tr.x[-1].ravel().tolist())))
"""


def measure(n: int, pairs: bool, build: str, repeats: int) -> dict:
    with tempfile.TemporaryDirectory() as cache:
        code = CHILD.format(root=str(ROOT), cache=cache, n=n, pairs=pairs, build=build, repeats=repeats)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=7200)
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[16, 64, 256, 1000])
    parser.add_argument("--pairs", type=int, nargs="*", default=[16, 32, 64])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--unrolled-up-to", type=int, default=256)
    parser.add_argument("--out", default=str(ROOT / "docs" / "performance" / "compile_time"))
    args = parser.parse_args()
    lines = ["| model | N | build | assemble [s] | first call [s] | compile [s] | C source [KB] "
             "| run, 1 s [ms] | steps | max end difference |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    rows = []
    cases = [(n, False) for n in args.n] + [(n, True) for n in args.pairs]
    for n, pairs in cases:
        mapped_row = None
        for build in ("mapped", "unrolled"):
            if build == "unrolled" and n > args.unrolled_up_to:
                continue
            row = measure(n, pairs, build, args.repeats)
            rows.append(row)
            if build == "mapped":
                mapped_row = row
                diff = "—"
            else:
                diff = f"{max(abs(a - b) for a, b in zip(row['end'], mapped_row['end'], strict=True)):.1e}"
            model = "chain + all pairs" if pairs else "chain"
            line = (f"| {model} | {n} | {build} | {row['assemble']:.3f} | {row['first']:.2f} | "
                    f"{row['compile']:.2f} | {row['source_kb']:.0f} | {row['run'] * 1e3:.2f} | "
                    f"{row['steps']} | {diff} |")
            lines.append(line)
            print(line, flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    header = (f"`python benchmarks/compile_time.py {' '.join(sys.argv[1:])}` on {platform.machine()}, "
              f"{time.strftime('%Y-%m-%d')}; each row a fresh process with an empty compile cache.\n\n")
    (out / "compile_time.md").write_text(header + "\n".join(lines) + "\n")
    (out / "compile_time.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
