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
import hashlib
import math
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import tomlparse
from ..bulk import collector_paused
from ..errors import InputError, SceneError
from ..model.parameters import RESERVED_NAMES
from ..model.structure import Model
from ..model.system import System, sketch
from .build import SceneBuilder
from .expectations import (
    ExpectResult,
    check_expectations,
    closed_form_error,
    closed_form_positions,
    expect_requirements,
)
from .keys import (
    EXPECT_KEYS,
    OUTPUT_FORMATS,
    OUTPUT_PLOTS,
    OUTPUT_QUANTITIES,
    SIMULATE_DEFAULTS,
    TOP_LEVEL_TABLES,
)
from .overrides import _apply_overrides, _override_origin, apply_overrides, data_copy, parse_override
from .validate import moderate_level, nesting_levels

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

# Names a parameter or a reduced coordinate may not take (they mean something in formulas).
RESERVED_NAMES = RESERVED_NAMES


@dataclass
class Scene:
    """A loaded scene (``C.load_scene``): the ``system`` to simulate, its ``settings`` (the
    ``[simulate]`` table with defaults), ``outputs``, the ``[reduced]`` coordinates and the
    ``[expect]`` checks; ``run()`` simulates with the scene's own settings. In Jupyter a Scene
    shows as a table of what it holds and how it runs."""

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
    #: the [simulate] keys the file gave itself (``settings`` fills the rest with defaults)
    given_settings: frozenset | None = None  # None: not known (a Scene built in Python)
    #: (the System as loaded, its Structure, its plain numbers): built while loading
    structure: tuple | None = dataclasses.field(default=None, repr=False, compare=False)

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, {self.system!r})"

    def _repr_html_(self) -> str:
        """Jupyter: the system's table, then how the scene runs and what it checks."""
        from ..notebook import table

        s = self.settings
        rows = [("file", str(self.path) if self.path else "(built in Python)")]
        if self.description:
            rows.append(("description", self.description))
        rows += self.system.summary()
        rows.append(("simulate", ", ".join(f"{k} = {v}" for k, v in s.items() if v is not None)))
        rows.append(("outputs", ", ".join(self.outputs.get("quantities", ()))))
        if self.reduced:
            rows.append(("reduced coordinates", ", ".join(self.reduced.get("coordinates", ()))))
        if self.expect:
            rows.append(("expect", ", ".join(self.expect)))
        return table(repr(self), rows)

    def loaded_model(self) -> Model | None:
        """The Model of ``system`` from the Structure built while loading the scene (None for
        a scene built otherwise, or whose ``system`` was replaced since): ``run(model=...)``
        then builds nothing and skips the structure's fingerprint (0.25 s at 10,000
        particles). For a caller that has not changed the system in place since loading, as
        ``constrained run``: such changes are not seen in the loaded Structure."""
        if self.structure is None or self.structure[0] is not self.system:
            return None
        return Model(self.system, structure=self.structure[1], numbers=self.structure[2])

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
        from ..run.options import from_scene
        from ..run.simulate import simulate

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

    def _repr_html_(self) -> str:
        """Jupyter: the [expect] checks, the trajectory's summary and the viewer with the
        scene's constraints drawn."""
        from .. import notebook

        checks = [("expect", f"{len(self.expectations) - len(self.failed)} of {len(self.expectations)} "
                             "checks pass")] + [("  ", r.line) for r in self.expectations]
        rows = checks + self.trajectory.summary()
        return (notebook.table(repr(self), rows)
                + notebook.view("viewer", self.trajectory, system=self.scene.system, title=self.scene.name))

    def __repr__(self) -> str:
        n, bad = len(self.expectations), len(self.failed)
        return f"RunResult({self.scene.name!r}, {len(self.trajectory.t)} samples, expect {n - bad}/{n} pass)"


# --- public entry points ---------------------------------------------------------------------


def load_scene(path: str | Path, overrides: Iterable[str] | None = None, *, equations: bool = True) -> Scene:
    """Read the TOML scene at ``path``, apply ``--set`` style ``overrides``, validate, build.
    ``equations=False``: the scene checked and its System built, but not its equations of motion
    (no Structure, its formulas not differentiated, no start checks): what drawing it needs
    (``view``, ``plot``), at a fraction of a large scene's cost; such a scene is not kept."""
    with collector_paused():  # (constrained.bulk: a third of a 10,000-particle scene's reading)
        return _load_scene(path, overrides, equations)


