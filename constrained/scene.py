"""TOML scene files: read, apply ``--set`` overrides, validate, build a System.

``load_scene(path)`` returns a :class:`Scene` with the assembled-ready ``system``, the run
``settings`` (the ``[simulate]`` table with defaults), the requested ``outputs``, the
optional ``[reduced]`` coordinates and the raw ``[expect]`` table. Every problem is a
:class:`SceneError` whose one-paragraph message names the file, the key path
(``particles[1].mass``, ``constraints[2].a``, ``simulate.rtol``) and what is wrong.
"""

from __future__ import annotations

import collections
import copy
import dataclasses
import difflib
import functools
import hashlib
import math
import re
import threading
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import expressions
from .constraints import CONSTRAINT_TYPES
from .defaults import DEFAULT_METHOD
from .effects import EFFECT_TYPES
from .errors import InputError
from .expectations import (
    ExpectResult,
    check_expectations,
    closed_form_error,
    closed_form_positions,
    expect_requirements,
    force_names,
)
from .model import kept_structure
from .parameters import RESERVED_NAMES
from .regularity import undefined_items
from .symbols import Symbols
from .system import Particle, System, sketch
from .trajectory import QUANTITIES

__all__ = [
    "Scene",
    "SceneError",
    "load_scene",
    "build_scene",
    "apply_overrides",
    "parse_override",
    "TOP_LEVEL_TABLES",
    "SIMULATE_DEFAULTS",
    "OUTPUT_QUANTITIES",
    "OUTPUT_PLOTS",
    "OUTPUT_FORMATS",
    "EXPECT_KEYS",
    "ExpectResult",
    "check_expectations",
    "closed_form_error",
    "closed_form_positions",
    "expect_requirements",
]

TOP_LEVEL_TABLES = (
    "scene",
    "particles",
    "constraints",
    "effects",
    "parameters",
    "definitions",
    "simulate",
    "outputs",
    "reduced",
    "expect",
    "events",
)

SIMULATE_DEFAULTS: dict[str, Any] = {
    "t_end": None,
    "t_start": 0.0,
    "method": DEFAULT_METHOD,
    "rtol": 1e-8,
    "atol": 1e-10,
    "dt": None,
    "output_dt": None,
    "samples": None,
    "base": "DOP853",
    "max_initial_correction": 1e-3,
    "compiled": "auto",
}

#: Limits of [simulate]: output samples a run may store, fixed steps it may take (dt), and
#: the largest |time| (beyond it a float cannot resolve a step).
MAX_SAMPLES = 1_000_000
MAX_STEPS = 1e10
MAX_TIME = 1e12

OUTPUT_QUANTITIES = ("positions", "velocities", *QUANTITIES)
OUTPUT_PLOTS = (
    "trajectory",
    "energy",
    "constraint_residual",
    "constraint_forces",
    "multipliers",
    "phase",
    "action",
    "animation",
    "viewer",
)
OUTPUT_FORMATS = ("npz", "csv")
OUTPUT_DEFAULTS: dict[str, list[str]] = {
    "quantities": ["multipliers", "constraint_forces", "energy", "constraint_residual"],
    "plots": [],
    "formats": ["npz"],
}

#: Keys of the [expect] table (see docs/scene-format.md, "[expect]").
EXPECT_KEYS = (
    "energy_drift",
    "constraint_residual",
    "velocity_residual",
    "final",
    "closed_form",
    "bounds",
    "reaches",
    "conserved",
    "period",
)
# Keys of one [expect.conserved.NAME] entry.
_CONSERVED_KEYS = ("axis", "point", "translation", "tol")

# Scene keys of each constraint / effect type: (required, optional), besides type and name.
CONSTRAINT_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "distance": (("a", "length"), ("b", "point")),
    "pin": (("a", "point"), ()),
    "plane": (("particles", "normal"), ("offset",)),
    "surface": (("particles", "expr"), ()),
    "curve": (("particles", "expr"), ()),
    "custom": (("expr",), ()),
}
EFFECT_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "gravity": (("g",), ("particles",)),
    "spring": (("a", "k"), ("b", "point", "rest")),
    "potential": (("expr",), ()),
    "central": (("a", "expr"), ("b", "point")),
    "pairwise": (("expr",), ("particles",)),
    "damping": (("coefficient",), ("particles", "a", "b")),
    "force": (("particle", "expr"), ()),
    "electromagnetic": (("charges",), ("phi", "A")),
}
#: Optional keys every constraint type takes: one-sided (see docs/scene-format.md).
ONE_SIDED_KEYS = ("unilateral", "restitution")
#: Keys of one [[events]] entry: (required, optional).
EVENT_KEYS = (("name", "expr"), ("direction", "stop"))
# Names a parameter or a reduced coordinate may not take (they mean something in formulas).
RESERVED_NAMES = RESERVED_NAMES


class SceneError(InputError):
    """A scene that cannot be used: ``file``, ``key`` (a key path) and ``reason``.

    ``str(error)`` is one paragraph: ``scene file F, key K: reason``.
    """

    def __init__(self, reason: str, *, file: str | Path | None = None, key: str | None = None):
        self.file = None if file is None else str(file)
        self.key = key
        reason = _one_line(reason)
        parts = []
        if self.file is not None:
            parts.append(f"scene file {self.file}")
        if key:
            parts.append(f"key {key}")
        super().__init__(reason, where=", ".join(parts) or None)
        self.reason = reason


@dataclass
class Scene:
    """A loaded scene: the System to simulate and what to do with it."""

    path: Path | None
    name: str
    system: System
    settings: dict
    outputs: dict
    reduced: dict | None
    raw: dict
    expect: dict | None = None
    description: str = ""
    expectations: list | None = None
    #: [scene] units: name (a parameter, a sweep summary column) -> unit, for axis labels
    units: dict | None = None

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, {self.system!r})"

    def with_overrides(self, overrides: Iterable[str]) -> Scene:
        """A new Scene: this one's file contents with ``--set`` style ``"KEY=VALUE"`` overrides."""
        file = None if self.path is None else str(self.path)
        return build_scene(apply_overrides(self.raw, list(overrides), file=file), path=self.path)

    def with_parameters(self, parameters: Mapping[str, float] | None) -> Scene:
        """A new Scene whose system has these parameters' values (``System.with_parameters``);
        the same as ``with_overrides(["parameters.NAME=VALUE", ...])`` without reading the
        scene again."""
        if not parameters:
            return self
        system = self.system.with_parameters(parameters)
        raw = copy.deepcopy(self.raw)  # the file's contents with the new values, as --set gives
        raw.setdefault("parameters", {}).update(system.parameters)
        return dataclasses.replace(self, system=system, raw=raw)

    def run(self, overrides: Iterable[str] | None = None, *, quantities=None, progress=None,
            parameters: Mapping[str, float] | None = None, model=None):
        """Simulate with the scene's own ``[simulate]`` settings and check its ``[expect]``.

        ``overrides``: ``"KEY=VALUE"`` strings as the CLI's ``--set`` (e.g.
        ``["simulate.t_end=2"]``), applied to a copy. ``quantities``: what to compute besides
        t, x, v (default: ``[outputs] quantities``). Returns a ``RunResult``: ``.trajectory``,
        ``.expectations`` (one ``ExpectResult`` per check), ``.ok``, ``.failed``, ``.report()``;
        it unpacks as ``trajectory, checks = scene.run()``. ``parameters`` (name -> value):
        new values of the scene's [parameters] for this run (its [expect] formulas see them
        too); ``model``: a Model of this scene (``assemble(scene.system)``), reused for the new
        values without rebuilding anything.
        """
        from .run_options import from_scene
        from .simulate import simulate

        scene = (self.with_overrides(overrides) if overrides else self).with_parameters(parameters)
        s = scene.settings
        if s["t_end"] is None:
            raise SceneError("no end time: give t_end in [simulate], or override simulate.t_end",
                             file=None if scene.path is None else str(scene.path), key="simulate.t_end")
        wanted = set(scene.outputs["quantities"] if quantities is None else quantities)
        kwargs = from_scene(scene, outputs=wanted | expect_requirements(scene)).simulate_kwargs()
        if progress is not None:
            kwargs["progress"] = progress
        if model is not None:  # the given Model, for this scene's values (nothing rebuilt)
            kwargs.update(model=model, parameters=dict(scene.system.parameters))
        trajectory = simulate(scene.system, s["t_end"], **kwargs)
        trajectory.info.setdefault("sketch", sketch(scene.system))  # rods for `constrained plot`
        return RunResult(scene, trajectory, check_expectations(scene, trajectory))


