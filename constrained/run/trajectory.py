"""Trajectory: the arrays of one run, and saving/loading them as ``.npz``."""

from __future__ import annotations

import itertools
import json
import os
import tempfile
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .event_records import checked_segments, records_from, records_to_arrays

#: Arrays a Trajectory may carry besides t, x, v (in the order files list them).
QUANTITIES = (
    "multipliers",
    "constraint_forces",
    "energy",
    "constraint_residual",
    "velocity_residual",
    "action",
)
#: The unit of each array (a multiplier is a force when its constraint row is in metres, as
#: distances, pins and planes are; a row f in other units gives λ in J per unit of f).
UNITS = {
    "t": "s", "x": "m", "v": "m/s", "multipliers": "N", "constraint_forces": "N", "energy": "J",
    "constraint_residual": "m", "velocity_residual": "m/s", "action": "J·s",
}
#: What each array is, in words (xarray's ``long_name``).
MEANINGS = {
    "t": "time", "x": "position", "v": "velocity",
    "multipliers": "Lagrange multiplier of each constraint row (N for rows in metres; J per unit of f "
                   "otherwise)",
    "constraint_forces": "constraint force (J^T λ) on each particle", "energy": "total energy",
    "constraint_residual": "max |f| over the constraint rows, each in metres",
    "velocity_residual": "max |J v + f_t| over the constraint rows", "action": "action S(t) = ∫ L dt",
}


