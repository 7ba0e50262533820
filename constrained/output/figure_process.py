"""Figures of a run drawn by a helper process started before the run.

``constrained run`` starts the helper as soon as it knows the scene asks for figures; the
helper imports matplotlib (≈0.3 s) while this process builds the model and simulates, then
draws the figures (:func:`constrained.plot.save_figures`, PNGs in parallel) from the
trajectory it is sent. Where a "fork" start is not available, or the helper ends before it has
answered, the figures are drawn here instead: the helper only ever saves time.

The helper is quiet and never outlives the run: it runs in a process group of its own, so a
terminal's Ctrl-C reaches the run only (which then ends the helper), it ignores SIGINT, and it
never prints a traceback — a failure is sent back as a one-line error (a failed write keeps its
errno and file, so the run fails as if it had written the file itself), or dropped when the run
is gone. ``close`` ends the whole group (the helper and its drawing workers) when the helper
does not end by itself. This module imports nothing heavy.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from pathlib import Path

__all__ = ["FigureProcess"]

#: seconds ``close`` waits for a helper that was told to stop before it ends its process group
GRACE_S = 5.0


def _serve(conn, other_end) -> None:
    """The helper: import the plotting code, then draw one request (or none) and exit."""
    other_end.close()  # the parent's end: EOF here when the parent goes away
    try:
        os.setpgid(0, 0)
    except OSError:
        pass
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # (inherited by its drawing workers)
    try:
        _draw(conn)
    except BaseException:  # noqa: BLE001 - the parent is gone (a broken pipe): nothing to tell
        pass
    finally:
        conn.close()


def _draw(conn) -> None:
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
        conn.send(("error", "ImportError", str(failure), None, None))
        return
    try:
        paths = plot.save_figures(traj, kinds, out_dir, system=system, parallel=True,
                                  progress=lambda amount: conn.send(("progress", amount)))
    except Exception as exc:  # noqa: BLE001 - sent back and raised in the parent
        if isinstance(exc, OSError):
            conn.send(("error", "OSError", exc.strerror or str(exc), exc.errno,
                       None if exc.filename is None else str(exc.filename)))
        else:
            conn.send(("error", type(exc).__name__, str(exc), None, None))
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
        try:  # (also here: the group exists before either process goes on)
            os.setpgid(self.proc.pid, self.proc.pid)
        except OSError:
            pass
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
                self.close(abandon=True)

    def wait(self, progress=None) -> list[Path]:
        """The paths written (by the helper, or here when it could not take the work)."""
        if self.sent:
            paths = self._receive(progress)
            if paths is not None:
                return paths
        from .plot import save_figures

        traj, kinds, out_dir, system = self.request
        # here, in a process that may run threads (CasADi, BLAS, tqdm): no forking, one by one
        return save_figures(traj, kinds, out_dir, system=system, progress=progress)

    def save(self, traj, kinds, out_dir, *, system=None, progress=None) -> list[Path]:
        """``start`` and ``wait`` in one call."""
        self.start(traj, kinds, out_dir, system=system)
        return self.wait(progress)

    def _receive(self, progress) -> list[Path] | None:
        """The helper's paths; its failure raised here as it would be in this process (OSError
        with its errno and file, InputError, ImportError, else RuntimeError); None when the
        helper ended without answering."""
        from ..errors import InputError

        try:
            while True:
                try:
                    kind, *rest = self.conn.recv()
                except (EOFError, OSError):  # the helper is gone (the pipe closed or reset)
                    return None
                if kind == "progress":
                    if progress is not None:
                        progress(rest[0])
                elif kind == "done":
                    return [Path(p) for p in rest[0]]
                else:
                    name, message, errno, filename = rest
                    if name == "OSError":
                        raise OSError(errno, message, filename)
                    if name == "ImportError":
                        raise ImportError(message)
                    if name in ("InputError", "ExpressionError"):
                        raise InputError(message)
                    raise RuntimeError(f"drawing the figures failed: {name}: {message}")
        finally:
            self.close(abandon=True)

    def close(self, *, abandon: bool = False) -> None:
        """End the helper: told to stop and given GRACE_S to end, else (or at once when
        ``abandon``: its work is done or not wanted) its whole process group killed."""
        if self.proc is None:
            return
        try:
            self.conn.send(None)
        except (OSError, ValueError):
            pass
        self.conn.close()
        if not abandon:
            self.proc.join(timeout=GRACE_S)
        if abandon or self.proc.is_alive():
            # the helper and the workers it forked, before the helper is reaped (its pid, the
            # group's id, cannot be reused until then): nothing of it outlives the run
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except OSError:
                self.proc.kill()
            self.proc.join()
        self.proc = None

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        self.close(abandon=exc_type is not None)  # the run failed or was interrupted
        return False
