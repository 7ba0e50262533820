"""What the driver watches a run for besides its steps: the constraints losing rank (a
singular configuration, at every model size) and a failed step explained by a limit
position passed (constraints that no position satisfies together beyond it)."""

from __future__ import annotations

import time

import numpy as np

from ..manifold import diagnostics
from ..manifold.manifold import Manifold
from .base import Solver

#: Up to this many coordinates the singular watch takes the dense SVD of the row-normalized J.
DENSE_WATCH_MAX = diagnostics.DENSE_SVD_MAX
#: The singular watch may take this fraction of a run's wall time at most (it is skipped
#: until this much time has passed since its last, measured, cost).
WATCH_SHARE = 0.02
#: The cost a first check is taken to have (a small model's SVD and Jacobian).
FIRST_CHECK_S = 1e-4
#: Up to this many coordinates a failed step is checked for a limit position passed
#: (diagnostics.incompatible_constraints: a dense least-squares solve).
LIMIT_CHECK_MAX = 3000


class SingularWatch:
    """The rank-th singular value σ of the row-normalized J along the run (rank: the
    independent rows at the start); it falls to 0 at a singular configuration.

    Dense SVD for small models; beyond DENSE_WATCH_MAX coordinates the smallest eigenvalue
    σ² of S = Ĵ Ĵᵀ (the independent rows) by inverse iteration on its sparse LU — O(N) on a
    chain. Checks are throttled so they cost at most WATCH_SHARE of the run's wall time.
    """

    def __init__(self, manifold: Manifold, rows: list[int], tol: float | None):
        m = manifold.model if isinstance(manifold, Manifold) else manifold  # (a Model: a batch's member)
        self.model, self.rows = m, rows
        self.on = bool(tol) and bool(rows)
        # (σ of a long straight chain is ≈ 1.1 / rows: the threshold scales with it)
        self.tol = diagnostics.RANK.singular_watch(tol, len(rows)) if self.on else tol
        self.dense = m.n_coordinates <= DENSE_WATCH_MAX
        # as if a first check had cost FIRST_CHECK_S: a run shorter than FIRST_CHECK_S / WATCH_SHARE
        # is not slowed by the watch at all
        self.next_check = time.perf_counter() + FIRST_CHECK_S / WATCH_SHARE
        self._vector = None

    def singularity(self, x, t: float) -> diagnostics.Singularity:
        """σ and the rows of the near-dependency (the left singular vector's weights)."""
        if self.dense:
            return diagnostics.singularity(self.model, x, t, rank=len(self.rows))
        found, vector = diagnostics.sparse_singularity(self.model, x, t, self.rows, start=self._vector)
        self._vector = vector if vector is not None else self._vector
        return found

    def check(self, x, t: float) -> str | None:
        """The stop sentence when σ < tol at (x, t), else None (throttled)."""
        if not self.on:
            return None
        now = time.perf_counter()
        if now < self.next_check:
            return None
        sigma = (diagnostics.rank_sigma(self.model, x, t, len(self.rows)) if self.dense
                 else self.singularity(x, t).sigma)
        self.next_check = now + (time.perf_counter() - now) / WATCH_SHARE
        if sigma >= self.tol:
            return None
        return singular_stop(t, self.singularity(x, t))


def singular_stop(t: float, found: diagnostics.Singularity) -> str:
    """The sentence of a run the singular watch stopped at t: the instant and the rows of the
    near-dependency ``found`` there — for the driver and for a batch's members alike
    (run/variants/watch.MemberSingular)."""
    return f"singular configuration reached at t = {t:.6g} s; likely cause: {found.describe()}"


def past_a_limit(stepper: Solver, last, t_next: float) -> str | None:
    """When a failed step was heading for t_next: the sentence naming the constraints that no
    position satisfies together there (a limit position passed between the last good state
    and t_next, where their rows became dependent), else None."""
    m = stepper.model
    if not m.n_constraints or not m.rheonomic or m.n_coordinates > LIMIT_CHECK_MAX or not t_next > last[0]:
        return None
    try:
        found = diagnostics.incompatible_constraints(m, last[1], t_next)
    except Exception:  # a diagnosis must never hide the stop itself
        return None
    if found.compatible:
        return None
    names = ", ".join(f"'{name}'" for name in found.labels)
    return (f"singular configuration between t = {last[0]:.6g} s and {t_next:.6g} s: beyond it no "
            f"position satisfies the constraints {names} together (a limit position, where their rows "
            "become dependent); likely cause: the drive carries the mechanism past that limit")


