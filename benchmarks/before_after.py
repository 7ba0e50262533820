"""Every method, before and after a change, side by side in one run.

    git worktree add /tmp/before <old-commit>
    python benchmarks/before_after.py --before /tmp/before --after . --repeats 7 \
        --out docs/performance/before_after

Each (scene, method) case runs in a fresh subprocess per checkout, alternating before/after,
so the two see the same machine load. A subprocess imports ``constrained`` from its checkout,
loads the scene, runs once to warm up (model build, step-loop construction, compile caches),
then times ``repeats`` whole ``simulate()`` calls with the model passed back in (what a user
pays per run once the model exists) and reports the median, the solver loop's share
(``stats["wall_time_s"]``), and the end position's error against a tight reference run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import textwrap
from pathlib import Path

CASES = [
    # (label, scene, t_end, method, options)
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "dopri", {}),
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "dopri", {"base": "DOPRI5"}),
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "projection", {}),
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "projection", {"base": "CVODES"}),
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "baumgarte", {}),
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "idas", {}),
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "ggl", {}),
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "pantelides", {}),
    ("double pendulum", "scenarios/double_pendulum.toml", 2.0, "rattle", {"dt": 1e-3}),
    ("3-D chain", "scenarios/chain_3d.toml", 1.0, "dopri", {}),
    ("3-D chain", "scenarios/chain_3d.toml", 1.0, "projection", {}),
]

CHILD = textwrap.dedent("""
    import json, sys, time, warnings
    sys.path.insert(0, sys.argv[1])
    warnings.simplefilter("ignore")
    import numpy as np
    import constrained as C
    scene_path, t_end, method, options, repeats, rtol = (sys.argv[2], float(sys.argv[3]), sys.argv[4],
                                                         json.loads(sys.argv[5]), int(sys.argv[6]),
                                                         float(sys.argv[7]))
    scene = C.load_scene(scene_path)
    model = C.assemble(scene.system)
    ref = C.simulate(scene.system, t_end, rtol=1e-12, atol=1e-12, outputs=[], model=model)
    kw = dict(method=method, rtol=rtol, atol=rtol, outputs=[], model=model, **options)
    tr = C.simulate(scene.system, t_end, **kw)  # warm-up: step loops built, caches filled
    calls, loops = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        tr = C.simulate(scene.system, t_end, **kw)
        calls.append(time.perf_counter() - started)
        loops.append(tr.stats["wall_time_s"])
    print(json.dumps({"call": calls, "loop": loops, "steps": int(tr.stats.get("steps", 0)),
                      "error": float(np.max(np.abs(tr.x[-1] - ref.x[-1])))}))
""")


def run_case(checkout: Path, case, repeats: int, rtol: float) -> dict:
    _, scene, t_end, method, options = case
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(checkout), str(checkout / scene), str(t_end), method,
         json.dumps(options), str(repeats), str(rtol)],
        capture_output=True, text=True, timeout=900, cwd=checkout)
    if out.returncode:
        return {"failed": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True)
    parser.add_argument("--after", type=Path, default=Path("."))
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds per case")
    parser.add_argument("--rtol", type=float, default=1e-9)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    rows = []
    for case in CASES:
        samples = {"before": [], "after": []}
        info = {}
        for _ in range(args.rounds):
            for side in ("before", "after"):
                r = run_case(getattr(args, side).resolve(), case, args.repeats, args.rtol)
                if "failed" in r:
                    info[side] = r["failed"]
                    continue
                samples[side].extend(r["call"])
                info[f"{side}_error"] = r["error"]
                info[f"{side}_steps"] = r["steps"]
        label, _, _, method, options = case
        name = method + (":" + options["base"] if "base" in options else "")
        row = {"scene": label, "method": name, **info}
        for side in ("before", "after"):
            row[f"{side}_ms"] = 1e3 * statistics.median(samples[side]) if samples[side] else None
        if row["before_ms"] and row["after_ms"]:
            row["ratio"] = row["after_ms"] / row["before_ms"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    lines = ["| scene | method | before [ms] | after [ms] | after / before | error before | error after |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        def fmt(v, spec):
            return format(v, spec) if isinstance(v, float) else str(v if v is not None else "—")
        lines.append(f"| {r['scene']} | `{r['method']}` | {fmt(r.get('before_ms'), '.3g')} | "
                     f"{fmt(r.get('after_ms'), '.3g')} | {fmt(r.get('ratio'), '.2f')} | "
                     f"{fmt(r.get('before_error'), '.2g')} | {fmt(r.get('after_error'), '.2g')} |")
    table = "\n".join(lines)
    print(table)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "before_after.json").write_text(json.dumps(rows, indent=1))
        (args.out / "before_after.md").write_text(table + "\n")


if __name__ == "__main__":
    main()
