"""Property test of the scene loader (issue 18, item 10): generated scenes -- valid ones,
subtly broken ones and TOML garbage -- never give a traceback, an exit status other than
0, 1 or 2, or a partly written output folder. Issue 27 added the second audit's probes as
generators: names formulas cannot use (keywords, e, functions), [definitions] chains and
cycles, restitution as numbers and formulas, events of any name, nesting thousands deep,
misused ``simulate`` keywords, and damaged trajectory files for ``plot`` and ``view`` --
with no placeholder token (⟦k⟧) in any message.

The command line runs in this process (``main(argv)``; much faster than a subprocess):
``check`` on every generated scene, ``run`` (t_end of a few ms) on a smaller share.

Examples: 2,000 by default (CI, derandomized: the same examples every time), split over the
tests below. A longer, randomized exploration:

    CONSTRAINED_HYPOTHESIS_EXAMPLES=20000 python -m pytest -q tests/test_scene_fuzz.py
"""

from __future__ import annotations

import contextlib
import copy
import functools
import io
import json
import keyword
import math
import os
import shutil
import signal
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import constrained.cli.main as cli_module
from constrained.cli.main import main

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow  # thousands of generated scenes: CI's run (--all), not the developer's loop

TOTAL = int(os.environ.get("CONSTRAINED_HYPOTHESIS_EXAMPLES", "2000"))
#: A generated run still going after this many seconds is interrupted (as by Ctrl-C).
RUN_SECONDS = 3.0
# Shares of the examples: check of mutated scenes, check of garbage text, run of scenes.
SHARES = {"check": 0.46, "garbage": 0.30, "run": 0.07, "hostile": 0.10, "api": 0.05, "npz": 0.02}


def examples(name: str) -> settings:
    return settings(max_examples=max(1, round(TOTAL * SHARES[name])), deadline=None, database=None,
                    derandomize="CONSTRAINED_HYPOTHESIS_EXAMPLES" not in os.environ,
                    suppress_health_check=list(HealthCheck), print_blob=True)


@pytest.fixture(scope="module", autouse=True)
def fast_loop():
    """Generated scenes may ask for compiled = true: keep the C compiler out of the loop. And
    build the argument parser once (argparse's gettext look-ups cost ~20 ms per build)."""
    old = os.environ.get("CONSTRAINED_COMPILE")
    os.environ["CONSTRAINED_COMPILE"] = "0"
    build = cli_module.build_parser
    cli_module.build_parser = functools.cache(build)
    yield
    cli_module.build_parser = build
    if old is None:
        os.environ.pop("CONSTRAINED_COMPILE")
    else:
        os.environ["CONSTRAINED_COMPILE"] = old


# --- a small TOML writer (values: str, int, float, bool, lists, tables) --------------------------


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        # (TOML has no surrogate-pair escapes; DEL, which JSON leaves raw, must be escaped)
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def to_toml(scene: dict) -> str:
    """Plain top-level keys first, then [tables] and [[arrays of tables]]."""
    def entry(kv) -> str:
        return f"{json.dumps(str(kv[0]))} = {toml_value(kv[1])}"

    plain, tables = [], []
    for name, value in scene.items():
        head = json.dumps(str(name))
        if isinstance(value, list) and value and all(isinstance(x, dict) for x in value):
            for item in value:
                tables += [f"[[{head}]]", *map(entry, item.items()), ""]
        elif isinstance(value, dict):
            tables += [f"[{head}]", *map(entry, value.items()), ""]
        else:
            plain.append(f"{head} = {toml_value(value)}")
    return "\n".join([*plain, "", *tables]) + "\n"


# --- strategies -------------------------------------------------------------------------------

coord = st.floats(-3, 3, allow_nan=False).map(lambda x: round(x, 3))
vec3 = st.lists(coord, min_size=3, max_size=3)
METHODS = ["projection", "ggl", "rattle", "dopri", "idas", "baumgarte", "pantelides", "reduced", "nonsense"]
TOKENS = ["x_p1", "y_p1", "z_p2", "vx_p1", "t", "k", "r", "x", "1", "2.5", "9", "0", "1e308", "1e-320",
          "**", "*", "+", "-", "/", "(", ")", "sin(", "sqrt(", "exp(", "log(", "atan2(", ",", "foo",
          "__import__", ".", " ", "^", "[", "]", "'", "lambda", "==", "if", "pi", "e", "abs(", "max("]
