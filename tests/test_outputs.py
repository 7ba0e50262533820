"""A run's outputs are one consistent set (issue 18, items 2 and 8): a run that stops early,
is interrupted or killed between writing the npz and the figures, or fails with a partial
trajectory, never leaves files of two runs side by side in --out, nor a stray temporary."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import BLOWUP_TOML, pendulum_toml

from constrained.cli.main import main
from constrained.output.output_set import user_path

ROOT = Path(__file__).resolve().parents[1]

PENDULUM = pendulum_toml(0.2)
FULL = PENDULUM + """
[outputs]
quantities = ["energy"]
plots = ["trajectory", "energy"]
formats = ["npz", "csv"]
"""
BLOWUP = BLOWUP_TOML


def scene(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def listing(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def no_strays(tmp_path: Path) -> None:
    strays = [p for p in tmp_path.rglob("*") if p.name.endswith(".part") or ".staging-" in p.name
              or ".old-" in p.name]
    assert not strays, strays


def t_end_of(npz: Path) -> float:
    with np.load(npz) as data:
        return float(data["t"][-1])


def test_a_second_run_replaces_the_first_runs_whole_set(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(scene(tmp_path, FULL)), "--out", str(out), "--quiet"]) == 0
    assert {"trajectory.npz", "trajectory.csv", "trajectory.png", "energy.png"} <= set(listing(out))
    small = scene(tmp_path, PENDULUM, "small.toml")
    assert main(["run", str(small), "--out", str(out), "--quiet", "--set", "simulate.t_end=0.1"]) == 0
    assert sorted(listing(out)) == ["trajectory.npz"]  # no csv, no figures of run 1
    assert t_end_of(out / "trajectory.npz") == pytest.approx(0.1)
    no_strays(tmp_path)


def test_ctrl_c_while_the_figures_are_drawn_keeps_the_data_as_one_set(tmp_path, capsys, monkeypatch):
    """Ctrl-C after the npz and csv were written, while the figures are drawn: the run's data
    is kept (issue 27: what was computed is saved), as a set of its own — the earlier run's
    figures are gone, never beside the new data; exit 130, one line."""
    out = tmp_path / "out"
    path = scene(tmp_path, FULL)
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    assert {"trajectory.png", "energy.png"} <= set(listing(out))
    capsys.readouterr()

    import constrained.output.figure_process

    def interrupted(*args, **kwargs):  # Ctrl-C after the npz was written, while the figures are drawn
        raise KeyboardInterrupt

    monkeypatch.setattr(constrained.output.figure_process.FigureProcess, "wait", interrupted)
    assert main(["run", str(path), "--out", str(out), "--quiet", "--set", "simulate.t_end=0.1"]) == 130
    assert sorted(listing(out)) == ["trajectory.csv", "trajectory.npz"]
    assert t_end_of(out / "trajectory.npz") == pytest.approx(0.1)
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "error" not in err and "interrupted (Ctrl-C)" in err
    no_strays(tmp_path)


def test_a_run_killed_between_the_npz_and_the_figures_leaves_one_set(tmp_path):
    out = tmp_path / "out"
    path = scene(tmp_path, FULL)
    env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
    first = subprocess.run([sys.executable, "-m", "constrained.cli", "run", str(path), "--out", str(out),
                            "--quiet"], env=env, capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    before = listing(out)
    killer = (
        "import os, signal, sys, constrained.output.figure_process as fp\n"
        "from constrained.cli.main import main\n"
        "def die(*a, **k):\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
        "fp.FigureProcess.wait = die\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    killed = subprocess.run([sys.executable, "-c", killer, "run", str(path), "--out", str(out), "--quiet",
                             "--set", "simulate.t_end=0.1"], env=env, capture_output=True, timeout=300)
    assert killed.returncode == -signal.SIGKILL
    assert listing(out) == before  # the killed run's npz is not beside the old figures
    # the killed run's staging folder is a hidden sibling; the next run into out removes it
    assert main(["run", str(path), "--out", str(out), "--quiet", "--set", "simulate.t_end=0.1"]) == 0
    assert t_end_of(out / "trajectory.npz") == pytest.approx(0.1)
    no_strays(tmp_path)


def test_a_partial_trajectory_is_saved_as_its_own_set(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(scene(tmp_path, FULL)), "--out", str(out), "--quiet"]) == 0
    code = main(["run", str(scene(tmp_path, BLOWUP, "blowup.toml")), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1
    assert f"saved in {out / 'trajectory.npz'}" in err and ".part" not in err and "staging" not in err
    assert sorted(listing(out)) == ["trajectory.npz"]  # not the pendulum's figures
    assert 0 < t_end_of(out / "trajectory.npz") < 3.0
    no_strays(tmp_path)


def test_bad_input_and_a_failing_verb_leave_the_folder_as_it_was(tmp_path, capsys):
    out = tmp_path / "out"
    good = scene(tmp_path, FULL)
    assert main(["run", str(good), "--out", str(out), "--quiet"]) == 0
    before = listing(out)
    assert main(["run", str(good), "--out", str(out), "--set", "constraints[0].length=2"]) == 2
    assert main(["crosscheck", str(good), "--out", str(out)]) == 2  # no [reduced] section
    assert listing(out) == before
    no_strays(tmp_path)


def test_other_verbs_and_the_users_files_are_kept_each_verb_replaces_its_own(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    path = scene(tmp_path, FULL)
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    assert main(["statics", str(path), "--out", str(out), "--quiet"]) == 0
    assert main(["plot", str(out / "trajectory.npz"), "--kinds", "phase", "--quiet"]) == 0
    names = set(listing(out))
    assert {"notes.txt", "trajectory.npz", "trajectory.csv", "equilibrium.json", "phase.png"} <= names
    # a new run replaces its own files and the figures plot drew from the old trajectory
    assert main(["run", str(scene(tmp_path, PENDULUM, "p.toml")), "--out", str(out), "--quiet"]) == 0
    names = set(listing(out))
    assert {"notes.txt", "trajectory.npz", "equilibrium.json", "statics.png"} <= names
    assert not names & {"trajectory.csv", "trajectory.png", "energy.png", "phase.png"}
    assert (out / "notes.txt").read_text() == "mine"
    no_strays(tmp_path)


def test_a_folder_of_an_earlier_version_is_cleaned_of_the_runs_files(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    for name in ("trajectory.npz", "trajectory.csv", "energy.png", "animation.gif"):
        (out / name).write_bytes(b"old run")
    assert main(["run", str(scene(tmp_path, PENDULUM)), "--out", str(out), "--quiet"]) == 0
    assert sorted(listing(out)) == ["trajectory.npz"]
    assert (out / "trajectory.npz").read_bytes() != b"old run"


@pytest.mark.parametrize("verb", ["run", "statics", "bench"])
def test_an_unwritable_output_folder_is_bad_input_exit_2_before_any_work(tmp_path, capsys, verb):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    extra = ["--methods", "projection", "--tolerances", "1e-6", "--repeats", "1"] if verb == "bench" else []
    code = main([verb, str(scene(tmp_path, PENDULUM)), "--out", str(blocker / "sub"), "--quiet", *extra])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "cannot write the output folder" in lines[0]
    assert str(blocker / "sub") in lines[0]
    assert blocker.read_text() == "not a folder"


def test_a_disk_that_fills_during_a_write_names_the_file_being_written(tmp_path, capsys, monkeypatch):
    """A full disk shows in write(), whose OSError carries no file name: the message named the
    --out folder, not the file that could not be written."""
    import constrained.run.trajectory as trajectory

    real_fdopen = trajectory.os.fdopen

    class FillsUp:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()
            return False

    monkeypatch.setattr(trajectory.os, "fdopen", lambda fd, mode: FillsUp(real_fdopen(fd, mode)))
    out = tmp_path / "out"
    code = main(["run", str(scene(tmp_path, PENDULUM)), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"cannot write {out / 'trajectory.npz'}: No space left on device" in err, err
    assert not out.exists()
    no_strays(tmp_path)


def test_a_failed_write_names_the_users_file_not_the_hidden_temporary(tmp_path, capsys, monkeypatch):
    import constrained.run.trajectory as trajectory

    def full_disk(prefix="", suffix="", dir=None):
        raise OSError(28, "No space left on device", os.path.join(dir, f"{prefix}x1y2z3{suffix}"))

    monkeypatch.setattr(trajectory.tempfile, "mkstemp", full_disk)
    out = tmp_path / "out"
    code = main(["run", str(scene(tmp_path, PENDULUM)), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert "No space left on device" in err and str(out / "trajectory.npz") in err
    assert ".part" not in err and "staging" not in err
    assert not out.exists()
    no_strays(tmp_path)


def test_user_path_names_the_output_folder():
    assert user_path("/a/.out.staging-12-abc123/trajectory.npz") == "/a/out/trajectory.npz"
    assert user_path("/a/out/.out.staging-12-abc123/x.png") == "/a/out/x.png"


def test_an_output_folder_given_as_a_symlink_stays_a_symlink(tmp_path, capsys):
    real = tmp_path / "real"
    real.mkdir()
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    path = scene(tmp_path, FULL)
    assert main(["run", str(path), "--out", str(link), "--quiet"]) == 0
    assert main(["run", str(path), "--out", str(link), "--quiet", "--set", "simulate.t_end=0.1"]) == 0
    assert link.is_symlink()
    assert t_end_of(real / "trajectory.npz") == pytest.approx(0.1)
    no_strays(tmp_path)
