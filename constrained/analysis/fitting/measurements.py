"""Measured data for a fit: a table of times and observed values, read from CSV.

The file has a header row. Column ``t`` holds the times (seconds, strictly increasing); every
other column is an observable (constrained.fitting.observables), named by its formula —
``x_bob``, ``y_bob`` — or by a name the caller maps to a formula; a column ``sigma_NAME``
gives the standard deviation of each value of ``NAME`` (same units). An empty cell, ``nan``
or ``NA`` is a missing value (left out of the fit). Anything else that is not a finite
number is refused with the file, line and column named.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import InputError

__all__ = ["Measurements", "read_measurements"]

MISSING = {"", "nan", "na", "n/a", "none", "null"}


@dataclass(frozen=True)
class Measurements:
    """``t`` (T,), ``names`` (k,), ``values`` (T, k) with NaN where missing, ``sigma`` (T, k) or
    None (standard deviations; NaN where not given), ``source`` (the file, for messages)."""

    t: np.ndarray
    names: tuple[str, ...]
    values: np.ndarray
    sigma: np.ndarray | None = None
    source: str = "data"

    def __post_init__(self):
        t = np.asarray(self.t, float).ravel()
        values = np.asarray(self.values, float)
        if values.ndim == 1:
            values = values[:, None]
        where = self.source
        if t.size == 0:
            raise InputError("no measurements (no rows)", where=where)
        if values.shape != (t.size, len(self.names)):
            raise InputError(f"values have shape {values.shape}, expected ({t.size}, {len(self.names)}): one "
                             "column per name, one row per time", where=where)
        if not np.all(np.isfinite(t)):
            bad = int(np.argmin(np.isfinite(t)))
            raise InputError(f"{self._row(bad)}: the time {t[bad]} is not a finite number", where=where)
        if np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0)) + 1
            what = "repeats the time before it" if t[k] == t[k - 1] else "goes back in time"
            raise InputError(f"{self._row(k)}: t = {t[k]:g} s {what} (t = {t[k - 1]:g} s): the times "
                             "(column t) must be strictly increasing; sort the rows by time, and merge or "
                             "drop repeated times", where=where)
        if np.any(np.isinf(values)):
            raise InputError("a value is infinite", where=where)
        with np.errstate(invalid="ignore"):
            huge = np.abs(values) > LARGEST_VALUE
        if np.any(huge):
            i, j = np.argwhere(huge)[0]
            raise InputError(f"{self._row(int(i))}: the value of '{self.names[j]}', {values[i, j]:.3g}, "
                             "is too large to fit (the squares of such residuals overflow); give the data in "
                             "units that keep the numbers moderate", where=where)
        if not np.any(np.isfinite(values)):
            raise InputError("every value is missing", where=where)
        sigma = None
        if self.sigma is not None:
            sigma = np.broadcast_to(np.asarray(self.sigma, float), values.shape).copy()
            given = np.isfinite(sigma)
            if np.any(given & (sigma <= 0)):
                i, j = np.argwhere(given & (sigma <= 0))[0]
                raise InputError(f"{self._row(int(i))}: the standard deviation of '{self.names[j]}' is "
                                 f"{sigma[i, j]:g}; it must be positive", where=where)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "sigma", sigma)
        object.__setattr__(self, "names", tuple(self.names))

    def _row(self, i: int) -> str:
        """Row i named as the file's line (header on line 1) when read from a file, else by index."""
        return f"line {i + 2}" if self.source != "data" else f"row {i} (from 0)"

    @property
    def count(self) -> int:
        """How many values are measured (not missing)."""
        return int(np.sum(np.isfinite(self.values)))


#: Measured values beyond this are refused: a residual of 1e154 squared is the largest double.
LARGEST_VALUE = 1e150


def _cell(text: str, path, line: int, column: str) -> float:
    text = text.strip()
    if text.lower() in MISSING:
        return math.nan
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"line {line}, column '{column}': {text!r} is not a number",
                         where=str(path)) from None
    if math.isinf(value):
        raise InputError(f"line {line}, column '{column}': the value is infinite", where=str(path))
    if abs(value) > LARGEST_VALUE:
        raise InputError(f"line {line}, column '{column}': {value:.3g} is too large to fit: the squares "
                         "of such residuals overflow the sum of squares (the fit wandered to NaN); give "
                         "the data in units that keep the numbers moderate", where=str(path))
    return value


def read_measurements(path) -> Measurements:
    """Measurements from a CSV file (see the module)."""
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as f:
            rows = [r for r in csv.reader(f) if r and not (len(r) == 1 and not r[0].strip())]
    except FileNotFoundError:
        raise InputError("no such file", where=str(path)) from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read it as CSV ({exc})", where=str(path)) from None
    if len(rows) < 2:
        raise InputError("needs a header row and at least one row of data", where=str(path))
    header = [h.strip() for h in rows[0]]
    if "t" not in header:
        raise InputError(f"no column 't' (the times) in the header {header}", where=str(path))
    if len(set(header)) != len(header):
        raise InputError(f"a column is named twice in the header {header}", where=str(path))
    table = np.empty((len(rows) - 1, len(header)))
    for i, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(f"line {i} has {len(row)} cells, the header {len(header)}", where=str(path))
        table[i - 2] = [_cell(c, path, i, header[j]) for j, c in enumerate(row)]
    t = table[:, header.index("t")]
    if not np.all(np.isfinite(t)):
        raise InputError(f"line {int(np.argmin(np.isfinite(t))) + 2}: the time is missing", where=str(path))
    names = [h for h in header if h != "t" and not h.startswith("sigma_")]
    if not names:
        raise InputError("no measured column besides t", where=str(path))
    for h in header:
        if h.startswith("sigma_") and h[len("sigma_"):] not in names:
            raise InputError(f"column '{h}' gives the uncertainty of '{h[6:]}', which is not a column",
                             where=str(path))
    values = table[:, [header.index(n) for n in names]]
    sigma = None
    if any(f"sigma_{n}" in header for n in names):
        sigma = np.column_stack([table[:, header.index(f"sigma_{n}")] if f"sigma_{n}" in header
                                 else np.full(len(t), np.nan) for n in names])
    return Measurements(t, tuple(names), values, sigma, source=str(path))
