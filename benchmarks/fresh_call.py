"""A fresh call as a user writes it, against Exudyn, side by side in one process (issue 16).

    python benchmarks/fresh_call.py [--rounds 15] [--out docs/performance/fresh_call]

The double pendulum of ``scenarios/double_pendulum.toml`` to t = 2 s, end position within
1e-9 m of the reference (``peers.reference``: constrained at rtol 1e-13, cross-checked with
SciPy on the angles). Each runner's tolerance is the loosest of 1e-8 … 1e-12 that meets
1e-9; then the runners alternate for ``--rounds`` rounds and the median is reported.

- ``constrained, as a user writes it``: the call README.md's speed sentence is about —
  ``scene = load_scene(path)`` and ``simulate(scene.system, 2.0, rtol=..., atol=...)`` per
  call: the scene read from its file each call, no method named (the default), the default
  outputs (every derived quantity) at the default output times (every step).
- ``constrained scene.run()``: ``load_scene(path, ["simulate.t_end=2", "simulate.rtol=…",
  "simulate.atol=…"]).run()`` — the scene's own settings (no method named in the bundled
  scene), its [outputs] quantities and its [expect] checks, what ``constrained run`` computes.
- ``constrained <method>, lean``: ``load_scene(path)`` + ``simulate(system, 2.0, method=...,
  t_eval=[0, 2], outputs=set())`` per call — only the end state, no derived quantities. The
  scene is read and the model assembled every call in all three (assembly reuses the
  structure of an equal scene: nothing is differentiated or compiled again, see
  ``constrained.model.structure.assemble``).
- ``Exudyn tree + DOPRI5``: the kinematic tree built (``SystemContainer``, ``Assemble``) and
  solved per call (benchmarks/peers.py).
- "new values": the same with a new m1 and l2 every call — constrained reads
  ``scenarios/double_pendulum_parametric.toml`` with ``--set``-style overrides
  (``parameters.m1=…``), Exudyn builds its tree with that mass and length.
- "new plain numbers": the same with the plain scene ``scenarios/double_pendulum.toml``, its
  numbers overridden as written (``particles.p1.mass=…``, ``constraints[1].length=…`` and
  p2's start for that length): plain numbers are hidden parameters (constrained.lifting), so
  this shares the structure and the compiled step loop too.
- "first call in a new process": a subprocess that imports the package, reads the scene and
  runs once as a user writes it, and as the lean call (the compile cache warm), its wall time
  from the interpreter's start to the end of the run minus that of an empty interpreter.
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import peers  # noqa: E402  (the problems and the Exudyn builder shared with peers.py)

import constrained as C  # noqa: E402

DOUBLE = ROOT / "scenarios" / "double_pendulum.toml"
PARAMETRIC = ROOT / "scenarios" / "double_pendulum_parametric.toml"
RTOLS = (1e-8, 1e-9, 1e-10, 1e-11, 1e-12)
TARGET = 1e-9


def user_call(rtol: float, overrides=(), plain=False):
    """As a user writes it: the scene read from its file, no method named, default outputs."""
    scene = C.load_scene(PARAMETRIC if overrides and not plain else DOUBLE, list(overrides))
    tr = C.simulate(scene.system, 2.0, rtol=rtol, atol=rtol * 1e-2)
    return tr.x[-1][:, :2]


def scene_run_call(rtol: float, overrides=(), plain=False):
    """``Scene.run()``: the scene's own settings, [outputs] and [expect] checks (``constrained run``)."""
    settings = ["simulate.t_end=2", f"simulate.rtol={rtol!r}", f"simulate.atol={rtol * 1e-2!r}"]
    scene = C.load_scene(PARAMETRIC if overrides and not plain else DOUBLE, [*overrides, *settings])
    return scene.run().trajectory.x[-1][:, :2]


def constrained_call(method: str, rtol: float, overrides=(), plain=False):
    scene = C.load_scene(PARAMETRIC if overrides and not plain else DOUBLE, list(overrides))
    tr = C.simulate(scene.system, 2.0, method=method, rtol=rtol, atol=rtol * 1e-2, t_eval=[0.0, 2.0],
                    outputs=set())
    return tr.x[-1][:, :2]


