"""Ctrl-C always works (issue 27, items 4-6): while a step loop is being compiled (an empty
cache and a slow compiler), in every verb that computes for long (run, a batched sweep, bench,
path, plot's animation), and at the last step of a run. The command exits 130 promptly with one
line that is not called an error, leaves no helper process running, and an interrupted run
keeps its multipliers, constraint forces, energy and residuals and draws its figures."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from interrupting import env as _env
from interrupting import interrupt_when

from constrained.codegen import compiled

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenarios"
needs_cc = pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler on this machine")

#: A C compiler that takes a minute: it says it has started (a file), then waits, then compiles.
SLOW_CC = """#!{python}
import os, sys, time
open({marker!r}, "w").close()
time.sleep(60)
os.execvp("cc", ["cc", *sys.argv[1:]])
"""


def _slow_compiler(tmp_path: Path) -> tuple[dict, Path]:
    """The environment of a command whose every compilation takes a minute (an empty cache),
    and the file that appears once a compilation has started."""
    marker = tmp_path / "compiling"
    cc = tmp_path / "slow-cc"
    cc.write_text(SLOW_CC.format(python=sys.executable, marker=str(marker)))
    cc.chmod(0o755)
    return {"CC": str(cc), "CONSTRAINED_CACHE": str(tmp_path / "cache"), "CONSTRAINED_COMPILE": "1"}, marker


def _interrupt(args, busy, cwd, extra_env, *, settle=0.3, timeout=120.0):
    """``interrupt_when`` with more environment, and a tag every process it starts inherits
    (to find one left running)."""
    tag = uuid.uuid4().hex
    env = {**_env(), **extra_env, "CONSTRAINED_TEST_TAG": tag}
    proc = subprocess.Popen([sys.executable, "-m", "constrained.cli", *args], env=env, cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + timeout
        while not busy():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the command never got busy"
            time.sleep(0.05)
        time.sleep(settle)
        assert proc.poll() is None, "the command ended before it could be interrupted"
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=90)
        return proc.returncode, time.monotonic() - sent, out, err, tag
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _left_running(tag: str) -> list[int]:
    """Processes still running with the tag in their environment (a helper, a compiler)."""
    time.sleep(0.2)
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if f"CONSTRAINED_TEST_TAG={tag}".encode() in (entry / "environ").read_bytes():
                    found.append(int(entry.name))
            except OSError:
                pass
    return found


def _stopped_quietly(code: int, seconds: float, err: str, tag: str, *, limit: float = 10.0) -> None:
    """Exit 130 within ``limit`` seconds; one line on stderr, no traceback, not an error; nothing
    left running."""
    assert code == 130, err
    assert seconds < limit, (seconds, err)
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "interrupted" in lines[0], err
    assert "Traceback" not in err and "error" not in err.lower(), err
    if Path("/proc/self/environ").exists():
        assert _left_running(tag) == [], "processes left running"


# --- item 4: Ctrl-C while a step loop is compiled ---------------------------------------------------
@needs_cc
@pytest.mark.slow
@pytest.mark.parametrize("method", ["dopri", "rattle"])
def test_ctrl_c_while_the_step_loop_compiles_stops_the_run(tmp_path, method):
    """dopri compiles before its time loop, rattle inside it (where Ctrl-C is a request the
    loop honours): either way the compiler is ended at once, not waited for."""
    env, marker = _slow_compiler(tmp_path)
    args = ["run", str(SCENES / "double_pendulum.toml"), "--out", str(tmp_path / "out"),
            "--set", f"simulate.method={method}", "--set", "simulate.t_end=100", "--set", "simulate.dt=1e-3",
            "--set", "simulate.compiled=true", "--set", 'outputs.plots=["energy"]']
    code, seconds, _, err, tag = _interrupt(args, marker.exists, tmp_path, env)
    _stopped_quietly(code, seconds, err, tag)
    assert not list((tmp_path / "cache").glob("*.so"))  # nothing half-built kept


@needs_cc
@pytest.mark.slow
def test_ctrl_c_while_a_batched_sweep_compiles_stops_it(tmp_path):
    env, marker = _slow_compiler(tmp_path)
    scene = tmp_path / "kapitza.toml"  # the sweep scene on dopri (batched), compiled
    text = (SCENES / "kapitza_sweep.toml").read_text()
    text = text.replace('method = "rattle"', 'method = "dopri"').replace("dt = 2e-3\n", "compiled = true\n")
    scene.write_text(text)
    args = ["sweep", str(scene), "--vary", "parameters.a=lin(0.002, 0.02, 8)", "--out", str(tmp_path / "sw"),
            "--scheduler", "sequential", "--quiet"]
    code, seconds, _, err, tag = _interrupt(args, marker.exists, tmp_path, env)
    _stopped_quietly(code, seconds, err, tag)


@needs_cc
@pytest.mark.slow
def test_ctrl_c_while_bench_compiles_stops_the_measurement(tmp_path):
    env, marker = _slow_compiler(tmp_path)
    args = ["bench", str(SCENES / "double_pendulum.toml"), "--out", str(tmp_path / "bench"),
            "--set", "simulate.t_end=0.5", "--set", "simulate.compiled=true", "--methods", "rattle,dopri",
            "--tolerances", "1e-6", "--repeats", "1", "--quiet"]
    code, seconds, _, err, tag = _interrupt(args, marker.exists, tmp_path, env)
    _stopped_quietly(code, seconds, err, tag)
    assert not (tmp_path / "bench").exists()


# --- Ctrl-C in the other long verbs ----------------------------------------------------------------
@pytest.mark.slow
def test_ctrl_c_during_the_path_search_stops_it_and_keeps_the_last_iterate(tmp_path):
    out = tmp_path / "path"
    args = ["path", str(SCENES / "double_pendulum.toml"), "--to", "p1=[0,-1,0]; p2=[0,-2,0]", "--time", "1",
            "--nodes", "1500", "--max-iter", "3000", "--out", str(out)]
    # busy once IPOPT iterates: the path's setup prints nothing, so wait on the CPU time spent
    started = time.monotonic()
    code, seconds, _, err, tag = _interrupt(args, lambda: time.monotonic() - started > 6.0, tmp_path, {},
                                            settle=0.0)
    _stopped_quietly(code, seconds, err, tag, limit=15.0)


@pytest.mark.slow
def test_ctrl_c_while_plot_draws_the_animation_stops_it(tmp_path):
    """150 particles wandering for 2,000 samples: each frame of the GIF draws 150 trails, so the
    animation takes many seconds; Ctrl-C in the middle of it ends the command at once."""
    from constrained.run.trajectory import Trajectory

    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 20.0, 2000)
    x = np.cumsum(rng.normal(0.0, 0.01, (len(t), 150, 3)), axis=0)
    saved = Trajectory(t, x, np.gradient(x, t, axis=0)).save(tmp_path / "trajectory.npz")
    out = tmp_path / "figures"
    args = ["plot", str(saved), "--kinds", "animation", "--out", str(out)]
    drawing = lambda: bool(list(tmp_path.glob(".figures.staging-*")))  # noqa: E731 (the set is open)
    code, seconds, _, err, tag = _interrupt(args, drawing, tmp_path, {}, settle=2.0)
    _stopped_quietly(code, seconds, err, tag)
    assert not out.exists() or not any(out.iterdir())  # no GIF, no temporary


# --- item 5: one line, no traceback from the figure helper; item 6: the partial run is whole -------
def _interrupt_after_start(args, cwd, extra_env=None):
    """Interrupt once the run says its time loop runs (stdout line)."""
    tag = uuid.uuid4().hex
    env = {**_env(), **(extra_env or {}), "CONSTRAINED_TEST_TAG": tag}
    proc = subprocess.Popen([sys.executable, "-m", "constrained.cli", *args], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 90
        line = ""
        while "Ctrl-C stops" not in line and time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line, proc.communicate()
        time.sleep(0.5)
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=90)
        return proc.returncode, time.monotonic() - sent, err, tag
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow
@pytest.mark.parametrize("method", ["dopri", "projection"])
def test_an_interrupted_run_keeps_every_quantity_and_draws_its_figures(tmp_path, method):
    out = tmp_path / "out"
    args = ["run", str(SCENES / "double_pendulum.toml"), "--out", str(out), "--set", "simulate.t_end=1e4",
            "--set", f"simulate.method={method}",
            "--set", 'outputs.plots=["trajectory", "energy", "constraint_residual", "multipliers"]',
            "--set", 'outputs.formats=["npz", "csv"]', "--set", 'outputs.quantities=["multipliers", '
            '"constraint_forces", "energy", "constraint_residual", "velocity_residual"]']
    code, seconds, err, tag = _interrupt_after_start(args, tmp_path)
    _stopped_quietly(code, seconds, err, tag, limit=30.0)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    with np.load(out / "trajectory.npz") as data:
        arrays = {k: data[k] for k in data.files}
        info = json.loads(str(data["meta"]))["info"]
    assert info["status"] == "interrupted" and 0 < info["t_end_reached"] < 1e4
    n = len(arrays["t"])
    assert n > 10
    for name in ("multipliers", "constraint_forces", "energy", "constraint_residual", "velocity_residual"):
        assert name in arrays and len(arrays[name]) == n and np.all(np.isfinite(arrays[name])), name
    # the physics of what was kept: energy conserved, constraints held, forces = Jᵀλ along the rods
    assert np.max(np.abs(arrays["energy"] - arrays["energy"][0])) < 1e-5
    assert np.max(arrays["constraint_residual"]) < 1e-8
    x, F = arrays["x"], arrays["constraint_forces"]
    rod2 = x[:, 1] - x[:, 0]  # the force on p2 is along the second rod
    assert np.max(np.abs(np.cross(F[:, 1], rod2)[:, 2])) < 1e-6 * max(1.0, np.max(np.abs(F)))
    for figure in ("trajectory.png", "energy.png", "constraint_residual.png", "multipliers.png",
                   "trajectory.csv"):
        assert (out / figure).stat().st_size > 0, figure
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_ctrl_c_as_the_figures_are_finished_names_every_file_it_keeps(tmp_path, monkeypatch, capsys):
    """Ctrl-C reaches the run just as the helper has drawn the figures (whole, in the set) but
    before its answer is read: the folder keeps them, and the one line names every file in it
    (it named the npz and the csv only, while the figures were there too)."""
    from constrained.cli.main import main
    from constrained.output import figure_process

    real_wait = figure_process.FigureProcess.wait

    def drawn_then_ctrl_c(self, progress=None):
        real_wait(self, progress)
        raise KeyboardInterrupt

    monkeypatch.setattr(figure_process.FigureProcess, "wait", drawn_then_ctrl_c)
    out = tmp_path / "out"
    code = main(["run", str(SCENES / "simple_pendulum.toml"), "--out", str(out),
                 "--set", "simulate.t_end=0.5", "--set", 'outputs.plots=["trajectory", "energy"]',
                 "--set", 'outputs.formats=["npz", "csv"]'])
    err = capsys.readouterr().err
    assert code == 130 and "Traceback" not in err and "error" not in err, err
    kept = sorted(p.name for p in out.iterdir())
    assert {"trajectory.npz", "trajectory.csv", "trajectory.png", "energy.png"} <= set(kept)
    named = err.split("written: ")[1].strip().split(", ")
    assert sorted(Path(p).name for p in named) == kept, err


def test_a_second_ctrl_c_while_the_quantities_are_computed_keeps_the_run_and_its_other_files(
        tmp_path, monkeypatch, capsys):
    """Two Ctrl-C in quick succession: the first stops the run, the second arrives while its
    multipliers and forces are computed, so the run keeps t, x, v only. The figures of the
    quantities it does not have are left out; the rest of the set is written, exit 130 (it was
    exit 2, "this trajectory has no multipliers", and nothing written)."""
    from constrained.cli import run as cli_run
    from constrained.cli.main import main
    from constrained.run import simulate as run_simulate

    real_progress, real_trajectory_from = cli_run._progress, run_simulate.trajectory_from
    pressed = []

    class FirstCtrlC(real_progress):
        def __call__(self, t):
            super().__call__(t)
            if t >= 0.3 and not pressed:
                pressed.append(t)
                os.kill(os.getpid(), signal.SIGINT)

    def second_ctrl_c(*args, **kwargs):
        if len(pressed) == 1 and args[4]:  # the first call, asked for derived quantities
            pressed.append("again")
            os.kill(os.getpid(), signal.SIGINT)
        return real_trajectory_from(*args, **kwargs)

    monkeypatch.setattr(cli_run, "_progress", FirstCtrlC)
    monkeypatch.setattr(run_simulate, "trajectory_from", second_ctrl_c)
    out = tmp_path / "out"
    code = main(["run", str(SCENES / "double_pendulum.toml"), "--out", str(out), "--set", "simulate.t_end=50",
                 "--set", 'outputs.plots=["trajectory", "multipliers", "energy", "phase"]',
                 "--set", 'outputs.formats=["npz", "csv"]'])
    err = capsys.readouterr().err
    assert pressed == [pressed[0], "again"]
    assert code == 130 and "Traceback" not in err and "error" not in err, err
    assert "were not computed" in err and len(err.strip().splitlines()) == 1, err
    kept = sorted(p.name for p in out.iterdir())
    assert kept == ["phase.png", "trajectory.csv", "trajectory.npz", "trajectory.png"], kept
    with np.load(out / "trajectory.npz") as data:
        assert "multipliers" not in data.files and 0.3 <= data["t"][-1] < 50
        # what was kept is the motion: both rods held to round-off
        x = data["x"]
        assert np.allclose(np.linalg.norm(x[:, 0], axis=1), 1.0, atol=1e-9)


def test_ctrl_c_in_the_last_step_is_a_stop_not_a_lost_request(monkeypatch):
    """The request arrives while the run's last step is computed: the run is complete, and it
    is reported as interrupted (the caller stops), not silently dropped."""
    import constrained as C
    from constrained import interrupt

    system = C.load_scene(SCENES / "double_pendulum.toml").system

    def press_at_the_end(t):
        if t >= 0.5:
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(C.RunInterrupted) as info:  # one call of up to t_end: the request comes last
        C.simulate(system, 0.5, method="rattle", dt=1e-3, progress=press_at_the_end)
    kept = info.value.trajectory
    assert kept.t[-1] == pytest.approx(0.5) and kept.info["status"] == "interrupted"
    assert kept.multipliers is not None and kept.energy is not None
    assert not interrupt.requested()


@pytest.mark.parametrize("method", ["idas", "dopri", "rattle"])
def test_ctrl_c_landing_in_python_code_inside_a_call_into_c_keeps_the_run(method):
    """SIGINT inside ``interrupt.external()`` raises KeyboardInterrupt where Python runs (here a
    progress callback; in a run, the glue around an IDAS call): the driver stops there and keeps
    what was reached. It used to stop without marking the request seen, so the run's watch()
    raised it again as a bare KeyboardInterrupt and the CLI kept nothing (a CI failure of
    test_runtime's idas case under load)."""
    import constrained as C
    from constrained import interrupt

    system = C.load_scene(SCENES / "double_pendulum.toml").system
    pressed = []

    def press_inside_a_call(t):
        if not pressed:
            pressed.append(t)
            with interrupt.external():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)  # (the handler raises here at the latest)

    settings = {"dt": 1e-3} if method == "rattle" else {}
    with pytest.raises(C.RunInterrupted) as info:
        C.simulate(system, 1e4, method=method, progress=press_inside_a_call, **settings)
    kept = info.value.trajectory
    assert kept.info["status"] == "interrupted" and len(kept.t) >= 2
    assert 0 < kept.info["t_end_reached"] <= pressed[0] + 1e-12
    assert not interrupt.requested()


