"""Bursts of object creation without Python's cyclic garbage collector.

Reading a scene of 10,000 particles, or building its Structure, makes millions of small
objects (dicts, lists, CasADi proxies) that all stay alive. The collector's passes are
triggered by the count of new objects, and its full passes walk the whole heap, which keeps
growing: they took a third of reading a 10,000-link rope (2.8 s → 1.9 s without them) and
three quarters of a 100 × 100 cloth's structure fingerprint. Nothing built there is garbage
in a cycle, so ``collector_paused()`` turns the collector off for the block and restores it
after (nested blocks and other threads' blocks: it is back on when the last one ends)."""

from __future__ import annotations

import contextlib
import gc
import threading

_lock = threading.Lock()
_state = {"depth": 0, "was_enabled": False}


@contextlib.contextmanager
def collector_paused():
    """The cyclic garbage collector off inside the block (reference counting still frees)."""
    with _lock:
        if _state["depth"] == 0:
            _state["was_enabled"] = gc.isenabled()
            gc.disable()
        _state["depth"] += 1
    try:
        yield
    finally:
        with _lock:
            _state["depth"] -= 1
            if _state["depth"] == 0 and _state["was_enabled"]:
                gc.enable()