#: The collapse watch looks at the time advanced in windows of steps that double in length,
#: from this many steps on.
COLLAPSE_FIRST_SAMPLE = 256
#: ... and calls it a collapse only when the mean step has fallen this far below its largest
COLLAPSE_DROP = 1e-3
#: ... and the mean step of each of the last two windows fell below this fraction of the one
#: before (0.5: each window, twice as many steps as the one before, advanced less time).
COLLAPSE_RATIO = 0.5


class CollapseWatch:
    """Steps that shrink towards zero before t_end: a finite-time singularity (a rod whose
    length is driven to zero, a body falling into a 1/r potential) speeds the motion up
    without bound, and an adaptive method's steps shrink with it: the run would crawl on for
    millions of steps, storing ever more samples, without reaching t*.

    The watch takes the time advanced in windows of steps that double in length (256, 512, …
    steps). Steady steps advance twice as far in each window as in the one before; a collapse
    advances less. When the mean step of each of the last two windows fell below
    COLLAPSE_RATIO of the window before, the mean step is below COLLAPSE_DROP of the run's
    largest, and the windows' geometric series sums to an instant t* before t_end, the run
    stops, naming t*: within a few thousand steps of the collapse's onset whatever its physics.
    A passage through a short fast phase (a close encounter) recovers within a window and is
    not stopped."""

    def __init__(self, t_end: float):
        self.t_end = t_end
        self.samples: list[tuple[int, float]] = []
        self.next_at = COLLAPSE_FIRST_SAMPLE
        self.h_max = 0.0

    def check(self, steps: int, t: float, h: float) -> str | None:
        """The stop sentence when the steps collapse towards a t* before t_end, else None: h
        (the step proposed after ``steps`` accepted steps, at t) counts towards the largest,
        and from ``next_at`` steps on the window ends there (``sample``)."""
        if h > 0 and np.isfinite(h):
            self.h_max = max(self.h_max, h)
        if steps < self.next_at:
            return None
        return self.sample(steps, t, self.h_max)

    def sample(self, steps: int, t: float, h_max: float) -> str | None:
        """A window ends at (steps, t), ``h_max`` the largest step proposed so far: the stop
        sentence when the last windows collapse towards a t* before t_end, else None. (A
        batch keeps each member's largest step and next window itself: run/variants/watch.py.)"""
        self.h_max = h_max
        self.next_at = 2 * max(steps, self.next_at)
        self.samples.append((steps, t))
        if len(self.samples) < 4:
            return None
        (n0, t0), (n1, t1), (n2, t2), (n3, t3) = self.samples[-4:]
        h1, h2, h3 = (t1 - t0) / (n1 - n0), (t2 - t1) / (n2 - n1), (t3 - t2) / (n3 - n2)
        if not (h1 > 0 and h2 < COLLAPSE_RATIO * h1 and h3 < COLLAPSE_RATIO * h2
                and h3 < COLLAPSE_DROP * self.h_max):
            return None
        sigma = h3 / h2  # < 1/2: the next windows' advances form a converging series
        t_star = t3 + (n3 - n2) * h3 * 2 * sigma / (1 - 2 * sigma)
        if not t_star < self.t_end:
            return None
        return (f"the step size collapsed: the mean step fell from {self.h_max:.3g} s to {h3:.3g} s, "
                f"shrinking faster with every step, towards t* ≈ {t_star:.6g} s, where the motion "
                "becomes singular (a finite-time blow-up: no number of steps reaches t*)")


def collapse_stop(reason: str, cause: str) -> str:
    """The sentence of a run the collapse watch stopped: its ``reason`` (``CollapseWatch.check``:
    the steps' fall and the instant t* they head for), then the likely cause at its last good
    state (``diagnostics.likely_cause``) — for the driver and for a batch's members alike."""
    return f"{reason}; {cause}"
