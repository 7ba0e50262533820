"""constrained against peer libraries on planar pendulum chains, in one process run, alternating.

Problems (point masses on massless rigid links, pivot at the origin, gravity along −y):

- ``double``: the double pendulum of ``scenarios/double_pendulum.toml`` (1 kg, 1 m, 9.81 m/s²,
  released at rest from the scene's positions, θ ≈ 2.0 and 2.5 rad) to t = 2 s. Target: the
  cheapest run with end-position error ≤ 1e-9 m.
- ``chain``: the planar N-link chain (unit masses and links, every link at 0.5 rad from the
  vertical, at rest, g = 9.81) to t = 1 s, N from ``--n``. Target: error ≤ 1e-6 m.

The error of a run is the largest difference of the bobs' end positions (x, y in metres)
against a reference: ``constrained`` projection at rtol 1e-13 (double; cross-checked with
SciPy DOP853 at rtol 1e-13 on the angle ODE) or 1e-12 (chain; cross-checked with the NumPy
baseline at rtol 1e-12). Their agreement is printed with each table.

Peers (each reported as skipped, with the reason, when not installed):

- ``constrained`` — Cartesian coordinates + Lagrange multipliers; one row group per entry of
  ``--methods`` (``a:b`` is method ``a`` with ``base="b"``; adaptive methods get rtol and
  atol = rtol·1e-2, like every adaptive peer here). Build = ``constrained.assemble``.
- ``sympy`` — ``sympy.physics.mechanics.LagrangesMethod`` in absolute angles, lambdify (cse),
  SciPy DOP853 on M(y) ẏ = F(y). Build = derivation + lambdify.
- ``pydy-lambdify`` / ``pydy-cython`` — ``KanesMethod`` (u = θ') turned into a right-hand side
  by ``pydy.codegen.ode_function_generators.generate_ode_function`` (lambdify or Cython
  backend), SciPy DOP853. Build = derivation + code generation (+ C compilation).
- ``exudyn-tree-dopri5`` / ``exudyn-tree-rk67`` — ``ObjectKinematicTree`` of RevoluteZ joints
  (relative angles), point mass 1 at (0, −1, 0) of each link, zero link inertia; exudyn's
  explicit DOPRI5 (adaptive, rtol sweep) and RK67 (fixed steps).
- ``exudyn-ga-dense`` / ``exudyn-ga-sparse`` — ``NodePoint2D`` + ``ObjectMassPoint2D`` masses
  held by ``ObjectConnectorDistance`` constraints (redundant coordinates, index 3),
  generalized-α (ρ∞ = 0.9, exudyn's default; Newton tolerance 1e-10) with the dense
  (``EXUdense``) or sparse (``EigenSparse``) linear solver; fixed-step sweep.
- ``mujoco-rk4`` — MJCF chain of hinge joints (relative angles), each body a point mass 1 at
  (0, −1, 0) with inertia 1e-12 kg·m² (MuJoCo refuses zero inertia; 1e-12 of the pendulum's
  m·l² = 1), no geoms, contacts disabled, no damping/armature; ``integrator="RK4"``,
  timestep sweep; ``mj_step(m, d, nstep)`` in one call.
- ``numpy`` — hand-vectorized baseline in absolute angles θ_i: M(θ) θ'' = −C(θ) θ'² − g c sin θ
  solved densely, SciPy DOP853.

Timing: every peer is built once per problem size (build time reported separately), warmed
up once at its coarsest setting (constrained: once at every setting, as it compiles per
step size for some methods), then ``--repeats`` passes run every (peer, setting) in turn,
so that load drifts hit all peers alike; the median is reported. "sim wall" is the wall time of the call that
simulates a built model from its initial state to t_end (for constrained the whole
``simulate(..., model=...)`` call, which includes projecting the initial state; the solver
loop alone is in the notes column). A peer whose runs at a size would take more than
``--budget`` seconds (predicted from its previous size or setting) is skipped there, and so
are the peers whose derivation explodes (sympy above N = 16, pydy above N = 32); each skip
is printed. Fixed-step peers take n = round(t_end / dt) steps of exactly t_end / n.

Peak memory: each (peer, size) is run once more, at the setting shown, in a fresh
subprocess (tracemalloc cannot see C/C++ allocations). That process imports what the peer
needs, resets the kernel's peak-RSS counter (writing 5 to /proc/self/clear_refs), builds
and runs. "peak RSS" is the process's VmHWM (interpreter + imports + build + run) and "Δ" is
VmHWM after the run minus VmRSS at the reset, i.e. the peak that the build and run added on
top of the imports. (``ru_maxrss`` is not used: Linux carries the parent's peak RSS into a
child across fork + exec, so it reads the benchmark process's size.)

    python benchmarks/peers.py --problems double
    python benchmarks/peers.py --problems chain --n 8 32 128 256 --repeats 3
        [--peers constrained,numpy,sympy,pydy,exudyn,mujoco] [--methods projection,projection:CVODES]
        [--rtols ...] [--budget 60] [--blas-threads 1] [--no-memory] [--quick] [--json PATH]

Every peer runs with one BLAS thread (``--blas-threads``; MuJoCo, Exudyn and CasADi are
single-threaded here anyway): on a shared 2-core machine a multithreaded OpenBLAS
spin-waits for the busy core, which made single runs of the NumPy baseline 30× slower.

Tables (markdown) go to stdout, progress to stderr.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
DOUBLE_SCENE = ROOT / "scenarios" / "double_pendulum.toml"

G, BEND, T_END = 9.81, 0.5, 1.0
LEVELS = (1e-3, 1e-6, 1e-9)
MAX_N = {"sympy": 16, "pydy": 32}  # derivation time explodes beyond (measured: see the module doc)


def _constrained():
    """constrained, imported on first use (so that a memory probe of another peer does not load it)."""
    return importlib.import_module("constrained")


# --------------------------------------------------------------------------------------------
# Problems


@dataclass(frozen=True)
class Problem:
    kind: str  # "double" | "chain"
    n: int
    theta0: tuple  # absolute angles from the downward vertical [rad]
    omega0: tuple  # their rates [rad/s]
    t_end: float
    target: float  # the error level the comparison is about [m]

    def system(self):
        """The constrained System: the scene file for the double pendulum, chain(n) otherwise."""
        if self.kind == "double":
            return _constrained().load_scene(DOUBLE_SCENE).system
        return chain(self.n)

    def positions(self, theta) -> np.ndarray:
        return angles_to_xy(theta)

    def to_json(self) -> dict:
        return asdict(self)


def angles_to_xy(theta) -> np.ndarray:
    """(n, 2) bob positions of a chain of unit links at absolute angles theta."""
    theta = np.asarray(theta, float)
    return np.stack([np.cumsum(np.sin(theta)), -np.cumsum(np.cos(theta))], axis=1)


def xy_to_angles(x, v) -> tuple[np.ndarray, np.ndarray]:
    """Absolute link angles and rates of a planar chain from its (n, ≥2) positions/velocities."""
    x = np.asarray(x, float)[:, :2]
    v = np.asarray(v, float)[:, :2]
    d = np.diff(np.vstack([np.zeros(2), x]), axis=0)
    dv = np.diff(np.vstack([np.zeros(2), v]), axis=0)
    theta = np.arctan2(d[:, 0], -d[:, 1])
    omega = (d[:, 0] * dv[:, 1] - d[:, 1] * dv[:, 0]) / np.sum(d * d, axis=1)
    return theta, omega


def chain(n: int):
    C = _constrained()
    s = C.System(name=f"{n}-link chain")
    for i in range(n):
        s.add_particle(f"p{i}", 1.0, [(i + 1) * np.sin(BEND), -(i + 1) * np.cos(BEND), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=1.0))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=1.0))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -G, 0]))
    return s


def chain_problem(n: int) -> Problem:
    return Problem("chain", n, (BEND,) * n, (0.0,) * n, T_END, 1e-6)


def double_problem(t_end: float = 2.0) -> Problem:
    """The scene's double pendulum, started from exactly the state constrained starts from.

    The scene gives positions to 10 decimals; constrained projects them onto the rods (a
    change of ~4e-11 m). The angles are taken from that projected state, so that every peer
    integrates the same initial condition.
    """
    C = _constrained()
    from constrained.run.simulate import consistent_state

    system = C.load_scene(DOUBLE_SCENE).system
    model = C.assemble(system)
    x, v, _ = consistent_state(model, system.positions, system.velocities, 0.0, size=system.size())
    theta, omega = xy_to_angles(x.reshape(-1, 3), v.reshape(-1, 3))
    return Problem("double", len(theta), tuple(map(float, theta)), tuple(map(float, omega)), t_end, 1e-9)


# --------------------------------------------------------------------------------------------
# The peers' runners. Each run returns (wall [s], (n, 2) end positions, notes dict).


def constrained_run(system, t_end: float, method: str = "projection", rtol: float = 1e-8, model=None,
                    **options):
    """Simulate ``system`` with constrained's ``method`` (``"a:b"`` = method a, base b) to t_end.

    Returns (wall time of the whole ``simulate`` call [s], (N, 3) end positions, stats).
    ``atol`` defaults to rtol·1e-2; other ``options`` go to ``simulate`` (e.g. dt). Raises
    constrained's InputError when the method (or an option) is unknown.
    """
    C = _constrained()
    name, _, base = method.partition(":")
    if base:
        options.setdefault("base", base)
    options.setdefault("atol", rtol * 1e-2)
    start = time.perf_counter()
    tr = C.simulate(system, t_end, method=name, rtol=rtol, model=model, t_eval=[0.0, t_end],
                    outputs=set(), **options)
    wall = time.perf_counter() - start
    return wall, np.asarray(tr.x[-1]), dict(tr.stats)


def numpy_rhs(n: int):
    """ẏ for y = (θ, θ'): angles from the vertical; c_ij = n − max(i, j) particles hang below both links."""
    idx = np.arange(n)
    c = n - np.maximum.outer(idx, idx)
    ci = n - idx

    def rhs(t, y):
        th, w = y[:n], y[n:]
        d = th[:, None] - th[None, :]
        M = c * np.cos(d)
        b = -(c * np.sin(d)) @ (w * w) - G * ci * np.sin(th)
        return np.concatenate([w, np.linalg.solve(M, b)])

    return rhs


def numpy_chain(n: int, rtol: float, theta0=None, omega0=None, t_end: float = T_END):
    """The NumPy baseline (see ``numpy_rhs``) with SciPy DOP853; returns (wall, (3n,) end positions)."""
    rhs = numpy_rhs(n)
    theta0 = np.full(n, BEND) if theta0 is None else np.asarray(theta0, float)
    omega0 = np.zeros(n) if omega0 is None else np.asarray(omega0, float)
    y0 = np.concatenate([theta0, omega0])
    start = time.perf_counter()
    sol = solve_ivp(rhs, (0.0, t_end), y0, method="DOP853", rtol=rtol, atol=rtol * 1e-2, t_eval=[t_end])
    wall = time.perf_counter() - start
    th = sol.y[:n, -1]
    pos = np.stack([np.cumsum(np.sin(th)), -np.cumsum(np.cos(th)), np.zeros(n)], axis=1)
    return wall, pos.ravel()


def fixed_steps(problem: Problem, dt: float) -> int:
    """Number of fixed steps for step size ``dt``: they are then t_end / n each, landing on t_end."""
    return max(1, int(round(problem.t_end / dt)))


def _dop853(rhs, problem: Problem, rtol: float):
    y0 = np.concatenate([problem.theta0, problem.omega0])
    start = time.perf_counter()
    sol = solve_ivp(rhs, (0.0, problem.t_end), y0, method="DOP853", rtol=rtol, atol=rtol * 1e-2,
                    t_eval=[problem.t_end])
    wall = time.perf_counter() - start
    if not sol.success:
        raise RuntimeError(sol.message)
    return wall, angles_to_xy(sol.y[: problem.n, -1]), {"nfev": int(sol.nfev)}


def _chain_mechanics(n: int, *, kane: bool):
    """sympy.physics.mechanics model of the chain in absolute angles q_i; bob i hangs at
    P_{i−1} + (sin q_i, −cos q_i). Returns (q, u, method object, gravity symbol)."""
    import sympy as sm
    import sympy.physics.mechanics as me

    g = sm.Symbol("g")
    q = me.dynamicsymbols(f"q0:{n}")
    N = me.ReferenceFrame("N")
    O = me.Point("O")
    O.set_vel(N, 0)
    prev, particles, loads = O, [], []
    if kane:
        u = me.dynamicsymbols(f"u0:{n}")
        for i in range(n):
            P = prev.locatenew(f"P{i}", sm.sin(q[i]) * N.x - sm.cos(q[i]) * N.y)
            P.set_vel(N, prev.vel(N) + u[i] * (sm.cos(q[i]) * N.x + sm.sin(q[i]) * N.y))
            particles.append(me.Particle(f"m{i}", P, 1))
            loads.append((P, -g * N.y))
            prev = P
        km = me.KanesMethod(N, q_ind=q, u_ind=u, kd_eqs=[q[i].diff() - u[i] for i in range(n)])
        km.kanes_equations(particles, loads)
        return q, u, km, g
    for i in range(n):
        P = prev.locatenew(f"P{i}", sm.sin(q[i]) * N.x - sm.cos(q[i]) * N.y)
        P.set_vel(N, P.pos_from(O).dt(N))
        particle = me.Particle(f"m{i}", P, 1)
        particle.potential_energy = g * P.pos_from(O).dot(N.y)
        particles.append(particle)
        prev = P
    lm = me.LagrangesMethod(me.Lagrangian(N, *particles), q)
    lm.form_lagranges_equations()
    return q, [qi.diff() for qi in q], lm, g


# --------------------------------------------------------------------------------------------
# Peers


class Peer:
    name = ""
    group = ""
    label = ""
    requires: tuple[str, ...] = ()
    kind = "rtol"  # "rtol" (adaptive) or "dt" (fixed step)
    exponent = 3.0  # assumed growth of a run's cost with N, to predict the next size
    max_n: int | None = None
    warm_each_setting = False

    def available(self) -> str | None:
        """None when usable, else why not."""
        for module in self.requires:
            if importlib.util.find_spec(module) is None:
                return f"not installed (no module {module!r})"
        return None

    def settings(self, problem: Problem, args) -> list[float]:
        if self.kind == "rtol":
            if args.rtols:
                return list(args.rtols)
            if problem.kind == "double":
                return [1e-8, 1e-10, 1e-12] if args.quick else [1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13]
            return [1e-6] if args.quick else [1e-4, 1e-5, 1e-6, 1e-7, 1e-8]
        steps = self.steps(problem)
        return steps[:: max(1, len(steps) // 2)] if args.quick else steps

    def steps(self, problem: Problem) -> list[float]:
        return []

    def describe(self, value: float) -> str:
        return f"rtol {value:g}" if self.kind == "rtol" else f"dt {value:g}"

    def build(self, problem: Problem):
        raise NotImplementedError

    def run(self, built, problem: Problem, value: float):
        raise NotImplementedError


class ConstrainedPeer(Peer):
    group = "constrained"
    requires = ("casadi",)
    exponent = 1.0
    warm_each_setting = True

    def __init__(self, method: str):
        self.method = method
        self.name = f"constrained:{method}"
        self.label = f"constrained {method}"
        from constrained.solvers import METHODS  # fixed-step methods (rattle) get a dt sweep

        solver = METHODS.get(method.partition(":")[0])
        self.kind = "dt" if solver is not None and not getattr(solver, "adaptive", True) else "rtol"

    def steps(self, problem):
        return [1e-2, 1e-3, 1e-4] if problem.kind == "double" else [1e-2, 2.5e-3, 1e-3]

    def build(self, problem):
        C = _constrained()
        system = problem.system()
        return system, C.assemble(system)

    def run(self, built, problem, value):
        system, model = built
        if self.kind == "dt":
            wall, x, stats = constrained_run(system, problem.t_end, self.method, model=model,
                                             dt=problem.t_end / fixed_steps(problem, value))
        else:
            wall, x, stats = constrained_run(system, problem.t_end, self.method, value, model)
        notes = {"solver_s": stats.get("wall_time_s"), "steps": stats.get("steps")}
        return wall, x[:, :2], notes


class NumpyPeer(Peer):
    name = group = "numpy"
    label = "NumPy angles + DOP853"

    def build(self, problem):
        return None

    def run(self, built, problem, rtol):
        wall, pos = numpy_chain(problem.n, rtol, problem.theta0, problem.omega0, problem.t_end)
        return wall, pos.reshape(-1, 3)[:, :2], {}


class SympyPeer(Peer):
    name = group = "sympy"
    label = "SymPy LagrangesMethod + lambdify + DOP853"
    requires = ("sympy",)
    max_n = MAX_N["sympy"]

    def build(self, problem):
        import sympy as sm

        q, qd, lm, g = _chain_mechanics(problem.n, kane=False)
        state = list(q) + list(qd)
        values = {g: G}
        fM = sm.lambdify([state], lm.mass_matrix_full.subs(values), "numpy", cse=True)
        fF = sm.lambdify([state], lm.forcing_full.subs(values), "numpy", cse=True)

        def rhs(t, y):
            return np.linalg.solve(np.asarray(fM(y), float), np.asarray(fF(y), float).ravel())

        return rhs

    def run(self, rhs, problem, rtol):
        return _dop853(rhs, problem, rtol)


class PydyPeer(Peer):
    group = "pydy"
    max_n = MAX_N["pydy"]

    def __init__(self, backend: str):
        self.backend = backend
        self.name = f"pydy-{backend}"
        self.label = f"PyDy KanesMethod + {backend} + DOP853"
        self.requires = ("sympy", "pydy") + (("Cython",) if backend == "cython" else ())

    def build(self, problem):
        from pydy.codegen.ode_function_generators import generate_ode_function

        q, u, km, g = _chain_mechanics(problem.n, kane=True)
        f = generate_ode_function(km.forcing_full, q, u, constants=[g], mass_matrix=km.mass_matrix_full,
                                  generator=self.backend)
        p = np.array([G])
        return lambda t, y: f(y, t, p)

    def run(self, rhs, problem, rtol):
        return _dop853(rhs, problem, rtol)


def _exudyn_settings(exu, t_end: float):
    s = exu.SimulationSettings()
    s.timeIntegration.endTime = t_end
    s.timeIntegration.verboseMode = 0
    s.solution.file.write = False
    s.solution.sensors.active = False
    s.show.computationTime = False
    s.show.statistics = False
    return s


class ExudynTreePeer(Peer):
    group = "exudyn"
    requires = ("exudyn",)

    def __init__(self, solver: str):
        self.solver = solver
        self.name = f"exudyn-tree-{solver.lower()}"
        self.kind = "rtol" if solver == "DOPRI5" else "dt"
        self.label = f"Exudyn KinematicTree + {solver}"

    def steps(self, problem):
        return [1e-2, 2.5e-3, 1e-3]

    def build(self, problem):
        import exudyn as exu
        from exudyn.itemInterface import NodeGenericODE2, ObjectKinematicTree

        n = problem.n
        rel = np.diff(np.concatenate([[0.0], problem.theta0]))  # joint angles are relative
        rel_rate = np.diff(np.concatenate([[0.0], problem.omega0]))
        sc = exu.SystemContainer()
        mbs = sc.AddSystem()
        node = mbs.AddNode(NodeGenericODE2(referenceCoordinates=[0.0] * n, initialCoordinates=list(rel),
                                           initialCoordinates_t=list(rel_rate), numberOfODE2Coordinates=n))
        mbs.AddObject(ObjectKinematicTree(
            nodeNumber=node, jointTypes=[exu.JointType.RevoluteZ] * n, linkParents=list(range(-1, n - 1)),
            jointTransformations=exu.Matrix3DList([np.eye(3)] * n),
            jointOffsets=exu.Vector3DList([[0.0, 0.0, 0.0]] + [[0.0, -1.0, 0.0]] * (n - 1)),
            linkInertiasCOM=exu.Matrix3DList([np.zeros((3, 3))] * n),
            linkCOMs=exu.Vector3DList([[0.0, -1.0, 0.0]] * n), linkMasses=[1.0] * n, gravity=[0.0, -G, 0.0]))
        mbs.Assemble()
        return sc, mbs, node

    def run(self, built, problem, value):
        import exudyn as exu

        sc, mbs, node = built
        s = _exudyn_settings(exu, problem.t_end)
        ti = s.timeIntegration
        if self.kind == "rtol":
            ti.automaticStepSize = True
            ti.relativeTolerance, ti.absoluteTolerance = value, value * 1e-2
            ti.numberOfSteps = 10  # caps the step at t_end / 10
        else:
            ti.automaticStepSize = False
            ti.numberOfSteps = fixed_steps(problem, value)
        solver = getattr(exu.DynamicSolverType, self.solver)
        start = time.perf_counter()
        exu.SolveDynamic(mbs, s, solverType=solver)
        wall = time.perf_counter() - start
        q = np.asarray(mbs.GetNodeOutput(node, exu.OutputVariableType.Coordinates), float)
        return wall, angles_to_xy(np.cumsum(q)), {}


class ExudynPointsPeer(Peer):
    group = "exudyn"
    requires = ("exudyn",)
    kind = "dt"

    def __init__(self, sparse: bool):
        self.sparse = sparse
        self.name = f"exudyn-ga-{'sparse' if sparse else 'dense'}"
        self.label = f"Exudyn points + distance, gen.-α, {'EigenSparse' if sparse else 'EXUdense'}"
        self.exponent = 1.0 if sparse else 3.0

    def steps(self, problem):
        if problem.kind == "double":
            return [1e-2, 1e-3, 1e-4, 1e-5, 2.5e-6]
        return [1e-2, 1e-3, 2.5e-4, 1e-4]

    def build(self, problem):
        import exudyn as exu
        from exudyn.itemInterface import (
            LoadForceVector,
            MarkerBodyPosition,
            MarkerNodePosition,
            NodePoint2D,
            ObjectConnectorDistance,
            ObjectGround,
            ObjectMassPoint2D,
        )

        sc = exu.SystemContainer()
        mbs = sc.AddSystem()
        ground = mbs.AddObject(ObjectGround(referencePosition=[0.0, 0.0, 0.0]))
        prev = mbs.AddMarker(MarkerBodyPosition(bodyNumber=ground, localPosition=[0.0, 0.0, 0.0]))
        xy = angles_to_xy(problem.theta0)
        th, om = np.asarray(problem.theta0), np.asarray(problem.omega0)
        vxy = np.cumsum(np.stack([om * np.cos(th), om * np.sin(th)], axis=1), axis=0)
        nodes = []
        for i in range(problem.n):
            node = mbs.AddNode(NodePoint2D(referenceCoordinates=list(xy[i]), initialCoordinates=[0.0, 0.0],
                                           initialVelocities=list(vxy[i])))
            mbs.AddObject(ObjectMassPoint2D(mass=1.0, nodeNumber=node))
            marker = mbs.AddMarker(MarkerNodePosition(nodeNumber=node))
            mbs.AddLoad(LoadForceVector(markerNumber=marker, loadVector=[0.0, -G, 0.0]))
            mbs.AddObject(ObjectConnectorDistance(markerNumbers=[prev, marker], distance=1.0))
            prev = marker
            nodes.append(node)
        mbs.Assemble()
        return sc, mbs, nodes

    def run(self, built, problem, dt):
        import exudyn as exu

        sc, mbs, nodes = built
        s = _exudyn_settings(exu, problem.t_end)
        s.timeIntegration.numberOfSteps = fixed_steps(problem, dt)
        s.timeIntegration.generalizedAlpha.spectralRadius = 0.9
        s.timeIntegration.newton.relativeTolerance = 1e-10
        s.timeIntegration.newton.absoluteTolerance = 1e-12
        s.linearSolver.solverType = (exu.LinearSolverType.EigenSparse if self.sparse
                                     else exu.LinearSolverType.EXUdense)
        start = time.perf_counter()
        exu.SolveDynamic(mbs, s, solverType=exu.DynamicSolverType.GeneralizedAlpha)
        wall = time.perf_counter() - start
        xy = np.array([mbs.GetNodeOutput(nd, exu.OutputVariableType.Position)[:2] for nd in nodes])
        return wall, xy, {}


class MujocoPeer(Peer):
    name = "mujoco-rk4"
    group = "mujoco"
    label = "MuJoCo hinge chain + RK4"
    requires = ("mujoco",)
    kind = "dt"
    exponent = 2.0
    INERTIA = 1e-12  # MuJoCo requires inertia > mjMINVAL; 1e-12 of m l² = 1

    def steps(self, problem):
        if problem.kind == "double":
            return [1e-2, 2.5e-3, 1e-3, 2.5e-4, 1e-4]
        return [1e-2, 2.5e-3, 1e-3]

    @classmethod
    def mjcf(cls, n: int) -> str:
        body, inertia = "", f"{cls.INERTIA:g}"
        for i in reversed(range(n)):
            pos = "0 0 0" if i == 0 else "0 -1 0"
            body = (f'<body name="b{i}" pos="{pos}"><joint name="j{i}" type="hinge" axis="0 0 1"/>'
                    f'<inertial pos="0 -1 0" mass="1" diaginertia="{inertia} {inertia} {inertia}"/>'
                    f"{body}</body>")
        return (f'<mujoco><compiler angle="radian"/><option timestep="0.001" integrator="RK4" '
                f'gravity="0 {-G} 0"><flag contact="disable"/></option>'
                f"<worldbody>{body}</worldbody></mujoco>")

    def build(self, problem):
        import mujoco

        m = mujoco.MjModel.from_xml_string(self.mjcf(problem.n))
        return m, mujoco.MjData(m)

    def run(self, built, problem, dt):
        import mujoco

        m, d = built
        mujoco.mj_resetData(m, d)
        nstep = fixed_steps(problem, dt)
        m.opt.timestep = problem.t_end / nstep
        d.qpos[:] = np.diff(np.concatenate([[0.0], problem.theta0]))  # hinge angles are relative
        d.qvel[:] = np.diff(np.concatenate([[0.0], problem.omega0]))
        start = time.perf_counter()
        mujoco.mj_step(m, d, nstep)
        wall = time.perf_counter() - start
        mujoco.mj_kinematics(m, d)  # positions of the end state (mj_step leaves them one step behind)
        return wall, d.xipos[1:, :2].copy(), {}


def make_peers(methods) -> list[Peer]:
    return [*(ConstrainedPeer(m) for m in methods), SympyPeer(), PydyPeer("lambdify"), PydyPeer("cython"),
            ExudynTreePeer("DOPRI5"), ExudynTreePeer("RK67"), ExudynPointsPeer(False), ExudynPointsPeer(True),
            MujocoPeer(), NumpyPeer()]


# --------------------------------------------------------------------------------------------
# Reference, memory probe


def reference(problem: Problem):
    """(end positions (n, 2), note) — constrained at a tight tolerance, cross-checked."""
    C = _constrained()
    if problem.kind == "double":
        tr = C.simulate(problem.system(), problem.t_end, rtol=1e-13, atol=1e-13, t_eval=[0.0, problem.t_end],
                        outputs=set())
        ref = np.asarray(tr.x[-1])[:, :2]
        _, check, _ = _dop853(numpy_rhs(problem.n), problem, 1e-13)
        agree = float(np.max(np.abs(check - ref)))
        exact = Problem("double", 2, (2.0, 2.5), (0.0, 0.0), problem.t_end, problem.target)
        _, moved, _ = _dop853(numpy_rhs(2), exact, 1e-13)
        shift = float(np.max(np.abs(moved - check)))
        theta = ", ".join(f"{t:.13f}" for t in problem.theta0)
        note = [f"reference: constrained projection at rtol = atol = 1e-13 on the scene; SciPy DOP853 on the "
                f"angle ODE at rtol 1e-13 agrees within {agree:.1e} m",
                f"initial angles from the scene's positions as constrained projects them: θ = ({theta}) rad; "
                f"starting from the [reduced] table's exact 2.0, 2.5 instead moves the "
                f"t = {problem.t_end:g} s positions by {shift:.1e} m"]
        return ref, note, agree
    tr = C.simulate(problem.system(), problem.t_end, rtol=1e-12, atol=1e-14, t_eval=[0.0, problem.t_end],
                    outputs=set(), compiled=False)
    ref = np.asarray(tr.x[-1])[:, :2]
    _, pos = numpy_chain(problem.n, 1e-12, problem.theta0, problem.omega0, problem.t_end)
    agree = float(np.max(np.abs(pos.reshape(-1, 3)[:, :2] - ref)))
    return ref, [f"reference: constrained projection at rtol 1e-12 (atol 1e-14); the NumPy baseline at "
                 f"rtol 1e-12 agrees within {agree:.1e} m"], agree


def _status_mb() -> dict:
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0]) / 1024
    return out


def probe(spec: dict) -> dict:
    """In a fresh process: import the peer's modules, reset the peak-RSS counter, build, run once."""
    problem = Problem(**{k: tuple(v) if isinstance(v, list) else v for k, v in spec["problem"].items()})
    peer = {p.name: p for p in make_peers([spec["peer"].partition(":")[2]] if spec["peer"].startswith(
        "constrained:") else [])}[spec["peer"]]
    for module in peer.requires:
        importlib.import_module(module)
    if isinstance(peer, ConstrainedPeer):
        _constrained()
    elif peer.group in ("sympy", "pydy"):
        import sympy.physics.mechanics  # noqa: F401
    imports = _status_mb()  # VmHWM so far: interpreter + imports (exec starts a fresh counter)
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # VmHWM := VmRSS, so that the next VmHWM is the build's and run's own peak
        method = "VmHWM reset via /proc/self/clear_refs"
    except OSError:
        method = "VmHWM (not resettable here: Δ is a lower bound)"
    before = _status_mb()
    built = peer.build(problem)
    peer.run(built, problem, spec["value"])
    after = _status_mb()
    return {"peak_rss_mb": max(imports["VmHWM"], after["VmHWM"]), "imports_rss_mb": before["VmRSS"],
            "delta_mb": max(0.0, after["VmHWM"] - before["VmRSS"]), "method": method}


def run_probe(problem: Problem, peer: Peer, value: float, timeout: float = 900) -> dict:
    spec = json.dumps({"problem": problem.to_json(), "peer": peer.name, "value": value})
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--_probe", spec],
                          capture_output=True, text=True, timeout=timeout, cwd=str(ROOT),
                          env={**os.environ, "PYTHONPATH": path})
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode or not lines:
        raise RuntimeError((proc.stderr.strip().splitlines() or ["no output"])[-1][:200])
    return json.loads(lines[-1])


