"""The solver contract: every method is a small stepper class; solvers/driver.py runs them.

A Solver takes one run's Manifold (constrained.manifold: the immutable Model, the row set
decided at the start, the KKT solve and projections, the run's counters) — never the scene.
It implements

    init(x0, v0, t0, t_end) -> state          a consistent start (also used for restarts)
    step(state, t_stop) -> Advance            one or more accepted steps towards t_stop

and makes no decisions: the driver (solvers/driver.py, THE time loop) owns output times,
dense output, events, progress, Ctrl-C, the singular-configuration, stiffness and
non-finite watches and the step limit, and returns a Solution: output times and states,
the events met, plus counters in ``stats`` — ``steps``, ``nfev`` (right-hand sides),
``njev`` (constraint Jacobians), ``nlu`` (factorizations), ``projections``; methods that
know it add ``rejected``.

Redundant constraint rows: the manifold holds an independent subset (``rows``); methods
that build their own equations use ``self.rows`` (all rows when none is redundant), and the
multipliers of a run are always the minimum-norm ones over every row.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .. import interrupt
from ..errors import InputError
from ..manifold import diagnostics
from ..manifold.manifold import Manifold
from ..model.structure import Model
from .dense import hermite


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
    EVENT = "terminal event"

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
    Status.EVENT: "a terminal event was reached",
}

class Failure(str):
    """The text of a stop, carrying its ``status``: reads as the sentence a user sees, and
    simulate branches on ``status`` instead of parsing the words."""

    status: Status

    def __new__(cls, status: Status, text: str):
        obj = super().__new__(cls, text)
        obj.status = status
        return obj


@dataclass(frozen=True)
class Event:
    """A function of the state whose zero crossings the driver locates (solve_ivp's habits).

    ``function(t, x, v) -> g`` with flat x and v; ``direction`` +1 takes only rising
    crossings (g from − to +), −1 only falling ones, 0 both; a ``terminal`` event ends the
    run there (its state is the run's last sample). ``ignore_round_off`` (the user's events):
    a sign change between two values both within the run's resolution (how much g moves when
    the state moves by atol) is not a crossing: a quantity the constraints hold at zero only to
    round-off flips sign from sample to sample.

    ``rate(t, x, v) -> dg/dt`` along the motion (optional; a falling event, direction −1): a g
    that stays positive at both samples of a step but turns around between them (rate < 0
    before, > 0 after: a bead that dips through a floor and comes back within one step) is
    checked at its minimum on the dense output, and a minimum below zero is a crossing.
    """

    name: str
    function: Callable[[float, np.ndarray, np.ndarray], float]
    direction: int = 0
    terminal: bool = True
    ignore_round_off: bool = False
    rate: Callable[[float, np.ndarray, np.ndarray], float] | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"an event needs a name, got {self.name!r}")
        if not callable(self.function):
            raise InputError(f"event '{self.name}': function must be callable g(t, x, v)")
        if self.direction not in (-1, 0, 1):
            raise InputError(f"event '{self.name}': direction must be -1, 0 or 1, got {self.direction!r}")

    def crossed(self, g_before: float, g_after: float) -> bool:
        """Whether g went through zero between two samples in the allowed direction (from
        exactly zero too: a gap that starts closed and opens the forbidden way)."""
        rising = g_before <= 0 < g_after or g_before < 0 == g_after
        falling = g_before >= 0 > g_after or g_before > 0 == g_after
        return {1: rising, -1: falling, 0: rising or falling}[self.direction]


@dataclass(frozen=True)
class EventHit:
    """An event located to round-off: the instant ``t`` and the state (x, v) there."""

    event: Event
    t: float
    x: np.ndarray
    v: np.ndarray


@dataclass(frozen=True)
class Advance:
    """What one ``Solver.step`` call did: its accepted samples (times increasing, the last
    one the new state) with accelerations ``a`` where the method has them (for the driver's
    quintic Hermite dense output), an ``interpolant(t) -> (x, v)`` where the method has its
    own (one step), the step size ``h`` proposed next, and — when the step failed — a status
    and its sentence (the samples are then the good ones before the failure)."""

    state: object
    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    a: np.ndarray | None = None
    interpolant: Callable[[float], tuple[np.ndarray, np.ndarray]] | None = None
    h: float | None = None
    status: Status = Status.COMPLETED
    message: str = ""

    @classmethod
    def empty(cls, state, n: int, status: Status = Status.COMPLETED, message: str = "") -> Advance:
        """No accepted sample: the call failed before one (status, message), or it only
        rearranged the stepper's work (COMPLETED: the driver calls again)."""
        return cls(state, np.zeros(0), np.zeros((0, n)), np.zeros((0, n)), status=status, message=message)


