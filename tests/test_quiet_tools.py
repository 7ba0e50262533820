"""sweep's install hint and dashboard-free local cluster; bench without raw CasADi warnings (issue 19)."""

from __future__ import annotations

import builtins
import socket
import warnings
from pathlib import Path

import constrained as C

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def test_sweep_without_dask_names_both_install_commands(tmp_path, monkeypatch, capsys):
    from constrained.cli.main import main

    real_import = builtins.__import__

    def no_dask(name, *args, **kwargs):
        if name == "distributed" or name.startswith("distributed."):
            raise ImportError("No module named 'distributed'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_dask)
    code = main(["sweep", str(SCENARIOS / "simple_spring.toml"), "--vary", "parameters.k=[3, 4]",
                 "--scheduler", "local",
                 "--set", "simulate.t_end=0.1", "--out", str(tmp_path / "s"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    # the distribution's name on the package index ("constrained" there is another project)
    assert "pip install 'constrained-particles[dask]'" in err and "pip install '.[dask]'" in err
    assert "--scheduler sequential" in err
    # without --scheduler a small sweep runs in this process: no Dask needed
    code = main(["sweep", str(SCENARIOS / "simple_spring.toml"), "--vary", "parameters.k=[3, 4]",
                 "--set", "simulate.t_end=0.1", "--out", str(tmp_path / "auto")])
    assert code == 0 and "ran in-process" in capsys.readouterr().out


def test_local_cluster_serves_no_dashboard_and_does_not_fight_for_port_8787(tmp_path, caplog):
    from constrained.sweeps.sweep import sweep  # Dask: the [test] extra installs it

    busy = socket.socket()
    busy.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        busy.bind(("127.0.0.1", 8787))
        busy.listen()
    except OSError:  # already taken by someone else: the situation the test is about
        busy.close()
        busy = None
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            r = sweep(SCENARIOS / "simple_spring.toml", ["parameters.k=[3, 4]"], workers=1, scheduler="local",
                      overrides=["simulate.t_end=0.1", "expect={}"], out_dir=tmp_path / "s", progress=False)
    finally:
        if busy is not None:
            busy.close()
    assert r.computed == 2 and r.failed == 0
    said = [str(w.message) for w in caught] + [rec.getMessage() for rec in caplog.records]
    assert not [s for s in said if "8787" in s or "already in use" in s], said


def test_bench_reports_casadi_notices_once_in_plain_words(capfd):
    from constrained.analysis.bench import work_precision

    scene = C.load_scene(SCENARIOS / "double_pendulum.toml")
    result = work_precision(scene.system, 0.3, methods=("pantelides",), tolerances=(1e-6, 1e-8), repeats=1)
    err = capfd.readouterr().err
    assert "NLP is overconstrained" not in err and "CasADi -" not in err
    notes = [n for n in result.notes if "overconstrained" in n]
    assert len(notes) == 1 and "pantelides" in notes[0] and "not a failure" in notes[0]
    assert all(row["status"] == "ok" for row in result.rows)


def test_bench_passes_other_stderr_output_through(capfd):
    import os

    from constrained.analysis.bench import BenchResult, _casadi_stderr, _report_casadi_messages

    result = BenchResult(scene="s", t_end=1.0)
    with _casadi_stderr() as printed:
        os.write(2, b"CasADi - WARNING(\"NLP is overconstrained: 3 > 2\")\nsomething else\n")
    _report_casadi_messages(result, "m", printed)
    err = capfd.readouterr().err
    assert "something else" in err and "overconstrained" not in err
    assert len(result.notes) == 1 and "1 time(s)" in result.notes[0]
