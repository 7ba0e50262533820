"""What the ``constrained`` command says: its name, error and progress lines, numbers as
text, and the refusals every verb shares (no end time, no [reduced] section). Light to
import: the verb modules (cli_run, cli_verbs) and the parser (cli) all use it."""

from __future__ import annotations

import sys

from ..errors import InconsistentStateError, InputError, SceneError

PROG = "constrained"

#: ``check`` lists up to this many particles, constraint rows and redundant rows each.
LISTED = 40


def _end_time(scene, file: str) -> float:
    """The scene's t_end, or the refusal naming simulate.t_end."""
    if scene.settings["t_end"] is None:
        raise SceneError("no end time: give t_end in [simulate], or pass --set simulate.t_end=...",
                         file=file, key="simulate.t_end")
    return scene.settings["t_end"]


def _needs_reduced(file: str, verb: str):
    """The refusal of a verb that needs the scene's [reduced] coordinates."""
    raise SceneError(f"no [reduced] section: {verb} needs generalized coordinates "
                     "(coordinates, initial, rates, map)", file=file, key="reduced")


def _fmt_correction(corr) -> str:
    if isinstance(corr, dict) and "position" in corr:
        text = f"positions moved by {corr['position']:.3g} m"
        if "velocity" in corr:
            text += f", velocities by {corr['velocity']:.3g} m/s"
        if corr.get("worst_constraint") and corr.get("max_residual_before"):
            text += (
                f" (largest violation before: {corr['max_residual_before']:.3g} in "
                f"'{corr['worst_constraint']}')"
            )
        return text
    return _fmt_value(corr)


# --- messages --------------------------------------------------------------------------------


def _scene_error(exc: InputError, file: str) -> SceneError:
    """An InputError raised after loading (simulate, assemble) -> SceneError naming the file
    (a SceneError already names it and passes through)."""
    if isinstance(exc, SceneError):
        return exc
    from ..scene.keys import SIMULATE_DEFAULTS
    from ..scene.overrides import _KEY_RE

    where = getattr(exc, "where", None)
    reason = getattr(exc, "reason", None) or str(exc)
    key = None
    if where in SIMULATE_DEFAULTS:
        key = f"simulate.{where}"
    elif where and _KEY_RE.fullmatch(where):
        key = where
    elif where:
        reason = f"{where}: {reason}"
    if key is None and isinstance(exc, InconsistentStateError):
        key = "particles"
    return SceneError(reason, file=file, key=key)


def _say_error(message: str) -> None:
    print(f"{PROG}: error: " + " ".join(str(message).split()), file=sys.stderr)


def _say_stopped(message: str) -> None:
    """A stop the user asked for (Ctrl-C): one line on stderr, not called an error."""
    print(f"{PROG}: " + " ".join(str(message).split()), file=sys.stderr)


def _say(message: str, *, always: bool = False) -> None:
    print(message, file=sys.stderr if always else sys.stdout)


def _vec(v) -> str:
    return "(" + ", ".join(f"{float(c):.6g}" for c in v) + ")"


def _fmt_value(v) -> str:
    import numpy as np

    if isinstance(v, float | np.floating):
        return f"{float(v):.3g}"
    return str(v)


class ReaderGone:
    """The command's stdout, quiet once its reader has gone (``constrained run scene.toml |
    head -3``): the rest of the report is dropped, the run and its files are not. Without it
    the first line written after the reader left raised BrokenPipeError, which the command
    took for an unwritable --out folder and discarded the run ("cannot write out: Broken
    pipe; nothing was written")."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._silence()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._silence()

    def _silence(self) -> None:
        """The stream's descriptor pointed at /dev/null: what is buffered and what follows go
        there."""
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, self._stream.fileno())
        finally:
            os.close(devnull)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)
