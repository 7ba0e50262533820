"""The single run's watches for each member of a batched run: the stiffness watch
(``solvers.stiffness.StiffnessWatch``) on the batch's wall clock shared out among the members
(``MemberWatch``), the collapse watch (``solvers.watches.CollapseWatch``) on each member's
own steps (``MemberCollapse``), and the singular-configuration watch
(``solvers.watches.SingularWatch``) on each member's share of the clock (``MemberSingular``).

A single run is stopped when, after AFTER_S seconds of wall time, reaching t_end at its pace
would take BUDGET_S or more and its steps are held down by a barely stretched stiff spring or
a damper. Inside a batch the wall clock is the whole batch's: a member with a stiff spring
(k = 1e9 N/m on a 10 g bead among soft members) used to run its whole step budget before it
was named. Here each member is judged on its own share of the clock and its own steps.

A single run whose steps collapse towards a finite-time blow-up (a rod driven to zero length)
is stopped within a few thousand steps, naming the instant t*; a batched member used to crawl
on until its step size reached its floor (10,261,543 steps for a rod of length 1 − t, 2,535
alone). Here each member's steps are watched as its own run's are.

A single run stops where the constraints lose rank (a mechanism driven to its limit position,
two rods pulled collinear), naming the rows; a batched member used to go on until a projection
failed or its steps collapsed there, with a generic cause. Here each member is checked as its
own run is, on its share of the clock.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from ...codegen.fast_call import FastCall
from ...manifold import diagnostics
from ...model.cache import ParametricView, structure_cache
from ...solvers.stiffness import StiffnessWatch, stiff_stop
from ...solvers.watches import (
    COLLAPSE_FIRST_SAMPLE,
    DENSE_WATCH_MAX,
    FIRST_CHECK_S,
    WATCH_SHARE,
    CollapseWatch,
    SingularWatch,
    collapse_stop,
    singular_stop,
)
from .reasons import DIAGNOSED_MAX, variant_model


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


class MemberCollapse:
    """``CollapseWatch`` for each member, as the driver runs it for a single run: after each
    call in which a member took accepted steps and is short of t_end, the step it proposes
    counts towards its largest (kept here for every member, in one array), and a member whose
    accepted steps reached its next window's end (256, 512, … steps, as its own run's) is
    sampled: steps that collapse towards a t* before t_end stop it, at the state it reached,
    with its own run's sentence (``collapse_stop``: the watch's reason, then the likely cause
    there). The calls are the batch's chunks of attempts, which are its own run's calls when
    it has no output times in between (dopri chains as many attempts), so it is judged on the
    same windows; output times split its own run's calls differently, and move its windows' ends
    by less than a call. The first DIAGNOSED_MAX members stopped get the likely cause (a model
    view and an SVD or two each), the others the watch's reason alone."""

    def __init__(self, model, P: np.ndarray, t_end: float):
        self.model, self.P, self.t_end = model, P, float(t_end)
        self.h_max = np.zeros(len(P))
        self.next_at = np.full(len(P), float(COLLAPSE_FIRST_SAMPLE))
        self.watches: dict[int, CollapseWatch] = {}
        self.diagnosed = 0

    def stops(self, members: np.ndarray, before: np.ndarray, S: np.ndarray, scal: dict, n3: int) -> list:
        """(member, sentence) of each of ``members`` (running after the call, ``before`` their
        accepted steps before it) whose steps collapse; ``S`` the batch's state matrix."""
        t, steps, h = S[scal["t"], members], S[scal["n_acc"], members], S[scal["h"], members]
        moved = (steps > before) & (t < self.t_end)  # (the driver: a call with accepted steps)
        seen = moved & (h > 0) & np.isfinite(h)
        self.h_max[members[seen]] = np.maximum(self.h_max[members[seen]], h[seen])
        stopped = []
        for i in np.flatnonzero(moved & (steps >= self.next_at[members])):
            k = int(members[i])
            watch = self.watches.setdefault(k, CollapseWatch(self.t_end))
            reason = watch.sample(int(steps[i]), float(t[i]), float(self.h_max[k]))
            self.next_at[k] = watch.next_at
            if reason:
                stopped.append((k, self.sentence(k, reason, S[:n3, k], S[n3:2 * n3, k], float(t[i]))))
        return stopped

    def sentence(self, k: int, reason: str, x: np.ndarray, v: np.ndarray, t: float) -> str:
        """Member k's own run's sentence at its last good state (x, v, t), and where that is
        (as ``simulate`` ends its message)."""
        if self.diagnosed >= DIAGNOSED_MAX:
            return _at_last_good(reason, t)
        self.diagnosed += 1
        try:
            cause = diagnostics.likely_cause(variant_model(self.model, self.P[k]), x, v, t)
        except Exception:  # a diagnosis must never hide the stop itself
            return _at_last_good(reason, t)
        return _at_last_good(collapse_stop(reason, cause), t)


