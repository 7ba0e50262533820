"""An independent route: the raw index-3 DAE reduced by CasADi's own structural index
reduction (Pantelides' algorithm, ``casadi.dae_reduce_index``), then solved by IDAS.

The DAE handed to CasADi is the one of the theory, in first-order implicit form:

    0 = f(x, t),   0 = M v' − F(x, v, t) − Jᵀλ,   0 = x' − v

CasADi finds which equations to differentiate (structurally, not by our γ formula),
builds the semi-explicit index-1 system and its invariants, and generates consistent
initial values from our projected start. Its graph matching depends on the order of the
equations: for some orderings (e.g. a plane constraint listed first) the structural
detection fails, so the block orders are tried in turn — the reduced DAE is equivalent
whichever succeeds. The invariants are not re-imposed: the drift is what IDAS leaves.
"""

from __future__ import annotations

import itertools
import time

import casadi as ca
import numpy as np

from ... import interrupt
from ...errors import InputError
from ..base import DRIVER_OPTIONS, Advance, Status
from ..driver import Stepper
from .idas import SPLIT, STEPS_PER_CALL, CallSize
from .messages import quiet, tolerance_cause

#: Output times of pantelides' first IDAS call (see idas.CallSize).
PANTELIDES_FIRST_CALL_OUTPUTS = 50
#: The largest model (coordinates) whose index pantelides reduces unless told otherwise
#: (``max_coordinates``): CasADi's reduction is one call that Ctrl-C cannot stop, and its time
#: grows as about the cube of the size (a chain of 1 cm links: 0.85 s at 150 coordinates,
#: 8.5 s at 450, 57 s at 900, over 2 minutes at 3,000).
MAX_COORDINATES = 450