formula = st.one_of(
    st.lists(st.sampled_from(TOKENS), min_size=1, max_size=25).map("".join),
    st.builds(lambda n, s: s * n + "1", st.integers(1, 3000), st.sampled_from(["-", "+", "(", "sin("])),
    st.builds(lambda n: "**".join(["9"] * n), st.integers(2, 6)),
    st.text(max_size=40),
)
weird = st.one_of(
    st.sampled_from([0, 0.0, -0.0, -1, 1, 2**63 - 1, -(2**63), 1e308, -1e308, 5e-324, 1e100, 1e101,
                     float("inf"), float("-inf"), float("nan"), True, False, "", " ", "p1", "p9",
                     [], [0], [0, 0], [0, 0, 0], [0, 0, 0, 0], [[0, 0, 0]], {}, {"a": 1},
                     ["p1", "p1"], ["p1", "p2"], "distance", "lin(0, 1, 3)"]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(),
    formula,
    st.lists(st.one_of(coord, formula), min_size=3, max_size=3),
)


@st.composite
def valid_scene(draw) -> dict:
    """A scene that should load: particles on their constraints, effects, a short run."""
    n = draw(st.integers(1, 3))
    names = [f"p{i + 1}" for i in range(n)]
    pos = {p: draw(vec3) for p in names}
    particles = []
    for p in names:
        item = {"name": p, "mass": draw(st.floats(0.1, 10).map(lambda m: round(m, 3))), "position": pos[p]}
        if draw(st.booleans()):
            item["velocity"] = draw(vec3)
        particles.append(item)
    constraints = []
    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["distance", "pair", "plane", "pin", "surface", "custom"]))
        a = draw(st.sampled_from(names))
        xa = np.array(pos[a])
        if kind == "distance":
            anchor = draw(vec3)
            length = float(np.linalg.norm(xa - anchor))
            if draw(st.booleans()):  # a moving anchor: formulas of t, equal to the point at t = 0
                anchor = [f"{c!r} + 0.1*sin(3*t)" if i == 0 else c for i, c in enumerate(anchor)]
            constraints.append({"type": "distance", "a": a, "point": anchor, "length": length})
        elif kind == "pair" and n > 1:
            b = draw(st.sampled_from([q for q in names if q != a]))
            constraints.append({"type": "distance", "a": a, "b": b,
                                "length": float(np.linalg.norm(xa - np.array(pos[b])))})
        elif kind == "plane":
            normal = draw(st.sampled_from([[0, 0, 1], [1, 0, 0], [1, 1, 0]]))
            constraints.append({"type": "plane", "particles": [a], "normal": normal,
                                "offset": float(np.dot(normal, xa))})
        elif kind == "pin":
            constraints.append({"type": "pin", "a": a, "point": pos[a]})
        elif kind == "surface":
            constraints.append({"type": "surface", "particles": [a],
                                "expr": f"x**2 + y**2 + z**2 - {float(xa @ xa)!r}"})
        else:
            constraints.append({"type": "custom", "expr": f"z_{a} - {xa[2]!r}"})
    effects = []
    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["gravity", "spring", "damping", "potential", "force", "central"]))
        a = draw(st.sampled_from(names))
        if kind == "gravity":
            effects.append({"type": "gravity", "g": [0.0, -9.81, 0.0]})
        elif kind == "spring":
            effects.append({"type": "spring", "a": a, "point": draw(vec3), "k": 2.0, "rest": 0.5})
        elif kind == "damping":
            effects.append({"type": "damping", "coefficient": 0.3})
        elif kind == "potential":
            effects.append({"type": "potential", "expr": f"0.5*k*x_{a}**2"})
        elif kind == "force":
            expr = [f"-0.2*vx_{a}", f"-y_{a}", "0.1*sin(t)"]
            effects.append({"type": "force", "particle": a, "expr": expr})
        else:
            effects.append({"type": "central", "a": a, "point": [5.0, 5.0, 5.0], "expr": "-1/r"})
    simulate = {"t_end": draw(st.sampled_from([0.001, 0.003, 0.01])),
                "method": draw(st.sampled_from(METHODS[:5])), "compiled": False}
    if simulate["method"] == "rattle" or draw(st.booleans()):
        simulate["dt"] = draw(st.sampled_from([1e-4, 5e-4, 1e-3]))
    if draw(st.booleans()):
        simulate[draw(st.sampled_from(["output_dt", "samples"]))] = draw(st.sampled_from([2, 5]))
        if "output_dt" in simulate:
            simulate["output_dt"] = simulate["t_end"] / simulate["output_dt"]
    scene = {
        "scene": {"name": "generated"},
        "parameters": {"k": 1.5},
        "particles": particles,
        "simulate": simulate,
        "outputs": {"quantities": draw(st.lists(st.sampled_from(
                        ["multipliers", "constraint_forces", "energy", "constraint_residual",
                         "velocity_residual"]), unique=True)),
                    "plots": [], "formats": draw(st.sampled_from([["npz"], ["npz", "csv"]]))},
    }
    if constraints:
        scene["constraints"] = constraints
    if effects:
        scene["effects"] = effects
    if draw(st.booleans()):  # checks of the finished run
        scene["expect"] = {"energy_drift": 1.0, "final": {"x_p1": [0.0, 100.0]},
                           "bounds": {"y_p1": [-100.0, 100.0]}}
    if draw(st.booleans()):  # generalized coordinates: a translation of the whole system
        mapping = {p: [f"{pos[p][0]!r} + q", repr(pos[p][1]), repr(pos[p][2])] for p in names}
        scene["reduced"] = {"coordinates": ["q"], "initial": {"q": 0.0}, "rates": {"q": 0.0}, "map": mapping}
    return scene


