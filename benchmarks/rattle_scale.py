"""RATTLE at scale (issue 28): a large model's step on the vectorized build (the loops' LDLᵀ,
the simplified Newton iteration) against the exact-Newton step on the Structure's graphs
(CasADi's sparse QR of J(x_{n+1}) M⁻¹ J(x_n)ᵀ), on physical discretizations: the 1 cm rope of
10 g beads released horizontal, and the cloth of 1 cm squares and 15 mg beads pinned at two
diagonal corners (shear springs), as benchmarks/big_chain.py writes them.

Each (scene, route) runs three times in one process, each on a fresh model: ``--short`` steps
(the step built, the loops compiled or loaded: the first run's time), then ``--short`` and
``--long`` steps of ``--dt``, whose solver wall times' difference over the difference of the
steps is the cost of a step. The two routes' positions at the end of the short run are
compared (they solve the same step).

    python benchmarks/rattle_scale.py                          # rope 10,000, cloth 100 x 100
    python benchmarks/rattle_scale.py --rope 1000 --cloth 32 --short 20 --long 60
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for path in (ROOT, ROOT / "benchmarks"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from big_chain import chain_scene, cloth_scene  # noqa: E402


def _scene(text: str, steps: int, dt: float, folder: Path, name: str) -> Path:
    text = text.replace("[simulate]\n", f'[simulate]\nmethod = "rattle"\ndt = {dt!r}\n')
    text = "\n".join(f"t_end = {steps * dt!r}" if line.startswith("t_end =") else line
                     for line in text.splitlines()) + "\n"
    path = folder / f"{name}_{steps}.toml"
    path.write_text(text)
    return path


def _run(path: Path, exact: bool) -> tuple[float, np.ndarray, int]:
    from constrained.scene.load import load_scene
    from constrained.solvers.rattle import Rattle

    original = Rattle.vectorized
    if exact:
        Rattle.vectorized = lambda self: False
    try:
        scene = load_scene(path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            tr = scene.run().trajectory
            wall = time.perf_counter() - t0
    finally:
        Rattle.vectorized = original
    return wall, tr.x[-1], int(tr.stats["steps"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rope", type=int, nargs="*", default=[10000])
    ap.add_argument("--cloth", type=int, nargs="*", default=[100])
    ap.add_argument("--dt", type=float, default=2.5e-4)
    ap.add_argument("--short", type=int, default=4)
    ap.add_argument("--long", type=int, default=12)
    ap.add_argument("--routes", default="vectorized,exact")
    args = ap.parse_args(argv)
    cases = [(f"rope {n}", chain_scene(n)) for n in args.rope] + [(f"cloth {k} x {k}", cloth_scene(k))
                                                                  for k in args.cloth]
    print(f"RATTLE, dt = {args.dt:g} s; a step's cost from {args.short} and {args.long} steps "
          "(solver wall)\n")
    print("| scene | route | first run: build, compile, short steps (s) | per step (ms) | steps |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name, text in cases:
            ends = {}
            for route in args.routes.split(","):
                exact = route == "exact"
                first = _run(_scene(text, args.short, args.dt, Path(tmp), name.replace(" ", "")), exact)
                short = _run(_scene(text, args.short, args.dt, Path(tmp), name.replace(" ", "")), exact)
                long = _run(_scene(text, args.long, args.dt, Path(tmp), name.replace(" ", "")), exact)
                per_step = (long[0] - short[0]) / (long[2] - short[2])
                ends[route] = short[1]
                print(f"| {name} | {route} | {first[0]:.2f} | {1e3 * per_step:.1f} | "
                      f"{short[2]}, {long[2]} |", flush=True)
            if len(ends) == 2:
                a, b = ends.values()
                gap = np.max(np.abs(a - b))
                print(f"| {name} | max distance between the routes' positions | {gap:.1e} m | | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
