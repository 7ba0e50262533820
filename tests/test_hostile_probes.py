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

    proc = subprocess.run([sys.executable, "-m", "constrained.cli", "run", str(scene), "--out", str(out),
                           "--quiet", "--set", "simulate.t_end=2", "--set",
                           'outputs.plots=["trajectory", "energy", "animation"]'], env={**_env(), "CONSTRAINED_TEST_TAG": tag}, cwd=tmp_path,
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