# --------------------------------------------------------------------------------------------
# The measurement


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def level_of(error: float) -> float | None:
    met = [lv for lv in LEVELS if error <= lv]
    return min(met) if met else None


def measure(problem: Problem, peers: list[Peer], args, history: dict) -> dict:
    """Build, warm up and time every peer on ``problem``; ``history`` carries predictions across sizes."""
    section = {"problem": problem.kind, "n": problem.n, "t_end": problem.t_end, "target": problem.target,
               "notes": [], "skipped": [], "rows": []}
    log(f"== {problem.kind} N = {problem.n}: reference")
    ref, notes, agree = reference(problem)
    section["notes"] += notes
    section["reference_agreement"] = agree
    budget = args.budget
    live = []  # [peer, built, build_s, settings]
    for peer in peers:
        if peer.max_n is not None and problem.n > peer.max_n:
            section["skipped"].append(f"{peer.name}: N = {problem.n} > {peer.max_n}, its symbolic derivation "
                                      "alone would take minutes")
            continue
        prev = history.get(peer.name)
        if prev is not None:
            guess = prev["t"] * (problem.n / prev["n"]) ** peer.exponent * args.repeats
            if guess > budget:
                section["skipped"].append(
                    f"{peer.name}: predicted {guess:.0f} s for its coarsest setting × {args.repeats} repeats "
                    f"(from {prev['t']:.2f} s at N = {prev['n']}, cost ∝ N^{peer.exponent:g}) > budget "
                    f"{budget:g} s")
                continue
        log(f"   build {peer.name}")
        try:
            start = time.perf_counter()
            built = peer.build(problem)
            build_s = time.perf_counter() - start
        except Exception as exc:  # a peer that cannot build is reported, not fatal
            section["skipped"].append(f"{peer.name}: build failed: {_one_line(exc)}")
            continue
        values = peer.settings(problem, args)
        try:  # warm-up: one-time costs stay out of the medians
            wall, _, _ = peer.run(built, problem, values[0])
            if peer.warm_each_setting and wall < 1.0:  # slower runs dwarf one-time costs anyway
                for value in values[1:]:
                    peer.run(built, problem, value)
        except Exception as exc:
            section["skipped"].append(f"{peer.name}: {_one_line(exc)}")
            continue
        history[peer.name] = {"n": problem.n, "t": wall}  # replaced by the coarsest setting's median below
        live.append([peer, built, build_s, values])

    results = {(p.name, v): {"walls": [], "error": None, "notes": {}} for p, _, _, vs in live for v in vs}
    dropped = set()
    for rep in range(args.repeats):
        log(f"   repeat {rep + 1}/{args.repeats}")
        for entry in live:  # alternate: every peer and setting once per pass
            peer, built, _, values = entry
            spent = 0.0
            for k, value in enumerate(list(values)):
                if (peer.name, value) in dropped:
                    continue
                try:
                    wall, xy, info = peer.run(built, problem, value)
                except Exception as exc:
                    res = results[(peer.name, value)]
                    res["failed"] = _one_line(exc)
                    dropped.add((peer.name, value))
                    continue
                res = results[(peer.name, value)]
                res["walls"].append(wall)
                res["error"] = float(np.max(np.abs(np.asarray(xy)[:, :2] - ref)))
                res["notes"] = info
                if info.get("solver_s") is not None:
                    res.setdefault("solver_s", []).append(info["solver_s"])
                if rep:
                    continue
                spent += wall * args.repeats
                if wall * args.repeats > budget:
                    dropped.add((peer.name, value))  # measured once, not repeated
                if k + 1 < len(values):
                    nxt = values[k + 1]
                    ratio = value / nxt if peer.kind == "dt" else 1.6
                    if spent + wall * ratio * args.repeats > budget:
                        rest = values[k + 1:]
                        for v in rest:
                            dropped.add((peer.name, v))
                            results.pop((peer.name, v), None)
                        entry[3] = values[: k + 1]
                        section["skipped"].append(
                            f"{peer.name}: {', '.join(peer.describe(v) for v in rest)} not run — predicted "
                            f"{spent + wall * ratio * args.repeats:.0f} s > budget {budget:g} s at this size")
                        break

    for peer, _, build_s, values in live:
        for value in values:
            res = results.get((peer.name, value))
            if res is None:
                continue
            row = {"peer": peer.name, "group": peer.group, "label": peer.label,
                   "setting": peer.describe(value), "kind": peer.kind, "value": value, "build_s": build_s}
            if not res["walls"]:
                row.update(status=f"failed: {res.get('failed', '?')}")
            else:
                row.update(status="ok", wall_s=statistics.median(res["walls"]), walls_s=res["walls"],
                           repeats=len(res["walls"]), requested_repeats=args.repeats, error=res["error"],
                           notes={**res["notes"], **({"solver_s": statistics.median(res["solver_s"]),
                                                       "solver_walls_s": res["solver_s"]}
                                                      if res.get("solver_s") else {})})
            section["rows"].append(row)
    for peer, _, _, values in live:  # predictions for the next size: the coarsest setting's median
        walls = results.get((peer.name, values[0]), {}).get("walls")
        if walls:
            history[peer.name] = {"n": problem.n, "t": statistics.median(walls)}
    ok = [r for r in section["rows"] if r["status"] == "ok"]
    for row in ok:
        row["level"] = level_of(row["error"])
        if row["level"] is not None:
            best = min(r["wall_s"] for r in ok if r["error"] <= row["level"])
            row["ratio"] = row["wall_s"] / best

    if args.memory:
        for peer, _, _, _ in live:
            rows = [r for r in ok if r["peer"] == peer.name]
            if not rows:
                continue
            hit = [r for r in rows if r["error"] <= problem.target]
            row = min(hit, key=lambda r: r["wall_s"]) if hit else min(rows, key=lambda r: r["error"])
            log(f"   memory {peer.name} at {row['setting']}")
            try:
                row["memory"] = run_probe(problem, peer, row["value"])
            except Exception as exc:
                row["memory"] = {"error": _one_line(exc)}
    return section


