"""constrained against OpenMM on a polymer: rigid bonds and all-pairs soft repulsion (issue 28).

The problem, in SI units (a physical discretization: 1 cm links, 10 g beads): N beads of
10 g joined in a chain by rigid bonds of b = 1 cm (distance constraints); every pair of beads
not bonded repels with V(r) = ε (σ/r)¹², σ = 1 cm, ε = 1e-4 J (no cutoff); no gravity. The
chain starts as a self-avoiding random walk (no two beads closer than 0.9 b), the beads
moving at about 0.1 m/s, zero total momentum, velocities projected onto the bonds (the state
constrained starts from, given to both); run to T = 0.2 s (about two bond lengths of travel).

Error of a run: the largest distance between a bead's end position and the reference's, in
bond lengths. Reference: constrained's dopri at rtol = atol = 1e-12 (its agreement with
OpenMM's Reference platform at its smallest step is printed).

Peers (each run alternately, ``--repeats`` passes, the median kept):

- ``constrained`` dopri (DOP853, compiled step loop, warm: the compile is cached on disk and
  done before timing) at rtol = atol·100 swept over ``--rtols``; the pairs are one mapped
  kernel (``pairwise`` with ``exclude_bonded``).
- ``constrained-rattle`` (not by default): ``rattle`` at OpenMM's steps (``--steps``), its
  CPU time per step printed beside OpenMM Reference's (issue 28's goal 4: ≤ 1.5×).
- ``openmm-cpu`` / ``openmm-reference``: the same numbers in OpenMM's units (nm, ps, amu and
  kJ/mol form a consistent set: 1 kJ/mol = 1 amu nm² ps⁻²): ``addConstraint`` per bond,
  ``CustomNonbondedForce("eps*(sig/r)^12")`` with ``NoCutoff`` and the bonds excluded,
  ``VerletIntegrator`` (CCMA constraints, tolerance 1e-10), the CPU platform on one thread
  (single-precision forces) and the Reference platform (double); step swept over ``--steps``
  (numbers of steps to T), started from v(−dt/2) = v0 − dt/2 a0 (its leapfrog's velocities
  lag the positions by half a step). Context creation is the build, not timed with the run.

Times are CPU seconds of the call (``time.process_time``: both run on one thread), wall
seconds beside. The last table: each peer's cheapest run with error ≤ ``--target`` and the
ratio to OpenMM CPU. Measure on a quiet machine; a busy one inflates everything unevenly.

    python benchmarks/polymer.py                        # N = 100, target 1e-3
    python benchmarks/polymer.py --n 1000 --target 1e-5 --repeats 1
        [--rtols 1e-4 1e-5 ...] [--steps 250 500 ...] [--peers constrained,openmm-cpu,openmm-reference]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

MASS, BOND, SIGMA, EPSILON, SPEED, T_END = 0.01, 0.01, 0.01, 1e-4, 0.1, 0.2
EXPR = "eps*(sig/r)**12"


def start(n: int, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """(x0, v0) (n, 3): a self-avoiding random walk of bond BOND, random velocities of zero sum."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n, 3))
    for i in range(1, n):
        for _ in range(10_000):
            u = rng.normal(size=3)
            trial = x[i - 1] + BOND * u / np.linalg.norm(u)
            if i < 2 or np.min(np.linalg.norm(x[:i - 1] - trial, axis=1)) >= 0.9 * BOND:
                x[i] = trial
                break
        else:
            raise RuntimeError("the random walk could not be continued")
    v = rng.normal(0, SPEED / np.sqrt(3), (n, 3))
    return x, v - v.mean(axis=0)


def polymer(n: int):
    """The constrained System (start not yet projected)."""
    import constrained as C

    x, v = start(n)
    s = C.System(name=f"polymer of {n}", parameters={"eps": EPSILON, "sig": SIGMA})
    for i in range(n):
        s.add_particle(f"b{i}", MASS, x[i], v[i])
    for i in range(1, n):
        s.add(C.Distance(f"b{i - 1}", f"b{i}", length=BOND))
    s.add(C.Pairwise(EXPR, exclude_bonded=True))
    return s


