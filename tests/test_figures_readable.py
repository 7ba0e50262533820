"""Figures a reader can read (issue 19): sane log axes, labels inside the canvas, titles that
say what is shown, units on sweep axes, an animation with rods and of a useful size."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.output import animation, plot
from constrained.run.trajectory import Trajectory

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


@pytest.fixture(scope="module")
def crosscheck():
    scene = C.load_scene(SCENARIOS / "simple_pendulum.toml")
    return C.cross_check(scene, t_end=1.0)


def test_crosscheck_log_axis_starts_near_the_data_not_at_1e_300(crosscheck, tmp_path):
    from constrained.analysis.crosscheck import save_crosscheck_figure

    assert crosscheck.position_difference[0] == 0.0  # same start: an exact zero at t = 0
    path = save_crosscheck_figure(crosscheck, tmp_path / "crosscheck.png")
    assert path.stat().st_size > 1000
    # draw it again to read the axes (the function only returns the path)
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    captured = {}
    original = Figure.savefig

    def keep(self, *args, **kwargs):
        captured["fig"] = self
        return original(self, *args, **kwargs)

    Figure.savefig = keep
    try:
        save_crosscheck_figure(crosscheck, tmp_path / "again.png")
    finally:
        Figure.savefig = original
    ax = captured["fig"].axes[0]
    low, high = ax.get_ylim()
    positive = np.concatenate([crosscheck.position_difference, crosscheck.velocity_difference])
    positive = positive[positive > 0]
    assert low >= 1e-18 and low >= positive.min() / 100
    assert high >= positive.max()
    assert "max |Δx|" in ax.get_title()


def test_energy_title_of_a_driven_scene_does_not_say_drift():
    hoop = C.load_scene(SCENARIOS / "bead_on_rotating_hoop.toml").run(["simulate.t_end=0.5", "expect={}"])
    title = plot.energy_figure(hoop.trajectory).axes[0].get_title()
    assert "drift" not in title.lower() and "not conserved" in title and "rheonomic" in title
    free = C.load_scene(SCENARIOS / "simple_pendulum.toml").run(["simulate.t_end=0.5", "expect={}"])
    assert plot.energy_figure(free.trajectory).axes[0].get_title().startswith("Energy drift")


def test_driven_title_survives_save_and_load(tmp_path):
    hoop = C.load_scene(SCENARIOS / "bead_on_rotating_hoop.toml").run(["simulate.t_end=0.2", "expect={}"])
    hoop.trajectory.save(tmp_path / "t.npz")
    again = Trajectory.load(tmp_path / "t.npz")
    assert plot.driving_terms(again) == ["moving (rheonomic) constraints"]


def test_residual_note_on_zeros_is_in_the_title_not_over_the_curve():
    tr = C.load_scene(SCENARIOS / "simple_pendulum.toml").run(["simulate.t_end=0.3", "expect={}"]).trajectory
    tr.constraint_residual = np.zeros_like(tr.t)
    tr.constraint_residual[1::2] = 1e-16  # half the samples exactly zero
    ax = plot.residual_figure(tr).axes[0]
    assert "exact zeros drawn at" in ax.get_title()
    assert not ax.texts  # nothing written inside the axes


def test_3d_labels_fit_in_the_canvas():
    tr = C.load_scene(SCENARIOS / "spherical_pendulum.toml").run(["simulate.t_end=1", "expect={}"]).trajectory
    fig = plot.trajectory_figure(tr)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    assert ax.name == "3d"
    canvas = fig.bbox
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        box = axis.label.get_window_extent(renderer)
        assert axis.label.get_text().endswith("[m]")
        assert box.x0 >= canvas.x0 - 1 and box.x1 <= canvas.x1 + 1, axis.label.get_text()
        assert box.y0 >= canvas.y0 - 1 and box.y1 <= canvas.y1 + 1, axis.label.get_text()


def test_sweep_axis_labels_carry_units():
    from constrained.sweeps.sweep import axis_label

    units = {"a": "m", "nu": "rad/s", "up": "m"}
    assert axis_label("parameters.a", units) == "a [m]"
    assert axis_label("parameters.b", units) == "b (parameter)"
    assert axis_label("up", units) == "up [m]"
    assert axis_label("particles.p1.mass") == "particles.p1.mass [kg]"
    assert axis_label("particles[0].velocity") == "particles[0].velocity [m/s]"
    assert axis_label("effects[1].k") == "effects[1].k [N/m]"
    assert axis_label("simulate.t_end") == "simulate.t_end [s]"
    scene = C.load_scene(SCENARIOS / "kapitza_sweep.toml")
    assert scene.units["a"] == "m" and scene.units["nu"] == "rad/s"


def test_scene_units_must_be_strings(tmp_path):
    text = (SCENARIOS / "free_particle.toml").read_text()
    path = tmp_path / "bad_units.toml"
    path.write_text(text.replace("[scene]\n", "[scene]\nunits = { a = 3 }\n", 1))
    with pytest.raises(C.InputError, match="scene.units"):
        C.load_scene(path)


@pytest.mark.filterwarnings("ignore:Animation was deleted")
def test_animation_is_large_and_draws_rods_without_the_scene(tmp_path):
    from PIL import Image

    scene = C.load_scene(SCENARIOS / "double_pendulum.toml")
    result = scene.run(["simulate.t_end=0.5", "expect={}"])
    result.trajectory.save(tmp_path / "trajectory.npz")
    saved = Trajectory.load(tmp_path / "trajectory.npz")  # no System: the stored sketch
    assert saved.info["sketch"]["rods"] == [[0, 1]] and len(saved.info["sketch"]["anchors"]) == 1
    pairs, anchors = animation.links(None, saved)
    assert pairs == [(0, 1)] and anchors[0][0] == 0
    fig, draw, frames = animation.animation_parts(saved, None, True, 5)
    rods = [a for a in draw(2) if getattr(a, "get_color", lambda: None)() == "0.25"]
    assert len(rods) == 2  # p1–p2 and pivot–p1
    written = animation.save_animation(saved, tmp_path / "a.gif", max_frames=6)
    (gif,) = [p for p in written if p.suffix == ".gif"]
    image = Image.open(gif)
    assert min(image.size) >= 560 and image.n_frames == 6


def test_run_writes_its_figures_through_the_helper_process(tmp_path):
    from constrained.cli.main import main

    out = tmp_path / "run"
    assert main(["run", str(SCENARIOS / "simple_pendulum.toml"), "--set", "simulate.t_end=0.5",
                 "--set", "expect={}", "--out", str(out), "--quiet"]) == 0
    for kind in C.load_scene(SCENARIOS / "simple_pendulum.toml").outputs["plots"]:
        assert (out / f"{kind}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", kind
    assert not (out / "animation.gif").exists()  # animations only when asked for


def test_figure_process_draws_here_when_the_work_cannot_be_sent(tmp_path):
    from constrained.output.figure_process import FigureProcess

    tr = C.load_scene(SCENARIOS / "simple_pendulum.toml").run(["simulate.t_end=0.2", "expect={}"]).trajectory

    class Unpicklable:
        hook = None

        def __reduce__(self):
            raise TypeError("cannot be sent to another process")

    done = []
    with FigureProcess() as figures:
        paths = figures.save(tr, ["energy"], tmp_path, system=Unpicklable(), progress=done.append)
    assert [p.name for p in paths] == ["energy.png"] and (tmp_path / "energy.png").stat().st_size > 1000
    assert sum(done) == 1


def test_animation_draws_the_sphere_or_circle_a_rod_to_a_pivot_allows():
    from matplotlib.patches import Circle
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    def run(name):
        return C.load_scene(SCENARIOS / name).run(["simulate.t_end=0.5", "expect={}"]).trajectory

    fig, _, _ = animation.animation_parts(run("spherical_pendulum.toml"), None, False, 4)
    ax = fig.axes[0]
    assert ax.name == "3d"
    assert any(isinstance(c, Line3DCollection) for c in ax.collections)  # the wireframe sphere
    fig, _, _ = animation.animation_parts(run("simple_pendulum.toml"), None, False, 4)
    ax = fig.axes[0]
    assert ax.name != "3d" and [p for p in ax.patches if isinstance(p, Circle)]  # the circle, planar