def _load_scene(path: str | Path, overrides: Iterable[str] | None, equations: bool = True) -> Scene:
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
    if equations and plain is None and overrides and all(_sets_a_parameter(text) for text in overrides):
        try:  # read (and keep) the file's own scene: the overrides are values on it
            load_scene(path)
        except SceneError:
            pass  # (the file's own values may be the invalid ones): read it with the overrides
        with _LOADED_LOCK:
            plain = _LOADED.get((*digest, ()))
    values = _parameter_values(overrides, plain, file) if equations else None
    if values is not None:  # only new parameter values for a scene read before
        return _with_parameter_values(plain, values, file)
    raw, kept, moderate = _parsed(data, digest, file)
    if overrides:  # (their values: checked by the scene's own walk)
        (raw, set_paths), moderate = _apply_overrides(raw, overrides, file), False
    else:  # the kept parse is copied; a big one is not kept, and is this call's own
        raw, set_paths = (data_copy(raw) if kept else raw), []
    if not equations:  # (a full scene kept serves too; this one is not kept)
        return _built(raw, path, file, set_paths, equations=False, moderate=moderate)
    key = (*digest, tuple(overrides))
    scene = _built(raw, path, file, set_paths, moderate=moderate)
    if scene.system.n_particles > KEPT_PARTICLES:  # not kept: the caller's own, no copy
        return scene
    with _LOADED_LOCK:
        if overrides and key not in _SEEN:  # kept from its second reading: new numbers each
            _SEEN[key] = None               # call (a loop over --set values) copy nothing
            while len(_SEEN) > SCENES_KEPT:
                _SEEN.popitem(last=False)
            return scene
        _LOADED[key] = scene
        while len(_LOADED) > SCENES_KEPT:
            _LOADED.popitem(last=False)
    return _copied(scene)


#: What a TOML nested beyond what the reader (recursive) takes is told.
NESTED_TOO_DEEPLY = "its arrays or tables are nested too deeply"
#: The deepest nesting of tables and arrays a scene may have (a scene needs 4: the copies and
#: checks of its data recurse once per level).
MAX_NESTING = 64


def refuse_deep_nesting(raw: dict, file: str) -> bool:
    """SceneError when tables and arrays nest deeper than MAX_NESTING (counted without recursion:
    TOML's dotted table names, [a.a.a...], nest without limit). Returns whether every number in
    ``raw`` is finite and moderate (the scene's ``finite_everywhere``, answered by this walk)."""
    return _refused_or_moderate([nesting_and_numbers(raw)], file)


def nesting_and_numbers(raw: dict) -> tuple[bool, bool]:
    """``(too_deep, moderate)``: whether tables and arrays in ``raw`` nest deeper than
    MAX_NESTING, and (when not) whether every number in it is finite and moderate."""
    moderate = True
    for depth, (level, types) in enumerate(nesting_levels(raw), 1):
        if depth > MAX_NESTING and any(isinstance(v, dict | list) for v in level):
            return True, False
        moderate = moderate and moderate_level(level, types)
    return False, moderate


def _refused_or_moderate(answers: list, file: str) -> bool:
    """``refuse_deep_nesting`` of a document from the ``nesting_and_numbers`` of its parts."""
    if any(too_deep for too_deep, _ in answers):
        raise SceneError(f"{NESTED_TOO_DEEPLY} (more than {MAX_NESTING} levels)", file=file)
    return all(moderate for _, moderate in answers)


#: Scenes validated in this process, by file content (its SHA-256) and overrides: reading one
#: again (a sweep, a fresh call) skips the validation and formula checks (about 1 ms). Each
#: caller gets its own copies of the mutable parts.
SCENES_KEPT = 32
#: Scenes of more particles are not kept: copying one costs a good part of validating it.
KEPT_PARTICLES = 2000
_LOADED: collections.OrderedDict = collections.OrderedDict()
_LOADED_LOCK = threading.Lock()
#: Keys (file content, overrides) read once: a scene read with overrides is kept when read again.
_SEEN: collections.OrderedDict = collections.OrderedDict()