def _one_line(exc) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0][:160] if text else ''}"


# --------------------------------------------------------------------------------------------
# Output


def versions() -> dict:
    out = {"python": platform.python_version()}
    for module in ("numpy", "scipy", "casadi", "sympy", "pydy", "Cython", "exudyn", "mujoco"):
        try:
            out[module] = importlib.import_module(module).__version__
        except Exception:
            out[module] = None
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    out["machine"] = f"{cpu}, {os.cpu_count()} logical CPUs, {platform.system()} {platform.release()}"
    return out


def _mem(row) -> str:
    mem = row.get("memory")
    if not mem:
        return ""
    if "error" in mem:
        return f"probe failed ({mem['error'][:60]})"
    return f"{mem['peak_rss_mb']:.0f} (+{mem['delta_mb']:.1f})"


def _err(row, agree: float) -> str:
    if row["error"] < agree:
        return f"< {agree:.0e} (ref.)"
    return f"{row['error']:.1e}"


def _notes(row) -> str:
    notes = row.get("notes") or {}
    parts = []
    if notes.get("solver_s") is not None:
        parts.append(f"solver loop {notes['solver_s']:.4f} s (median), {notes.get('steps')} steps")
    elif notes.get("nfev"):
        parts.append(f"{notes['nfev']} rhs")
    if row.get("status") == "ok" and row["repeats"] < row.get("requested_repeats", 1):
        parts.append(f"{row['repeats']} run(s): over budget to repeat")
    return "; ".join(parts)