@dataclass
class RunResult:
    """A scene run with its own settings (``Scene.run()``): the Trajectory and the scene's
    ``[expect]`` results. ``ok`` is True when every check passes (and when the scene has none);
    ``failed`` lists the checks that did not; ``report()`` is the text ``constrained run``
    prints. It unpacks as ``trajectory, checks = scene.run()``."""

    scene: Scene
    trajectory: Any
    expectations: list

    @property
    def ok(self) -> bool:
        return all(r.ok for r in self.expectations)

    @property
    def failed(self) -> list:
        return [r for r in self.expectations if not r.ok]

    def report(self) -> str:
        n, bad = len(self.expectations), len(self.failed)
        lines = [f"expect: {n - bad} of {n} checks pass", *("  " + r.line for r in self.expectations)]
        return "\n".join(lines)

    def __iter__(self):
        return iter((self.trajectory, self.expectations))

    def __repr__(self) -> str:
        n, bad = len(self.expectations), len(self.failed)
        return f"RunResult({self.scene.name!r}, {len(self.trajectory.t)} samples, expect {n - bad}/{n} pass)"


# --- public entry points ---------------------------------------------------------------------


def load_scene(path: str | Path, overrides: Iterable[str] | None = None) -> Scene:
    """Read the TOML scene at ``path``, apply ``--set`` style ``overrides``, validate, build."""
    path = Path(path)
    file = str(path)
    if not path.exists():
        raise SceneError("no such file", file=file)
    if path.is_dir():
        raise SceneError("is a directory, not a scene file", file=file)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SceneError(f"cannot read the file ({exc.strerror or exc})", file=file) from None
    overrides = list(overrides or [])
    digest = (str(path.resolve()), hashlib.sha256(data).hexdigest())
    with _LOADED_LOCK:
        loaded = _LOADED.get((*digest, tuple(overrides)))
        plain = _LOADED.get((*digest, ()))
    if loaded is not None:
        return _copied(loaded)
    if plain is None and overrides and all(_sets_a_parameter(text) for text in overrides):
        try:  # read (and keep) the file's own scene: the overrides are values on it
            load_scene(path)
        except SceneError:
            pass  # (the file's own values may be the invalid ones): read it with the overrides
        with _LOADED_LOCK:
            plain = _LOADED.get((*digest, ()))
    values = _parameter_values(overrides, plain, file)
    if values is not None:  # only new parameter values for a scene read before
        return _with_parameter_values(plain, values, file)
    raw = _parsed(data, digest, file)
    raw, set_paths = _apply_overrides(raw, overrides, file) if overrides else (_data_copy(raw), [])
    key = (*digest, tuple(overrides))
    try:
        scene = build_scene(raw, path=path)
    except SceneError as exc:
        origin = _override_origin(exc.key, set_paths)
        if origin is None:
            raise
        raise SceneError(f"{exc.reason} (value given by --set {origin})", file=file, key=exc.key) from None
    if scene.system.n_particles > KEPT_PARTICLES:  # not kept: the caller's own, no copy
        return scene
    with _LOADED_LOCK:
        _LOADED[key] = scene
        while len(_LOADED) > SCENES_KEPT:
            _LOADED.popitem(last=False)
    return _copied(scene)


#: Scenes validated in this process, by file content (its SHA-256) and overrides: reading one
#: again (a sweep, a fresh call) skips the validation and formula checks (about 1 ms). Each
#: caller gets its own copies of the mutable parts.
SCENES_KEPT = 32
#: Scenes of more particles are not kept: copying one costs a good part of validating it.
KEPT_PARTICLES = 2000
_LOADED: collections.OrderedDict = collections.OrderedDict()
_LOADED_LOCK = threading.Lock()


def _parsed(data: bytes, digest: tuple, file: str) -> dict:
    """The TOML of a scene file, parsed once per content (kept: callers copy it)."""
    with _LOADED_LOCK:
        raw = _PARSED.get(digest)
    if raw is None:
        try:
            raw = tomllib.loads(data.decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise SceneError(f"not UTF-8 text (byte {exc.start})", file=file) from None
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(f"not valid TOML: {exc}", file=file) from None
        with _LOADED_LOCK:
            _PARSED[digest] = raw
            while len(_PARSED) > SCENES_KEPT:
                _PARSED.popitem(last=False)
    return raw


#: Parsed scene files by (path, SHA-256 of the content): ``--set`` overrides apply to a copy.
_PARSED: collections.OrderedDict = collections.OrderedDict()


def _sets_a_parameter(text) -> bool:
    return isinstance(text, str) and text.strip().startswith("parameters.") and "=" in text


def _parameter_values(overrides: list[str], scene: Scene | None, file: str) -> dict | None:
    """``{name: value}`` when every override sets a number of the scene's [parameters]
    (``parameters.NAME=VALUE``), else None (the scene is then read and validated anew)."""
    if scene is None or not overrides:
        return None
    values = {}
    for text in overrides:
        tokens, value = parse_override(text, file=file)
        number = not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)
        if len(tokens) != 2 or tokens[0] != "parameters" or tokens[1] not in scene.system.parameters \
                or not number:
            return None
        values[tokens[1]] = float(value)
    return values