class Pantelides(Stepper):
    name = "pantelides"
    OPTIONS = ("max_coordinates", *DRIVER_OPTIONS)

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, max_coordinates: int = MAX_COORDINATES,
                 **options):
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        # redundant rows: the DAE takes the independent subset (see solvers.base)
        if self.model.n_constraints == 0:
            raise InputError("method 'pantelides' is for constrained systems; this one has none")
        if isinstance(max_coordinates, bool) or not isinstance(max_coordinates, int) or max_coordinates < 1:
            raise InputError(f"max_coordinates must be a whole number of at least 1, got {max_coordinates!r}")
        n3 = self.model.n_coordinates
        if n3 > max_coordinates:
            raise InputError(
                f"method 'pantelides' reduces the index symbolically (CasADi's dae_reduce_index) in one "
                f"call that Ctrl-C cannot stop, at a cost growing as about the cube of the size (57 s for "
                f"a chain of 900 coordinates); this model has {n3} coordinates, above max_coordinates = "
                f"{max_coordinates}: use method 'idas' (IDAS on the index-2 form built directly) or 'dopri', "
                "or, to wait for it, raise max_coordinates (Python: simulate(..., max_coordinates=...))")
        self.dae, self.reduced, self.index = self._reduce()
        self.semi_explicit, self.to_original, _ = ca.dae_map_semi_expl(self.dae, self.reduced)

    def _reduce(self):
        m = self.model
        n3, C = m.n_coordinates, len(self.rows)
        x, v, dx, dv = (ca.SX.sym(k, n3) for k in ("x", "v", "dx", "dv"))
        lam, t = ca.SX.sym("lam", C), ca.SX.sym("t")
        F, J, _ = m.dynamics(x, v, t)
        J = J[self.rows, :]
        # rows of f, then the velocity rows A v + b = 0 (model/velocity.py) as they are
        G, c0 = m.velocity_terms(x, t)
        held = ca.vertcat(m.constraint(x, t), (ca.mtimes(G, v) + c0)[m.n_position_rows:])[self.rows]
        blocks = [held, ca.DM(m.masses) * dv - F - ca.mtimes(J.T, lam), dx - v]
        last = None
        for order in itertools.permutations(range(3)):
            dae = {"x_impl": ca.vertcat(x, v), "dx_impl": ca.vertcat(dx, dv), "z": lam,
                   "alg": ca.vertcat(*[blocks[k] for k in order]), "t": t}
            try:
                reduced, stats = ca.dae_reduce_index(dae, {"algorithm": "pantelides"})
                return dae, reduced, int(stats.get("index", -1))
            except RuntimeError as exc:
                last = str(exc).splitlines()[-1]
        raise InputError(f"CasADi's structural index reduction failed for this system ({last}); "
                         "use method 'projection' or 'idas'")

    def prepare(self, t0, t_end, t_eval) -> None:
        self._grid = np.asarray(t_eval, float) if t_eval is not None else self.default_grid(t0, t_end)
        self.stats.update(rejected=0, index=self.index)

    def default_grid(self, t0, t_end):
        return np.linspace(t0, t_end, 201)

    def init(self, x0, v0, t0, t_end, first_step=None):
        """Consistent values of the reduced DAE (CasADi's ``dae_init_gen``) at our start."""
        n3, C = self.model.n_coordinates, len(self.rows)
        a0, lam0 = self.manifold.accelerations(x0, v0, t0)
        lam0 = lam0[self.rows]
        if not hasattr(self, "_init_gen"):
            force = ca.DM([-1.0] * (2 * n3))
            self._init_gen = ca.dae_init_gen(
                self.dae, self.reduced, "ipopt", {"x_impl": force, "dx_impl": force, "z": ca.DM([-1.0] * C)},
                {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False})
        args = {"x_impl": np.concatenate([x0, v0]), "dx_impl": np.concatenate([v0, a0]), "z": lam0}
        if "t" in self._init_gen.name_in():
            args["t"] = t0
        start = self._init_gen(**args)
        times = tuple(float(tk) for tk in self._grid if t0 < tk < t_end) + (float(t_end),)
        # one IDAS call per group of output times (idas.CallSize): the driver acts between calls
        # its calls cannot be split by a step budget (IDAS on CasADi's reduced DAE runs to the
        # end of a call, Ctrl-C waits for it): fewer outputs a call than idas and ggl
        self._calls = CallSize(first=PANTELIDES_FIRST_CALL_OUTPUTS)
        return (float(t0), start["x0"], start["z0"], times)

    def step(self, state, t_stop) -> Advance:
        n3 = self.model.n_coordinates
        t_prev, y, z, times = state
        seg, rest = list(times[:self._calls.size]), times[self._calls.size:]
        integ = ca.integrator("pantelides", "idas", self.semi_explicit, t_prev, seg, {
            "abstol": self.atol, "reltol": self.rtol, "max_num_steps": STEPS_PER_CALL})
        called = time.perf_counter()
        try:
            with interrupt.external(), quiet():
                sol = integ(x0=y, z0=z)
        except RuntimeError as exc:
            if self.stop_requested():
                raise KeyboardInterrupt from None
            reason = str(exc).splitlines()[-1][:200]
            # what a failed call computed is lost: retry it over fewer output times, then an
            # interval that needs more than STEPS_PER_CALL steps in SPLIT parts, so that a
            # failure (a collapse towards a singularity) is met in bounded work and reported
            # from the last output before it, not from the start of a long call
            if len(seg) > 1:
                self._calls.size = max(1, len(seg) // 2)
                return Advance.empty(state, n3)
            if "TOO_MUCH_WORK" in reason and seg[0] - t_prev > 1e-9 * max(abs(seg[0]), 1e-300):
                inner = tuple(float(tk) for tk in np.linspace(t_prev, seg[0], SPLIT + 1)[1:-1])
                return Advance.empty((t_prev, y, z, inner + tuple(times)), n3)
            return Advance.empty(state, n3, Status.SOLVER_FAILED,
                                 f"IDAS stopped after t = {t_prev:.6g} s ({reason})"
                                 + tolerance_cause(self.rtol, self.atol, float(np.max(np.abs(y[:n3])))))
        self._calls.took(time.perf_counter() - called)
        stats = integ.stats()
        for key, skey in (("steps", "nsteps"), ("nfev", "nfevals"), ("nlu", "nlinsetups"),
                          ("rejected", "netfails")):
            self.stats[key] = self.stats.get(key, 0) + int(stats.get(skey, 0))
        X = np.asarray(self.to_original(xf=sol["xf"], zf=sol["zf"])["x_impl"])
        new = (seg[-1], sol["xf"][:, -1], sol["zf"][:, -1], rest)
        return Advance(new, np.array(seg), X[:n3].T, X[n3:].T)