def exudyn_call(problem, rtol: float, m1: float = 1.0, l2: float = 1.0):
    peer = peers.ExudynTreePeer("DOPRI5")
    if m1 != 1.0 or l2 != 1.0:  # a tree with that mass and length
        import exudyn as exu
        from exudyn.itemInterface import NodeGenericODE2, ObjectKinematicTree

        rel = np.diff(np.concatenate([[0.0], problem.theta0]))
        sc = exu.SystemContainer()
        mbs = sc.AddSystem()
        node = mbs.AddNode(NodeGenericODE2(referenceCoordinates=[0.0] * 2, initialCoordinates=list(rel),
                                           initialCoordinates_t=[0.0, 0.0], numberOfODE2Coordinates=2))
        mbs.AddObject(ObjectKinematicTree(
            nodeNumber=node, jointTypes=[exu.JointType.RevoluteZ] * 2, linkParents=[-1, 0],
            jointTransformations=exu.Matrix3DList([np.eye(3)] * 2),
            jointOffsets=exu.Vector3DList([[0.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
            linkInertiasCOM=exu.Matrix3DList([np.zeros((3, 3))] * 2),
            linkCOMs=exu.Vector3DList([[0.0, -1.0, 0.0], [0.0, -l2, 0.0]]), linkMasses=[m1, 1.0],
            gravity=[0.0, -peers.G, 0.0]))
        mbs.Assemble()
        built = (sc, mbs, node)
    else:
        built = peer.build(problem)
    _, xy, _ = peer.run(built, problem, rtol)
    return xy


def timed(call) -> float:
    started = time.perf_counter()
    call()
    return time.perf_counter() - started


def first_call_in_a_new_process(code: str) -> float:
    """Seconds from an interpreter's start to the end of ``code``, minus an empty interpreter's."""
    def wall(source):
        started = time.perf_counter()
        subprocess.run([sys.executable, "-c", source], check=True, cwd=ROOT, capture_output=True)
        return time.perf_counter() - started

    empty = min(wall("pass") for _ in range(3))
    return min(wall(code) for _ in range(3)) - empty


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--methods", default="dopri,projection")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    problem = peers.double_problem()
    ref = np.asarray(peers.reference(problem)[0], float)
    runners = {"constrained, as a user writes it": user_call, "constrained scene.run()": scene_run_call}
    runners.update({f"constrained {m}, lean": functools.partial(constrained_call, m)
                    for m in args.methods.split(",")})
    try:
        import exudyn  # noqa: F401

        runners["Exudyn tree + DOPRI5"] = functools.partial(exudyn_call, problem)
    except ImportError:
        print("Exudyn not installed: constrained only (pip install -e .[bench])")
    chosen, errors = {}, {}
    for name, call in runners.items():
        for rtol in RTOLS:
            call(rtol)  # warm: caches filled, libraries loaded
            error = float(np.max(np.abs(call(rtol) - ref)))
            if error <= TARGET or rtol == RTOLS[-1]:
                chosen[name], errors[name] = rtol, error
                break
    fresh = {name: [] for name in runners}
    varied = {name: [] for name in runners}
    plain = {name: [] for name in runners}
    rng = np.random.default_rng(1)
    for _ in range(args.rounds):
        m1, l2 = float(rng.uniform(0.5, 2.0)), float(rng.uniform(0.5, 1.5))
        for name, call in runners.items():
            fresh[name].append(timed(lambda c=call, n=name: c(chosen[n])))
            if name.startswith("constrained"):
                overrides = (f"parameters.m1={m1}", f"parameters.l2={l2}")
                varied[name].append(timed(lambda c=call, n=name, o=overrides: c(chosen[n], o)))
                p2 = [float(np.sin(2.0) + l2 * np.sin(2.5)), float(-np.cos(2.0) - l2 * np.cos(2.5))]
                written = (f"particles.p1.mass={m1}", f"constraints[1].length={l2}",
                           f"particles.p2.position=[{p2[0]!r}, {p2[1]!r}, 0.0]")
                plain[name].append(timed(lambda c=call, n=name, o=written: c(chosen[n], o, True)))
            else:
                varied[name].append(timed(functools.partial(exudyn_call, problem, chosen[name], m1, l2)))
                plain[name].append(varied[name][-1])
    peer = "Exudyn tree + DOPRI5" if "Exudyn tree + DOPRI5" in runners else None
    rows = []
    for name in runners:
        row = {"runner": name, "rtol": chosen[name], "error": errors[name],
               "fresh_ms": 1e3 * statistics.median(fresh[name]),
               "new_values_ms": 1e3 * statistics.median(varied[name]),
               "new_plain_numbers_ms": 1e3 * statistics.median(plain[name])}
        rows.append(row)
    for row in rows:
        if peer:
            base = next(r for r in rows if r["runner"] == peer)
            row["fresh_ratio"] = row["fresh_ms"] / base["fresh_ms"]
            row["new_values_ratio"] = row["new_values_ms"] / base["new_values_ms"]
            row["new_plain_numbers_ratio"] = row["new_plain_numbers_ms"] / base["new_values_ms"]
    code = ("import constrained as C; s = C.load_scene('scenarios/double_pendulum.toml'); "
            "C.simulate(s.system, 2.0, method='{m}', rtol={r}, atol={a}, t_eval=[0.0, 2.0], outputs=set())")
    first = {f"{m}, lean": first_call_in_a_new_process(code.format(m=m, r=chosen[f"constrained {m}, lean"],
                                                                   a=chosen[f"constrained {m}, lean"] * 1e-2))
             for m in args.methods.split(",")}
    rtol = chosen["constrained, as a user writes it"]
    first["as a user writes it"] = first_call_in_a_new_process(
        "import constrained as C; s = C.load_scene('scenarios/double_pendulum.toml'); "
        f"C.simulate(s.system, 2.0, rtol={rtol!r}, atol={rtol * 1e-2!r})")
    lines = ["| runner | rtol | end error [m] | fresh call [ms] | ratio | new m1, l2 each call [ms] "
             "| ratio | the same as plain numbers [ms] | ratio |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['runner']} | {r['rtol']:g} | {r['error']:.1e} | {r['fresh_ms']:.2f} | "
                     f"{r.get('fresh_ratio', float('nan')):.2f}× | {r['new_values_ms']:.2f} | "
                     f"{r.get('new_values_ratio', float('nan')):.2f}× | {r['new_plain_numbers_ms']:.2f} | "
                     f"{r.get('new_plain_numbers_ratio', float('nan')):.2f}× |")
    lines.append("")
    lines += [f"First call in a new process (import + load + run, cache warm), {m}: {1e3 * s:.0f} ms"
              for m, s in first.items()]
    table = "\n".join(lines)
    print(table)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "fresh_call.md").write_text(table + "\n")
        (args.out / "fresh_call.json").write_text(json.dumps({"rows": rows, "first_call_s": first}, indent=1))


if __name__ == "__main__":
    main()
