"""Ctrl-C during a run: a request to stop, honoured at the next safe point.

Python's default SIGINT handler raises KeyboardInterrupt wherever the interpreter happens to
be: inside a projection, half-way through building the output arrays, or inside a CasADi
call (where SUNDIALS turns it into a failed residual). Runs then either lost what they had
computed or carried on. ``watch()`` replaces the handler for the length of a run with one
that only records the request; the solvers' loops ask ``requested()`` after every step or
chunk and stop there, keeping every state computed so far.

Long calls into CasADi (an IDAS or CVODES segment) cannot be left between steps, so they
run inside ``external()``: there the handler raises KeyboardInterrupt as usual, which
CasADi turns into an error of that call; the caller then sees ``requested()`` and keeps the
state from before the call.

A request is never lost: a loop that stops on it has *seen* it (``requested()`` returned
True); one nobody saw — Ctrl-C during the last step, or while a step loop was compiled
(``pending()`` asks without seeing) — makes ``watch()`` raise KeyboardInterrupt when its block
ends, so the caller stops as if Python's handler had raised it.

Outside the main thread (where signal handlers cannot be set) both are no-ops and
KeyboardInterrupt behaves as Python's default.
"""

from __future__ import annotations

import contextlib
import signal
import threading

_state = {"requested": False, "active": 0, "raising": 0, "seen": False}


def requested() -> bool:
    """Whether Ctrl-C was pressed since the current run began; a True answer is *seen*: the
    caller stops on it (a loop honouring the request)."""
    if _state["requested"]:
        _state["seen"] = True
    return _state["requested"]


def pending() -> bool:
    """Whether Ctrl-C was pressed, asked by code that does not itself stop the run (it only
    cuts its own work short, e.g. a compiler): the request stays for a loop to see."""
    return _state["requested"]


def _handler(signum, frame):
    _state["requested"] = True
    if _state["raising"]:
        raise KeyboardInterrupt


@contextlib.contextmanager
def watch():
    """Record SIGINT as a stop request (instead of KeyboardInterrupt) inside the block."""
    if threading.current_thread() is not threading.main_thread() or _state["active"]:
        yield
        return
    try:
        previous = signal.signal(signal.SIGINT, _handler)
    except (ValueError, OSError):  # not settable here (embedded interpreter)
        yield
        return
    _state.update(requested=False, active=1, raising=0, seen=False)
    try:
        yield
    finally:
        # the run has read the request (its Solution says "interrupted"); what runs next
        # outside a watch must not see it
        unseen = _state["requested"] and not _state["seen"]
        signal.signal(signal.SIGINT, previous)
        _state.update(active=0, raising=0, requested=False, seen=False)
    if unseen:  # (only when the block ended normally: an exception already leaving wins)
        raise KeyboardInterrupt


@contextlib.contextmanager
def external():
    """Inside the block SIGINT raises KeyboardInterrupt again (for long calls into C that check
    Python's signals themselves); the request is recorded either way."""
    _state["raising"] += 1
    try:
        yield
    finally:
        _state["raising"] -= 1


def reset() -> None:
    """Forget a recorded request (a new run begins)."""
    _state.update(requested=False, seen=False)


def forget_handled_keyboard_interrupt() -> None:
    """Forget CPython's note of a KeyboardInterrupt raised inside ``exec``/``eval`` of a string
    (as SciPy's and NumPy's lazy imports do): CPython keeps it even after the interrupt was
    handled and then ends the process by SIGINT instead of with its exit status. The command
    line calls this once it has handled Ctrl-C itself (exit status 130)."""
    try:
        import ctypes

        ctypes.c_int.in_dll(ctypes.pythonapi, "_Py_UnhandledKeyboardInterrupt").value = 0
    except (ImportError, AttributeError, ValueError, OSError):  # not CPython, or not this version's
        pass
