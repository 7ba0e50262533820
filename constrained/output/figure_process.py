"""Figures of a run drawn by a helper process started before the run.

``constrained run`` starts the helper as soon as it knows the scene asks for figures; the
helper imports matplotlib (≈0.3 s) while this process builds the model and simulates, then
draws the figures (:func:`constrained.plot.save_figures`, PNGs in parallel) from the
trajectory it is sent. Where a "fork" start is not available, or anything about the helper
fails before it has written a file, the figures are drawn here instead: the helper only ever
saves time. This module imports nothing heavy.
"""

from __future__ import annotations

import multiprocessing
from pathlib import Path

__all__ = ["FigureProcess"]


def _serve(conn, other_end) -> None:
    """The helper: import the plotting code, then draw one request (or none) and exit."""
    other_end.close()  # the parent's end: EOF here when the parent goes away
    try:
        from . import plot
    except ImportError as exc:  # reported when the request comes
        plot, failure = None, exc
    try:
        request = conn.recv()
    except EOFError:
        return
    if request is None:
        return
    traj, kinds, out_dir, system = request
    if plot is None:
        conn.send(("error", "ImportError", str(failure)))
        return
    try:
        paths = plot.save_figures(traj, kinds, out_dir, system=system, parallel=True,
                                  progress=lambda amount: conn.send(("progress", amount)))
    except Exception as exc:  # noqa: BLE001 - sent back and raised in the parent
        conn.send(("error", type(exc).__name__, str(exc)))
        return
    conn.send(("done", [str(p) for p in paths]))


class FigureProcess:
    """A helper process drawing one run's figures. ``save(...)`` has the signature of
    ``plot.save_figures`` (plus ``progress``); ``close()`` ends the helper if unused."""

    def __init__(self):
        self.proc = self.conn = None
        try:
            ctx = multiprocessing.get_context("fork")
        except ValueError:  # no fork on this platform: draw in this process
            return
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child, self.conn), name="constrained-figures")
        self.proc.start()
        child.close()

    def start(self, traj, kinds, out_dir, *, system=None) -> None:
        """Send the helper its work and return at once (``wait`` collects the result)."""
        self.request = (traj, list(kinds), Path(out_dir), system)
        self.sent = False
        if self.proc is not None:
            try:
                self.conn.send(self.request)
                self.sent = True
            except Exception:  # noqa: BLE001 - e.g. something that does not pickle: draw here
                self.close()

    def wait(self, progress=None) -> list[Path]:
        """The paths written (by the helper, or here when it could not take the work)."""
        if self.sent:
            return self._receive(progress)
        from .plot import save_figures

        traj, kinds, out_dir, system = self.request
        # here, in a process that may run threads (CasADi, BLAS, tqdm): no forking, one by one
        return save_figures(traj, kinds, out_dir, system=system, progress=progress)

    def save(self, traj, kinds, out_dir, *, system=None, progress=None) -> list[Path]:
        """``start`` and ``wait`` in one call."""
        self.start(traj, kinds, out_dir, system=system)
        return self.wait(progress)

    def _receive(self, progress) -> list[Path]:
        from ..errors import InputError

        try:
            while True:
                kind, *rest = self.conn.recv()
                if kind == "progress":
                    if progress is not None:
                        progress(rest[0])
                elif kind == "done":
                    return [Path(p) for p in rest[0]]
                else:
                    name, message = rest
                    if name == "ImportError":
                        raise ImportError(message)
                    if name in ("InputError", "ExpressionError"):
                        raise InputError(message)
                    raise RuntimeError(f"drawing the figures failed: {name}: {message}")
        except EOFError:
            raise RuntimeError("the figure process ended without drawing the figures") from None
        finally:
            self.close()

    def close(self) -> None:
        if self.proc is None:
            return
        try:
            self.conn.send(None)
        except (OSError, ValueError):
            pass
        self.conn.close()
        self.proc.join(timeout=5)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join()
        self.proc = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
