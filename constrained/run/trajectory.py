"""Trajectory: the arrays of one run, and saving/loading them as ``.npz``."""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .event_records import records_from, records_to_arrays

#: Arrays a Trajectory may carry besides t, x, v (in the order files list them).
QUANTITIES = (
    "multipliers",
    "constraint_forces",
    "energy",
    "constraint_residual",
    "velocity_residual",
    "action",
)


@dataclass
class Trajectory:
    """One run. Shapes: t (T,), x and v (T, N, 3), multipliers (T, C),
    constraint_forces (T, N, 3), energy / residuals (T,), action (T,): the cumulative
    S(t) = ∫ L dt in J·s. Quantities a run was not asked for are None. ``stats`` holds
    the solver's counters and wall time.
    """

    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    multipliers: np.ndarray | None = None
    constraint_forces: np.ndarray | None = None
    energy: np.ndarray | None = None
    constraint_residual: np.ndarray | None = None
    velocity_residual: np.ndarray | None = None
    action: np.ndarray | None = None
    particle_names: list[str] = field(default_factory=list)
    constraint_labels: list[str] = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    #: What happened when (constrained.events.EventRecord): releases, contacts and impacts of
    #: one-sided constraints, and user events; saved as the ``event_*`` arrays.
    events: list = field(default_factory=list)

    @property
    def n_particles(self) -> int:
        return self.x.shape[1]

    def particle(self, name: str) -> int:
        """Index of the particle called ``name``."""
        try:
            return self.particle_names.index(name)
        except ValueError:
            raise InputError(
                f"no particle '{name}' in this trajectory ({', '.join(self.particle_names)})"
            ) from None

    def head(self, n: int) -> Trajectory:
        """The first ``n`` samples (a copy of the arrays' views, same names and info)."""
        cut = {k: (None if getattr(self, k) is None else getattr(self, k)[:n])
               for k in ("t", "x", "v", *QUANTITIES)}
        last = float(self.t[n - 1]) if 0 < n <= len(self.t) else -np.inf
        return Trajectory(**cut, particle_names=list(self.particle_names),
                          constraint_labels=list(self.constraint_labels), stats=dict(self.stats),
                          info=dict(self.info), events=[e for e in self.events if e.t <= last])

    def arrays(self, quantities=None) -> dict[str, np.ndarray]:
        """``t, x, v`` and the requested quantities that were computed, by contract name."""
        out = {"t": self.t, "x": self.x, "v": self.v}
        for name in QUANTITIES if quantities is None else quantities:
            value = getattr(self, name)
            if value is not None:
                out[name] = value
        return out

    def save(self, path, quantities=None) -> Path:
        """Write an ``.npz`` atomically (temporary file in the same folder, then rename)."""
        path = Path(path)
        arrays = self.arrays(quantities)
        meta = {
            "particle_names": self.particle_names,
            "constraint_labels": self.constraint_labels,
            "stats": _jsonable(self.stats),
            "info": _jsonable(self.info),
        }
        if self.events:
            event_arrays, meta["events"] = records_to_arrays(self.events, self.n_particles)
            arrays.update(event_arrays)
        arrays["meta"] = np.array(json.dumps(_jsonable(meta)))
        atomic_write(path, lambda f: np.savez(f, **arrays))
        return path

    @classmethod
    def load(cls, path) -> Trajectory:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"no such file: {path}")
        try:
            data = np.load(path, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise ValueError("a single array, not an .npz archive of named arrays")
            with data:
                arrays = {k: data[k] for k in data.files}
            meta = json.loads(str(arrays.pop("meta"))) if "meta" in arrays else {}
            if not isinstance(meta, dict):
                raise ValueError("its 'meta' entry is not a table")
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as exc:
            why = str(exc).split(". ")[0] if not isinstance(exc, zipfile.BadZipFile | EOFError | zlib.error) \
                else "truncated or damaged archive"
            if "pickled" in why:
                why = "not an .npz archive of arrays"
            raise InputError(f"{path} is not a readable trajectory file written by constrained ({why}); "
                             "run the scene again to write it") from None
        missing = [k for k in ("t", "x", "v") if k not in arrays]
        if missing:
            raise InputError(f"{path} lacks the arrays {', '.join(missing)}")
        t, x, v = arrays["t"], arrays["x"], arrays["v"]
        if t.ndim != 1 or x.ndim != 3 or x.shape[0] != len(t) or x.shape[2:] != (3,) or v.shape != x.shape:
            raise InputError(f"{path}: the arrays t {t.shape}, x {x.shape}, v {v.shape} do not have the "
                             "shapes of a trajectory (T,), (T, N, 3), (T, N, 3)")
        T, N = x.shape[:2]
        shapes = {"multipliers": (T, None), "constraint_forces": (T, N, 3), "energy": (T,),
                  "constraint_residual": (T,), "velocity_residual": (T,), "action": (T,)}
        for name in ("t", "x", "v", *QUANTITIES):
            a = arrays.get(name)
            if a is None:
                continue
            want = shapes.get(name)
            wrong = want is not None and (a.ndim != len(want) or any(
                w is not None and w != n for w, n in zip(want, a.shape, strict=False)))
            if a.dtype.kind not in "fiu" or wrong:
                shape = "(" + ", ".join("C" if w is None else str(w) for w in want) + ") " if want else ""
                raise InputError(f"{path}: the array {name} has shape {a.shape} and type {a.dtype}, not the "
                                 f"{shape}numbers its t {t.shape} and x {x.shape} need; the file is "
                                 "damaged: run the scene again to write it")
        return cls(
            **{k: arrays.get(k) for k in ("t", "x", "v", *QUANTITIES)},
            particle_names=meta.get("particle_names", []),
            constraint_labels=meta.get("constraint_labels", []),
            stats=meta.get("stats", {}),
            info=meta.get("info", {}),
            events=records_from(arrays, meta.get("events", [])),
        )

    def __repr__(self) -> str:
        have = [k for k in QUANTITIES if getattr(self, k) is not None]
        return (
            f"Trajectory({len(self.t)} samples, t = {self.t[0]:g}..{self.t[-1]:g} s, "
            f"{self.n_particles} particles, with {', '.join(have) or 'positions only'}"
            + (f", {len(self.events)} events" if self.events else "") + ")"
        )


def atomic_write(path: Path, write) -> None:
    """Call ``write(fileobj)`` on a temporary file beside ``path``, then rename it into place."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the mode open() would
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is not None and str(exc.filename) != str(path):
            # name the user's file, not the hidden temporary one (or its folder)
            raise OSError(exc.errno, exc.strerror, str(path)) from None
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value
