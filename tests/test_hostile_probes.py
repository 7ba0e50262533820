"""The hostile audit's probes (issue 27), each a behaviour that must hold: full disks and files
too large while the figures are drawn, malformed and extreme scenes, names that are keywords,
misused arguments, placeholders in messages, impacts on moving surfaces. Ctrl-C has its own
file (test_ctrl_c.py), the compile cache its own (test_compile_cache.py), scene fuzzing too
(test_scene_fuzz.py)."""

from __future__ import annotations

import errno
import os
import resource
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from conftest import pendulum_toml
from interrupting import env as _env

import constrained as C
from constrained.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"


def _listing(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())} if folder.exists() else {}


def _strays(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.endswith(".part") or ".staging-" in p.name
            or ".old-" in p.name or (p.name.startswith(".") and p.suffix in (".gif", ".png", ".mp4"))]


def _tagged(tag: str) -> list[int]:
    """Processes running with ``CONSTRAINED_TEST_TAG=tag`` in their environment."""
    time.sleep(0.3)
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if f"CONSTRAINED_TEST_TAG={tag}".encode() in (entry / "environ").read_bytes():
                    found.append(int(entry.name))
            except OSError:
                pass
    return found


# --- items 2 and 3: a requested output that cannot be written is a failed run ----------------------
FIGURES = pendulum_toml(0.5) + '\n[outputs]\nplots = ["trajectory", "energy"]\nformats = ["npz", "csv"]\n'