def paths(value, prefix=()):
    """Every key path into a scene (tables, arrays, leaves)."""
    yield prefix
    if isinstance(value, dict):
        for k, v in value.items():
            yield from paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from paths(v, (*prefix, i))


@st.composite
def mutated_scene(draw) -> dict:
    """A valid scene with one to three small defects: a value replaced by something odd, a key
    removed or an unknown key added."""
    scene = copy.deepcopy(draw(valid_scene()))  # no shared lists: a mutation changes one place
    for _ in range(draw(st.integers(1, 3))):
        where = draw(st.sampled_from([p for p in paths(scene) if p]))
        parent = scene
        for k in where[:-1]:
            parent = parent[k]
        op = draw(st.sampled_from(["replace", "replace", "replace", "delete", "add"]))
        last = where[-1]
        if op == "replace":
            parent[last] = copy.deepcopy(draw(weird))
        elif op == "delete":
            if isinstance(parent, dict):
                del parent[last]
            else:
                parent.pop(last)
        elif isinstance(parent, dict):
            key = draw(st.sampled_from(["extra", "Mass", "lenght", "type", "b", "point"]))
            parent[key] = copy.deepcopy(draw(weird))
    return scene


#: Names a formula cannot use as a parameter (Python's keywords, e, the functions, x, t ...) and
#: names it can.
NAMES = st.one_of(st.sampled_from([*keyword.kwlist, "e", "pi", "t", "x", "r", "vx", "sin", "sqrt", "k",
                                   "e_r", "lambda_", "m1", "g", "x_p1"]),
                  st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,6}", fullmatch=True))
RESTITUTION = st.one_of(st.floats(-1, 2), st.sampled_from(
    ["e_r", "k", "k/2", "e", "k - 2", "0.5*e_r", "nan", "", "lambda", "e_r +", "t"]), weird)
#: Event formulas that do not vanish at a generated start (positions have three decimals).
EVENT_EXPRS = ["x_p1 - 0.12345", "y_p1 + 0.6789", "t - 0.0021", "vx_p1 - 0.4321", "x_p1 +", "foo", ""]