def _parsed(data: bytes, digest: tuple, file: str) -> tuple[dict, bool, bool]:
    """The TOML of a scene file, parsed once per content, whether it is kept (then callers
    copy it) and whether its numbers are all finite and moderate. A scene of more than
    KEPT_PARTICLES particles is not kept: copying it costs a good part of parsing it."""
    with _LOADED_LOCK:
        raw, moderate = _PARSED.get(digest, (None, False))
    if raw is not None:
        return raw, True, moderate
    try:
        # (each piece of a large scene walked as it is read: tomlparse.loads_walked)
        raw, answers = tomlparse.loads_walked(data.decode("utf-8"), nesting_and_numbers)
    except UnicodeDecodeError as exc:
        raise SceneError(f"not UTF-8 text (byte {exc.start})", file=file) from None
    except tomlparse.TOMLDecodeError as exc:
        raise SceneError(f"not valid TOML: {exc}", file=file) from None
    except RecursionError:  # (Python's TOML reader recurses once per level)
        raise SceneError(f"not valid TOML: {NESTED_TOO_DEEPLY}", file=file) from None
    moderate = _refused_or_moderate(answers, file)
    particles = raw.get("particles")
    if isinstance(particles, list) and len(particles) > KEPT_PARTICLES:
        return raw, False, moderate
    with _LOADED_LOCK:
        _PARSED[digest] = raw, moderate
        while len(_PARSED) > SCENES_KEPT:
            _PARSED.popitem(last=False)
    return raw, True, moderate


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
    raw = data_copy(scene.raw)
    for table, entries in (raw_update or {}).items():
        raw.setdefault(table, {}).update(entries)
    copied = scene.system.copy() if system is None else system
    built = scene.structure
    structure = (copied, *built[1:]) if system is None and built and built[0] is scene.system else None
    return dataclasses.replace(
        scene, system=copied, structure=structure,
        settings=data_copy(scene.settings),
        outputs=data_copy(scene.outputs), reduced=data_copy(scene.reduced),
        raw=raw, expect=data_copy(scene.expect),
        expectations=None if scene.expectations is None else list(scene.expectations),
        units=None if scene.units is None else dict(scene.units))




def _built(raw: Mapping, path: Path, file: str, set_paths: list, *, equations: bool = True,
           moderate: bool = False) -> Scene:
    """``build_scene``, a refusal of a value given by --set naming that override."""
    try:
        return build_scene(raw, path=path, equations=equations, numbers_checked=moderate)
    except SceneError as exc:
        origin = _override_origin(exc.key, set_paths)
        if origin is None:
            raise
        raise SceneError(f"{exc.reason} (value given by --set {origin})", file=file, key=exc.key) from None


def build_scene(raw: Mapping, path: str | Path | None = None, *, equations: bool = True,
                numbers_checked: bool = False) -> Scene:
    """Validate a parsed scene dictionary (TOML layout) and build the Scene (``equations``: as
    ``load_scene``'s). ``numbers_checked``: every number in ``raw`` is known to be finite and
    moderate (``refuse_deep_nesting``'s answer), so the builder need not walk them again."""
    builder = SceneBuilder(raw, None if path is None else Path(path))
    builder.equations, builder.numbers_checked = equations, numbers_checked
    return Scene(**builder.build())


def check_regular_start(scene: Scene, *, loaded: bool = False) -> None:
    """Refuse (SceneError) a scene whose constraints or effects are undefined at its particles'
    initial positions (a rod whose particle sits on its anchor, 1/r at r = 0). ``load_scene``
    checks this itself, except for scenes with a [reduced] section, whose particle positions
    may be placeholders for the mapped start of ``crosscheck``: verbs that start from the
    particle positions call this, with ``loaded=True`` for a scene just returned by
    ``load_scene`` (then only a [reduced] scene is checked: twice costs seconds at 10⁴ particles)."""
    if loaded and "reduced" not in scene.raw:
        return
    builder = SceneBuilder(scene.raw, scene.path)
    builder.names = [p.name for p in scene.system.particles]
    builder.regular_start(scene.system, scene.settings["t_start"])