class MemberSingular:
    """``SingularWatch`` for each member, on its share of the batch's clock (``share``: the
    seconds ``MemberWatch`` charges it). A single run checks σ, the rank-th singular value of
    the row-normalized J (rank: the run's rows), after a call that took accepted steps short of
    t_end, once FIRST_CHECK_S / WATCH_SHARE of wall time has passed, and then whenever the time
    since its last check is its cost / WATCH_SHARE. Here a member is due when its share has
    reached as much: the due members of a call are checked together, σ from one mapped
    evaluation of their J and one stacked SVD (``diagnostics.rank_sigmas``), and each is charged
    its part of that cost. A member whose σ < ``tol`` is stopped at the state it reached, with
    its own run's sentence (``singular_stop``: the instant and the rows of the near-dependency,
    ``diagnostics.dependency``). Members that never take FIRST_CHECK_S / WATCH_SHARE of the
    clock (5 ms: a short batch's) are not checked on the way, as such a run is not. Beyond
    DENSE_WATCH_MAX coordinates each due member's own SingularWatch takes σ on the sparse J.

    A batched member costs far less wall time than its own run (a compiled batch of four beads
    on two rods, two of them driven to their limit, ended in 5 ms), so its share may never come
    due where its own run's clock does. ``last_looks``: a member stopped by a failed step or a collapse
    (FAILURES) is looked at once more at its last good state; at a singular configuration it is
    reported as one, in the watch's words, as its own run's watch, looking there, reports it."""

    #: The clock the checks are timed with (a test may put a fake one here).
    clock = staticmethod(time.perf_counter)
    #: The stops a singular configuration at the last good state explains (the driver's
    #: STEP_FAILURES, and the collapse watch's).
    FAILURES = ("projection failed", "step size collapsed")

    def __init__(self, model, P: np.ndarray, rows, tol: float | None, t_end: float, share: np.ndarray):
        self.model, self.P, self.rows, self.tol = model, P, list(rows), tol
        self.t_end, self.share = float(t_end), share
        self.on = bool(tol) and bool(self.rows)
        # (the dense checks' threshold, as SingularWatch scales it for the sparse path)
        self.threshold = diagnostics.RANK.singular_watch(tol, len(self.rows)) if self.on else tol
        self.due = np.full(len(P), FIRST_CHECK_S / WATCH_SHARE)
        self.dense = model.n_coordinates <= DENSE_WATCH_MAX
        self.watches: dict[int, SingularWatch] = {}  # (the sparse path's, per member)

    def stops(self, members: np.ndarray, before: np.ndarray, S: np.ndarray, scal: dict, n3: int) -> list:
        """(member, sentence) of each of ``members`` (running after the call, ``before`` their
        accepted steps before it) that is due and at a singular configuration."""
        if not self.on or not members.size:
            return []
        t = S[scal["t"], members]
        moved = (S[scal["n_acc"], members] > before) & (t < self.t_end)  # (the driver's condition)
        due = members[moved & (self.share[members] >= self.due[members])]
        if not due.size:
            return []
        tick = self.clock()
        found = self._singular(due, S, scal["t"], n3)
        cost = (self.clock() - tick) / due.size
        # (a member whose evaluation failed stays off: its due is infinite)
        self.due[due] = np.maximum(self.due[due], self.share[due] + cost / WATCH_SHARE)
        return found

    def last_looks(self, status: list, S: np.ndarray, scal: dict, n3: int) -> list:
        """(member, sentence) of each member stopped with one of FAILURES whose last good state
        (its frozen column of S) is a singular configuration (the sparse path: the first
        DIAGNOSED_MAX such members)."""
        failed = np.array([k for k, st in enumerate(status) if st in self.FAILURES], int)
        if not self.on or not failed.size:
            return []
        return self._singular(failed if self.dense else failed[:DIAGNOSED_MAX], S, scal["t"], n3)

    def _singular(self, members: np.ndarray, S: np.ndarray, t_slot: int, n3: int) -> list:
        """(member, sentence) of each of ``members`` whose σ at its state in S is below tol."""
        try:
            sigma, found = self._sigmas(members, S, t_slot, n3)
        except Exception:  # a diagnosis only: a watch that cannot judge lets the members run
            self.due[members] = np.inf
            return []
        return [(int(k), _at_last_good(singular_stop(S[t_slot, k], found(i)), S[t_slot, k]))
                for i, k in enumerate(members) if sigma[i] < self.threshold]

    def _sigmas(self, due: np.ndarray, S: np.ndarray, t_slot: int, n3: int):
        """(σ of each due member, i -> the near-dependency of the i-th)."""
        if not self.dense:  # each member's own run's sparse watch (its inverse-iteration vector kept)
            found = [self._watch(int(k)).singularity(S[:n3, k], float(S[t_slot, k])) for k in due]
            return np.array([f.sigma for f in found]), found.__getitem__
        n, c = 1 << (due.size - 1).bit_length(), self.model.n_constraints  # (calls of 1, 2, 4, … columns)
        cols = np.concatenate([due, np.repeat(due[-1:], n - due.size)])
        (G,) = mapped_jacobian(self.model, n)(S[:n3, cols].ravel(order="F"), S[t_slot, cols],
                                              self.P[cols].ravel())
        Jn = diagnostics.row_normalized(G.reshape(n, n3, c).transpose(0, 2, 1)[:due.size])
        rank, labels = len(self.rows), self.model.constraint_labels
        return (diagnostics.rank_sigmas(Jn, rank),
                lambda i: diagnostics.dependency(Jn[i], labels, rank=rank))

    def _watch(self, k: int) -> SingularWatch:
        if k not in self.watches:
            self.watches[k] = SingularWatch(variant_model(self.model, self.P[k]), self.rows, self.tol)
        return self.watches[k]


def _at_last_good(sentence: str, t: float) -> str:
    """A stopped member's sentence ended as its own run's message ends (``simulate``)."""
    return f"{sentence}; the last good state is at t = {t:.6g} s"


def mapped_jacobian(model, n: int) -> FastCall:
    """``(x, t, p) -> G`` for n columns at once (each G the dense C × 3N matrix of every row,
    ``manifold.dense_jacobian``'s, with the column's parameters): once per structure and n."""
    cache, prefix = structure_cache(model)
    key = (*prefix, "ensemble jacobian", n)
    if key not in cache:
        kind = ca.MX if getattr(model.structure, "pairs", ()) else ca.SX
        X, T = kind.sym("x", model.n_coordinates), kind.sym("t")
        P = kind.sym("p", len(model.parameter_vector))
        G = ca.densify(ParametricView(model, P).velocity_terms(X, T)[0])
        cache[key] = FastCall(ca.Function("ensemble_jacobian", [X, T, P], [G]).map(n))
    return cache[key]