def test_a_request_nobody_saw_is_raised_when_the_watch_ends():
    from constrained import interrupt

    with pytest.raises(KeyboardInterrupt):
        with interrupt.watch():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            assert interrupt.pending()  # (asking without acting on it)
    with interrupt.watch():  # seen: the block's caller acted on it
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert interrupt.requested()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_the_exit_status_after_a_handled_ctrl_c_is_130_not_death_by_sigint(tmp_path):
    """CPython remembers a KeyboardInterrupt raised inside exec() of a string (SciPy's lazy
    imports do that) and kills the process by SIGINT at exit, even after the command handled
    it: the command must exit with its own status."""
    module = tmp_path / "ctrlc_probe"
    module.mkdir()
    (module / "__main__.py").write_text(
        "import os, signal, sys\n"
        "from constrained.interrupt import forget_handled_keyboard_interrupt\n"
        "try:\n"
        "    exec('import os, signal, time\\nos.kill(os.getpid(), signal.SIGINT)\\ntime.sleep(5)')\n"
        "except KeyboardInterrupt:\n"
        "    forget_handled_keyboard_interrupt()\n"
        "sys.exit(130)\n")
    env = {**_env(), "PYTHONPATH": f"{ROOT}{os.pathsep}{tmp_path}"}
    proc = subprocess.run([sys.executable, "-m", "ctrlc_probe"], env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 130, (proc.returncode, proc.stderr)


def test_a_second_ctrl_c_as_the_command_ends_does_not_kill_it(tmp_path):
    """Ctrl-C pressed twice: the second arrives while the command, having handled the first,
    cleans up and exits. It is the same request: one line, exit status 130 (the process died by
    SIGINT, or printed a KeyboardInterrupt traceback, depending on where the second landed)."""
    module = tmp_path / "twice_probe"
    module.mkdir()
    (module / "__main__.py").write_text(
        "import os, signal, sys\n"
        "from constrained import interrupt\n"
        "from constrained.cli import main as cli\n"
        "from constrained.cli import verbs\n"
        "def stopped(args):\n"
        "    raise KeyboardInterrupt  # the first Ctrl-C, in the verb\n"
        "verbs._check = stopped\n"
        "forget = interrupt.forget_handled_keyboard_interrupt\n"
        "def second():\n"
        "    os.kill(os.getpid(), signal.SIGINT)  # the second, as the command ends\n"
        "    forget()\n"
        "interrupt.forget_handled_keyboard_interrupt = second\n"
        f"sys.argv = ['constrained', 'check', {str(SCENES / 'simple_pendulum.toml')!r}]\n"
        "sys.exit(cli.main())\n")
    env = {**_env(), "PYTHONPATH": f"{ROOT}{os.pathsep}{tmp_path}"}
    proc = subprocess.run([sys.executable, "-m", "twice_probe"], env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 130, (proc.returncode, proc.stderr)
    assert proc.stderr.strip() == "constrained: interrupted (Ctrl-C)", proc.stderr


@pytest.mark.slow
def test_a_sequential_sweep_interrupted_says_one_line(tmp_path):
    out = tmp_path / "sweep"
    args = ["sweep", str(SCENES / "kapitza_sweep.toml"), "--vary", "simulate.t_end=[0.05, 1e4]",
            "--out", str(out), "--scheduler", "sequential", "--quiet", "--per-run"]
    code, seconds, err = interrupt_when(args, lambda: bool(list((out / "chunks").glob("*.parquet"))),
                                        cwd=tmp_path, settle=1.0)
    assert code == 130 and seconds < 10 and "Traceback" not in err
    assert "error" not in err.lower() and len(err.strip().splitlines()) == 1, err


def _press_ctrl_c_once_compiling(marker: Path) -> None:
    """In a thread: Ctrl-C (SIGINT to this process) once the slow compiler has started."""
    import threading

    def press():
        while not marker.exists():
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=press, daemon=True).start()


@needs_cc
def test_a_compilation_inside_a_run_ends_at_once_on_ctrl_c(tmp_path, monkeypatch):
    """Inside a run Ctrl-C is only a request (the loop stops at its next step): the compiler
    must not be waited for — it is ended, the Function comes back uncompiled, and the request
    stays for the loop to see."""

    import casadi as ca

    from constrained import interrupt

    env, marker = _slow_compiler(tmp_path)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    x = ca.SX.sym("x", 2)
    f = ca.Function("ctrlc_compile", [x], [ca.sin(x)])

    _press_ctrl_c_once_compiling(marker)
    started = time.monotonic()
    with interrupt.watch():
        g = compiled.compile_function(f)
        assert interrupt.requested()  # the loop's check: it stops here
    assert time.monotonic() - started < 10.0  # not the compiler's minute
    assert g is f and "interrupted" in compiled.last_error
    assert not list((tmp_path / "cache").glob("*.so"))


@needs_cc
def test_a_step_loop_whose_compilation_ctrl_c_cut_is_compiled_by_the_next_run(tmp_path, monkeypatch):
    """Ctrl-C during the compile of dopri's step loop, where a Ctrl-C is a stop request (inside
    the CLI's watch, as in `constrained bench` or a sweep), stops the run; the uncompiled loop
    that served the stopped run is not kept in the process: the next run compiles (it used to
    run in the virtual machine for the rest of the process)."""

    import constrained as C
    from constrained import interrupt
    from constrained.errors import RunInterrupted

    env, marker = _slow_compiler(tmp_path)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    name = f"bob_{uuid.uuid4().hex[:8]}"  # a structure no other test has built
    system = C.System(name="pendulum")
    system.add_particle(name, 0.3, [0.6, -0.8, 0.0])
    system.add(C.Distance(name, point=[0, 0, 0], length=1.0), C.Gravity([0, -9.81, 0]))

    _press_ctrl_c_once_compiling(marker)
    started = time.monotonic()
    with interrupt.watch(), pytest.raises(RunInterrupted):
        C.simulate(system, 1.0, method="dopri", compiled=True)
    assert time.monotonic() - started < 30.0
    monkeypatch.delenv("CC")  # the machine's own compiler for the next run
    run = C.simulate(system, 1.0, method="dopri", compiled=True)
    assert run.stats["evaluation"] == "compiled"