@dataclass
class Trajectory:
    """One run. Shapes: t (T,), x and v (T, N, 3), multipliers (T, C),
    constraint_forces (T, N, 3), energy / residuals (T,), action (T,): the cumulative
    S(t) = ∫ L dt in J·s. Quantities a run was not asked for are None. ``stats`` holds
    the solver's counters and wall time.

    As SciPy's ``solve_ivp`` result: ``success``, ``status`` (a ``C.Status``), ``message``, and
    the arrays by name, ``traj["x"]``. ``to_pandas()`` / ``to_xarray()`` give them as a table
    with the particles' names and the units; in Jupyter the trajectory shows a summary and the
    interactive viewer. Example::

        import constrained as C

        scene = C.load_scene("scenarios/double_pendulum.toml")
        traj = C.simulate(scene.system, 2.0)
        traj.success, traj.message          # (True, 'the run reached t_end')
        traj["x"][-1, traj.particle("p2")]  # where p2 is at t = 2 s, in metres
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

    # --- SciPy's habits ------------------------------------------------------------------
    @property
    def status(self):
        """How the run ended, a ``C.Status`` (``Status.COMPLETED``, ``Status.EVENT`` for a
        terminal event, ``Status.INTERRUPTED``, ...). A run that failed raised a
        SimulationError whose ``trajectory`` keeps what was computed, with this status."""
        from ..solvers.base import Status

        stop = self.info.get("stop")
        if stop in Status._value2member_map_:
            return Status(stop)
        said = self.info.get("status", "completed")
        known = {"completed": Status.COMPLETED, "interrupted": Status.INTERRUPTED}
        return known.get(said, Status.SOLVER_FAILED)

    @property
    def success(self) -> bool:
        """True when the run reached t_end or a terminal event (SciPy's ``success``)."""
        return self.info.get("status", "completed") == "completed"

    @property
    def message(self) -> str:
        """One sentence on how the run ended (the error's text for a run that stopped early)."""
        return str(self.info.get("message") or self.status.message)

    def keys(self) -> list[str]:
        """The names ``traj[name]`` takes: t, x, v and the quantities this run computed."""
        return list(self.arrays())

    def __getitem__(self, name: str) -> np.ndarray:
        """The array called ``name`` (``traj["x"]`` is ``traj.x``), by the names of ``keys()``."""
        if name in ("t", "x", "v", *QUANTITIES):
            value = getattr(self, name)
            if value is not None:
                return value
            raise KeyError(f"this run did not compute {name!r}: ask for it with "
                           f"outputs=[..., {name!r}] (it has {', '.join(self.keys())})")
        raise KeyError(f"no array {name!r} in a trajectory (it has {', '.join(self.keys())})")

    def __contains__(self, name) -> bool:
        return name in self.keys()

    def to_pandas(self):
        """A pandas DataFrame, one row per sample, indexed by ``t``: columns ``x_P, y_P, z_P``,
        ``vx_P, vy_P, vz_P`` per particle P (the names formulas use), ``Fx_P, Fy_P, Fz_P`` for
        the constraint forces, ``lambda[LABEL]`` per constraint row, ``energy``, the residuals,
        ``action``, as far as the run has them; ``df.attrs["units"]`` gives each column's unit.
        Needs pandas (``pip install pandas``)."""
        from ..extras import need

        pd = need("pandas", "data", "Trajectory.to_pandas")
        columns, units = {}, {}
        names = self._names()
        for key, prefix, unit in (("x", "", "m"), ("v", "v", "m/s"), ("constraint_forces", "F", "N")):
            value = getattr(self, key)
            if value is None:
                continue
            for i, name in enumerate(names):
                for k, axis in enumerate("xyz"):
                    column = f"{prefix}{axis}_{name}"
                    columns[column], units[column] = value[:, i, k], unit
        if self.multipliers is not None:
            lam = np.asarray(self.multipliers).reshape(len(self.t), -1)
            for k, label in enumerate(self._labels(lam.shape[1])):
                columns[f"lambda[{label}]"], units[f"lambda[{label}]"] = lam[:, k], UNITS["multipliers"]
        for key in ("energy", "constraint_residual", "velocity_residual", "action"):
            if getattr(self, key) is not None:
                columns[key], units[key] = np.asarray(getattr(self, key)), UNITS[key]
        frame = pd.DataFrame(columns, index=pd.Index(np.asarray(self.t), name="t"))
        frame.attrs["units"] = {"t": "s", **units}
        frame.attrs["info"] = {k: v for k, v in self.info.items() if isinstance(v, str | int | float)}
        return frame

    def to_xarray(self):
        """An xarray Dataset: ``x``, ``v``, ``constraint_forces`` over (t, particle, axis),
        ``multipliers`` over (t, constraint), the scalar series over t; coordinates the particles'
        names, the axes x, y, z and the constraint rows' labels; every variable with ``units``
        and ``long_name`` attributes. Needs xarray (``pip install xarray``)."""
        from ..extras import need

        xr = need("xarray", "data", "Trajectory.to_xarray")
        variables = {}
        for key in ("x", "v", "constraint_forces"):
            if getattr(self, key) is not None:
                variables[key] = (("t", "particle", "axis"), np.asarray(getattr(self, key)),
                                  {"units": UNITS[key], "long_name": MEANINGS[key]})
        if self.multipliers is not None:
            variables["multipliers"] = (("t", "constraint"),
                                        np.asarray(self.multipliers).reshape(len(self.t), -1),
                                        {"units": UNITS["multipliers"], "long_name": MEANINGS["multipliers"]})
        for key in ("energy", "constraint_residual", "velocity_residual", "action"):
            if getattr(self, key) is not None:
                variables[key] = (("t",), np.asarray(getattr(self, key)),
                                  {"units": UNITS[key], "long_name": MEANINGS[key]})
        coords = {"t": ("t", np.asarray(self.t), {"units": "s", "long_name": "time"}),
                  "particle": self._names(), "axis": ["x", "y", "z"]}
        if self.multipliers is not None:
            coords["constraint"] = self._labels(variables["multipliers"][1].shape[1])
        attrs = {k: v for k, v in self.info.items() if isinstance(v, str | int | float)}
        return xr.Dataset(variables, coords=coords, attrs={**attrs, "message": self.message})

    def _names(self) -> list[str]:
        names = list(self.particle_names or [])
        return names if len(names) == self.n_particles else [f"particle{i}" for i in range(self.n_particles)]

    def _labels(self, count: int) -> list[str]:
        labels = list(self.constraint_labels or [])
        return labels if len(labels) == count else [f"row{k}" for k in range(count)]

    def _repr_html_(self) -> str:
        """Jupyter: the summary table and the interactive viewer (constrained.output.viewer)."""
        from .. import notebook

        return notebook.table(repr(self), self.summary()) + notebook.view("viewer", self)

    def summary(self) -> list[tuple[str, str]]:
        """``(what, value)`` rows: how the run ended, its span, sizes, method and cost."""
        t = np.asarray(self.t, dtype=float)
        rows = [("status", f"{self.status.value}: {self.message}"),
                ("time", f"{t[0]:g} … {t[-1]:g} s, {len(t)} samples" if len(t) else "no samples"),
                ("particles", ", ".join(self._names()[:12]) + (" …" if self.n_particles > 12 else ""))]
        if self.constraint_labels:
            rows.append(("constraint rows", f"{len(self.constraint_labels)}"))
        for key, what in (("method", "method"), ("rtol", "rtol")):
            if key in self.info:
                rows.append((what, f"{self.info[key]}"))
        for key, what in (("steps", "steps"), ("wall_time_s", "solver time [s]")):
            if key in self.stats:
                value = self.stats[key]
                rows.append((what, f"{value:.3g}" if isinstance(value, float) else f"{value}"))
        if self.energy is not None and len(self.energy):
            e = np.asarray(self.energy, dtype=float)
            rows.append(("energy drift max |E − E0| [J]", f"{np.nanmax(np.abs(e - e[0])):.3g}"))
        if self.constraint_residual is not None and len(self.constraint_residual):
            rows.append(("max constraint residual [m]", f"{np.nanmax(self.constraint_residual):.3g}"))
        if self.events:
            rows.append(("events", f"{len(self.events)}"))
        rows.append(("arrays", ", ".join(f"{k} [{UNITS[k]}]" for k in self.keys())))
        return rows

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
            "stats": self.stats,
            "info": self.info,
        }
        if self.events:
            event_arrays, meta["events"] = records_to_arrays(self.events, self.n_particles)
            arrays.update(event_arrays)
        arrays["meta"] = np.array(json.dumps(_jsonable(meta)))
        atomic_write(path, lambda f: write_npz(f, arrays))
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
        _refuse_disordered(path, t, meta, N)
        info = meta.get("info", {})
        if not isinstance(info, dict):
            raise InputError(f"{path}: its meta 'info' is not a table; the file is damaged: run the scene "
                             "again to write it")
        if "segments" in info:  # (the smooth pieces of a run with one-sided constraints: stationarity's)
            asked = info.get("t_end")
            labels = meta.get("constraint_labels")
            if not (isinstance(labels, list) and labels and all(isinstance(a, str) for a in labels)):
                labels = None  # (a file without the rows' labels: the held rows are checked on use)
            info["segments"] = checked_segments(
                info["segments"], t, labels, f"{path}: info['segments']",
                "the file is damaged: run the scene again to write it",
                t_end=asked if isinstance(asked, int | float) and not isinstance(asked, bool) else None)
        return cls(
            **{k: arrays.get(k) for k in ("t", "x", "v", *QUANTITIES)},
            particle_names=meta.get("particle_names", []),
            constraint_labels=meta.get("constraint_labels", []),
            stats=meta.get("stats", {}),
            info=info,
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
        os.chmod(tmp, file_mode())  # mkstemp makes 0600; give the mode open() would
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and (exc.filename is None or str(exc.filename) != str(path)):
            # name the user's file, not the hidden temporary one (or its folder), nor nothing
            # (a write that fails, as on a full disk, raises an OSError without a file name)
            raise OSError(exc.errno, exc.strerror, str(path)) from None
        raise


def write_npz(f, arrays: dict) -> None:
    """Write ``arrays`` to the open binary file ``f`` as ``np.savez(f, **arrays)`` does (the same
    members, headers and bytes: an archive ``np.load`` reads), each plain array's bytes written
    from its own memory. (np.savez copies an array to new 16 MiB bytes objects first: fresh pages
    whose faults cost 0.2 s on the 84 MB of a 10,000-particle rope.)"""
    npy = np.lib.format
    with zipfile.ZipFile(f, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, value in arrays.items():
            value = np.asanyarray(value)
            with archive.open(name + ".npy", "w", force_zip64=True) as member:
                if type(value) is np.ndarray and value.flags.c_contiguous and value.dtype.kind in "biufcSU":
                    try:  # (the version np.save picks for these: 1.0 unless the header is too long)
                        npy.write_array_header_1_0(member, npy.header_data_from_array_1_0(value))
                    except ValueError:
                        npy.write_array(member, value)
                        continue
                    member.write(memoryview(value.reshape(-1).view(np.uint8)))
                else:
                    npy.write_array(member, value)


def file_mode() -> int:
    """The mode ``open()`` gives a new file (0o666 less the umask): what a file written through a
    temporary (mkstemp makes 0600) is given before it is renamed into place."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


#: Values ``_jsonable`` gives back as they are.
_PLAIN = frozenset((str, float, int, bool, type(None)))


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        kinds = set(map(type, value))
        if kinds <= _PLAIN:  # (names, labels: tens of thousands at once)
            return list(value)
        if kinds <= {list, tuple} and _PLAIN.issuperset(map(type, itertools.chain.from_iterable(value))):
            return value  # (pairs of indices: a sketch's rods; json writes a tuple as a list)
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


def _refuse_disordered(path: Path, t: np.ndarray, meta: dict, n_particles: int) -> None:
    """A file whose times go backwards, or whose particle names are not one per particle, was
    not written by a run (hand-edited, or put together from two files): refused as damaged
    instead of drawn as lines that double back, or labelled with the wrong names. (Equal
    consecutive times are kept: a run records an impact's state before and after it.)"""
    with np.errstate(invalid="ignore"):
        finite = np.asarray(t, float)[np.isfinite(np.asarray(t, float))]
        back = np.flatnonzero(np.diff(finite) < 0)
    if back.size:
        k = int(back[0])
        raise InputError(f"{path}: its times go backwards (t = {finite[k]:g} s, then {finite[k + 1]:g} s); "
                         "the file is damaged: run the scene again to write it")
    names = meta.get("particle_names", [])
    if names and (not isinstance(names, list) or len(names) != n_particles
                  or not all(isinstance(n, str) for n in names)):
        count = len(names) if isinstance(names, list) else "no list of"
        raise InputError(f"{path}: its meta names {count} particle(s), but x holds {n_particles}; the "
                         "file is damaged: run the scene again to write it")