@st.composite
def hostile_scene(draw) -> tuple[dict, int]:
    """A valid scene with the second audit's features: (scene, how deep an array nests in
    [scene] (0: none; written as text, past what a recursive writer takes))."""
    scene = copy.deepcopy(draw(valid_scene()))
    params = scene["parameters"]
    for _ in range(draw(st.integers(0, 3))):
        params[draw(NAMES)] = draw(st.sampled_from([0.5, 1.0, -1.0, 2.0]))
    if draw(st.booleans()):  # a chain of definitions, either order, maybe closed into a cycle
        depth = draw(st.integers(1, 60))
        chain = {f"d{i}": f"d{i + 1} + 1e-3" for i in range(depth)}
        chain[f"d{depth}"] = draw(st.sampled_from(["k", f"d{draw(st.integers(0, depth))}", "k*"]))
        items = list(chain.items())
        if draw(st.booleans()):
            items.reverse()
        scene["definitions"] = dict(items)
        if draw(st.booleans()):
            scene["particles"][0]["mass"] = "d0"
    if draw(st.booleans()):  # a one-sided floor below p1
        y = float(scene["particles"][0]["position"][1])
        floor = {"type": "plane", "particles": ["p1"], "normal": [0.0, 1.0, 0.0], "offset": y - 0.25}
        if draw(st.booleans()):
            floor["unilateral"] = True
        if draw(st.booleans()):
            floor["restitution"] = draw(RESTITUTION)
        if draw(st.booleans()):
            params["e_r"] = draw(st.sampled_from([0.0, 0.5, 1.0, 1.5, -0.5]))
        scene.setdefault("constraints", []).append(floor)
        scene.setdefault("effects", []).append({"type": "gravity", "g": [0.0, -9.81, 0.0]})
    if draw(st.booleans()):  # events of any name
        scene["events"] = [{"name": draw(st.text(max_size=12)), "expr": draw(st.sampled_from(EVENT_EXPRS)),
                            **({"stop": True} if draw(st.booleans()) else {})}
                           for _ in range(draw(st.integers(1, 2)))]
    nesting = draw(st.sampled_from([0, 0, 0, 3, 500, 5000, 100_000]))
    return scene, nesting


def hostile_toml(scene: dict, nesting: int) -> str:
    text = to_toml(scene)
    if nesting:  # an extra table with an array nested `nesting` deep (TOML's reader recurses per level)
        text += f'\n[scratch]\nv = {"[" * nesting}{"]" * nesting}\n'
    return text


def garbage_text() -> st.SearchStrategy[str]:
    lines = ["[scene]", "[[particles]]", "[[constraints]]", "[[effects]]", "[simulate]", "[outputs]",
             "[reduced]", "[expect]", "[parameters]", 'name = "p1"', "mass = 1", "mass = 1e999",
             "position = [0, 0, 0]", 'type = "distance"', 'a = "p1"', "point = [0, 0, 0]", "length = 1",
             "t_end = 0.01", 'expr = "x_p1 +"', "[[particles]", "= 3", 'name = "p1', "x = [1, 2",
             "\x00", "mass = [", '"""', "a.b.c = 1", "[scene.name]", 'g = [0, "9**9**9**9", 0]']
    return st.one_of(
        st.text(max_size=300),
        st.lists(st.sampled_from(lines), max_size=20).map("\n".join),
        st.builds(lambda s, cut: to_toml(s)[:cut], valid_scene(), st.integers(0, 2000)),
        st.binary(max_size=200).map(lambda b: b.decode("latin-1")),
        st.builds(lambda n, key: f"{key} = " + "[" * n + "]" * n, st.integers(1, 200_000),
                  st.sampled_from(["x", "mass"])),
        st.builds(lambda n: "[" + ".".join(["a"] * n) + "]\nx = 1", st.integers(1, 5000)),
    )


# --- the properties ---------------------------------------------------------------------------


def cli(argv) -> tuple[int, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])  # an exception escaping here is a defect
    return code, err.getvalue()


def assert_clean(code, err: str, text: str, interrupted: bool = False) -> None:
    event(f"exit {code}" + (" (interrupted)" if interrupted else ""))  # --hypothesis-show-statistics
    assert code in ((0, 1, 2, 130) if interrupted else (0, 1, 2)), (code, err, text)
    assert "Traceback" not in err, (err, text)
    assert "⟦" not in err, (err, text)  # a plain number's token of the Structure's build
    if code == 2:
        lines = [ln for ln in err.strip().splitlines() if ln.startswith("constrained: error: ")]
        assert len(lines) == 1, (err, text)


class Deadline:
    """Ctrl-C (KeyboardInterrupt) after ``seconds``: a generated run that would take long (huge
    forces, tiny steps) is interrupted, and must then save a consistent partial set too."""

    def __init__(self, seconds: float):
        self.seconds, self.fired = seconds, False

    def fire(self, *args):
        self.fired = True
        raise KeyboardInterrupt

    def __enter__(self) -> Deadline:
        self.old = signal.signal(signal.SIGALRM, self.fire)
        signal.setitimer(signal.ITIMER_REAL, self.seconds)
        return self

    def __exit__(self, *exc):
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, self.old)


