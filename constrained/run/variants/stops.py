"""Where a column of a batched run stops (``run.ensemble``): the chunk's columns that stayed
good are taken, the others frozen at their last good attempt and given a status.

The batch advances every column by a chunk of attempts in one call that returns only the
chunk's end (dopri's step folded, ``ensemble.CHUNK`` times). A column that comes out of it
non-finite or off the constraints failed somewhere inside the chunk: its chunk is replayed
from the chunk's start with dopri's own chained steps, which return every attempt, and the
column is frozen at the attempt before the first bad one — where its own run stops — instead
of at the chunk's start, up to a chunk of attempts earlier.
"""

from __future__ import annotations

import numpy as np

from ...solvers.dopri import NOT_FINITE, PROJECTION_FAIL
from .reasons import DIAGNOSED_MAX


class Replay:
    """The failed columns' chunks replayed attempt by attempt (``last_good``), for at most
    DIAGNOSED_MAX columns a run (those whose stop is diagnosed in full)."""

    def __init__(self, chains: dict, res_slot: int, attempts: int):
        self.chains, self.res_slot, self.attempts = chains, res_slot, attempts
        self.left = DIAGNOSED_MAX

    def last_good(self, start: np.ndarray, limit: float) -> np.ndarray | None:
        """The state after the last of the chunk's attempts from ``start`` before the first one
        that comes out non-finite or with a projection residual above ``limit`` (m; ``start``
        itself when that is the first attempt); None when no attempt of the replay does (its
        evaluation differs from the batch's in round-off) or the replays are used up."""
        if self.left <= 0:
            return None
        self.left -= 1
        last, done = start, 0
        while done < self.attempts:
            k = max(c for c in self.chains if c <= self.attempts - done)
            (out,) = self.chains[k](last)
            for attempt in out.reshape(k, -1):
                if not (np.all(np.isfinite(attempt)) and attempt[self.res_slot] <= limit):
                    return last
                last = attempt
            done += k
        return None


def judge(new: np.ndarray, S: np.ndarray, cols: np.ndarray, status: list, running: np.ndarray,
          scal: dict, scale: np.ndarray, max_steps: int | None, replay: Replay | None = None) -> None:
    """Take the chunk's columns that stayed good; freeze and report the others (a column that
    failed inside the chunk at its last good attempt, ``Replay.last_good``)."""
    finite = np.all(np.isfinite(new), axis=0)
    residual_ok = new[scal["res"]] <= PROJECTION_FAIL * scale[cols]
    for i, k in enumerate(cols):
        if not (finite[i] and residual_ok[i]):
            status[k], running[k] = ("non-finite" if not finite[i] else "projection failed"), False
            last = replay.last_good(S[:, k], PROJECTION_FAIL * scale[k]) if replay is not None else None
            if last is not None:
                S[:, k] = last
            continue
        S[:, k] = new[:, i]
        if max_steps and S[scal["n_acc"], k] + S[scal["n_rej"], k] > max_steps:
            status[k], running[k] = "step limit", False
        elif S[scal["t"], k] < S[scal["t_target"], k] and \
                S[scal["h"], k] < 1e-14 * max(1.0, abs(S[scal["t"], k])):
            # (every trial came out non-finite: dopri.NOT_FINITE)
            status[k] = "non-finite" if S[scal["rejected"], k] == NOT_FINITE else "step size collapsed"
            running[k] = False