def markdown(section: dict) -> str:
    title = ("Double pendulum (scenarios/double_pendulum.toml)" if section["problem"] == "double"
             else f"Planar {section['n']}-link chain")
    lines = [f"### {title}, t = {section['t_end']:g} s, target error ≤ {section['target']:g} m", ""]
    lines += [f"- {note}" for note in section["notes"]]
    lines += [f"- skipped: {s}" for s in section["skipped"]]
    lines += ["", "| problem | N | peer | setting | build [s] | median sim wall [s] | error [m] | "
              "ratio to fastest at its level | peak RSS [MB] (Δ build+run) | notes |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in section["rows"]:
        head = (f"| {section['problem']} | {section['n']} | {r['peer']} | {r['setting']} | "
                f"{r['build_s']:.3f} |")
        if r["status"] != "ok":
            lines.append(f"{head} — | {r['status']} | | {_mem(r)} | |")
            continue
        ratio = f"{r['ratio']:.2f}× @ ≤{r['level']:.0e}" if r.get("level") else "(error > 1e-3)"
        lines.append(f"{head} {r['wall_s']:.4g} | {_err(r, section['reference_agreement'])} | {ratio} | "
                     f"{_mem(r)} | {_notes(r)} |")
    lines += ["", f"Cheapest run of each peer per accuracy level (N = {section['n']}; ratio to the fastest "
              "peer at that level):", "",
              "| error ≤ | peer | setting | median sim wall [s] | error [m] | build [s] | ratio |",
              "|---|---|---|---|---|---|---|"]
    ok = [r for r in section["rows"] if r["status"] == "ok"]
    for level in LEVELS:
        best = {}
        for r in ok:
            if r["error"] <= level and (r["peer"] not in best or r["wall_s"] < best[r["peer"]]["wall_s"]):
                best[r["peer"]] = r
        if not best:
            lines.append(f"| {level:g} | (none) | | | | | |")
            continue
        fastest = min(r["wall_s"] for r in best.values())
        for r in sorted(best.values(), key=lambda r: r["wall_s"]):
            mark = "**" if level == section["target"] else ""
            lines.append(f"| {mark}{level:g}{mark} | {r['peer']} | {r['setting']} | {r['wall_s']:.4g} | "
                         f"{_err(r, section['reference_agreement'])} | {r['build_s']:.3f} | "
                         f"{r['wall_s'] / fastest:.2f}× |")
        missing = sorted({r["peer"] for r in ok} - set(best))
        if missing:
            lines.append(f"| {level:g} | not reached by: {', '.join(missing)} | | | | | |")
    return "\n".join(lines) + "\n"


def write_json(path: Path, data) -> None:
    from constrained.run.trajectory import atomic_write  # temporary file, then rename

    text = json.dumps(data, indent=1, default=float) + "\n"
    atomic_write(Path(path), lambda f: f.write(text.encode()))


def select(peers: list[Peer], wanted: str | None) -> list[Peer]:
    if not wanted:
        return peers
    keys = {w.strip() for w in wanted.split(",") if w.strip()}
    chosen = [p for p in peers if p.name in keys or p.group in keys or p.name.split(":")[0] in keys]
    unknown = keys - {p.name for p in chosen} - {p.group for p in chosen} - {"constrained"}
    if unknown:
        raise SystemExit(f"unknown peer(s) {', '.join(sorted(unknown))}; known: "
                         f"{', '.join(dict.fromkeys([p.group for p in peers] + [p.name for p in peers]))}")
    return chosen


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", default="double,chain", help="comma list of double, chain")
    parser.add_argument("--n", type=int, nargs="+", default=[8, 32, 128, 256], help="chain sizes")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--peers", default=None,
                        help="comma list of groups (constrained, sympy, pydy, exudyn, mujoco, numpy) "
                             "or peer names")
    parser.add_argument("--methods", default="projection,projection:CVODES",
                        help="constrained methods, comma list; a:b = method a with base b")
    parser.add_argument("--rtols", type=float, nargs="+", default=None,
                        help="override the rtol sweep of the adaptive peers")
    parser.add_argument("--budget", type=float, default=60.0,
                        help="seconds one peer may take at one size (all settings × repeats), predicted")
    parser.add_argument("--no-memory", dest="memory", action="store_false",
                        help="skip the memory subprocesses")
    parser.add_argument("--blas-threads", type=int, default=1,
                        help="BLAS threads for every peer (default 1: all single-threaded; 0: leave as is)")
    parser.add_argument("--quick", action="store_true", help="short sweeps, 1 repeat, no memory probes")
    parser.add_argument("--json", type=Path, default=None, help="write the results here (atomically)")
    parser.add_argument("--_probe", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if args.blas_threads > 0:  # the memory probes inherit this before they import numpy
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.blas_threads)
    with blas_limit(args.blas_threads):
        run(args)