class Folder:
    """One scratch folder, emptied after each example (function-scoped fixtures and @given do
    not mix, and creating and removing a folder per example costs more than the example)."""

    root: Path | None = None

    def __enter__(self) -> Path:
        if Folder.root is None or not Folder.root.is_dir():
            Folder.root = Path(tempfile.mkdtemp(prefix="fuzz-"))
        return Folder.root

    def __exit__(self, *exc):
        for p in Folder.root.iterdir():
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            elif p.name != "scene.toml":
                p.unlink()


@pytest.fixture(scope="module", autouse=True)
def scratch():
    yield
    if Folder.root is not None:
        shutil.rmtree(Folder.root, ignore_errors=True)


@examples("check")
@given(st.one_of(mutated_scene(), valid_scene()))
def test_check_never_crashes_on_generated_scenes(scene):
    text = to_toml(scene)
    with Folder() as tmp:
        path = tmp / "scene.toml"
        path.write_text(text)
        code, err = cli(["check", path])
        assert_clean(code, err, text)
        assert sorted(p.name for p in tmp.iterdir()) == ["scene.toml"]  # check writes nothing


@examples("garbage")
@given(garbage_text())
def test_check_never_crashes_on_garbage(text):
    with Folder() as tmp:
        path = tmp / "scene.toml"
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
        code, err = cli(["check", path])
        assert_clean(code, err, text)
        assert code != 0 or "particles" in text


@examples("run")
@given(st.one_of(valid_scene(), mutated_scene()))
def test_run_never_crashes_and_writes_one_whole_set_or_nothing(scene):
    text = to_toml(scene)
    with Folder() as tmp:
        path = tmp / "scene.toml"
        path.write_text(text)
        out = tmp / "out"
        with Deadline(RUN_SECONDS) as deadline:
            code, err = cli(["run", path, "--out", out, "--quiet"])
        assert_clean(code, err, text, deadline.fired)
        strays = [p.name for p in tmp.iterdir() if p.name not in ("scene.toml", "out")]
        assert not strays, (strays, err, text)
        check_output_set(code, out, scene, err, text)


def check_output_set(code: int, out: Path, scene: dict, err: str, text: str) -> None:
    """Bad input writes nothing; a run that had to stop (1) or was interrupted before its
    first sample writes nothing or its trajectory; otherwise one set: the npz, and the csv
    when asked (an interrupted run writes its set too, issue 27; a second interrupt while
    writing keeps what was whole)."""
    if code == 2 or not out.exists():
        assert not out.exists(), (err, text)
        return
    files = sorted(p.name for p in out.iterdir())
    assert "trajectory.npz" in files, (files, err, text)
    expected = {"trajectory.npz", "trajectory.csv"}  # one run's set: nothing else, no temporaries
    assert set(files) <= expected, (files, err, text)
    wants_csv = "csv" in scene_formats(scene)
    if code == 0:
        assert ("trajectory.csv" in files) == wants_csv, (files, text)
    elif code == 1:
        assert files == ["trajectory.npz"], (files, text)
    else:
        assert wants_csv or "trajectory.csv" not in files, (files, text)
    with np.load(out / "trajectory.npz") as data:
        assert data["x"].shape[0] == data["t"].shape[0] > 0


def scene_formats(scene: dict) -> list:
    outputs = scene.get("outputs")
    formats = outputs.get("formats", ["npz"]) if isinstance(outputs, dict) else ["npz"]
    return formats if isinstance(formats, list) else []


@examples("hostile")
@given(hostile_scene(), st.booleans())
def test_the_second_audits_scenes_check_and_run_cleanly(generated, run):
    scene, nesting = generated
    text = hostile_toml(scene, nesting)
    with Folder() as tmp:
        path = tmp / "scene.toml"
        path.write_text(text)
        code, err = cli(["check", path])
        assert_clean(code, err, text)
        if nesting > 900:  # beyond what Python's TOML reader recurses through: refused, said so
            assert code == 2 and "nested too deeply" in err, err
        if code != 0 or not run:
            return
        out = tmp / "out"
        with Deadline(RUN_SECONDS) as deadline:
            code, err = cli(["run", path, "--out", out, "--quiet"])
        assert_clean(code, err, text, deadline.fired)
        check_output_set(code, out, scene, err, text)


#: simulate's keywords, misspelled ones, and ones of some other method.
KEYWORDS = ["rtol", "atol", "dt", "t_eval", "t_start", "outputs", "method", "max_initial_correction",
            "parameters", "events", "model", "compiled", "progress", "max_steps", "singular_tol", "base",
            "max_step", "project_outputs", "rest_speed", "max_events", "rtool", "t_evel", "paramaters",
            "outptus", "max_setps", "metod", "tol", "step", ""]


