"""The solver contract: every method is a short class with the same ``run`` and counters.

A Solver takes one run's Manifold (constrained.manifold: the immutable Model, the row set
decided at the start, the KKT solve and projections, the run's counters) — never the scene —
and a consistent start (x0, v0, t0), and returns a Solution: output times and states, plus
counters in ``stats`` — ``steps``, ``nfev`` (right-hand sides), ``njev`` (constraint
Jacobians), ``nlu`` (factorizations), ``projections``; methods that know it add ``rejected``.

Redundant constraint rows: the manifold holds an independent subset (``rows``); methods
that build their own equations use ``self.rows`` (all rows when none is redundant), and the
multipliers of a run are always the minimum-norm ones over every row.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from .. import diagnostics, interrupt
from ..errors import InputError
from ..manifold import Manifold
from ..model import Model


class Status(enum.Enum):
    """How a run ended; ``message`` is one plain sentence for each."""

    COMPLETED = "completed"
    INTERRUPTED = "interrupted"
    STEP_SIZE_COLLAPSED = "step size collapsed"
    PROJECTION_FAILED = "projection failed"
    NON_FINITE = "non-finite values"
    SINGULAR_CONFIGURATION = "singular configuration"
    STIFF = "stiff"
    STEP_LIMIT = "step limit"
    SOLVER_FAILED = "solver failed"

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Status.COMPLETED: "the run reached t_end",
    Status.INTERRUPTED: "the run was stopped by Ctrl-C; what was computed is kept",
    Status.STEP_SIZE_COLLAPSED: "the step size fell to round-off before t_end",
    Status.PROJECTION_FAILED: "the state could not be brought back onto the constraints",
    Status.NON_FINITE: "positions, velocities or forces became infinite or NaN",
    Status.SINGULAR_CONFIGURATION: "the constraints became dependent (a singular configuration)",
    Status.STIFF: "the steps follow an oscillation far faster than the run (stiffness)",
    Status.STEP_LIMIT: "the run took more steps than allowed",
    Status.SOLVER_FAILED: "the integrator (SUNDIALS) stopped with an error",
}

class Failure(str):
    """The text of a stop, carrying its ``status``: reads as the sentence a user sees, and
    simulate branches on ``status`` instead of parsing the words."""

    status: Status

    def __new__(cls, status: Status, text: str):
        obj = super().__new__(cls, text)
        obj.status = status
        return obj


@dataclass
class Solution:
    t: np.ndarray
    x: np.ndarray  # (T, 3N)
    v: np.ndarray  # (T, 3N)
    stats: dict = field(default_factory=dict)
    failure: str | None = None  # why the run stopped early, if it did (a Failure)

    @property
    def status(self) -> Status:
        if not self.failure:
            return Status.COMPLETED
        return getattr(self.failure, "status", Status.SOLVER_FAILED)


class Solver:
    """Base class. Subclasses set ``name`` and implement ``run``."""

    name = ""
    adaptive = True
    #: The order p of the method (global error ∝ h^p), or None for variable-order methods
    #: (SUNDIALS' BDF and Adams) whose error follows the tolerance instead.
    order: int | None = None
    #: The method's own keyword options (besides rtol, atol, dt, compiled, progress): the
    #: declaration the scene reader and run_options consult.
    OPTIONS: tuple[str, ...] = ()
    #: The base integrators or tableaus ``base`` may name (methods that take one).
    BASES: tuple[str, ...] = ()

    def __init__(self, manifold, *, rtol: float = 1e-8, atol: float = 1e-10, dt: float | None = None,
                 compiled="auto", progress=None, **options):
        for key, value in (("rtol", rtol), ("atol", atol)):
            if not (isinstance(value, int | float) and np.isfinite(value) and 0 < value < 1):
                raise InputError(f"{key} must be a number between 0 and 1, got {value!r}")
        if dt is not None and not (isinstance(dt, int | float) and np.isfinite(dt) and dt > 0):
            raise InputError(f"dt must be a positive number of seconds, got {dt!r}")
        if options:
            raise InputError(
                f"method '{self.name}' does not take the option(s) {', '.join(sorted(options))}"
            )
        if compiled not in (True, False, "auto"):
            raise InputError(f"compiled must be true, false or \"auto\", got {compiled!r}")
        if isinstance(manifold, Model):  # a bare Model: every row independent
            manifold = Manifold(manifold)
        #: This run's view of the constraints (row set, KKT solve, counters).
        self.manifold: Manifold = manifold
        self.model: Model = manifold.model
        #: The constraint rows the method's own equations use (an independent set).
        self.rows: list[int] = (list(range(manifold.model.n_constraints)) if manifold.rows is None
                                else list(manifold.rows))
        self.rtol, self.atol, self.dt = float(rtol), float(atol), dt
        #: The compiled-evaluation setting as given (see constrained.compiled).
        self.compiled_setting = compiled
        if progress is not None and not callable(progress):
            raise InputError(f"progress must be a function of the time reached, got {progress!r}")
        self._progress = progress
        self.stats = {"steps": 0, "nfev": 0, "njev": 0, "nlu": 0, "projections": 0}
        self._stiffness: diagnostics.StiffnessWatch | None = None

    def report(self, t: float) -> None:
        """Tell the ``progress`` callback (if any) that the run has reached time ``t``."""
        if self._progress is not None:
            self._progress(float(t))

    def counted(self) -> dict:
        """The run's statistics: the method's own counts, and the manifold's where larger
        (work done in the KKT solves and projections is counted there)."""
        stats = dict(self.stats)
        for key, value in self.manifold.counters.as_dict().items():
            stats[key] = max(int(stats.get(key, 0)), value)
        return stats

    def watch_stiffness(self, x0, t0: float, t_end: float) -> None:
        """Start watching the run for a stiff spring (diagnostics.StiffnessWatch)."""
        self._stiffness = diagnostics.StiffnessWatch(self.model, x0, t0, t_end, method=self.name)

    def too_stiff(self, t: float, steps: int, x=None) -> str | None:
        """The ``failure`` that stops a run whose steps follow a stiff spring's oscillation
        (after a few seconds of wall time, when t_end is far at that pace), else None."""
        verdict = self._stiffness.check(t, steps, x) if self._stiffness is not None else None
        if verdict is None:
            return None
        return Failure(Status.STIFF,
            f"the steps follow a fast oscillation at t = {float(t):.6g} s; {verdict}")

    def stiff_hint(self) -> str:
        """For the end-of-run stiffness warning: the fastest spring and what to do about it."""
        e = self._stiffness.fastest() if self._stiffness is not None else None
        if e is None:
            return ""
        hint = f"; the fastest spring, '{e.label}' (effect {e.index}), has period {e.period:.3g} s"
        return hint + (f": {e.constraint_advice()}" if e.rigid_like else "")

    @staticmethod
    def stop_requested() -> bool:
        """Whether Ctrl-C asked the run to stop (see constrained.interrupt): loops ask after
        every step or chunk, and stop there keeping what they computed."""
        return interrupt.requested()

    @staticmethod
    def interrupted_at(t: float) -> str:
        """The ``failure`` of a run stopped by Ctrl-C after its last state, at time t."""
        return Failure(Status.INTERRUPTED, f"{Status.INTERRUPTED.value} at t = {float(t):.6g} s")

    def require_independent_constraints(self, why: str) -> None:
        """Refuse a run whose constraint rows are dependent (``Manifold.redundant``)."""
        if self.manifold.redundant:
            raise InputError(
                f"method '{self.name}' needs independent constraints ({why} for redundant ones); "
                "remove the implied constraints or use method 'projection'"
            )

    def run(self, x0, v0, t0: float, t_end: float, t_eval=None) -> Solution:
        raise NotImplementedError