def _with_parameter_values(scene: Scene, values: dict, file: str) -> Scene:
    """A copy of the kept ``scene`` for new parameter values, checked as reading them from the
    file would: the formulas evaluated again (masses positive) and the start regular."""
    try:
        scene = _copied(scene, scene.system.with_parameters(values), {"parameters": values})
    except InputError as exc:
        raise SceneError(exc.reason, file=file, key=f"parameters ({', '.join(values)})") from None
    if "reduced" not in scene.raw:
        try:
            check_regular_start(scene)
        except SceneError as exc:
            raise SceneError(f"{exc.reason} (with the values given by --set)", file=file,
                             key=exc.key) from None
    return scene


def _copied(scene: Scene, system=None, raw_update: dict | None = None) -> Scene:
    """A Scene sharing nothing mutable with ``scene``; with ``system`` (a new System) instead
    of a copy of its own and ``raw_update`` ({table: {key: value}}) applied to its contents."""
    raw = _data_copy(scene.raw)
    for table, entries in (raw_update or {}).items():
        raw.setdefault(table, {}).update(entries)
    return dataclasses.replace(
        scene, system=scene.system.copy() if system is None else system,
        settings=_data_copy(scene.settings),
        outputs=_data_copy(scene.outputs), reduced=_data_copy(scene.reduced),
        raw=raw, expect=_data_copy(scene.expect),
        expectations=None if scene.expectations is None else list(scene.expectations),
        units=None if scene.units is None else dict(scene.units))


def _data_copy(value):
    """A deep copy of TOML-like data (dicts, lists, scalars), several times faster than
    ``copy.deepcopy``; anything else is deep-copied the usual way."""
    if isinstance(value, dict):
        return {k: _data_copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_data_copy(v) for v in value]
    if value is None or isinstance(value, str | int | float | bool | tuple):
        return value if not isinstance(value, tuple) else copy.deepcopy(value)
    return copy.deepcopy(value)


def build_scene(raw: Mapping, path: str | Path | None = None) -> Scene:
    """Validate a parsed scene dictionary (TOML layout) and build the Scene."""
    return _Builder(raw, None if path is None else Path(path)).build()


def check_regular_start(scene: Scene, *, loaded: bool = False) -> None:
    """Refuse (SceneError) a scene whose constraints or effects are undefined at its particles'
    initial positions (a rod whose particle sits on its anchor, 1/r at r = 0). ``load_scene``
    checks this itself, except for scenes with a [reduced] section, whose particle positions
    may be placeholders for the mapped start of ``crosscheck``: verbs that start from the
    particle positions call this, with ``loaded=True`` for a scene just returned by
    ``load_scene`` (then only a [reduced] scene is checked: twice costs seconds at 10⁴ particles)."""
    if loaded and "reduced" not in scene.raw:
        return
    builder = _Builder(scene.raw, scene.path)
    builder.names = [p.name for p in scene.system.particles]
    builder.regular_start(scene.system, scene.settings["t_start"])


def apply_overrides(raw: Mapping, overrides: Iterable[str] | None, *, file=None) -> dict:
    """A deep copy of ``raw`` with ``--set`` overrides ``"KEY=VALUE"`` applied.

    KEY is a dotted path (``simulate.t_end``, ``parameters.k``, ``reduced.initial.th1``);
    entries of ``[[particles]]``, ``[[constraints]]``, ``[[effects]]`` are addressed by index
    (``particles[0].mass``) or by their ``name`` (``particles.p1.mass``). VALUE is read as a
    TOML value (``2``, ``[1, 0, 0]``, ``"sin(t)"``); a bare word that is not TOML is a string.
    Keys that do not exist are added, so that validation refuses them like keys in the file.
    """
    out, _ = _apply_overrides(raw, list(overrides or []), None if file is None else str(file))
    return out


def parse_override(text: str, *, file=None) -> tuple[list[str | int], Any]:
    """Split ``"KEY=VALUE"`` into the key path (names and indices) and the parsed value."""
    if not isinstance(text, str) or "=" not in text:
        raise SceneError(
            f"--set {text!r}: expected KEY=VALUE, e.g. simulate.t_end=2",
            file=file,
            key=text.strip() if isinstance(text, str) and text.strip() else None,
        )
    key, value = text.split("=", 1)
    key = key.strip()
    if not _KEY_RE.fullmatch(key):
        raise SceneError(
            f"--set {text!r}: {key!r} is not a key path (write e.g. simulate.t_end, "
            "particles.p1.mass or particles[0].mass)",
            file=file,
            key=key or None,
        )
    tokens: list[str | int] = []
    for name, index in _TOKEN_RE.findall(key):
        tokens.append(name if name else int(index))
    return tokens, _parse_value(value.strip())


# --- overrides -------------------------------------------------------------------------------

_SEG = r"[A-Za-z0-9_\-]+(?:\[\d+\])*"
_KEY_RE = re.compile(rf"{_SEG}(?:\.{_SEG})*")
_TOKEN_RE = re.compile(r"([A-Za-z0-9_\-]+)|\[(\d+)\]")


#: A decimal number as TOML writes one (no leading zeros, digits on both sides of the point).
_NUMBER_RE = re.compile(r"[+-]?(?:0|[1-9][0-9]*)(?:(\.[0-9]+)?([eE][+-]?[0-9]+)?)")


_NUMBERS_RE = re.compile(rf"\[\s*(?:{_NUMBER_RE.pattern}\s*,\s*)*{_NUMBER_RE.pattern}\s*,?\s*\]")


def _parse_value(text: str):
    number = _NUMBER_RE.fullmatch(text)
    if number:  # the common case, read as TOML would without its parser
        return float(text) if number.group(1) or number.group(2) else int(text)
    if _NUMBERS_RE.fullmatch(text):  # a list of such numbers (a position, a vector)
        return [_parse_value(entry.strip()) for entry in text.strip()[1:-1].split(",") if entry.strip()]
    try:
        return tomllib.loads(f"value = {text}")["value"]
    except tomllib.TOMLDecodeError:
        pass
    try:
        return float(text) if any(c in text for c in ".eE") or text.lower() in ("inf", "nan") else int(text)
    except ValueError:
        return text


def _apply_overrides(raw: Mapping, overrides: list[str], file: str | None):
    """Apply overrides; returns the new dict and [(canonical key path, override text)]."""
    out = _data_copy(dict(raw))
    applied: list[tuple[str, str]] = []
    for text in overrides:
        tokens, value = parse_override(text, file=file)
        key = text.split("=", 1)[0].strip()
        cur: Any = out
        canon = ""
        for pos, tok in enumerate(tokens):
            last = pos == len(tokens) - 1
            if isinstance(tok, int):
                if not isinstance(cur, list):
                    raise SceneError(
                        f"--set {text}: {canon or 'the scene'} is not a list, it cannot be indexed",
                        file=file,
                        key=key,
                    )
                if tok >= len(cur):
                    raise SceneError(
                        f"--set {text}: index {tok} is out of range ({canon} has {len(cur)} entries)",
                        file=file,
                        key=key,
                    )
                canon = f"{canon}[{tok}]"
                if last:
                    cur[tok] = value
                else:
                    cur = cur[tok]
                continue
            if isinstance(cur, list):
                found = [i for i, e in enumerate(cur) if isinstance(e, dict) and e.get("name") == tok]
                if not found:
                    names = [e.get("name") for e in cur if isinstance(e, dict) and "name" in e]
                    listed = ", ".join(map(str, names)) or "none has a name"
                    raise SceneError(
                        f"--set {text}: {canon} has no entry named '{tok}' ({listed}); "
                        f"address entries by name or by index, e.g. {canon}[0]",
                        file=file,
                        key=key,
                    )
                canon = f"{canon}[{found[0]}]"
                if last:
                    cur[found[0]] = value
                else:
                    cur = cur[found[0]]
                continue
            if not isinstance(cur, dict):
                raise SceneError(
                    f"--set {text}: {canon} is a value ({cur!r}), not a table",
                    file=file,
                    key=key,
                )
            canon = f"{canon}.{tok}" if canon else tok
            if last:
                cur[tok] = value
            else:
                if tok not in cur:
                    if isinstance(tokens[pos + 1], int):
                        raise SceneError(
                            f"--set {text}: the scene has no list '{canon}' to index",
                            file=file,
                            key=key,
                        )
                    cur[tok] = {}
                cur = cur[tok]
        applied.append((canon, text.strip()))
    return out, applied