@functools.cache
def _small_system():
    import constrained as C

    s = C.System(name="pendulum")
    s.add_particle("p1", 1.0, [0.6, -0.8, 0.0], velocity=[0.8, 0.6, 0.0])  # (velocity: not tangent)
    s.set_parameter("k", 1.5)
    s.add(C.Distance("p1", point=[0.0, 0.0, 0.0], length=1.0), C.Gravity([0.0, -9.81, 0.0]))
    return s


@examples("api")
@given(st.sampled_from(["system", "system", "system", None, "scene", 3.0, "p1"]),
       st.one_of(st.sampled_from([0.003, 0.01, 0.0, -1.0, float("nan"), float("inf"), "2", None, True]),
                 st.floats(allow_nan=True)),
       st.dictionaries(st.sampled_from(KEYWORDS), weird, max_size=3))
def test_simulate_answers_misuse_with_its_own_errors(first, t_end, kwargs):
    """``simulate`` with anything as its system, end time and keywords: a Trajectory, or one of
    the package's errors (InputError, SimulationError) with a message -- never an internal
    AttributeError or TypeError, never a placeholder token."""
    import warnings

    import constrained as C

    thing = {"system": _small_system(), "scene": C.load_scene(ROOT / "scenarios" / "simple_pendulum.toml")}
    target = thing.get(first, first) if isinstance(first, str) else first
    with Deadline(RUN_SECONDS) as deadline, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            C.simulate(target, t_end, **kwargs)
        except C.ConstrainedError as exc:
            event(type(exc).__name__)
            assert str(exc) and "⟦" not in str(exc), exc
        except KeyboardInterrupt:  # the deadline, outside the run's watch
            assert deadline.fired


@functools.cache
def _saved_arrays() -> dict:
    import constrained as C

    system = C.load_scene(ROOT / "scenarios" / "double_pendulum.toml").system
    tr = C.simulate(system, 0.2, t_eval=np.linspace(0, 0.2, 21))
    with Folder() as tmp:
        path = tr.save(tmp / "good.npz")
        with np.load(path) as data:
            return {k: data[k] for k in data.files}


DAMAGE = st.sampled_from(["nan", "inf", "huge", "truncate", "reshape", "drop", "empty", "meta", "strings",
                          "none"])


@examples("npz")
@given(st.lists(st.tuples(DAMAGE, st.sampled_from(["t", "x", "v", "energy", "multipliers",
                                                   "constraint_forces", "meta"])), max_size=3),
       st.sampled_from(["plot", "view"]), st.integers(0, 2**32 - 1))
def test_plot_and_view_of_damaged_trajectory_files(damages, verb, seed):
    arrays = {k: np.array(v, copy=True) for k, v in _saved_arrays().items()}
    rng = np.random.default_rng(seed)
    for damage, name in damages:
        if name not in arrays:
            continue
        a = arrays[name]
        if a.ndim == 0 and damage in ("truncate", "reshape", "empty", "strings"):  # (meta: one string)
            a = arrays[name] = a.reshape(1)
        if damage in ("nan", "inf", "huge") and a.dtype.kind == "f" and a.size:
            mask = rng.random(a.shape) < 0.3
            a[mask] = {"nan": np.nan, "inf": np.inf, "huge": 1e300}[damage]
        elif damage == "truncate":
            arrays[name] = a[: len(a) // 2]
        elif damage == "reshape" and a.size:
            arrays[name] = a.reshape(-1)
        elif damage == "drop":
            del arrays[name]
        elif damage == "empty":
            arrays[name] = a[:0]
        elif damage == "meta":
            arrays["meta"] = np.array(rng.choice(["{", "[]", "null", '{"info": 3}', '{"events": {}}']))
        elif damage == "strings":
            arrays[name] = np.array(["a"] * max(1, len(a)))
    with Folder() as tmp:
        path = tmp / "run.npz"
        np.savez(path, **arrays)
        argv = [verb, path, "--out", tmp / ("figs" if verb == "plot" else "page.html"), "--quiet"]
        if verb == "plot":
            kinds = "trajectory,energy" if seed % 2 else "phase,multipliers,constraint_forces"
            argv[4:4] = ["--kinds", kinds]
        code, err = cli(argv)
        assert_clean(code, err, repr(damages))
