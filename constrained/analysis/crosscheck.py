"""The cross-check: the Cartesian route and the reduced route from the same start, compared.

The Cartesian run goes through the one map of settings (``run_options``), like ``run`` and
sweeps; the reduced run integrates Lagrange's equations in the scene's ``[reduced]``
coordinates on the Cartesian run's time grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..run.options import from_settings
from ..run.reduced import ReducedModel, _number
from ..run.simulate import simulate
from ..run.trajectory import Trajectory, atomic_write

#: The routes have separated once their position difference exceeds this fraction of the
#: system's size (CrossCheck.horizon).
SEPARATED = 1e-3
#: rtol and atol of both routes when neither the scene's [simulate] nor the caller gives them.
CROSSCHECK_TOL = 1e-10
#: Output samples when the scene gives no grid (output_dt, samples) and no t_eval is passed.
DEFAULT_SAMPLES = 201


def cross_check(scene, t_end: float | None = None, **settings) -> CrossCheck:
    """Run the Cartesian route (``simulate``) and the reduced route of ``scene.reduced`` from
    the same start (the reduced ``initial``/``rates`` mapped to x, v) on one time grid.

    ``settings`` override the scene's ``[simulate]`` ones: ``method``, ``rtol``, ``atol``,
    ``t_start``, ``t_eval``, ``samples``, ``output_dt``, a method's own options (``base`` …),
    ``parameters`` (extra names for the map); ``progress`` and ``model`` go to ``simulate``.
    """
    base = dict(getattr(scene, "settings", None) or {})
    extra_parameters = settings.pop("parameters", None)
    passthrough = {k: settings.pop(k) for k in ("progress", "model") if k in settings}
    t_end = (settings.pop("t_end", None) or base.get("t_end")) if t_end is None else t_end
    if t_end is None:
        raise InputError("no end time: give t_end, or t_end in the scene's [simulate]",
                         where="simulate.t_end")
    t_end = _number(t_end, "t_end")
    given = getattr(scene, "given_settings", None)
    for key in ("rtol", "atol"):  # tighter than simulate's 1e-8 unless the scene or the caller chose
        if key not in base or (given is not None and key not in given):
            base[key] = CROSSCHECK_TOL
    if all(settings.get(k) is None and base.get(k) is None for k in ("t_eval", "samples", "output_dt")):
        base["samples"] = DEFAULT_SAMPLES
    options = from_settings(base, scene=scene, t_end=t_end, **settings)
    t_start, rtol, atol = options.t_start, options.rtol, options.atol
    rm = ReducedModel.from_scene(scene, parameters=extra_parameters, t0=t_start)
    x0, v0 = rm.state(rm.initial, rm.rates, t_start)
    system = scene.system.with_state(x0, v0)
    kwargs = options.simulate_kwargs()
    cart = simulate(system, t_end, **kwargs, **passthrough)
    red = rm.solve(t_end, t_start=t_start, rtol=rtol, atol=atol, t_eval=cart.t)
    dx = np.max(np.linalg.norm(cart.x - red.x, axis=2), axis=1)
    dv = np.max(np.linalg.norm(cart.v - red.v, axis=2), axis=1)
    de = None
    if cart.energy is not None and red.energy is not None:
        de = float(np.max(np.abs(cart.energy - red.energy)))
    dF = None
    if cart.constraint_forces is not None and red.constraint_forces is not None and rm.model.n_constraints:
        dF = float(np.max(np.linalg.norm(cart.constraint_forces - red.constraint_forces, axis=2)))
    return CrossCheck(
        cartesian=cart,
        reduced=red,
        reduced_model=rm,
        t=cart.t,
        position_difference=dx,
        velocity_difference=dv,
        max_position_difference=float(np.max(dx)),
        max_velocity_difference=float(np.max(dv)),
        max_energy_difference=de,
        max_constraint_force_difference=dF,
        settings={"t_end": t_end, **{k: v for k, v in kwargs.items() if k != "t_eval"}},
    )


@dataclass
class CrossCheck:
    """The Cartesian and reduced routes from the same start on the same time grid.

    ``position_difference`` (T,) is max_i |x_i^cart − x_i^red|, ``velocity_difference``
    likewise; the ``max_*`` floats are their largest values over the run.
    """

    cartesian: Trajectory
    reduced: Trajectory
    reduced_model: ReducedModel
    t: np.ndarray
    position_difference: np.ndarray
    velocity_difference: np.ndarray
    max_position_difference: float
    max_velocity_difference: float
    max_energy_difference: float | None = None
    max_constraint_force_difference: float | None = None
    settings: dict = field(default_factory=dict)

    @property
    def energy_cartesian(self) -> np.ndarray | None:
        return self.cartesian.energy

    @property
    def energy_reduced(self) -> np.ndarray | None:
        return self.reduced.energy

    @property
    def jacobi_integral(self) -> np.ndarray | None:
        """``h = Σ q̇ ∂L/∂q̇ − L`` along the reduced route (T,), or None."""
        h = self.reduced.info.get("hamiltonian")
        return None if h is None else np.asarray(h, float)

    def horizon(self) -> tuple[float | None, float | None]:
        """(t_sep, τ): the first time the position difference exceeds SEPARATED × the system's
        size (None: never), and the e-folding time of its growth before that — the slope of
        log Δx(t) fitted between 100 × its first nonzero value and t_sep (None when it does not
        grow). Two routes of the same equations, each with its integration error, separate
        like two neighbouring starts: in a chaotic motion as e^{t/τ}, τ the Lyapunov time."""
        dx = np.asarray(self.position_difference, float)
        size = max(float(np.max(np.abs(self.cartesian.x), initial=0.0)), 1e-300)
        out = np.flatnonzero(dx > SEPARATED * size)
        t_sep = float(self.t[out[0]]) if out.size else None
        nonzero = dx[dx > 0]
        if t_sep is None or not nonzero.size:
            return t_sep, None
        grow = (dx > 100 * nonzero[0]) & (self.t <= t_sep)
        if np.count_nonzero(grow) < 3:
            return t_sep, None
        slope = float(np.polyfit(self.t[grow], np.log(dx[grow]), 1)[0])
        return t_sep, (1.0 / slope if slope > 0 else None)

    def horizon_line(self) -> str:
        """What the comparison compares: the routes' agreement in x and v over the whole run, or
        until they separate (then the growth's time scale, and that the energies decide)."""
        t_sep, tau = self.horizon()
        if t_sep is None:
            return (f"{'compared':<34}x, v at every sample: the routes stay within {SEPARATED:g} of the "
                    "system's size over the whole run")
        rate = f", the difference growing as e^(t/{tau:.3g} s) before" if tau else ""
        return (f"{'compared':<34}x, v agree until t = {t_sep:.4g} s, then the routes separate (difference "
                f"above {SEPARATED:g} of the size{rate}): the motion amplifies each route's integration "
                "error (chaos: a Lyapunov time), so beyond it only the energy and h compare; not a "
                "disagreement of the equations when those agree")

    def jacobi_integral_line(self) -> str:
        """One line on the Jacobi integral of the reduced route: value, drift and whether it is
        a constant of the motion (then its drift measures the integration; for a driven scene
        it is the conserved quantity that T + V is not)."""
        h = self.jacobi_integral
        if h is None or not len(h):
            return ""
        drift = float(np.max(np.abs(h - h[0])))
        if self.reduced_model.jacobi_integral_conserved():
            verdict = "conserved: L has no explicit t and no non-conservative force acts"
        else:
            verdict = ("not a constant here: L depends on t, non-conservative forces act, or a velocity "
                       "constraint does work (b ≠ 0)")
        return (f"{'Jacobi integral h = p·q_dot − L':<34}h0 = {float(h[0]):.12g} J, "
                f"max |h − h0| = {drift:.3e} J ({verdict})")

    def table(self) -> str:
        """A plain-text summary: differences, energies and residuals of both routes."""
        def drift(e):
            return float(np.max(np.abs(e - e[0]))) if e is not None and len(e) else float("nan")

        rows = [
            ("max position difference", f"{self.max_position_difference:.3e} m"),
            ("max velocity difference", f"{self.max_velocity_difference:.3e} m/s"),
        ]
        if self.max_energy_difference is not None:
            rows.append(("max energy difference", f"{self.max_energy_difference:.3e} J"))
        if self.max_constraint_force_difference is not None:
            rows.append(("max constraint-force difference", f"{self.max_constraint_force_difference:.3e} N"))
        out = [f"{k:<34}{v}" for k, v in rows]
        out.append(self.horizon_line())
        jacobi = self.jacobi_integral_line()
        if jacobi:
            out.append(jacobi)
        out.append("")
        out.append(f"{'route':<12}{'E(t0) [J]':>20}{'max |E - E0| [J]':>18}{'max |f|':>12}")
        for name, tr in (("cartesian", self.cartesian), ("reduced", self.reduced)):
            e0 = float(tr.energy[0]) if tr.energy is not None and len(tr.energy) else float("nan")
            cr = tr.constraint_residual
            res = float(np.max(cr)) if cr is not None and len(cr) else float("nan")
            out.append(f"{name:<12}{e0:>20.12g}{drift(tr.energy):>18.3e}{res:>12.3e}")
        return "\n".join(out)


def save_crosscheck_figure(check: CrossCheck, path) -> Path:
    """Position (and velocity) difference of the two routes against time, log scale (PNG)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    fig = Figure(figsize=(7, 4.2), constrained_layout=True)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    series = [(np.asarray(check.position_difference, float), "max$_i$ |Δx$_i$| [m]", "C0"),
              (np.asarray(check.velocity_difference, float), "max$_i$ |Δv$_i$| [m/s]", "C1")]
    positive = np.concatenate([d[np.isfinite(d) & (d > 0)] for d, _, _ in series])
    zeros = sum(int(np.count_nonzero(d == 0)) for d, _, _ in series)
    for d, label, colour in series:
        # exact zeros (t = 0: both routes start from the same state) have no logarithm: not drawn
        ax.semilogy(check.t, np.where(d > 0, d, np.nan), label=label, color=colour, lw=1.3)
    if len(positive):
        low, high = float(positive.min()), float(positive.max())
        # a lower limit a decade below the smallest difference, never below round-off of 1
        ax.set_ylim(max(low / 10, 1e-18), max(high * 10, low * 100))
    ax.set_xlabel("t [s]")
    ax.set_ylabel("difference, Cartesian − reduced")
    ax.set_title("Cross-check: Cartesian route vs Lagrange's equations in q\n"
                 f"max |Δx| = {check.max_position_difference:.2e} m, "
                 f"max |Δv| = {check.max_velocity_difference:.2e} m/s", fontsize="medium")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize="small", loc="lower right")
    if zeros:
        ax.text(0.01, 0.02, f"{zeros} exact zero{'s' if zeros > 1 else ''} (e.g. at the common start) "
                "not drawn on the log axis", transform=ax.transAxes, fontsize="x-small", color="0.4")
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    return path
