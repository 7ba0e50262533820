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
