"""SUNDIALS' own messages kept off the terminal. CasADi writes them to Python's ``sys.stderr``
from inside a call ("At t = 0.998755, , mxstep steps taken before reaching tout."), before
the call fails; the stepper then reports the failure in its own words (what collapsed, where,
the fix), so the raw lines only repeat it, a dozen at a time while a call is retried.

``quiet()`` wraps such a call: what the calling thread writes to ``sys.stderr`` meanwhile is
kept in the list it yields instead; other threads' writes pass through. One filter is
installed while any thread is inside ``quiet()``, and removed when the last one leaves
(unless something else replaced ``sys.stderr`` since: that is left alone)."""

from __future__ import annotations

import contextlib
import sys
import threading

_lock = threading.Lock()
#: thread id -> what that thread wrote to sys.stderr inside quiet()
_kept: dict[int, list[str]] = {}
#: [the filter, the stream it replaced] while installed
_installed: list = [None, None]


class _Filter:
    def __init__(self, stream):
        self.stream = stream

    def write(self, text: str) -> int:
        kept = _kept.get(threading.get_ident())
        if kept is None:
            return self.stream.write(text)
        kept.append(text)
        return len(text)

    def flush(self) -> None:
        self.stream.flush()

    def __getattr__(self, name):
        return getattr(self.stream, name)


@contextlib.contextmanager
def quiet():
    """Keep what this thread writes to sys.stderr inside the block (yielded as a list)."""
    ident = threading.get_ident()
    with _lock:
        if ident in _kept:  # nested: the outer block keeps it
            nested = True
        else:
            nested = False
            _kept[ident] = []
            if _installed[0] is None:
                _installed[:] = [_Filter(sys.stderr), sys.stderr]
                sys.stderr = _installed[0]
        kept = _kept[ident]
    try:
        yield kept
    finally:
        if not nested:
            with _lock:
                del _kept[ident]
                if not _kept and _installed[0] is not None:
                    if sys.stderr is _installed[0]:
                        sys.stderr = _installed[1]
                    _installed[:] = [None, None]


#: Below this, rtol (or atol over the state's size) asks IDAS for a local error at round-off.
TIGHTEST_TOLERANCE = 1e-13


def tolerance_cause(rtol: float, atol: float, scale: float) -> str:
    """"; likely cause: the tolerance …" for a failed IDAS call whose rtol or atol / scale is
    below TIGHTEST_TOLERANCE, else "". At rtol = atol = 1e-14 the bead on a rotating hoop
    stopped `idas` with IDA_LINESEARCH_FAIL at t = 0.3 s and `ggl` with IDA_CONV_FAIL at
    0.9 s, which were put down to "forces that blow up" at accelerations of 9–17 m/s²; at
    1e-13 both run. IDAS's Newton corrector cannot bring a step's error below the round-off
    of its own residual, ε × the size of the terms it sums."""
    if min(rtol, atol / max(scale, 1.0)) >= TIGHTEST_TOLERANCE:
        return ""
    return (f"; likely cause: the tolerance: rtol = {rtol:g}, atol = {atol:g} ask IDAS for a local error "
            "at the round-off of double precision, where its Newton corrector stops converging; "
            "loosen both to 1e-12 or above, or use dopri or projection, whose error at the end is "
            "about rtol (docs/methods.md)")
