"""RATTLE: the fixed-step constrained symplectic integrator (SHAKE for positions, RATTLE
for velocities), for long runs with bounded energy error and no secular drift.

One step of size h from (x_n, v_n, t_n):

    v½      = v_n + h/2 · M⁻¹ (F(x_n, v_n, t_n) + J(x_n)ᵀ λ)
    x_{n+1} = x_n + h v½,           with f(x_{n+1}, t_{n+1}) = 0   (Newton in λ)
    v_{n+1} = v½ + h/2 · M⁻¹ (F(x_{n+1}, v½, t_{n+1}) + J(x_{n+1})ᵀ μ),
              with J(x_{n+1}) v_{n+1} + f_t = 0                    (linear in μ)

It is symplectic and time-reversible for conservative forces F(x). Velocity-dependent forces
(damping, magnetic) are taken at v_n in the first half-kick and at v_{n+1} in the second,
F(x_{n+1}, v_{n+1}, t_{n+1}), solved by Newton (``implicit_kick``; one iteration is exact for
forces linear in v): the step is then the composition of an explicit half-step and its
adjoint, so symmetric and second order, and in a uniform magnetic field without constraints
|v| is kept exactly (the half-kicks form a Cayley map). Taken at v½ instead (as before), the
step was first order in those forces: a charge circling in B lost 60 % of its kinetic
energy over 10 turns at 400 steps a turn. Large constrained models in the virtual machine
(the vectorized build, ``vectorized.rattle_step_graph``) iterate that half-kick to its fixed
point instead (KICK_ITERATIONS times, each gaining h/2 |M⁻¹ ∂F/∂v|).

The whole step is one CasADi Function: Newton for λ is unrolled (``newton_iterations``
iterations from the previous step's λ, which converge quadratically), and the last
iteration's residual |f(x_{n+1})| is carried in the state as a running maximum, checked
after every chunk. Many steps are chained per call (``_chained``), so no Python runs per
step, and the chained steps can be compiled to machine code (``compiled``; see
constrained.codegen.compiled).

On a system that conserves its energy h = T + V (``conserves_energy``) the steps also carry
the energy watch (``ENERGY_WATCH``): h after every step, the largest |h − h₀| and the largest
one-step change |h_{n+1} − h_n|, with their times, returned in the run's stats. A close
encounter that a step jumps between two output times is seen there (constrained.run.simulate
decides whether to warn). V comes with the forces F(x_{n+1}) from one evaluation
(``forces_and_potential``: for pair potentials one pass of their kernel), T is ½ vᵀMv.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ..codegen import compiled as compiled_evaluation
from ..codegen.fast_call import FastCall
from ..errors import InputError
from ..manifold import diagnostics, mapped, residual
from ..manifold.graph import schur_solve_graph, velocity_correction_graph
from ..manifold.manifold import dynamics_values
from ..manifold.vectorized import graphs as vectorized
from ..model.cache import ParametricView, structure_cache
from .base import DRIVER_OPTIONS, Advance, Status
from .driver import Stepper, step_samples

#: Under compiled="auto", RATTLE's folded steps are compiled for models up to this size.
AUTO_COMPILE_COORDINATES = 90

#: Newton iterations of a step for λ by default: exact Newton (quadratic) and, on the
#: vectorized build, the simplified iteration (linear, by about h|v| / a rod's length).
NEWTON_ITERATIONS, SIMPLIFIED_ITERATIONS = 4, 10
#: A step's |f| within this many times its round-off floor (``Rattle.round_off_floor``) has
#: converged, whatever ``newton_tol`` says.
ROUND_OFF_FACTOR = 8.0

#: Largest number of output samples when the caller gives no output grid.
DEFAULT_SAMPLES = 2000
#: Coordinate-steps per chained call at most (Ctrl-C waits for a call): 16384 steps of a
#: 32-coordinate model, 16 steps of 10,000 particles (~0.1 s with a pair potential's cutoff).
CHUNK_WORK = 1 << 19
#: Chains up to this many steps are written out call by call (p shared, not carried).
UNROLLED_STEPS = 16
#: The energy watch's entries at the end of the step's state (h₀, h after the last step, the
#: largest h − h₀ and its time, the largest one-step change and its time), named as in the stats.
ENERGY_WATCH = ("energy_start", "energy_last", "energy_change", "energy_change_t", "energy_step_change",
                "energy_step_change_t")
#: Steps chained per call: the shortest that covers the steps to the next output is called;
#: steps past the count asked for are skipped (nearly free). The same few Functions serve every
#: dt, so a new step size compiles nothing.
CHUNKS = (1, 16, 256, 4096, 16384)


class Rattle(Stepper):
    name = "rattle"
    adaptive = False
    order = 2
    OPTIONS = ("newton_tol", "newton_iterations", "energy_watch", *DRIVER_OPTIONS)
    refines_events = False  # its step is fixed: events are located on the dense output
    refuses_velocity_rows = ("its step keeps f = 0 by a Newton iteration in the multipliers, and a "
                             "velocity row has no f (a discrete non-holonomic integrator is another method)")

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, newton_tol: float = 1e-12,
                 newton_iterations: int | None = None, energy_watch: bool = True, **options):
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        model = self.model
        if not isinstance(energy_watch, bool):
            raise InputError(f"energy_watch must be true or false, got {energy_watch!r}")
        #: Whether the steps carry the energy watch on a conservative system (False: a pair
        #: potential's φ is not summed every step, 7–11 % of a Lennard-Jones gas's step; no
        #: warning of a step that did not resolve the motion can then be given).
        self.energy_watch = energy_watch
        if newton_iterations is not None and not (isinstance(newton_iterations, int)
                                                  and 1 <= newton_iterations <= 50):
            raise InputError(
                f"newton_iterations must be a whole number from 1 to 50, got {newton_iterations!r}"
            )
        # "auto" compiles the folded steps of models up to AUTO_COMPILE_COORDINATES coordinates:
        # there the one-time C compile takes seconds and the chunks run ~2.7x faster; beyond,
        # the compiler's time grows steeply, so only compiled=True asks for it — except for pair
        # potentials, whose O(N²) work is one mapped kernel of fixed code (as for dopri): in the
        # virtual machine it costs ~10x the compiled kernel.
        self.compiled = compiled_evaluation.enabled(self.compiled_setting) and (
            self.compiled_setting is True or model.n_coordinates <= AUTO_COMPILE_COORDINATES
            or bool(model.structure.pairs)
        )
        if newton_iterations is None:  # (the simplified iteration contracts linearly: more)
            newton_iterations = SIMPLIFIED_ITERATIONS if self.vectorized() else NEWTON_ITERATIONS
        self.newton_iterations = newton_iterations
        if dt is None:
            raise InputError("method 'rattle' takes fixed steps: give dt (seconds), e.g. dt = 1e-3")
        self.newton_tol = newton_tol
        self._evaluation = "virtual machine"  # (until the chained steps are compiled)

    def _view(self, P) -> ParametricView:
        """The model's Functions with p = P: the mapped build when compiled and large (repeated
        rows and terms as mapped kernels, so the generated code and the compile time do not
        grow with the model), else the Structure's."""
        if self.compiled and mapped.applies(self.model):
            return mapped.MappedView(self.model, P)
        return ParametricView(self.model, P)

    def vectorized(self) -> bool:
        """Whether the step is built on the vectorized build (``vectorized.rattle_step_graph``:
        its Newton iteration simplified, its KKT solves the loops' LDLᵀ): large models with
        constraints, in the virtual machine."""
        return (not self.compiled and bool(self.model.n_constraints)
                and vectorized.applies(self.model, self.manifold.rows))

    def carries_forces(self) -> bool:
        """Whether the applied forces F are carried from one step to the next (state entries
        after p): when F depends on x and t alone, F(x_{n+1}) of a step's second half-kick is
        the next step's F(x_n), so a step evaluates the forces once (pair potentials: their
        O(N²) kernel once, as velocity Verlet)."""
        return not self.model.structure.forces_depend_on_velocity

    def watches_energy(self) -> bool:
        """Whether the steps carry the energy watch (``ENERGY_WATCH``): the system conserves
        its energy (``conserves_energy``; its forces then do not depend on v and are carried)."""
        return self.energy_watch and conserves_energy(self.model)

    def _step(self) -> ca.Function:
        """One RATTLE step (state, p) -> state on the state (x, v, t, λ, err, left, h, s[, F]) —
        err: running max of |f| after Newton (in metres: each row over its scale s at the run's
        start); left: the steps a call has still to take; the step h and the row scales s ride
        along in the state and the parameters p (with the pair potentials' neighbour lists:
        most of the numbers at 10,000 particles) are a second input, read and never copied from
        step to step, so one Function (one compile) serves every step size, start and parameter
        value of the structure; F: the forces at (x, t) when they do not depend on v
        (``carries_forces``); the energy watch after them (``watches_energy``)."""
        m = self.model
        rows = self.manifold.rows
        n3, C, n_all = m.n_coordinates, len(self.rows), m.n_constraints
        x, v, t, err = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t"), ca.MX.sym("err")
        left, h = ca.MX.sym("left"), ca.MX.sym("h")
        lam, scales = ca.MX.sym("lam", C), ca.MX.sym("scales", n_all)
        P = ca.MX.sym("p", len(m.parameter_vector))
        view = self._view(P)
        minv = view.inverse_masses if isinstance(view.inverse_masses, ca.MX) else ca.DM(view.inverse_masses)
        carry = self.carries_forces()
        vector = self.vectorized()
        watch = self.watches_energy()
        W1 = None  # (the energy less the kinetic at x_{n+1}, with the forces there: the watch)
        if carry:
            F0 = ca.MX.sym("F", n3)
            J0 = view.jacobian(x, t)[1] if C and not vector else None
        elif vector:
            F0 = J0 = None
        else:
            F0, J0, _ = view.dynamics(x, v, t)
        t1 = t + h
        passed = [h, scales]
        counted = [left - 1, *passed]
        if C and vector:  # large, in the virtual machine: the vectorized build and its LDLᵀ
            x1, v1, lam_k, f1, F1 = vectorized.rattle_step_graph(
                view, x, v, t, lam, h, F0=F0 if carry else None, iterations=self.newton_iterations,
                velocity_dependent=not carry)
            state = [x, v, t, lam, err, left, *passed]
            out = [x1, v1, t1, lam_k, ca.fmax(err, ca.mmax(ca.fabs(f1) / scales)), *counted]
        elif C:
            J0 = J0 if rows is None else J0[list(rows), :]
            kick = 0.5 * h * h * minv
            base = x + h * v + kick * F0
            lam_k = lam
            for _ in range(self.newton_iterations):
                f1, J1 = view.jacobian(base + kick * ca.mtimes(J0.T, lam_k), t1)
                if rows is not None:
                    f1, J1 = f1[list(rows)], J1[list(rows), :]
                # d f(x1(λ)) / dλ = J(x1) · h²/2 M⁻¹ J(x_n)ᵀ
                lam_k = lam_k - schur_solve_graph(J1, J0, kick, f1)
            v_half = v + 0.5 * h * minv * (F0 + ca.mtimes(J0.T, lam_k))
            x1 = x + h * v_half
            residual = ca.mmax(ca.fabs(view.constraint(x1, t1)) / scales)
            F1, W1 = forces_after(view, x1, v_half, t1, watch)
            v_pred = v_half + 0.5 * h * minv * F1
            v1 = v_pred - velocity_correction_graph(view, x1, v_pred, t1, rows=rows)
            if not carry:  # F depends on v: the second half-kick at v_{n+1}
                v1 = implicit_kick(view, P, x1, v_half, t1, h, v1, rows=rows, constrained=True)
            state = [x, v, t, lam, err, left, *passed]
            out = [x1, v1, t1, lam_k, ca.fmax(err, residual), *counted]
        else:
            v_half = v + 0.5 * h * minv * F0
            x1 = x + h * v_half
            F1, W1 = forces_after(view, x1, v_half, t1, watch)
            v1 = v_half + 0.5 * h * minv * F1
            if not carry:
                v1 = implicit_kick(view, P, x1, v_half, t1, h, v1, constrained=False)
            state = [x, v, t, err, left, *passed]
            out = [x1, v1, t1, err, *counted]
        if carry:
            state.append(F0)
            out.append(F1)
        if watch:
            watched = [ca.MX.sym(name) for name in ENERGY_WATCH]
            if W1 is None:  # (the vectorized build: its energy, O(N) as its forces)
                energy = vectorized.VectorizedView(m, P).energy(x1, v1, t1)
            else:
                masses = view.masses if isinstance(view.masses, ca.MX) else ca.DM(view.masses)
                energy = 0.5 * ca.dot(masses * v1, v1) + W1
            state += watched
            out += energy_watch(watched, energy, t1)
        state, out = ca.vertcat(*state), ca.vertcat(*out)
        step = ca.Function("rattle_attempt", [state, P], [out])
        # once the steps asked for are done, a step is skipped (short-circuit: nearly free); so
        # are the steps after a pair potential's neighbour list went stale, for ``step`` to
        # refresh it (the graph sums every pair where a list is stale: exact, but O(N²))
        S, Ps = ca.MX.sym("state", state.numel()), ca.MX.sym("p", P.numel())
        done = S[self._left_slot()] <= 0
        if m.structure.pairs:
            done = ca.logic_or(done, m.structure.pair_potentials.stale(S[:n3], Ps))
        return ca.Function("rattle_step", [S, Ps], [ca.if_else(done, S, step(S, Ps), True)])

    def _left_slot(self) -> int:
        """Where the steps left of a call stand in the state (x, v, t, λ, err, left, h, s[, F])."""
        return 2 * self.model.n_coordinates + len(self.rows) + 2

    def _chunks(self) -> dict[int, FastCall]:
        """The chained steps (CHUNKS, as many as one call may take), built once per structure,
        row set and Newton iterations (``structure_cache``) and compiled together when asked:
        every dt, start and parameter value of the structure shares them."""
        cache, prefix = structure_cache(self.model)
        key = (*prefix, "rattle", self.manifold.rows, self.newton_iterations, self.compiled,
               self.carries_forces(), self.vectorized(), self.watches_energy())
        chunks = cache.get(key)
        if chunks is None:
            with vectorized.shared_nodes():  # (a step's repeated products built once)
                step = self._step()
            n3 = self.model.n_coordinates
            # (one step alone only where no chain fits: a chain takes fewer steps by skipping
            # the rest, nearly free, and each Function more costs the compile cache's key the
            # serialization of its whole graph, ~0.4 s at 10,000 particles with a cutoff)
            lengths = [k for k in CHUNKS if k > 1 and k * n3 <= CHUNK_WORK] or [1]
            functions = {k: (step if k == 1 else _chained(step, k)) for k in lengths}
            evaluation = "virtual machine"
            if self.compiled:
                machine = compiled_evaluation.compile_functions(list(functions.values()))
                if all(f.class_name() == "External" for f in machine):
                    functions = dict(zip(functions, machine, strict=True))
                    evaluation = "compiled"
            chunks = evaluation, {k: FastCall(f) for k, f in functions.items()}
            if not (self.compiled and compiled_evaluation.cut_short()):  # (cut by Ctrl-C: not kept)
                cache[key] = chunks
        self._evaluation = chunks[0]
        return chunks[1]

    def prepare(self, t0, t_end, t_eval) -> None:
        """The fixed step: dt shortened slightly to land on t_end; t_eval must lie on its grid."""
        self._t0 = t0
        self._n_steps = max(1, math.ceil((t_end - t0) / self.dt - 1e-9))
        self.h = (t_end - t0) / self._n_steps
        if t_eval is not None:
            k = (np.asarray(t_eval) - t0) / self.h
            if np.max(np.abs(k - np.rint(k)), initial=0.0) > 1e-6:
                raise InputError(
                    f"method 'rattle' outputs at multiples of its step ({self.h:.6g} s: dt shortened "
                    "to land on t_end); give output times on that grid (t_eval; in a scene, "
                    "simulate.output_dt a multiple of dt) or none"
                )

    def default_grid(self, t0, t_end):
        """Every step up to DEFAULT_SAMPLES of them (fewer on a large model: driver.step_samples)."""
        samples = min(DEFAULT_SAMPLES, step_samples(self.model.n_coordinates))
        every = max(1, self._n_steps // samples)
        steps = list(range(0, self._n_steps + 1, every))
        if steps[-1] != self._n_steps:
            steps.append(self._n_steps)
        grid = t0 + self.h * np.array(steps, float)
        grid[-1] = t_end  # (the step was made to land there; no round-off short of it)
        return grid

    def init(self, x0, v0, t0, t_end, first_step=None):
        m = self.model
        C = len(self.rows)
        if not hasattr(self, "row_scales"):  # the run's scales, from its start
            self.scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
            self.row_scales = residual.row_scales(m, x0, t0) if C else np.zeros(0)
        lam0 = self.manifold.accelerations(x0, v0, t0)[1][self.rows] if C else np.zeros(0)
        scales = np.asarray(self.row_scales, float) if C else np.zeros(m.n_constraints)
        carried = []
        if self.carries_forces():
            F0 = m.parametric("dynamics")(x0, v0, t0, m.parameter_vector)[0]
            carried = [np.asarray(F0, float).ravel()]
        self._p = np.array(m.parameter_vector, float)  # (the neighbour lists refreshed in it)
        if self.watches_energy():
            if not hasattr(self, "energy_start"):  # (the run's, from its start)
                self.energy_start = float(m.parametric("energy")(x0, v0, t0, self._p))
            carried.append([self.energy_start, self.energy_start, 0.0, t0, 0.0, t0])
        state = [x0, v0, [t0], lam0, [0.0, 0.0, self.h], scales, *carried]
        return round((t0 - self._t0) / self.h), np.concatenate(state)

    def step(self, state, t_stop) -> Advance:
        """One chained call towards t_stop: the shortest chain that covers the steps left, else
        the longest (its steps past the count are skipped)."""
        m = self.model
        n3 = m.n_coordinates
        done, y = state
        left = max(1, round((t_stop - self._t0) / self.h) - done)
        chunks = self._chunks()
        size = next((c for c in chunks if c >= left), max(chunks))
        k = min(left, size)
        y = y.copy()
        counter = self._left_slot()
        if m.structure.pairs:  # neighbour lists rebuilt where particles moved far
            p = m.structure.pair_potentials.refreshed(self._p, y[:n3])
            if p is not None:
                self._p = p
        y[counter] = k  # the steps this call takes
        (new,) = chunks[size](y, self._p)
        # (a call stops early where a neighbour list went stale: at least one step is taken,
        # from the list refreshed above)
        k -= max(0, round(float(new[counter]))) if np.isfinite(new[counter]) else 0
        t_new = self._t0 + (done + k) * self.h
        if abs(t_new - t_stop) <= 1e-9 * self.h:
            t_new = t_stop
        if not np.all(np.isfinite(new)):
            cause = diagnostics.nonfinite_cause(m, y[:n3], y[n3:2 * n3], y[2 * n3])
            return Advance.empty(state, n3, Status.NON_FINITE,
                                 f"non-finite state between t = {y[2 * n3]:.6g} s and {t_new:.6g} s; {cause}")
        err = new[counter - 1]  # (the running max of |f| stands just before left)
        if err > self.newton_tol * self.scale and err > ROUND_OFF_FACTOR * self.round_off_floor(new):
            return Advance.empty(state, n3, Status.PROJECTION_FAILED, (
                               f"Newton for the position multipliers did not converge between t = "
                               f"{y[2 * n3]:.6g} s and {t_new:.6g} s (|f| = {err:.3g} m after "
                               f"{self.newton_iterations} iterations): reduce dt"
                               + (" or raise newton_iterations" if self.vectorized() else "")))
        self.stats["steps"] = done + k
        if self.watches_energy():
            self.stats.update(zip(ENERGY_WATCH, map(float, new[-len(ENERGY_WATCH):]), strict=True))
        return Advance((done + k, new), np.array([t_new]), new[None, :n3], new[None, n3:2 * n3], h=self.h)

    def round_off_floor(self, state) -> float:
        """The |f| (in metres, each row over its scale) that round-off leaves after a step at
        ``state``: x_{n+1} = x_n + h v_n + h²/2 M⁻¹ (F + Jᵀλ) sums the rows' forces J_rᵀ λ_r at
        each coordinate to ε Σ_r |J_ri λ_r|, so it moves coordinate i by
        δx_i = ε (|x_i| + h²/2 |J|ᵀ|λ| / m_i), and row r by Σ_i |J_ri| δx_i. A 1 mg bead between
        two 1 t beads on rods carries tensions of 1e4 N that cancel on it: at h = 0.01 s its
        position is known to 2e-10 m, above ``newton_tol`` (1e-12 m), which no iteration
        reaches (the run stopped with "Newton … did not converge"). Checked only when |f|
        exceeds ``newton_tol``."""
        m, n3, C = self.model, self.model.n_coordinates, len(self.rows)
        if not C:
            return 0.0
        x, v, t = state[:n3], state[n3:2 * n3], float(state[2 * n3])
        lam = np.abs(state[2 * n3 + 1:2 * n3 + 1 + C])
        _, J, _ = dynamics_values(m)(x, v, t)
        J = abs(J.sparse()[self.rows]) if isinstance(J, ca.DM) else np.abs(np.asarray(J)[self.rows])
        eps = np.finfo(float).eps
        moved = eps * (np.abs(x) + 0.5 * self.h * self.h * m.inverse_masses * (J.T @ lam))
        scales = np.asarray(self.row_scales, float)[self.rows]
        return float(np.max((J @ moved) / np.where(scales > 0, scales, 1.0), initial=0.0))

    def finish(self) -> None:
        done = self.stats["steps"]
        self.stats.update({"nfev": 2 * done, "dt": self.h,
                           "evaluation": self._evaluation})


def implicit_kick(view, P, x1, v_half, t1, h, v, *, rows=None, constrained: bool = True):
    """v_{n+1} of the second half-kick with the forces at v_{n+1}: the root of

        G(w) = w − v½ − h/2 M⁻¹ F(x_{n+1}, w, t_{n+1}) − M⁻¹ J(x_{n+1})ᵀ ν = 0,
        J(x_{n+1}) w + f_t = 0                                  (ν = h/2 μ, when ``constrained``)

    by Newton from ``v`` (the explicit kick, projected): with A = I − h/2 M⁻¹ ∂F/∂v and
    Y = A⁻¹ [M⁻¹ Jᵀ, G(v)], the step is δv = Y₁ ν − Y_G with (J Y₁) ν = J (Y_G − v) − f_t (the
    Schur complement ≈ J M⁻¹ Jᵀ, solved with the rows scaled by diag(J M⁻¹ Jᵀ)^(-1/2)). One
    iteration when ∂F/∂v does not depend on v (magnetic forces, Rayleigh damping: exact), two
    otherwise (a drag ∝ |v| v)."""
    n3 = x1.numel()
    minv = view.inverse_masses if isinstance(view.inverse_masses, ca.MX) else ca.DM(view.inverse_masses)
    xs, vs, ts = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
    Fs = view.dynamics(xs, vs, ts)[0]
    Ks = ca.jacobian(Fs, vs)
    force = ca.Function("force_and_velocity_jacobian", [xs, vs, ts, P], [Fs, Ks])
    iterations = 1 if not ca.depends_on(Ks, vs) else 2
    if constrained:
        J, f_t = view.velocity_terms(x1, t1)
        if rows is not None:
            J, f_t = J[list(rows), :], f_t[list(rows)]
        C = J.shape[0]
        d = 1.0 / ca.sqrt(ca.mtimes(J * J, minv))  # row scaling of the Schur complement
    for _ in range(iterations):
        F, K = force(x1, v, t1, P)
        G = v - v_half - 0.5 * h * minv * F
        A = ca.MX.eye(n3) - 0.5 * h * ca.mtimes(ca.diag(minv), K)
        if not constrained or C == 0:
            v = v - ca.solve(A, G, "qr")
            continue
        Y = ca.solve(A, ca.horzcat(ca.mtimes(ca.diag(minv), J.T), G), "qr")
        Y1, YG = Y[:, :C], Y[:, C]
        S = ca.mtimes(ca.diag(d), ca.mtimes(ca.mtimes(J, Y1), ca.diag(d)))
        nu = d * ca.solve(S, d * (ca.mtimes(J, YG - v) - f_t), "qr")
        v = v + ca.mtimes(Y1, nu) - YG
    return v


def conserves_energy(model) -> bool:
    """Whether the energy h = T + V of ``model`` is conserved by its motion: no time-dependent
    or velocity-dependent forces, scleronomic constraints, no velocity rows."""
    return not (model.rheonomic or {"time_dependent_forces", "velocity_constraints"} & model.active_terms
                or model.structure.forces_depend_on_velocity)


def forces_after(view, x1, v_half, t1, watch: bool) -> tuple:
    """(F(x_{n+1}, v½, t_{n+1}), W): with the energy watch W = h − ½ vᵀMv there, from the same
    evaluation (``forces_and_potential``), else None."""
    if watch:
        return view.forces_and_potential(x1, v_half, t1)
    return view.dynamics(x1, v_half, t1)[0], None


def energy_watch(watched: list, energy, t1) -> list:
    """The energy watch (``ENERGY_WATCH``) after a step that ends at t1 with energy h_{n+1}:
    h₀ kept, h_{n+1} the last, and the largest |h_{n+1} − h₀| and |h_{n+1} − h_n| so far with
    their times. A value that is not finite is not taken (the run's own checks name it)."""
    start, last, change, t_change, step_change, t_step = watched
    finite = ca.fabs(energy) < ca.inf
    larger = ca.logic_and(finite, ca.fabs(energy - start) > ca.fabs(change))
    jumped = ca.logic_and(finite, ca.fabs(energy - last) > ca.fabs(step_change))
    return [start, ca.if_else(finite, energy, last),
            ca.if_else(larger, energy - start, change), ca.if_else(larger, t1, t_change),
            ca.if_else(jumped, energy - last, step_change), ca.if_else(jumped, t1, t_step)]


def _chained(step: ca.Function, k: int) -> ca.Function:
    """``step`` (state, p) -> state taken ``k`` times in one Function. Up to UNROLLED_STEPS
    calls are written out, p shared by every call (read, never copied: at 10,000 particles with
    a pair potential p is mostly the neighbour list, ~8x the state); longer chains are CasADi's
    ``fold`` (one loop in the generated code, whose compile time does not grow with k), which
    carries p in its state."""
    S, P = ca.MX.sym("state", step.nnz_in(0)), ca.MX.sym("p", step.nnz_in(1))
    if k <= UNROLLED_STEPS:
        out = S
        for _ in range(k):
            out = step(out, P)
        return ca.Function(f"chain_{k}_{step.name()}", [S, P], [out])
    n = S.numel()
    SP = ca.MX.sym("state_p", n + P.numel())
    carried = ca.Function(f"{step.name()}_carrying_p", [SP], [ca.vertcat(step(SP[:n], SP[n:]), SP[n:])])
    return ca.Function(f"fold_{k}_{step.name()}", [S, P], [carried.fold(k)(ca.vertcat(S, P))[:n]])
