"""The single run's stiffness watch (``solvers.stiffness.StiffnessWatch``) for each member of a
batched run, on the batch's wall clock shared out among the members.

A single run is stopped when, after AFTER_S seconds of wall time, reaching t_end at its pace
would take BUDGET_S or more and its steps are held down by a barely stretched stiff spring or
a damper. Inside a batch the wall clock is the whole batch's: a member with a stiff spring
(k = 1e9 N/m on a 10 g bead among soft members) used to run its whole step budget before it
was named. Here each member is judged on its own share of the clock and its own steps.
"""

from __future__ import annotations

import time

import numpy as np

from ...solvers.stiffness import StiffnessWatch, stiff_stop
from .reasons import variant_model


class MemberWatch:
    """Each call of the batch's step loop on n members charges each of them Δt/n of its wall
    time Δt, so a member's share w_k is the wall time the batch spends on it (a member left
    alone at the end is charged whole calls, its block's filler columns included). From
    StiffnessWatch.AFTER_S of share on, every EVERY_S of it, a member's projected time to t_end
    at its own pace,

        T_k = w_k (t_end − t0) / (t_k − t0),

    goes with its own state, time and accepted steps n_k to ``StiffnessWatch.verdict``, the
    single run's judgement: T_k ≥ BUDGET_S, and the mean step (t_k − t0)/n_k within the period
    2π/ω of a barely stretched spring (or HELD × m/c of a damper). A verdict stops that member
    alone, in its own run's words (``stiff_stop``). A member's StiffnessWatch is built when it is
    first due, from that member's parameters and start (members that never take AFTER_S of the
    clock cost nothing; one with no stiff element is never looked at again)."""

    #: The clock the calls are timed with (a test may put a fake one here).
    clock = staticmethod(time.perf_counter)

    def __init__(self, model, P: np.ndarray, starts: np.ndarray, t0: float, t_end: float):
        self.model, self.P, self.starts = model, P, starts
        self.t0, self.t_end = float(t0), float(t_end)
        self.share = np.zeros(len(P))
        self.due = np.full(len(P), float(StiffnessWatch.AFTER_S))
        self.watches: dict[int, StiffnessWatch | None] = {}

    def charge(self, members: np.ndarray, seconds: float) -> None:
        """One call of ``seconds`` that advanced ``members``: each is charged its part."""
        self.share[members] += seconds / len(members)

    def stops(self, members: np.ndarray, t: np.ndarray, steps: np.ndarray, x: np.ndarray) -> list:
        """(member, sentence) of each of ``members`` the watch stops; ``t``, ``steps`` (accepted)
        are over all members, ``x`` their positions (coordinates, members)."""
        stopped = []
        for k in members[self.share[members] >= self.due[members]]:
            self.due[k] = self.share[k] + StiffnessWatch.EVERY_S
            done = float(t[k]) - self.t0
            projected = np.inf if done <= 0 else self.share[k] * (self.t_end - self.t0) / done
            if projected < StiffnessWatch.BUDGET_S:
                continue
            watch = self._watch(int(k))
            if watch is None:
                self.due[k] = np.inf
                continue
            try:
                verdict = watch.verdict(float(t[k]), int(steps[k]), x[:, k], projected)
            except Exception:  # a diagnosis only: a watch that cannot judge lets the member run
                verdict, self.due[k] = None, np.inf
            if verdict:
                stopped.append((int(k), stiff_stop(verdict, t[k])))
        return stopped

    def _watch(self, k: int) -> StiffnessWatch | None:
        """Member k's own run's watch, or None when it has no spring or damper to watch."""
        if k not in self.watches:
            try:
                watch = StiffnessWatch(variant_model(self.model, self.P[k]), self.starts[k], self.t0,
                                       self.t_end, method="dopri")
            except Exception:  # a diagnosis only: a member it cannot measure is not watched
                watch = None
            self.watches[k] = watch if watch is not None and (watch.elements or watch.dampers) else None
        return self.watches[k]