def consistent(system, model):
    """The start both peers take: constrained's projection of the system's state."""
    from constrained.run.simulate import consistent_state

    x, v, _ = consistent_state(model, system.positions, system.velocities, 0.0, size=system.size())
    return x.reshape(-1, 3), v.reshape(-1, 3)


# --- runners: each returns (cpu s, wall s, (n, 3) end positions, steps) -----------------------
def run_constrained(system, model, x0, v0, rtol: float, compiled=True):
    import constrained as C

    s = system.with_state(x0, v0)
    cpu, wall = time.process_time(), time.perf_counter()
    tr = C.simulate(s, T_END, model=model, rtol=rtol, atol=rtol * 1e-2, t_eval=[0.0, T_END],
                    outputs=set(), compiled=compiled)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    return cpu, wall, tr.x[-1], int(tr.stats["steps"])


def run_rattle(system, model, x0, v0, steps: int):
    """constrained's ``rattle`` (RATTLE: Verlet with the bonds solved to ``newton_tol`` each
    step) at OpenMM's step, T / steps: issue 28's goal 4 compares its CPU time per step with
    OpenMM Reference's."""
    import constrained as C

    s = system.with_state(x0, v0)
    cpu, wall = time.process_time(), time.perf_counter()
    tr = C.simulate(s, T_END, model=model, method="rattle", dt=T_END / steps, t_eval=[0.0, T_END],
                    outputs=set())
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    return cpu, wall, tr.x[-1], int(tr.stats["steps"])