def blas_limit(threads: int):
    """Limit the BLAS libraries loaded so far (NumPy's, SciPy's) to ``threads`` (0: no limit).

    On a shared 2-core machine a multithreaded OpenBLAS spin-waits for the busy core (runs of
    the NumPy baseline took 5 s instead of 0.15 s); constrained's ``simulate`` limits itself
    to one thread, so every peer runs single-threaded here by default.
    """
    import contextlib

    if threads <= 0 or importlib.util.find_spec("threadpoolctl") is None:
        return contextlib.nullcontext()
    import scipy.linalg  # noqa: F401 — load SciPy's BLAS now, so that the limit covers it
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=threads, user_api="blas")


def run(args) -> None:
    if args._probe:
        print(json.dumps(probe(json.loads(args._probe))))
        return
    if args.quick:
        args.repeats, args.memory = 1, False
    if args.repeats < 1:
        raise SystemExit("--repeats must be at least 1")
    problems = [p.strip() for p in args.problems.split(",") if p.strip()]
    if not problems or set(problems) - {"double", "chain"}:
        raise SystemExit("--problems takes a comma list of: double, chain")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    peers = select(make_peers(methods), args.peers)

    info = versions()
    command = "python benchmarks/peers.py " + " ".join(args.argv)
    print(f"## constrained vs peers\n\n`{command}`\n")
    print("Versions: " + ", ".join(f"{k} {v}" for k, v in info.items() if k != "machine" and v) + ".")
    print(f"Machine: {info['machine']}. BLAS threads per peer: "
          f"{args.blas_threads if args.blas_threads > 0 else 'library default'}.\n")
    usable = []
    print("| peer | what runs | sweep |\n|---|---|---|")
    for peer in peers:
        why = peer.available()
        sweep = "rtol (atol = rtol·1e-2)" if peer.kind == "rtol" else "fixed step dt"
        print(f"| {peer.name} | {peer.label} | {sweep} |")
        if not why:
            usable.append(peer)
    print()
    for peer in peers:
        why = peer.available()
        if why:
            print(f"- peer {peer.name}: {why} — skipped")
    print()
    out = {"command": command, "versions": info, "levels": LEVELS, "repeats": args.repeats,
           "budget_s": args.budget, "methods": methods, "blas_threads": args.blas_threads,
           "memory_method": "one subprocess per (peer, size): peak = VmHWM of the process; delta = VmHWM "
                            "after build+run (counter reset by /proc/self/clear_refs=5 after the imports) "
                            "minus VmRSS at the reset",
           "peers": {p.name: {"label": p.label, "kind": p.kind} for p in peers},
           "skipped_peers": {p.name: p.available() for p in peers if p.available()}, "sections": []}
    for kind in problems:
        history: dict = {}
        cases = [double_problem()] if kind == "double" else [chain_problem(n) for n in args.n]
        for problem in cases:
            section = measure(problem, usable, args, history)
            out["sections"].append(section)
            print(markdown(section), flush=True)
            if args.json:
                write_json(args.json, out)


if __name__ == "__main__":
    main()
