"""Exceptions a user of constrained can meet, each with a message a physicist understands."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pathlib import Path


class ConstrainedError(Exception):
    """Base class of every error this package raises on purpose."""


class InputError(ConstrainedError, ValueError):
    """Bad input: a scene key, an argument or a formula that cannot be used.

    ``where`` names the place (file and key, or argument) so the message can say it.
    """

    def __init__(self, message: str, *, where: str | None = None):
        self.where = where
        self.reason = message
        super().__init__(f"{where}: {message}" if where else message)


class ExpressionError(InputError):
    """A formula string that the whitelisted parser refuses."""


class InconsistentStateError(InputError):
    """An initial state too far from the constraints, or constraints that cannot all hold."""


class SimulationError(ConstrainedError, RuntimeError):
    """A run that had to stop (step size collapse, non-finite values).

    ``trajectory`` holds what was computed before the stop, when anything was.
    """

    def __init__(self, message: str, trajectory=None):
        self.trajectory = trajectory
        super().__init__(message)


class RunInterrupted(SimulationError):
    """A run stopped by Ctrl-C: ``trajectory`` holds the states computed until then
    (``trajectory.info["status"] == "interrupted"``)."""


class SceneError(InputError):
    """A scene that cannot be used: ``file``, ``key`` (a key path) and ``reason``.

    ``str(error)`` is one paragraph: ``scene file F, key K: reason``.
    """

    def __init__(self, reason: str, *, file: str | Path | None = None, key: str | None = None):
        self.file = None if file is None else str(file)
        self.key = key
        reason = one_line(reason)
        parts = []
        if self.file is not None:
            parts.append(f"scene file {self.file}")
        if key:
            parts.append(f"key {key}")
        super().__init__(reason, where=", ".join(parts) or None)
        self.reason = reason


def one_line(text: str) -> str:
    """``text`` with its runs of whitespace (newlines too) as single spaces."""
    return " ".join(str(text).split())


#: A message lists at most this many names (the particles of a 10,000-bead scene are not).
LISTED_NAMES = 12


def listed(names, shown: int = LISTED_NAMES) -> str:
    """``names`` joined for a message: all of a short list; of a long one the first few, the
    last and how many in all ("p0, p1, …, p9999: 10000 in all")."""
    names = [str(n) for n in names]
    if len(names) <= shown:
        return ", ".join(names)
    return f"{', '.join(names[:shown - 1])}, …, {names[-1]}: {len(names)} in all"


class InitialStateWarning(UserWarning):
    """The initial state was changed to satisfy the constraints (positions within
    ``max_initial_correction``, or velocities with components the constraints forbid): the run
    starts from the corrected state, in ``trajectory.info["initial_correction"]``."""


class UnresolvedStepWarning(UserWarning):
    """A fixed-step run (``rattle``) of a system whose energy is conserved ended with its energy
    changed by more than the method's error at a resolved step: the step did not resolve the
    motion somewhere (a close encounter, a collision in a 1/r potential), in
    ``trajectory.info["energy_not_conserved"]``."""


class LinearRangeWarning(UserWarning):
    """Sensitivities that grew by orders of magnitude along a run (chaos: e^(λt)): exact
    derivatives of the run, but a first-order prediction y(p + δp) ≈ y + (∂y/∂p) δp holds only
    for parameter changes far smaller than their inverse growth."""