class OpenMM:
    """One OpenMM Context of the polymer on ``platform``, built once."""

    def __init__(self, n: int, platform: str, steps: int):
        import openmm

        self.openmm, self.steps = openmm, steps
        system = openmm.System()
        for _ in range(n):
            system.addParticle(MASS)
        for i in range(1, n):
            system.addConstraint(i - 1, i, BOND)
        force = openmm.CustomNonbondedForce("eps*(sig/r)^12")
        force.addGlobalParameter("eps", EPSILON)
        force.addGlobalParameter("sig", SIGMA)
        force.setNonbondedMethod(openmm.CustomNonbondedForce.NoCutoff)
        for _ in range(n):
            force.addParticle([])
        for i in range(1, n):
            force.addExclusion(i - 1, i)
        system.addForce(force)
        integrator = openmm.VerletIntegrator(T_END / steps)
        integrator.setConstraintTolerance(1e-10)
        properties = {"Threads": "1"} if platform == "CPU" else {}
        self.context = openmm.Context(system, integrator, openmm.Platform.getPlatformByName(platform),
                                      properties)
        self.integrator = integrator

    def run(self, x0, v0, a0):
        """From (x0, v0); OpenMM's Verlet is a leapfrog whose velocities are half a step behind
        the positions: it is given v(−dt/2) = v0 − dt/2 a0 (a0 with the constraint forces),
        which keeps it second order (v0 itself would make it first order)."""
        cpu, wall = time.process_time(), time.perf_counter()
        self.context.setTime(0.0)
        self.context.setPositions(x0)
        self.context.setVelocities(v0 - 0.5 * (T_END / self.steps) * a0)
        self.integrator.step(self.steps)
        x = self.context.getState(getPositions=True).getPositions(asNumpy=True)._value
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        return cpu, wall, np.asarray(x, float), self.steps


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=100)
    parser.add_argument("--target", type=float, default=1e-3, help="error goal, in bond lengths")
    parser.add_argument("--rtols", type=float, nargs="+", default=[1e-3, 1e-4, 1e-5, 1e-6, 1e-7])
    parser.add_argument("--steps", type=int, nargs="+",
                        default=[100, 200, 300, 400, 600, 800, 1200, 1600, 3200])
    parser.add_argument("--peers", default="constrained,openmm-cpu,openmm-reference",
                        help="also: constrained-rattle (RATTLE at OpenMM's steps, issue 28's goal 4)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    import constrained as C

    peers = args.peers.split(",")
    system = polymer(args.n)
    build = time.perf_counter()
    model = C.assemble(system)
    build = time.perf_counter() - build
    x0, v0 = consistent(system, model)
    from constrained.manifold.manifold import Manifold

    a0 = Manifold(model).accelerations(x0.ravel(), v0.ravel(), 0.0)[0].reshape(-1, 3)
    print(f"# polymer of {args.n} beads, {args.n - 1} rigid bonds, {args.n * (args.n - 1) // 2 - args.n + 1} "
          f"repelling pairs, T = {T_END} s; constrained build {build:.2f} s", file=sys.stderr)
    reference = run_constrained(system, model, x0, v0, 1e-12)[2]
    settings = []
    if "constrained" in peers:
        for rtol in args.rtols:
            run_constrained(system, model, x0, v0, rtol)  # warm: compiles once, then cached
            settings.append(("constrained dopri", f"rtol {rtol:g}",
                             lambda rtol=rtol: run_constrained(system, model, x0, v0, rtol)))
    if "constrained-rattle" in peers:
        for steps in args.steps:
            run_rattle(system, model, x0, v0, steps)  # warm: the step loop built once per structure
            settings.append(("constrained rattle", f"{steps} steps",
                             lambda steps=steps: run_rattle(system, model, x0, v0, steps)))
    for peer, platform in (("openmm-cpu", "CPU"), ("openmm-reference", "Reference")):
        if peer not in peers:
            continue
        try:
            import openmm  # noqa: F401
        except ImportError:
            print(f"# {peer}: skipped (pip install openmm, the bench extra)", file=sys.stderr)
            continue
        for steps in args.steps:
            built = time.perf_counter()
            runner = OpenMM(args.n, platform, steps)
            built = time.perf_counter() - built
            runner.run(x0, v0, a0)  # warm
            settings.append((peer, f"{steps} steps (build {built:.2f} s)",
                             lambda r=runner: r.run(x0, v0, a0)))
    results = {k: [] for k in range(len(settings))}
    for _ in range(args.repeats):  # alternating passes: load drifts hit every peer alike
        for k, (_, _, call) in enumerate(settings):
            results[k].append(call())
    print("| peer | setting | error (bond lengths) | CPU s | wall s | steps |\n|---|---|---|---|---|---|")
    best: dict[str, tuple] = {}
    for k, (peer, setting, _) in enumerate(settings):
        runs = results[k]
        cpu, wall = statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)
        error = float(np.max(np.linalg.norm(runs[0][2] - reference, axis=1)) / BOND)
        print(f"| {peer} | {setting} | {error:.2e} | {cpu:.4f} | {wall:.4f} | {runs[0][3]} |")
        if error <= args.target and (peer not in best or cpu < best[peer][0]):
            best[peer] = (cpu, setting, error)
        if peer == "openmm-reference" and setting.startswith(f"{max(args.steps)} "):
            print(f"# reference check: OpenMM Reference at {max(args.steps)} steps differs from "
                  f"constrained's reference by {error:.2e} bond lengths", file=sys.stderr)
    print(f"\ncheapest run with error <= {args.target:g} bond lengths:\n")
    print("| peer | setting | error | CPU s | CPU / OpenMM CPU |\n|---|---|---|---|---|")
    base = best.get("openmm-cpu", (None,))[0]
    for peer, (cpu, setting, error) in best.items():
        ratio = f"{cpu / base:.2f}" if base else "—"
        print(f"| {peer} | {setting} | {error:.1e} | {cpu:.4f} | {ratio} |")
    names = {"constrained": "constrained dopri", "constrained-rattle": "constrained rattle"}
    missing = [names.get(p, p) for p in peers if names.get(p, p) not in best]
    fixed = ("constrained rattle", "openmm-reference")
    steps = [k for k, (peer, _, _) in enumerate(settings) if peer in fixed]
    if steps:
        print("\nCPU time per step (median), RATTLE against OpenMM Reference at the same steps:\n")
        print("| peer | steps | CPU ms per step |\n|---|---|---|")
        for k in steps:
            runs = results[k]
            per_step = 1e3 * statistics.median(r[0] for r in runs) / runs[0][3]
            print(f"| {settings[k][0]} | {runs[0][3]} | {per_step:.3f} |")
    if missing:
        print(f"\n(no run reached the target: {', '.join(missing)}; widen --rtols / --steps)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
