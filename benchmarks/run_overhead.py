"""Wall time of `constrained run` against the solver's own time, for the bundled scenes.

    PYTHONPATH=. python benchmarks/run_overhead.py [SCENE ...] [--repeats N]

Runs each scene (default: every scenarios/*.toml but the sweep) with its default outputs in a
fresh process, as a user would, into a temporary directory, and prints one row per scene:
the process's wall time (best of --repeats), the solver's wall_time_s (from the run's report),
and the overhead = wall − solver (start-up, imports, model building, files, figures). The goal
(issue 19) is overhead ≤ 1 s. Results: docs/performance.md, "Start-up and output overhead".
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def measure(scene: Path, repeats: int) -> tuple[float, float | None, int]:
    best, solver, status = float("inf"), None, 0
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "constrained.cli", "run", str(scene), "--out", out],
                                  capture_output=True, text=True, cwd=ROOT)
            wall = time.perf_counter() - t0
        status = proc.returncode
        found = re.search(r"wall_time_s ([0-9.e+-]+)", proc.stdout)
        if wall < best:
            best, solver = wall, float(found.group(1)) if found else None
    return best, solver, status


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", type=Path)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    scenes = args.scenes or sorted(p for p in (ROOT / "scenarios").glob("*.toml") if "sweep" not in p.name)
    print("| scene | wall [s] | solver [s] | overhead [s] | exit |\n|---|---:|---:|---:|---:|")
    for scene in scenes:
        wall, solver, status = measure(scene, args.repeats)
        solver_text = f"{solver:.3f}" if solver is not None else "?"
        over = f"{wall - solver:.2f}" if solver is not None else "?"
        print(f"| {scene.stem} | {wall:.2f} | {solver_text} | {over} | {status} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