@dataclass
class Solution:
    t: np.ndarray
    x: np.ndarray  # (T, 3N)
    v: np.ndarray  # (T, 3N)
    stats: dict = field(default_factory=dict)
    failure: str | None = None  # why the run stopped early, if it did (a Failure)
    events: list[EventHit] = field(default_factory=list)  # every event met, in time order

    @property
    def status(self) -> Status:
        if not self.failure:
            return Status.COMPLETED
        return getattr(self.failure, "status", Status.SOLVER_FAILED)


#: Options every method takes, honoured by the driver: a step limit (accepted plus rejected
#: steps; default none) and the threshold of the singular-configuration watch (None or 0
#: turns it off).
DRIVER_OPTIONS = ("max_steps", "singular_tol")
#: The run stops at a singular configuration when the rank-th singular value of the
#: row-normalized J (rank: at the start) falls below ``singular_tol``.
SINGULAR_TOL = 1e-4


class Solver:
    """Base class. Subclasses set ``name`` and implement ``init`` and ``step``."""

    name = ""
    adaptive = True
    #: The order p of the method (global error ∝ h^p), or None for variable-order methods
    #: (SUNDIALS' BDF and Adams) whose error follows the tolerance instead.
    order: int | None = None
    #: The method's own keyword options (besides rtol, atol, dt, compiled, progress): the
    #: declaration the scene reader and run_options consult (DRIVER_OPTIONS included).
    OPTIONS: tuple[str, ...] = DRIVER_OPTIONS
    #: The base integrators or tableaus ``base`` may name (methods that take one).
    BASES: tuple[str, ...] = ()
    #: Whether ``step`` stops exactly at the t_stop it is given: the driver then passes the
    #: output times as stops (and lands on event instants when refining them); otherwise
    #: outputs come from the dense output between steps.
    lands = True
    #: Whether the driver refines an event instant by restarting the stepper at the sample
    #: before and landing on candidate instants (else the dense output's root is taken).
    refines_events = True
    #: Whether the method is explicit (the driver then samples h·ρ(∂f/∂y) for stiffness).
    explicit = False
    #: Why the method cannot take velocity constraints (model/velocity.py), or None: it can.
    refuses_velocity_rows: str | None = None

    def __init__(self, manifold, *, rtol: float = 1e-8, atol: float = 1e-10, dt: float | None = None,
                 compiled="auto", progress=None, max_steps: int | None = None,
                 singular_tol: float | None = SINGULAR_TOL, **options):
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
        if max_steps is not None and (isinstance(max_steps, bool) or not (isinstance(max_steps, int)
                                                                           and max_steps > 0)):
            raise InputError(f"max_steps must be a positive whole number, got {max_steps!r}")
        if singular_tol is not None and not (isinstance(singular_tol, int | float)
                                             and 0 <= singular_tol < 1):
            raise InputError(f"singular_tol must be a number in [0, 1) or None, got {singular_tol!r}")
        if isinstance(manifold, Model):  # a bare Model: every row independent
            manifold = Manifold(manifold)
        #: This run's view of the constraints (row set, KKT solve, counters).
        self.manifold: Manifold = manifold
        self.model: Model = manifold.model
        if self.refuses_velocity_rows and self.model.n_position_rows < self.model.n_constraints:
            raise InputError(f"method '{self.name}' cannot take velocity constraints: "
                             f"{self.refuses_velocity_rows}; use another method (dopri, projection, "
                             "rodas, baumgarte, idas, ggl, pantelides, or reduced with [reduced] "
                             "coordinates)")
        #: The constraint rows the method's own equations use (an independent set).
        self.rows: list[int] = (list(range(manifold.model.n_constraints)) if manifold.rows is None
                                else list(manifold.rows))
        self.rtol, self.atol, self.dt = float(rtol), float(atol), dt
        self.max_steps = max_steps
        self.singular_tol = singular_tol
        #: The compiled-evaluation setting as given (see constrained.compiled).
        self.compiled_setting = compiled
        if progress is not None and not callable(progress):
            raise InputError(f"progress must be a function of the time reached, got {progress!r}")
        self.progress = progress
        self.stats = {"steps": 0, "nfev": 0, "njev": 0, "nlu": 0, "projections": 0}

    # --- the contract ---------------------------------------------------------------------
    def prepare(self, t0: float, t_end: float, t_eval) -> None:
        """Check the run's span and output times before anything is stepped (InputError)."""

    def default_grid(self, t0: float, t_end: float) -> np.ndarray | None:
        """Output times when the caller gives none: None means every accepted step."""
        return None

    def init(self, x0: np.ndarray, v0: np.ndarray, t0: float, t_end: float, first_step: float | None = None):
        """The stepper's state at a consistent (x0, v0, t0), for a run (or a restart) to t_end;
        ``first_step``: the step to try first (an event's refinement lands in one step)."""
        raise NotImplementedError

    def step(self, state, t_stop: float) -> Advance:
        """Advance towards t_stop (never past it) by one or more accepted steps."""
        raise NotImplementedError

    def start_acceleration(self, state) -> np.ndarray | None:
        """The acceleration at the start of a run from ``init``'s state, when the state holds
        it (the first interval's dense output is then quintic too), else None."""
        return None

    def between(self, t0: float, x0, v0, a0, t1: float, x1, v1, a1):
        """The dense output on [t0, t1] from two accepted samples (``dense.hermite``) for a
        method without an interpolant of its own: ``t -> (x, v)``."""
        return hermite(t0, x0, v0, a0, t1, x1, v1, a1)

    def output(self, t: float, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """An output sample taken from the dense output: projecting methods project it."""
        return x, v

    def derivative(self, t: float, y: np.ndarray) -> np.ndarray:
        """(x', v') of the method's ODE, for the stiffness estimate of explicit methods."""
        n = self.model.n_coordinates
        return np.concatenate([y[n:], self.manifold.accelerations(y[:n], y[n:], t)[0]])

    def stiffness_advice(self) -> tuple[str, str]:
        """(what, advice) for the end-of-run stiffness warning of an explicit method."""
        return f"method {self.name}", 'use method = "projection" with base = "Radau" or "CVODES_BDF"'

    def diagnose(self, x, v, t) -> str:
        """The likely cause of a stop, from the last good state (x, v, t)."""
        return diagnostics.likely_cause(self.model, x, v, t, self.manifold)

    def finish(self) -> None:
        """Called once after the run (the method's final statistics)."""

    # --- helpers --------------------------------------------------------------------------
    def counted(self) -> dict:
        """The run's statistics: the method's own counts, and the manifold's where larger
        (work done in the KKT solves and projections is counted there)."""
        stats = dict(self.stats)
        for key, value in self.manifold.counters.as_dict().items():
            stats[key] = max(int(stats.get(key, 0)), value)
        return stats

    @staticmethod
    def stop_requested() -> bool:
        """Whether Ctrl-C asked the run to stop (see constrained.interrupt)."""
        return interrupt.requested()

    def require_independent_constraints(self, why: str) -> None:
        """Refuse a run whose constraint rows are dependent (``Manifold.redundant``)."""
        if self.manifold.redundant:
            raise InputError(
                f"method '{self.name}' needs independent constraints ({why} for redundant ones); "
                "remove the implied constraints or use method 'projection'"
            )
