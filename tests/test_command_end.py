"""The command's end (session 15): a reader that goes away (``constrained run … | head``)
costs the rest of the report, never the run's files; the exit statuses survive the command's
fast exit (no interpreter teardown)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenarios" / "simple_pendulum.toml"


def _command(*args, **kwargs):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "constrained.cli", *args], env=env, **kwargs)


def test_a_closed_stdout_keeps_the_run_and_its_files(tmp_path):
    """Failed before: the first report line after the reader left raised BrokenPipeError,
    taken for an unwritable --out: "cannot write out: Broken pipe; nothing was written",
    exit status 2, no files."""
    out = tmp_path / "out"
    proc = _command("run", str(SCENE), "--out", str(out), "--set", "outputs.plots=[]",
                    stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before the first line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 0, err
    assert "Broken pipe" not in err
    with np.load(out / "trajectory.npz") as data:  # a whole run: the pendulum's length kept
        x = data["x"]
        assert x.shape[0] > 10
        r = np.linalg.norm(x[:, 0, :], axis=1)
        np.testing.assert_allclose(r, r[0], rtol=1e-9)


def test_exit_statuses_of_the_command(tmp_path):
    ok = _command("check", str(SCENE), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = ok.communicate(timeout=300)
    assert ok.returncode == 0 and b"particles" in out
    bad = _command("run", str(tmp_path / "missing.toml"), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = bad.communicate(timeout=300)
    assert bad.returncode == 2 and b"no such file" in err and b"Traceback" not in err