def _override_origin(key: str | None, applied: list[tuple[str, str]]) -> str | None:
    if not key:
        return None
    for canon, text in reversed(applied):
        if key == canon or any(a.startswith(b + c) for a, b in ((key, canon), (canon, key)) for c in ".["):
            return text if len(text) <= 80 else text[:77] + "..."
    return None


# --- validation ------------------------------------------------------------------------------


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _join(prefix: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{prefix}[{key}]"
    return f"{prefix}.{key}" if prefix else key


def _suggest(word: str, choices: Iterable[str]) -> str:
    close = difflib.get_close_matches(str(word), list(choices), n=1)
    return f"; did you mean '{close[0]}'?" if close else ""


def _why_singular(obj, system: System, t0: float) -> str:
    """The likely reason an item is undefined at the start: two ends at one place."""
    a, b, point = (getattr(obj, k, None) for k in ("a", "b", "point"))
    if not isinstance(a, str):
        return "; move the particles away from the singular point (e.g. r = 0 in a formula)"
    names = [p.name for p in system.particles]
    pos = np.asarray(system.positions, float).reshape(-1, 3)
    here = pos[names.index(a)] if a in names else None
    if isinstance(b, str) and b in names and here is not None and np.allclose(here, pos[names.index(b)]):
        return (f": particles '{a}' and '{b}' start at the same position, where the direction "
                "between them is undefined; move one of them")
    if point is not None and here is not None:
        return (f": particle '{a}' starts on the point {list(point)}, where the direction from "
                "the point is undefined; move the particle (to the rod's length from the point)")
    return "; move the particles away from the singular point"


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


_SINGULAR = {"quantities": "quantity", "plots": "plot", "formats": "format"}


def _name_or_value(value) -> str:
    return f"'{value}'" if isinstance(value, str) else _describe(value)


def _describe(value) -> str:
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return f"a list {value!r}" if len(repr(value)) < 60 else "a list"
    if isinstance(value, str):
        return f"the string {value!r}"
    if isinstance(value, bool):
        return f"the boolean {str(value).lower()}"
    return repr(value)


class _Builder:
    def __init__(self, raw: Mapping, path: Path | None):
        self.raw = dict(raw)
        self.path = path
        self.file = None if path is None else str(path)
        self.names: list[str] = []

    def fail(self, key: str | None, reason: str):
        raise SceneError(reason, file=self.file, key=key)

    # small checkers ---------------------------------------------------------------------
    def table(self, value, key: str, what: str = "a table") -> dict:
        if not isinstance(value, dict):
            self.fail(key, f"must be {what}, got {_describe(value)}")
        return value

    def keys(
        self,
        table: dict,
        key: str,
        allowed: Iterable[str],
        required: Iterable[str] = (),
        what: str = "",
    ) -> None:
        allowed = list(allowed)
        for k in table:
            if k not in allowed:
                self.fail(
                    _join(key, k),
                    f"unknown key '{k}'{' in ' + what if what else ''} "
                    f"(allowed keys: {', '.join(allowed)}){_suggest(k, allowed)}",
                )
        for k in required:
            if k not in table:
                self.fail(_join(key, k), f"missing required key '{k}'{' of ' + what if what else ''}")

    def number(self, value, key: str, what: str = "a number") -> float:
        if not _is_number(value):
            self.fail(key, f"must be {what}, got {_describe(value)}")
        if not math.isfinite(value):
            self.fail(key, f"must be a finite number, got {value!r}")
        return float(value)

    def positive(self, value, key: str, what: str = "a finite positive number") -> float:
        x = self.number(value, key, what)
        if x <= 0:
            self.fail(key, f"must be {what}, got {value!r}")
        return x

    def string(self, value, key: str, what: str = "a string") -> str:
        if not isinstance(value, str) or not value.strip():
            self.fail(key, f"must be {what} (non-empty), got {_describe(value)}")
        return value

    def identifier(self, value, key: str, what: str) -> str:
        if not isinstance(value, str) or not value.isidentifier():
            self.fail(
                key,
                f"{what} must be a plain identifier (letters, digits, underscore; not starting "
                f"with a digit), got {_describe(value)}",
            )
        return value

    def particle(self, value, key: str) -> str:
        if not isinstance(value, str):
            self.fail(key, f"must be a particle name, got {_describe(value)}")
        if value not in self.name_set():
            known = ", ".join(self.names)
            self.fail(
                key,
                f"names unknown particle '{value}' (particles: {known}){_suggest(value, self.names)}",
            )
        return value

    def name_set(self) -> frozenset:
        """``self.names`` as a set (kept while the list stays the same): a 10,000-particle
        scene looks names up 30,000 times."""
        cache = self.__dict__.get("_name_set")
        if cache is None or cache[0] is not self.names or cache[1] != len(self.names):
            cache = self._name_set = (self.names, len(self.names), frozenset(self.names))
        return cache[2]

    def particle_list(self, value, key: str) -> list[str]:
        if isinstance(value, str):
            return [self.particle(value, key)]
        if not isinstance(value, list) or not value:
            self.fail(key, f"must be a particle name or a non-empty list of names, got {_describe(value)}")
        out = [self.particle(v, _join(key, i)) for i, v in enumerate(value)]
        first: dict[str, int] = {}
        for i, name in enumerate(out):
            if first.setdefault(name, i) != i:
                self.fail(_join(key, i), f"particle '{name}' is listed twice")
        return out

    def formula(self, value, key: str):
        """A number or a formula string (parsed later, with the names of its context)."""
        if _is_number(value):
            return self.number(value, key)
        if not isinstance(value, str) or not value.strip():
            self.fail(key, f"must be a number or a formula string, got {_describe(value)}")
        return value

    def formulas(self, value, key: str, n: int, what: str) -> list:
        if not isinstance(value, list) or len(value) != n:
            got = f"{len(value)} entries" if isinstance(value, list) else _describe(value)
            self.fail(key, f"must be a list of {n} {what}, got {got}")
        return [self.formula(v, _join(key, i)) for i, v in enumerate(value)]

    def vector(self, value, key: str) -> list:
        return self.formulas(value, key, 3, "entries (numbers or formulas of t)")

    def string_list(self, value, key: str, allowed: tuple[str, ...], what: str) -> list[str]:
        if not isinstance(value, list):
            self.fail(key, f"must be a list of {what}, got {_describe(value)}")
        out: list[str] = []
        for i, v in enumerate(value):
            if not isinstance(v, str) or v not in allowed:
                self.fail(
                    _join(key, i),
                    f"unknown {_SINGULAR.get(what, what)} {_name_or_value(v)} "
                    f"(allowed: {', '.join(allowed)}){_suggest(v, allowed)}",
                )
            if v not in out:
                out.append(v)
        return out

    def finite_everywhere(self, value, key: str) -> None:
        if isinstance(value, float) and not math.isfinite(value):
            self.fail(key, f"the number {value!r} is not finite (inf and nan are not accepted)")
        if _is_number(value) and abs(value) > expressions.MAX_MAGNITUDE:
            self.fail(key, f"the number {value!r} is too large: beyond {expressions.MAX_MAGNITUDE:g} "
                      "in size, products and squares in the equations of motion overflow; use units "
                      "that keep the numbers moderate")
        if isinstance(value, dict):
            for k, v in value.items():
                self.finite_everywhere(v, _join(key, k))
        elif isinstance(value, list):
            for i, v in enumerate(value):
                self.finite_everywhere(v, _join(key, i))

    def array_of_tables(self, name: str) -> list[dict]:
        value = self.raw.get(name, [])
        if isinstance(value, dict):
            self.fail(name, f"must be an array of tables, written [[{name}]] (double brackets)")
        if not isinstance(value, list):
            self.fail(name, f"must be an array of tables [[{name}]], got {_describe(value)}")
        for i, item in enumerate(value):
            self.table(item, _join(name, i), f"a table (one [[{name}]] entry)")
        return value

    # sections ---------------------------------------------------------------------------
    def build(self) -> Scene:
        for k in self.raw:
            if k not in TOP_LEVEL_TABLES:
                self.fail(
                    k,
                    f"unknown top-level table '{k}' (allowed: {', '.join(TOP_LEVEL_TABLES)})"
                    f"{_suggest(k, TOP_LEVEL_TABLES)}",
                )
        for k in ("scene", "parameters", "definitions", "simulate", "outputs", "reduced", "expect"):
            if k in self.raw:
                self.table(self.raw[k], k, f"a table [{k}]")
        for k in TOP_LEVEL_TABLES:
            if k in self.raw and k != "expect":
                self.finite_everywhere(self.raw[k], k)

        name, description = self.scene_section()
        particles = self.particles()
        parameters = self.parameters()
        definitions = self.definitions(parameters)
        constraints = [
            self.item(i, item, "constraints") for i, item in enumerate(self.array_of_tables("constraints"))
        ]
        effects = [self.item(i, item, "effects") for i, item in enumerate(self.array_of_tables("effects"))]
        try:
            system = System(particles, constraints, effects, parameters, name, definitions)
        except InputError as exc:
            self.fail(exc.where, exc.reason)
        structure = self.structure(system)
        system.events = self.events_section(system)
        settings = self.simulate()
        if "reduced" not in self.raw:  # with [reduced], crosscheck starts from the mapped state
            self.regular_start(system, settings["t_start"], structure)
        outputs = self.outputs()
        reduced = self.reduced({**parameters, **definitions})
        expect = self.raw.get("expect")
        expectations = None if expect is None else self.expect_section(expect, system)
        return Scene(
            path=self.path,
            name=name,
            system=system,
            settings=settings,
            outputs=outputs,
            reduced=reduced,
            raw=self.raw,
            expect=None if expect is None else copy.deepcopy(expect),
            description=description,
            expectations=expectations,
            units=dict(self.raw.get("scene", {}).get("units", {})),
        )

    def expect_section(self, table: dict, system: System) -> list[dict]:
        """Validate [expect]; returns one normalized check per entry (formulas parsed once here)."""
        self.keys(table, "expect", EXPECT_KEYS, what="[expect]")
        s = Symbols(system)
        out: list[dict] = []

        def formula(text, key: str):
            if _is_number(text):
                return self.number(text, key)
            if not isinstance(text, str) or not text.strip():
                self.fail(key, f"must be a number or a formula string, got {_describe(text)}")
            try:
                s.parse(text, key, velocities=True, extra=force_names(s))
            except InputError as exc:
                self.fail(key, exc.reason)
            return text

        def tolerance(value, key: str) -> float:
            tol = self.number(value, key, "a tolerance (a number >= 0)")
            if tol < 0:
                self.fail(key, f"must be a tolerance >= 0, got {value!r}")
            return tol

        def pairs(name: str, what: str):
            sub = self.table(table[name], f"expect.{name}", f"a table formula -> {what}")
            for lhs, value in sub.items():
                key = _join(f"expect.{name}", lhs)
                formula(lhs, key)
                if not isinstance(value, list) or len(value) != 2:
                    got = f"{len(value)} entries" if isinstance(value, list) else _describe(value)
                    self.fail(key, f"must be a list {what}, got {got}")
                yield lhs, value, key

        for name in EXPECT_KEYS:
            if name not in table:
                continue
            key = f"expect.{name}"
            if name in ("energy_drift", "constraint_residual", "velocity_residual"):
                out.append({"kind": name, "key": key, "tol": tolerance(table[name], key)})
            elif name in ("final", "closed_form", "period"):
                for lhs, (value, tol), k in pairs(name, "[value or formula, tolerance]"):
                    out.append({"kind": name, "key": k, "lhs": lhs, "rhs": formula(value, _join(k, 0)),
                                "tol": tolerance(tol, _join(k, 1))})
            elif name in ("bounds", "reaches"):
                for lhs, (lo, hi), k in pairs(name, "[lowest, highest]"):
                    lo_, hi_ = (self.number(v, _join(k, i)) if not (_is_number(v) and math.isinf(v))
                                else float(v) for i, v in enumerate((lo, hi)))
                    if lo_ > hi_:
                        self.fail(k, f"lowest ({lo_:g}) is above highest ({hi_:g})")
                    out.append({"kind": name, "key": k, "lhs": lhs, "lo": lo_, "hi": hi_})
            else:  # conserved
                sub = self.table(table[name], key, "a table name -> {axis, point, translation, tol}")
                for label, entry in sub.items():
                    k = _join(key, label)
                    self.table(entry, k, "a table {axis = [..], point = [..], tol = ..} or "
                               "{translation = [..], tol = ..}")
                    self.keys(entry, k, _CONSERVED_KEYS, ("tol",), what="a conserved quantity")
                    if "axis" not in entry and "translation" not in entry:
                        self.fail(k, "give 'axis' (and optionally 'point') for a rotation, or "
                                  "'translation', the symmetry whose Noether charge is conserved")
                    if "point" in entry and "axis" not in entry:
                        self.fail(_join(k, "point"), "'point' needs 'axis' (the rotation axis)")
                    vec = {v: self.numbers3(entry[v], _join(k, v)) for v in ("axis", "point", "translation")
                           if v in entry}
                    for v in ("axis", "translation"):
                        if v in vec and not any(vec[v]):
                            self.fail(_join(k, v), "must not be the zero vector")
                    out.append({"kind": name, "key": k, "label": label,
                                "rotation": (vec["axis"], vec.get("point", [0.0, 0.0, 0.0]))
                                if "axis" in vec else None,
                                "translation": vec.get("translation"),
                                "tol": tolerance(entry["tol"], _join(k, "tol"))})
        return out

    def events_section(self, system: System) -> list:
        """[[events]]: name, a formula crossing zero, direction, stop (constrained.events)."""
        from .events import CONSTRAINT_KINDS
        from .user_events import DIRECTIONS, FormulaEvent

        s = Symbols(system)
        out, seen = [], {}
        for i, item in enumerate(self.array_of_tables("events")):
            key = _join("events", i)
            self.keys(item, key, EVENT_KEYS[0] + EVENT_KEYS[1], EVENT_KEYS[0], what="an event")
            name = self.string(item["name"], f"{key}.name", "an event name")
            if name in seen or name in CONSTRAINT_KINDS:
                taken = f"also events[{seen[name]}]" if name in seen else "a constraint event kind"
                self.fail(f"{key}.name", f"the event name '{name}' is taken ({taken}); give each event "
                          "its own name")
            seen[name] = i
            expr = self.string(item["expr"], f"{key}.expr", "a formula string (zero at the event)")
            try:
                s.parse(expr, f"{key}.expr", velocities=True)
            except InputError as exc:
                self.fail(exc.where or f"{key}.expr", exc.reason)
            direction = item.get("direction", "both")
            if direction not in DIRECTIONS and direction not in (-1, 0, 1) or isinstance(direction, bool):
                self.fail(f"{key}.direction", f"must be \"rising\" (the formula crossing zero upward), "
                          f"\"falling\" or \"both\", got {_describe(direction)}")
            stop = item.get("stop", False)
            if not isinstance(stop, bool):
                self.fail(f"{key}.stop", "must be true (the run ends at the event) or false, "
                          f"got {_describe(stop)}")
            out.append(FormulaEvent(name, str(expr), DIRECTIONS.get(direction, direction), stop, where=key))
        return out

    def scene_section(self) -> tuple[str, str]:
        table = self.raw.get("scene", {})
        self.keys(table, "scene", ("name", "description", "units"), what="[scene]")
        units = table.get("units", {})
        if not isinstance(units, dict) or not all(isinstance(v, str) for v in units.values()):
            self.fail("scene.units", "must be a table of unit strings, e.g. units = { a = \"m\", "
                      f"nu = \"rad/s\" }}, got {_describe(units)}")
        default = self.path.stem if self.path is not None else "scene"
        name = self.string(table["name"], "scene.name") if "name" in table else default
        description = table.get("description", "")
        if not isinstance(description, str):
            self.fail("scene.description", f"must be a string, got {_describe(description)}")
        return name, description

    def particles(self) -> list[Particle]:
        items = self.array_of_tables("particles")
        if not items:
            self.fail("particles", "the scene has no particles; add at least one [[particles]] table")
        out = []
        seen: dict[str, int] = {}
        for i, item in enumerate(items):
            key = _join("particles", i)
            self.keys(
                item,
                key,
                ("name", "mass", "position", "velocity"),
                ("name", "mass", "position"),
                what="a particle",
            )
            name = self.identifier(item["name"], f"{key}.name", "a particle name")
            if name in seen:
                self.fail(
                    f"{key}.name",
                    f"duplicate particle name '{name}' (also particles[{seen[name]}])",
                )
            seen[name] = i
            mass = item["mass"]
            if isinstance(mass, str):  # a formula of the parameters, evaluated by the System
                mass = self.formula(mass, f"{key}.mass")
            elif self.positive(mass, f"{key}.mass", "a finite positive number (kg) or a formula "
                               "of the parameters") < 1 / expressions.MAX_MAGNITUDE:
                self.fail(f"{key}.mass", f"the mass {mass!r} kg is too small (below "
                          f"{1 / expressions.MAX_MAGNITUDE:g}): 1/m overflows in the equations of motion; "
                          "use units that keep the numbers moderate")
            position = self.formulas(item["position"], f"{key}.position", 3,
                                     "numbers or formulas of the parameters (x, y, z)")
            velocity = self.formulas(item.get("velocity", [0.0, 0.0, 0.0]), f"{key}.velocity", 3,
                                     "numbers or formulas of the parameters (x, y, z)")
            try:
                out.append(Particle(name, mass, position, velocity, where=key))
            except InputError as exc:
                self.fail(exc.where or key, exc.reason)
        self.names = list(seen)
        return out

    def numbers3(self, value, key: str) -> list[float]:
        if not isinstance(value, list) or len(value) != 3:
            got = f"{len(value)} entries" if isinstance(value, list) else _describe(value)
            self.fail(key, f"must be a list of 3 numbers (x, y, z), got {got}")
        return [self.number(v, _join(key, i)) for i, v in enumerate(value)]

    def reserved_for_formulas(self) -> set[str]:
        names = set(RESERVED_NAMES)
        for p in self.names:
            for axis in "xyz":
                names |= {f"{axis}_{p}", f"v{axis}_{p}"}
        return names

    def parameters(self) -> dict[str, float]:
        table = self.raw.get("parameters", {})
        reserved = self.reserved_for_formulas()
        out = {}
        for k, v in table.items():
            key = _join("parameters", k)
            self.identifier(k, key, "a parameter name")
            if k in reserved:
                self.fail(
                    key,
                    f"the parameter name '{k}' is taken (it already means something in formulas)",
                )
            out[k] = self.number(v, key, "a number")
        return out

    def definitions(self, parameters: dict) -> dict:
        """[definitions]: name -> a formula in parameters and other definitions (or a number)."""
        table = self.raw.get("definitions", {})
        reserved = self.reserved_for_formulas()
        for k, v in table.items():
            key = _join("definitions", k)
            self.identifier(k, key, "a definition name")
            if k in reserved or k in parameters:
                what = "a parameter" if k in parameters else "it already means something in formulas"
                self.fail(key, f"the definition name '{k}' is taken ({what})")
            self.formula(v, key)
        return dict(table)

    def item(self, i: int, item: dict, section: str):
        """One [[constraints]] or [[effects]] entry -> the library object."""
        key = _join(section, i)
        kind = "constraint" if section == "constraints" else "effect"
        types = CONSTRAINT_TYPES if section == "constraints" else EFFECT_TYPES
        schema = CONSTRAINT_KEYS if section == "constraints" else EFFECT_KEYS
        if "type" not in item:
            self.fail(
                f"{key}.type",
                f"missing required key 'type' (known {kind} types: {', '.join(types)})",
            )
        typ = item["type"]
        if not isinstance(typ, str) or typ not in types:
            self.fail(
                f"{key}.type",
                f"unknown {kind} type {_name_or_value(typ)} (known types: {', '.join(types)})"
                f"{_suggest(typ, types)}",
            )
        if typ not in schema:
            self.fail(f"{key}.type", f"the {kind} type '{typ}' cannot be used from scene files yet")
        required, optional = schema[typ]
        if kind == "constraint":
            optional = (*optional, *ONE_SIDED_KEYS)
        self.keys(item, key, ("type", "name", *required, *optional), required, what=f"a {typ} {kind}")
        name = self.string(item["name"], f"{key}.name", "a name") if "name" in item else None
        args = {k: self.value(typ, k, v, f"{key}.{k}") for k, v in item.items() if k not in ("type", "name")}
        self.pairing(typ, args, key)
        cls = types[typ]
        try:
            return self.construct(cls, typ, args, name=name, where=key)
        except InputError as exc:
            self.fail(exc.where or key, exc.reason)

    def value(self, typ: str, k: str, v, key: str):
        if k == "unilateral":
            if not isinstance(v, bool):
                self.fail(key, f"must be true (a one-sided constraint) or false, got {_describe(v)}")
            return v
        if k == "restitution":
            return self.number(v, key, "a coefficient of restitution from 0 to 1")
        if k in ("a", "b", "particle"):
            return self.particle(v, key)
        if k == "particles":
            return self.particle_list(v, key)
        if k in ("point", "normal", "g", "A"):
            return self.vector(v, key)
        if k == "expr":
            if typ == "curve":
                return self.formulas(v, key, 2, "surface formulas")
            if typ == "force":
                return self.formulas(v, key, 3, "force formulas (Fx, Fy, Fz)")
            return self.formula(v, key)
        if k == "charges":
            self.table(v, key, "a table particle name -> charge")
            if not v:
                self.fail(key, "must name at least one particle")
            return {
                self.particle(name, _join(key, name)): self.formula(q, _join(key, name))
                for name, q in v.items()
            }
        return self.formula(v, key)  # length, offset, k, rest, coefficient, phi

    def pairing(self, typ: str, args: dict, key: str) -> None:
        if typ in ("distance", "spring", "central"):
            if ("b" in args) == ("point" in args):
                self.fail(key, "give exactly one of 'b' (a particle) or 'point'")
        if typ == "damping":
            if ("a" in args) != ("b" in args):
                self.fail(key, "pairwise damping needs both 'a' and 'b'")
            if "a" in args and "particles" in args:
                self.fail(key, "give either 'particles' or the pair 'a', 'b', not both")
        if "a" in args and args.get("b") == args["a"]:
            self.fail(f"{key}.b", f"'a' and 'b' name the same particle '{args['a']}'")

    @staticmethod
    def construct(cls, typ: str, args: dict, *, name, where):
        a = dict(args)
        sides = {k: a.pop(k) for k in ONE_SIDED_KEYS if k in a}
        if sides:  # one-sided keys go to every constraint type
            return _Builder.construct(functools.partial(cls, **sides), typ, a, name=name, where=where)
        if typ == "curve":
            return cls(a.pop("particles"), exprs=a.pop("expr"), name=name, where=where)
        if typ == "pin":
            return cls(a.pop("a"), a.pop("point"), name=name, where=where)
        if typ == "plane":
            return cls(a.pop("particles"), a.pop("normal"), a.pop("offset", 0.0), name=name, where=where)
        if typ == "surface":
            return cls(a.pop("particles"), a.pop("expr"), name=name, where=where)
        if typ in ("distance", "spring", "central"):
            return cls(a.pop("a"), a.pop("b", None), **a, name=name, where=where)
        if typ == "gravity":
            return cls(a.pop("g"), a.pop("particles", None), name=name, where=where)
        if typ == "damping":
            return cls(a.pop("coefficient"), a.pop("particles", None), **a, name=name, where=where)
        if typ == "force":
            return cls(a.pop("particle"), a.pop("expr"), name=name, where=where)
        if typ == "electromagnetic":
            return cls(a.pop("charges"), **a, name=name, where=where)
        return cls(**a, name=name, where=where)  # custom, potential: expr

    def structure(self, system: System) -> tuple:
        """The system's Structure and plain numbers (``model.kept_structure``: built here, or
        the one kept from an equal scene read before, and kept for the run), which parses and
        differentiates every formula: a bad one is reported at load time, with its item's key
        (``check_formulas`` finds the item when the Structure's error does not name one)."""
        try:
            return kept_structure(system)
        except (InputError, RuntimeError, TypeError, ValueError, ZeroDivisionError) as exc:
            self.check_formulas(system)
            if isinstance(exc, InputError):
                self.fail(exc.where or "effects", exc.reason)
            self.fail("constraints", f"the equations cannot be built: {exc}")

    def check_formulas(self, system: System) -> tuple[Symbols, dict]:
        """Parse every formula now (cheap), so a bad one is reported at load time; returns the
        Symbols and the built rows and terms, {(section, index): value}, for ``regular_start``."""
        s = Symbols(system)
        built = {}
        for section, items, call in (
            ("constraints", system.constraints, lambda c: c.rows(s)),
            ("effects", system.effects, lambda e: e.term(s)),
        ):
            for i, obj in enumerate(items):
                key = _join(section, i)
                try:
                    built[section, i] = call(obj)
                except InputError as exc:
                    self.fail(exc.where or key, exc.reason)
                except (RuntimeError, TypeError, ZeroDivisionError) as exc:
                    self.fail(key, f"cannot be built: {exc}")
        return s, built

    def regular_start(self, system: System, t0: float, structure: tuple | None = None) -> None:
        """Every constraint row, its gradient, and every effect's term and gradients must be
        finite at the initial state: a rod whose particle sits on its anchor, or a 1/r potential
        at r = 0, is refused here with the item's key instead of failing inside a solver
        (constrained.regularity: one sparse evaluation for the whole system, of a Function
        built once per structure). ``structure``: ``(Structure, numbers)`` of the system."""
        structure, numbers = structure if structure is not None else self.structure(system)
        for section, i, obj in undefined_items(system, t0, structure=structure, numbers=numbers)[:1]:
            what = "constraint" if section == "constraints" else "effect"
            self.fail(_join(section, i), f"this {what} ({obj.label}) is undefined at the initial state "
                      f"(t = {t0:g} s): its value or its gradient is not finite there"
                      f"{_why_singular(obj, system, t0)}")

    def simulate(self) -> dict:
        table = self.raw.get("simulate", {})
        self.keys(table, "simulate", SIMULATE_DEFAULTS, what="[simulate]")
        s = dict(SIMULATE_DEFAULTS)
        s.update(table)
        k = "simulate."
        if s["t_end"] is not None:
            s["t_end"] = self.positive(s["t_end"], k + "t_end", "a finite positive time (s)")
        s["t_start"] = self.number(s["t_start"], k + "t_start", "a time in s")
        if s["t_end"] is not None and s["t_end"] <= s["t_start"]:
            self.fail(k + "t_end", f"must be later than t_start = {s['t_start']:g}, got {s['t_end']:g}")
        s["method"] = self.string(s["method"], k + "method", "a method name")
        s["base"] = self.string(s["base"], k + "base", "an integrator name")
        self.method_and_base(s["method"], s["base"], "base" in table)
        s["rtol"] = self.number(s["rtol"], k + "rtol")
        if not 0 < s["rtol"] < 1:
            self.fail(k + "rtol", f"must be between 0 and 1 (exclusive), got {s['rtol']:g}")
        s["atol"] = self.number(s["atol"], k + "atol")
        if not 0 < s["atol"] < 1:
            self.fail(k + "atol", f"must be between 0 and 1 (exclusive), got {s['atol']:g}")
        for name in ("dt", "output_dt"):
            if s[name] is not None:
                s[name] = self.positive(s[name], k + name, "a finite positive time step (s)")
        if s["samples"] is not None:
            n = s["samples"]
            if not isinstance(n, int) or isinstance(n, bool) or n < 2:
                self.fail(k + "samples", f"must be a whole number >= 2, got {_describe(n)}")
        if s["samples"] is not None and s["output_dt"] is not None:
            self.fail(k + "samples", "give either 'samples' or 'output_dt', not both")
        self.run_size(s)
        mic = self.number(s["max_initial_correction"], k + "max_initial_correction")
        if mic < 0:
            self.fail(k + "max_initial_correction", f"must be zero or positive, got {mic!r}")
        s["max_initial_correction"] = mic
        if s["compiled"] not in (True, False, "auto"):
            self.fail(k + "compiled", f'must be true, false or "auto", got {_describe(s["compiled"])}')
        if s["method"] == "reduced" and "reduced" not in self.raw:
            self.fail(k + "method", "method 'reduced' needs the scene's [reduced] section "
                      "(coordinates, initial, rates, map)")
        return s

    def run_size(self, s: dict) -> None:
        """Times a step can resolve, and a bounded number of output samples and fixed steps."""
        k = "simulate."
        for name in ("t_start", "t_end"):
            if s[name] is not None and abs(s[name]) > MAX_TIME:
                self.fail(k + name, f"{s[name]:g} s is beyond {MAX_TIME:g} s: at such times a float "
                          "cannot resolve a time step; shift the clock (t_start = 0)")
        if s["samples"] is not None and s["samples"] > MAX_SAMPLES:
            self.fail(k + "samples", f"{s['samples']} output samples is more than the {MAX_SAMPLES} "
                      "accepted; ask for fewer")
        if s["t_end"] is None:
            return
        span = s["t_end"] - s["t_start"]
        if s["output_dt"] is not None and span / s["output_dt"] > MAX_SAMPLES:
            self.fail(k + "output_dt", f"{s['output_dt']:g} s over {span:g} s gives more than the "
                      f"{MAX_SAMPLES} output samples accepted; use a larger output_dt")
        if s["dt"] is not None and span / s["dt"] > MAX_STEPS:
            self.fail(k + "dt", f"{s['dt']:g} s over {span:g} s is more than {MAX_STEPS:g} steps; "
                      "use a larger dt")

    def method_and_base(self, method: str, base: str, base_given: bool) -> None:
        """``method`` must be a registered solver; ``base`` one its solver accepts."""
        from .solvers import METHODS

        if method not in METHODS:
            self.fail(
                "simulate.method",
                f"unknown method '{method}' (known methods: {', '.join(sorted(METHODS))})"
                f"{_suggest(method, METHODS)}",
            )
        cls = METHODS[method]
        if "base" not in cls.OPTIONS:
            if base_given:
                self.fail("simulate.base", f"method '{method}' does not take a base integrator")
            return
        bases = cls.BASES
        if bases and base not in bases:
            others = [m for m, c in METHODS.items() if base in c.BASES]
            hint = (f"; '{base}' is a base of method {', '.join(others)}: add method = "
                    f"\"{others[0]}\"" if others else _suggest(base, bases))
            self.fail(
                "simulate.base",
                f"unknown base integrator '{base}' for method '{method}' "
                f"(known: {', '.join(bases)}){hint}",
            )

    def outputs(self) -> dict:
        table = self.raw.get("outputs", {})
        self.keys(table, "outputs", OUTPUT_DEFAULTS, what="[outputs]")
        out = {k: list(v) for k, v in OUTPUT_DEFAULTS.items()}
        allowed = {
            "quantities": OUTPUT_QUANTITIES,
            "plots": OUTPUT_PLOTS,
            "formats": OUTPUT_FORMATS,
        }
        for k, v in table.items():
            out[k] = self.string_list(v, f"outputs.{k}", allowed[k], k)
        return out

    def reduced(self, parameters: dict) -> dict | None:
        if "reduced" not in self.raw:
            return None
        table = self.raw["reduced"]
        self.keys(
            table,
            "reduced",
            ("coordinates", "initial", "rates", "map"),
            ("coordinates", "initial", "map"),
            what="[reduced]",
        )
        coords = table["coordinates"]
        if not isinstance(coords, list) or not coords:
            self.fail("reduced.coordinates", f"must be a non-empty list of names, got {_describe(coords)}")
        taken = self.reserved_for_formulas() | set(parameters)
        for i, c in enumerate(coords):
            key = _join("reduced.coordinates", i)
            self.identifier(c, key, "a coordinate name")
            if c in coords[:i]:
                self.fail(key, f"coordinate '{c}' is listed twice")
            if c in taken:
                what = "a parameter" if c in parameters else "a name formulas already use"
                self.fail(key, f"the coordinate name '{c}' is taken ({what})")

        def values(name: str, complete: bool) -> dict[str, float]:
            tab = self.table(table.get(name, {}), f"reduced.{name}", "a table coordinate -> number")
            for k in tab:
                if k not in coords:
                    self.fail(
                        _join(f"reduced.{name}", k),
                        f"'{k}' is not a coordinate (coordinates: {', '.join(coords)}){_suggest(k, coords)}",
                    )
            if complete:
                for c in coords:
                    if c not in tab:
                        self.fail(_join(f"reduced.{name}", c), f"missing the initial value of '{c}'")
            return {c: self.number(tab.get(c, 0.0), _join(f"reduced.{name}", c)) for c in coords}

        initial = values("initial", True)
        rates = values("rates", False)
        mapping = self.table(table["map"], "reduced.map", "a table particle name -> [x, y, z] formulas")
        out_map = {}
        for k, v in mapping.items():
            key = _join("reduced.map", k)
            if k not in self.names:
                self.fail(key, f"names unknown particle '{k}' (particles: {', '.join(self.names)})")
            out_map[k] = self.formulas(v, key, 3, "formulas (x, y, z) in the coordinates")
        for p in self.names:
            if p not in out_map:
                self.fail(
                    _join("reduced.map", p),
                    f"particle '{p}' is not mapped; every particle needs x, y, z",
                )
        return {
            "coordinates": list(coords),
            "initial": initial,
            "rates": rates,
            "map": {p: out_map[p] for p in self.names},
        }