def test_a_full_disk_while_the_figures_are_drawn_fails_the_run_and_writes_nothing(tmp_path, capsys,
                                                                                  monkeypatch):
    scene = tmp_path / "scene.toml"
    scene.write_text(FIGURES)
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out), "--quiet"]) == 0
    before = _listing(out)
    capsys.readouterr()

    import constrained.output.plot as plot

    def disk_full(traj, kinds, out_dir, **kwargs):  # (the helper forks after this: it draws with it)
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(out_dir) / "energy.png"))

    monkeypatch.setattr(plot, "save_figures", disk_full)
    code = main(["run", str(scene), "--out", str(out), "--quiet", "--set", "simulate.t_end=0.3"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"cannot write {out / 'energy.png'}: No space left on device" in err, err
    assert "nothing was written" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert _listing(out) == before  # the earlier set, whole: not the new npz beside old figures
    assert not _strays(tmp_path)


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc to find processes")
def test_a_file_too_large_in_the_figure_helper_is_one_line_exit_2_and_no_process_is_left(tmp_path):
    """RLIMIT_FSIZE lets the data files (≈20-50 KB) through and stops the animation (≈600 KB)
    in the figure helper: exit 2, one line naming the file, no traceback from the helper, no
    helper or drawing worker left running, nothing of the set written."""
    scene = SCENES / "double_pendulum.toml"
    out = tmp_path / "out"
    tag = uuid.uuid4().hex

    def limit_file_size():
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))

    args = ["run", str(scene), "--out", str(out), "--quiet", "--set", "simulate.t_end=2", "--set",
            'outputs.plots=["trajectory", "energy", "animation"]']
    proc = subprocess.run([sys.executable, "-m", "constrained.cli", *args],
                          env={**_env(), "CONSTRAINED_TEST_TAG": tag}, cwd=tmp_path,
                          preexec_fn=limit_file_size, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "animation.gif: File too large" in proc.stderr and "nothing was written" in proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not out.exists() and not _strays(tmp_path)
    assert _tagged(tag) == []


def test_a_figure_that_cannot_be_drawn_fails_the_run(tmp_path, capsys, monkeypatch):
    scene = tmp_path / "scene.toml"
    scene.write_text(FIGURES)
    import constrained.output.plot as plot

    def broken(*args, **kwargs):
        raise ValueError("a drawing bug")

    monkeypatch.setattr(plot, "save_figures", broken)
    code = main(["run", str(scene), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "a drawing bug" in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


def test_the_helper_gone_before_it_answered_means_drawing_here(tmp_path, capsys, monkeypatch):
    """A helper that dies (killed, out of memory) only costs time: the figures are drawn in the
    run's own process and the run succeeds."""
    scene = tmp_path / "scene.toml"
    scene.write_text(FIGURES)
    import constrained.output.figure_process as fp

    def die(conn, other_end):
        os._exit(0)

    monkeypatch.setattr(fp, "_serve", die)
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert {"trajectory.png", "energy.png"} <= set(_listing(tmp_path / "out"))


# --- item 7: an event may be called anything ------------------------------------------------------
def test_an_event_named_with_spaces_runs_and_is_recorded_by_its_name(tmp_path, capsys):
    scene = tmp_path / "event.toml"
    # the pendulum crosses x = 0.2 m going out and coming back (amplitude 0.32 m at 1 m/s)
    scene.write_text(pendulum_toml(1.0) + '\n[[events]]\nname = "half way"\nexpr = "x_bob - 0.2"\n')
    assert main(["check", str(scene), "--quiet"]) == 0
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 0, capsys.readouterr().err
    traj = C.Trajectory.load(tmp_path / "out" / "trajectory.npz")
    assert [e.kind for e in traj.events] == ["half way", "half way"]
    for e in traj.events:
        assert e.x[0, 0] == pytest.approx(0.2, abs=1e-9)  # located to round-off on the crossing


# --- item 8: absurd nesting: a message and exit 2, quickly ----------------------------------------
def test_a_toml_nested_100000_deep_is_refused_with_exit_2(tmp_path, capsys):
    scene = tmp_path / "deep.toml"
    scene.write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n")
    for verb in (["check"], ["run", "--out", str(tmp_path / "out")],
                 ["sweep", "--vary", "simulate.t_end=[1, 2]", "--out", str(tmp_path / "sweep")]):
        assert main([verb[0], str(scene), *verb[1:]]) == 2
        err = capsys.readouterr().err
        assert "nested too deeply" in err and str(scene) in err and "Traceback" not in err, err


def _chain(n: int, forward: bool) -> str:
    """A scene whose mass is the end of a chain of n definitions, each using the next."""
    lines = ["[parameters]", "m0 = 1.0", "", "[definitions]"]
    if forward:  # d1 = m0 + 1e-3, d2 = d1 + 1e-3, ... (each uses the one before)
        lines += [f'd{k} = "{"m0" if k == 1 else f"d{k - 1}"} + 1e-3"' for k in range(1, n + 1)]
        top = f"d{n}"
    else:  # d1 = d2 + 1e-3, ..., dn = m0 (each uses the one after: a recursive order would overflow)
        lines += [f'd{k} = "d{k + 1} + 1e-3"' for k in range(1, n)] + [f'd{n} = "m0"']
        top = "d1"
    return "\n".join(lines) + f'\n\n[[particles]]\nname = "p"\nmass = "{top}"\nposition = [0, 0, 0]\n' \
        "\n[simulate]\nt_end = 0.01\n"


@pytest.mark.parametrize("forward", [True, False], ids=["each-uses-the-one-before", "each-uses-the-next"])
def test_a_definitions_chain_1100_deep_is_refused_quickly_and_1000_deep_works(tmp_path, capsys, forward):
    scene = tmp_path / "chain.toml"
    scene.write_text(_chain(1100, forward))
    assert main(["check", str(scene), "--quiet"]) == 2  # (was: a RecursionError after ~20 s)
    err = capsys.readouterr().err
    assert "nest more than 1000 deep" in err and "definitions.d" in err and "Traceback" not in err, err
    scene.write_text(_chain(1000, forward))
    system = C.load_scene(scene).system
    assert system.particles[0].mass == pytest.approx(1.0 + (1000 if forward else 999) * 1e-3, rel=1e-12)


def test_a_cycle_in_the_definitions_is_named():
    s = C.System()
    s.set_parameter("k", 1.0)
    s.define("a", "b + k")
    with pytest.raises(C.InputError, match="cycle: a -> b -> a"):
        s.define("b", "2 * a")


# --- item 9: a damaged saved run is drawn where it can be ------------------------------------------
@pytest.mark.parametrize("damage", ["some", "all", "no samples"])
def test_plot_of_a_file_with_nan_positions(tmp_path, capsys, damage):
    system = C.load_scene(SCENES / "double_pendulum.toml").system
    tr = C.simulate(system, 1.0, t_eval=np.linspace(0, 1, 51))
    if damage == "some":
        tr.x[10:20] = np.nan
    elif damage == "all":
        tr.x[:] = np.nan
    saved = tr.save(tmp_path / "trajectory.npz")
    if damage == "no samples":  # a hand-made or cut file: every per-sample array empty
        with np.load(saved, allow_pickle=False) as z:
            arrays = {k: z[k][:0] if z[k].ndim and len(z[k]) == len(tr.t) else z[k] for k in z.files}
        np.savez(saved, **arrays)
    code = main(["plot", str(saved), "--out", str(tmp_path / "figs")])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    if damage == "some":  # every kind drawn, the ten damaged samples left out and said so
        assert code == 0, err
        assert "10 of 51 samples" in out
        assert {"trajectory.png", "phase.png", "energy.png"} <= set(_listing(tmp_path / "figs"))
    else:
        assert code == 2 and "nothing to draw" in err and str(saved) in err


# --- item 10: parameter names that formulas cannot use --------------------------------------------
@pytest.mark.parametrize("name", ["lambda", "if", "None", "class"])
def test_a_parameter_named_like_a_keyword_is_refused_where_it_is_declared(tmp_path, capsys, name):
    scene = tmp_path / "kw.toml"
    scene.write_text(f"[parameters]\n{name} = 1.0\n" + pendulum_toml(0.1))
    assert main(["check", str(scene)]) == 2
    err = capsys.readouterr().err
    assert f"key parameters.{name}" in err and "keyword" in err and f"'{name}_'" in err, err
    with pytest.raises(C.InputError, match="keyword"):
        C.System().set_parameter(name, 1.0)


def test_e_is_refused_as_a_name_and_says_how_to_name_restitution(tmp_path, capsys):
    scene = tmp_path / "e.toml"
    scene.write_text("[parameters]\ne = 0.5\n" + pendulum_toml(0.1))
    assert main(["check", str(scene)]) == 2
    err = capsys.readouterr().err
    assert "Euler's number" in err and "'e_r'" in err and 'restitution = "e_r"' in err, err


BOUNCE = """
[parameters]
e_r = 0.5
h = 1.0

[[particles]]
name = "ball"
mass = 0.3
position = [0.0, "h", 0.0]

[[constraints]]
name = "floor"
type = "plane"
particles = ["ball"]
normal = [0.0, 1.0, 0.0]
offset = 0.0
unilateral = true
restitution = "e_r"

[[effects]]
type = "gravity"
g = [0.0, -9.81, 0.0]

[simulate]
t_end = 0.6
"""


def test_restitution_is_a_formula_of_the_parameters_and_can_be_swept(tmp_path):
    """A ball dropped from h = 1 m: it meets the floor at u = sqrt(2 g h) and leaves at e u, so
    it rises to e² h; the impact dissipates ½ (1 − e²) m u² = (1 − e²) m g h."""
    from constrained.sweeps.sweep import sweep

    scene = tmp_path / "bounce.toml"
    scene.write_text(BOUNCE)
    g, h, m = 9.81, 1.0, 0.3
    for e in (0.0, 0.5, 0.9):
        traj = C.load_scene(scene).run([f"parameters.e_r={e}", "simulate.t_end=0.5"]).trajectory
        (hit,) = [r for r in traj.events if r.kind == "impact"]
        assert hit.energy_lost == pytest.approx((1 - e**2) * m * g * h, rel=1e-8)
        assert hit.v[0, 1] == pytest.approx(e * np.sqrt(2 * g * h), rel=1e-8)
    result = sweep(scene, ["parameters.e_r=[0.25, 0.75, 1.5]"], out_dir=tmp_path / "sw",
                   scheduler="sequential", progress=False, figure=False)
    rows = {r["parameters.e_r"]: r for r in result.rows}
    t_hit, u = np.sqrt(2 * h / g), np.sqrt(2 * g * h)
    for e in (0.25, 0.75):  # at t_end = 0.6 s, risen from the floor at e u since t_hit
        dt = 0.6 - t_hit
        assert rows[e]["status"] == "ok"
        assert rows[e]["y_ball"] == pytest.approx(e * u * dt - 0.5 * g * dt**2, rel=1e-7)
    assert "restitution must be at most 1" in rows[1.5]["status"] and "'e_r' = 1.5" in rows[1.5]["status"]


# --- item 11: misused arguments, each with the message that helps -----------------------------------
@pytest.mark.parametrize("args, words", [
    (["--limit", "-2"], "--limit must be a whole number >= 0"),
    (["--workers", "0"], "--workers must be a whole number >= 1"),
    (["--chunk-size", "0"], "--chunk-size must be a whole number >= 1"),
])
def test_sweep_refuses_counts_that_make_no_sense(tmp_path, capsys, args, words):
    code = main(["sweep", str(SCENES / "simple_pendulum.toml"), "--vary", "simulate.t_end=[0.1, 0.2]",
                 "--out", str(tmp_path / "sw"), *args])
    err = capsys.readouterr().err
    assert code == 2 and words in err, err
    assert not (tmp_path / "sw").exists()


@pytest.mark.parametrize("first, words", [
    (None, "simulate() takes a System"), ("scene", "pass its .system"), (3.0, "got float"),
])
def test_simulate_of_something_else_than_a_system(first, words):
    thing = C.load_scene(SCENES / "simple_pendulum.toml") if first == "scene" else first
    with pytest.raises(C.InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
        C.simulate(thing, 2.0)
    with pytest.raises(C.InputError, match="simulate_many"):
        C.simulate_many(thing, 2.0, {})


@pytest.mark.parametrize("entry", ["equilibrium", "constraint_report", "degrees_of_freedom", "assemble"])
@pytest.mark.parametrize("first", [None, "scene"])
def test_the_other_entry_points_of_a_system_say_what_to_pass(entry, first):
    """statics and the structural reports took None (or a Scene) to an AttributeError."""
    thing = C.load_scene(SCENES / "simple_pendulum.toml") if first == "scene" else first
    words = "pass its .system" if first == "scene" else f"{entry}() takes a System"
    with pytest.raises(C.InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
        getattr(C, entry)(thing)


@pytest.mark.parametrize("restitution, words", [
    (-0.5, "at least 0.*into the constraint"), (1.5, "at most 1.*create energy"), (True, "a number from 0"),
])
def test_restitution_out_of_range_gets_its_own_reason(restitution, words):
    with pytest.raises(C.InputError, match=words):
        C.Plane(["p"], normal=[0, 1, 0], unilateral=True, restitution=restitution)


def test_gravity_given_a_number_is_refused_at_once_and_no_placeholder_leaks():
    with pytest.raises(C.InputError, match=r"vector of 3 entries .*, e.g. Gravity\(\[0, -9.81, 0\]\)"):
        C.Gravity(9.81)
    with pytest.raises(C.InputError, match="vector of 3 entries"):
        C.Distance("p", point=[0, 0], length=1.0)
    # what only the build can find: its message shows the numbers as written
    s = C.System()
    s.add_particle("p", 1.0, [1.0, 0.0, 0.0])
    s.add(C.Distance("p", point=[0.0, 0.0, 0.0], length=[1.5, 2.5]))
    with pytest.raises(C.InputError) as info:
        C.simulate(s, 1.0)
    assert "⟦" not in str(info.value) and "(1.5, 2.5)" in str(info.value)


@pytest.mark.parametrize("keyword, meant", [
    ("rtool", "rtol"), ("t_evel", "t_eval"), ("paramaters", "parameters"),
    ("max_initial_corection", "max_initial_correction"), ("outptus", "outputs"),
])
def test_a_misspelled_simulate_keyword_gets_a_did_you_mean(keyword, meant):
    system = C.load_scene(SCENES / "simple_pendulum.toml").system
    with pytest.raises(C.InputError, match=f"unknown keyword '{keyword}'; did you mean '{meant}'"):
        C.simulate(system, 0.1, **{keyword: 1})


def test_an_option_of_another_method_is_named_as_such():
    system = C.load_scene(SCENES / "simple_pendulum.toml").system
    with pytest.raises(C.InputError, match="'dopri' does not take the option 'max_step'; ggl, idas take"):
        C.simulate(system, 0.1, method="dopri", max_step=0.1)


def test_an_inconsistent_initial_velocity_is_corrected_with_a_warning():
    """The bob at (0, -1, 0) on a 1 m rod given v = (1, 1, 0): the radial 1 m/s cannot be, and is
    removed (as constrained run reports it); a consistent start warns nothing."""
    system = C.load_scene(SCENES / "simple_pendulum.toml").system
    system.particles[0].position[:] = [0.0, -1.0, 0.0]
    system.particles[0].velocity[:] = [1.0, 1.0, 0.0]
    with pytest.warns(C.InitialStateWarning, match=r"velocities changed by 1 m/s"):
        tr = C.simulate(system, 0.1)
    assert np.allclose(tr.v[0, 0], [1.0, 0.0, 0.0], atol=1e-12)
    system.particles[0].velocity[:] = [1.0, 0.0, 0.0]
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", C.InitialStateWarning)
        C.simulate(system, 0.1)


# --- item 12: an impact on a moving surface loses energy in the surface's frame ---------------------
MOVING_FLOOR = """
[parameters]
w = 2.0
e_r = 0.5

[[particles]]
name = "ball"
mass = 0.3
position = [0.0, 1.0, 0.0]
velocity = [0.0, -1.0, 0.0]

[[constraints]]
name = "lift"
type = "plane"
particles = ["ball"]
normal = [0.0, 1.0, 0.0]
offset = "w*t"
unilateral = true
restitution = "e_r"

[simulate]
t_end = 0.5
"""


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_energy_lost_on_a_rising_floor_is_half_one_minus_e_squared_m_u_squared(tmp_path, e):
    """No gravity: the ball falls at 1 m/s, the floor rises at w = 2 m/s; they meet at
    t = 1/3 s with relative speed u = 3 m/s. After the impact the ball moves at w + e u. In the
    floor's frame the loss is ½ (1 − e²) m u²; in the fixed frame the kinetic energy changes by
    ½ m ((w + e u)² − 1), which the moving floor supplies (positive for e = 1)."""
    scene = tmp_path / "lift.toml"
    scene.write_text(MOVING_FLOOR)
    traj = C.load_scene(scene).run([f"parameters.e_r={e}"]).trajectory
    (hit,) = [r for r in traj.events if r.kind == "impact"]
    m, w, u = 0.3, 2.0, 3.0
    assert hit.t == pytest.approx(1.0 / 3.0, abs=1e-9)
    assert hit.v[0, 1] == pytest.approx(w + e * u, abs=1e-9)
    assert hit.energy_lost == pytest.approx(0.5 * (1 - e**2) * m * u**2, abs=1e-9)
    assert hit.energy_lost >= 0
    change = 0.5 * m * ((w + e * u) ** 2 - 1.0)
    assert hit.extra["kinetic_energy_change"] == pytest.approx(change, abs=1e-9)


# --- item 13: a sweep's memory does not grow with its results ---------------------------------------
def _sweep_peak(tmp_path: Path, n: int) -> int:
    import gc
    import tracemalloc

    from constrained.sweeps.sweep import sweep

    gc.collect()
    tracemalloc.start()
    try:
        result = sweep(SCENES / "simple_spring.toml", [f"parameters.k=lin(1, 10, {n})"],
                       overrides=["simulate.t_end=0.01", "expect={}"], out_dir=tmp_path / f"sweep{n}",
                       scheduler="sequential", progress=False, figure=False, chunk_size=200,
                       summary=[f"max:s{i}=x_m*{i + 1}" for i in range(20)])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert result.complete and result.failed == 0 and result.total == n
    return peak


@pytest.mark.slow
def test_sweep_memory_does_not_grow_with_the_rows_it_has_computed(tmp_path):
    """Each row (46 columns here) goes to its chunk file and is streamed from there into the
    summary: the peak grows by what the design itself holds per variant (its point, run id,
    done flag: ≈ 0.5 KB), not by the rows (≈ 4 KB each when they were kept in memory)."""
    _sweep_peak(tmp_path, 50)  # (imports, the model's build and compile: before measuring)
    small, large = _sweep_peak(tmp_path, 1000), _sweep_peak(tmp_path, 4000)
    per_variant = (large - small) / 3000
    assert per_variant < 1500, f"{per_variant:.0f} bytes per variant"
    import pyarrow.parquet as pq

    table = pq.read_table(tmp_path / "sweep4000" / "summary.parquet")  # the table is whole, in order
    assert table.num_rows == 4000 and table.column("run").to_pylist() == list(range(4000))
    k = np.asarray(table.column("parameters.k").to_pylist())
    assert np.allclose(k, np.linspace(1, 10, 4000))
    s0, s1 = (np.asarray(table.column(c).to_pylist()) for c in ("s0", "s1"))  # max x_m, max 2 x_m
    assert np.all(s0 > 0) and np.allclose(s1, 2 * s0, rtol=1e-15)


# --- also: ggl failed at t = 0 on a loaded machine (test_runtime's Ctrl-C test, sometimes) ----------
def test_ggl_on_a_slow_clock_runs_as_on_a_fast_one(monkeypatch):
    """An output interval that needs more than STEPS_PER_CALL steps fails its SUNDIALS call
    (IDA_TOO_MUCH_WORK). Whether the call was then retried over fewer outputs hinged on how
    long the failed call took; on a loaded machine it was not, the first interval was split
    instead of the failing one, again and again, and the run failed at t = 0 (test_runtime's
    Ctrl-C test of ggl, sometimes). The retry is decided by step counts now: a clock 50x slower
    gives the same motion. (The simple pendulum takes ~120 steps a second at rtol 1e-8: an
    interval of 200 s is beyond one call.)"""
    import time as real_time

    import constrained.solvers.sundials.idas as idas

    system = C.load_scene(SCENES / "simple_pendulum.toml").system
    kw = dict(method="ggl", t_eval=[0.0, 200.0, 400.0], outputs=["energy", "constraint_residual"])
    fast = C.simulate(system, 400.0, **kw)

    class SlowClock:  # every call seems 50 times longer (a machine shared by other jobs)
        def __getattr__(self, name):
            return getattr(real_time, name)

        @staticmethod
        def perf_counter():
            return 50.0 * real_time.perf_counter()

    monkeypatch.setattr(idas, "time", SlowClock())
    slow = C.simulate(system, 400.0, **kw)
    assert slow.info["status"] == "completed" and list(slow.t) == [0.0, 200.0, 400.0]
    assert fast.stats["steps"] / 2 > idas.STEPS_PER_CALL  # (each interval is beyond one call)
    assert np.max(np.abs(slow.x - fast.x)) < 1e-5
    assert np.max(np.abs(slow.energy - slow.energy[0])) < 1e-6 * abs(slow.energy[0])
    assert np.max(slow.constraint_residual) < 1e-10
