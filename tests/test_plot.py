"""Figures of constrained.plot on synthetic trajectories: files written, not blank, labelled."""

from __future__ import annotations

import matplotlib.image as mpimg
import numpy as np
import pytest
from mpl_toolkits.mplot3d import Axes3D

from constrained.output.figure_style import motion_plane
from constrained.output.plot import (
    FIGURES,
    energy_figure,
    phase_figure,
    principal_coordinate,
    residual_figure,
    save_figures,
    trajectory_figure,
)
from constrained.run.trajectory import Trajectory

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
G = 9.81


def pendulum() -> Trajectory:
    """Unit-length pendulum of mass 1 in the x–y plane: θ(t) = 0.5 cos(2t), pivot at the origin."""
    t = np.linspace(0.0, 6.0, 301)
    theta = 0.5 * np.cos(2 * t)
    omega = -np.sin(2 * t)
    alpha = -2 * np.cos(2 * t)
    zeros = np.zeros_like(t)
    x = np.stack([np.sin(theta), -np.cos(theta), zeros], axis=-1)[:, None, :]
    v = np.stack([np.cos(theta) * omega, np.sin(theta) * omega, zeros], axis=-1)[:, None, :]
    energy = 0.5 * omega**2 - G * np.cos(theta)
    # the multiplier of |x| − 1 = 0: the radial force needed, m (g cos θ + ω²) (tension = −λ)
    lam = -(G * np.cos(theta) + omega**2)
    forces = lam[:, None, None] * x
    rng = np.random.default_rng(0)
    residual = np.abs(rng.normal(scale=1e-12, size=t.shape))
    residual[0] = 0.0  # an exact zero must not break the log axis
    vresidual = np.abs(rng.normal(scale=1e-10, size=t.shape)) * (1 + np.abs(alpha))
    return Trajectory(
        t=t,
        x=x,
        v=v,
        multipliers=lam[:, None],
        constraint_forces=forces,
        energy=energy,
        constraint_residual=residual,
        velocity_residual=vresidual,
        action=np.cumsum(np.gradient(t) * (0.5 * np.sum(v**2, axis=(1, 2)) - 9.81 * x[:, 0, 1])),
        particle_names=["bob"],
        constraint_labels=["rod: |bob − (0, 0, 0)| = 1"],
    )


def helix() -> Trajectory:
    """Two particles on helices (not planar), with many multipliers to truncate the legend."""
    t = np.linspace(0.0, 4 * np.pi, 400)
    x1 = np.stack([np.cos(t), np.sin(t), 0.1 * t], axis=-1)
    x2 = np.stack([0.5 * np.cos(t + 1), 0.5 * np.sin(t + 1), 0.1 * t + 0.2], axis=-1)
    v1 = np.stack([-np.sin(t), np.cos(t), np.full_like(t, 0.1)], axis=-1)
    v2 = np.stack([-0.5 * np.sin(t + 1), 0.5 * np.cos(t + 1), np.full_like(t, 0.1)], axis=-1)
    x = np.stack([x1, x2], axis=1)
    v = np.stack([v1, v2], axis=1)
    n_rows = 15
    lam = np.stack([np.sin(t + k) * (k + 1) for k in range(n_rows)], axis=-1)
    forces = -np.stack([x1 * [1, 1, 0], x2 * [1, 1, 0]], axis=1)
    return Trajectory(
        t=t,
        x=x,
        v=v,
        multipliers=lam,
        constraint_forces=forces,
        energy=np.full_like(t, 2.0) + 1e-9 * t,
        constraint_residual=np.zeros_like(t),
        velocity_residual=np.full_like(t, 1e-13),
        action=0.5 * t**2,
        particle_names=["a", "b"],
        constraint_labels=[f"row {k}" for k in range(n_rows)],
    )


def _check_labels(fig) -> None:
    assert fig.axes
    for ax in fig.axes:
        assert ax.get_xlabel().strip(), ax
        assert ax.get_ylabel().strip(), ax
        assert ax.get_title().strip(), ax


def _check_png(path) -> None:
    assert path.is_file()
    assert path.read_bytes()[:8] == PNG_MAGIC
    image = mpimg.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    assert float(np.std(image[..., :3])) > 0.02


@pytest.mark.parametrize("make", [pendulum, helix])
@pytest.mark.parametrize("kind", list(FIGURES))
def test_every_figure_is_saved_labelled_and_not_blank(tmp_path, make, kind):
    traj = make()
    paths = save_figures(traj, [kind], tmp_path, dpi=80)
    assert paths == [tmp_path / f"{kind}.png"]
    _check_png(paths[0])
    _check_labels(FIGURES[kind](traj))
    # no temporary files are left beside the figure
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{kind}.png"]


def test_save_all_kinds_at_once(tmp_path):
    paths = save_figures(pendulum(), FIGURES, tmp_path / "figs")
    assert [p.name for p in paths] == [f"{k}.png" for k in FIGURES]
    for p in paths:
        _check_png(p)


def test_unknown_kind_names_the_allowed_ones(tmp_path):
    with pytest.raises(ValueError, match="allowed: trajectory, energy"):
        save_figures(pendulum(), ["energy", "spaghetti"], tmp_path)
    assert not list(tmp_path.iterdir())


def test_planar_pendulum_is_drawn_in_2d_with_coordinate_axes():
    fig = trajectory_figure(pendulum())
    (ax,) = fig.axes
    assert not isinstance(ax, Axes3D)
    assert ax.get_xlabel() == "x [m]"
    assert ax.get_ylabel() == "y [m]"
    assert "bob" in [text.get_text() for text in ax.get_legend().get_texts()] or any(
        "bob" in [t.get_text() for t in child.get_texts()]
        for child in ax.get_children()
        if hasattr(child, "get_texts")
    )


def test_helix_is_drawn_in_3d():
    fig = trajectory_figure(helix())
    (ax,) = fig.axes
    assert isinstance(ax, Axes3D)
    assert ax.get_zlabel() == "z [m]"


def test_motion_plane_detection():
    traj = pendulum()
    origin, basis, labels = motion_plane(traj.x)
    assert labels == ("x", "y")
    assert motion_plane(helix().x) is None
    # a tilted plane is found and described by its principal directions
    rot = np.array([[1, 0, 0], [0, np.cos(0.7), -np.sin(0.7)], [0, np.sin(0.7), np.cos(0.7)]])
    tilted = traj.x @ rot.T + [0.0, 0.0, 3.0]
    origin, basis, labels = motion_plane(tilted)
    assert labels == ("u", "v")
    assert np.allclose(basis @ basis.T, np.eye(2))
    assert np.max(np.abs((tilted.reshape(-1, 3) - origin) @ np.cross(*basis))) < 1e-12
    fig = trajectory_figure(
        Trajectory(t=traj.t, x=tilted, v=traj.v @ rot.T, particle_names=["bob"])
    )
    (ax,) = fig.axes
    assert not isinstance(ax, Axes3D)
    assert ax.get_xlabel() == "u [m]"
    # just above the tolerance it is no longer planar
    bumped = tilted.copy()
    bumped[10, 0] += 1e-6 * np.cross(*basis)
    assert motion_plane(bumped) is None


def test_a_run_of_two_samples_of_one_particle_is_drawn_in_the_plane_holding_them():
    """Two positions on no coordinate plane (a free particle's 0.05 s, saved at its two ends):
    the SVD of two points has two directions, the plane's normal is the third (an IndexError
    that refused to write the run's outputs before)."""
    x = np.array([[[0.0, 0.0, 0.0]], [[0.05, 0.1, -0.02]]])
    origin, basis, labels = motion_plane(x)
    assert labels == ("u", "v") and np.allclose(basis @ basis.T, np.eye(2))
    assert np.max(np.abs((x.reshape(-1, 3) - origin) @ np.cross(*basis))) < 1e-15  # both on it
    traj = Trajectory(t=np.array([0.0, 0.05]), x=x, v=np.repeat([[[1.0, 2.0, -0.4]]], 2, axis=0),
                      particle_names=["ball"])
    (ax,) = trajectory_figure(traj).axes
    assert ax.get_xlabel() == "u [m]"
    assert motion_plane(x[:1]) is not None  # one point: a coordinate plane through it


def test_energy_figure_needs_energy():
    traj = pendulum()
    traj.energy = None
    with pytest.raises(ValueError, match="no energy"):
        energy_figure(traj)


def test_energy_title_gives_initial_energy():
    traj = pendulum()
    ax = energy_figure(traj).axes[0]
    assert f"{traj.energy[0]:.6g} J" in ax.get_title()
    assert "[J]" in ax.get_ylabel()


def test_residual_figure_uses_log_axes_and_survives_zeros():
    fig = residual_figure(helix())  # constraint residual identically zero
    assert len(fig.axes) == 2
    assert all(ax.get_yscale() == "log" for ax in fig.axes)
    assert "[m]" in fig.axes[0].get_ylabel() and "[m/s]" in fig.axes[1].get_ylabel()
    traj = pendulum()
    traj.constraint_residual = traj.velocity_residual = None
    with pytest.raises(ValueError):
        residual_figure(traj)


def test_multiplier_legend_is_truncated():
    fig = FIGURES["multipliers"](helix())
    texts = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert len(texts) == 13
    assert texts[:12] == [f"row {k}" for k in range(12)]
    assert texts[-1].startswith("…")


def test_phase_portrait_of_the_pendulum():
    traj = pendulum()
    s, ds, share = principal_coordinate(traj)
    # for a 1-DOF motion, ds/dt is the time derivative of s
    assert np.allclose(np.gradient(s, traj.t)[1:-1], ds[1:-1], atol=5e-3)
    assert share > 0.9
    ax = phase_figure(traj).axes[0]
    assert ax.get_xlabel() == "s [m]" and ax.get_ylabel() == "ds/dt [m/s]"
    assert "principal coordinate" in ax.get_title()


# --- animation and figures of a real run ----------------------------------------------------


def _short(traj: Trajectory, n: int = 40) -> Trajectory:
    """Every k-th sample, so that an animation test stays quick."""
    k = max(1, len(traj.t) // n)
    forces = None if traj.constraint_forces is None else traj.constraint_forces[::k]
    return Trajectory(t=traj.t[::k], x=traj.x[::k], v=traj.v[::k], constraint_forces=forces,
                      particle_names=traj.particle_names, constraint_labels=traj.constraint_labels)


@pytest.mark.filterwarnings("ignore:Animation was deleted")
@pytest.mark.parametrize("make", [pendulum, helix], ids=["planar", "3d"])
def test_animation_is_a_gif_with_labelled_axes(tmp_path, make):
    from constrained.output.animation import animation_figure
    from constrained.output.plot import KINDS

    assert "animation" in KINDS
    traj = _short(make())
    (path,) = [p for p in save_figures(traj, ["animation"], tmp_path) if p.suffix == ".gif"]
    assert path.name == "animation.gif"
    assert path.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    from PIL import Image

    with Image.open(path) as im:
        # the frames and their duration that playback chose (real time where it can)
        from constrained.output.animation import MAX_FRAMES, playback

        frames, ms = playback(float(traj.t[-1] - traj.t[0]), MAX_FRAMES, len(traj.t))
        assert im.n_frames == frames <= len(traj.t) and im.info["duration"] == ms
        frame = np.asarray(im.convert("L"))
        assert frame.std() > 5  # not blank
    fig, _ = animation_figure(traj, max_frames=10)
    ax = fig.axes[0]
    assert ax.get_xlabel().endswith("[m]") and ax.get_ylabel().endswith("[m]")


@pytest.mark.filterwarnings("ignore:Animation was deleted")
def test_every_kind_from_a_real_scene_run(tmp_path):
    """Each figure kind, drawn from an actual `constrained run` of a small scene, is a labelled,
    non-blank PNG (the animation a GIF), and `constrained plot` redraws them from the .npz."""
    from pathlib import Path

    from constrained.cli.main import main
    from constrained.output.plot import KINDS

    scene = Path(__file__).resolve().parent.parent / "scenarios" / "simple_pendulum.toml"
    out = tmp_path / "run"
    quantities = ('["multipliers", "constraint_forces", "energy", "constraint_residual", '
                  '"velocity_residual", "action"]')
    assert main(["run", str(scene), "--set", "simulate.t_end=1", "--set", "simulate.output_dt=0.05",
                 "--set", f"outputs.quantities={quantities}", "--set", "outputs.plots=[]",
                 "--set", "expect={}", "--quiet", "--out", str(out)]) == 0
    traj = Trajectory.load(out / "trajectory.npz")
    for kind in FIGURES:
        fig = FIGURES[kind](traj)
        _check_labels(fig)
    figs = tmp_path / "figs"
    assert main(["plot", str(out), "--out", str(figs), "--kinds", ",".join(KINDS), "--scene", str(scene),
                 "--quiet"]) == 0
    for kind in FIGURES:
        _check_png(figs / f"{kind}.png")
    assert (figs / "animation.gif").read_bytes()[:6] == b"GIF89a"


def test_plot_verb_bad_input_exits_2(tmp_path, capsys):
    from constrained.cli.main import main

    assert main(["plot", str(tmp_path / "nothere.npz")]) == 2
    assert "no such file" in capsys.readouterr().err


# --- the animation: speed said, forces in every frame, the scene's curves ----------------------


def test_animation_says_its_speed_and_plays_in_real_time_when_it_can():
    from constrained.output.animation import MIN_FRAME_MS, animation_parts, playback

    for span, samples in ((6.0, 301), (10.0, 357), (2.4, 25), (7.5, 40)):
        frames, ms = playback(span, 120, samples)
        assert frames <= min(120, samples) and ms % 10 == 0
        assert ms * (frames - 1) == pytest.approx(1000 * span, rel=0.05)  # real time, to 10 ms
    frames, ms = playback(0.5, 120, 100)  # too short for real time at 120 frames: slowed, and said
    assert ms == MIN_FRAME_MS and ms * (frames - 1) > 1000 * 0.5
    fig, draw, n = animation_parts(pendulum(), None, True, 120)
    assert "GIF plays in real time" in [t.get_text() for t in fig.texts]
    fast = pendulum()
    fast.t = fast.t / 10  # 0.6 s in 300 steps of 2 ms: 120 frames of 20 ms are longer than that
    fig, draw, n = animation_parts(fast, None, True, 120)
    speed = 0.6 / (0.02 * (n - 1))
    assert [t.get_text() for t in fig.texts] == [f"GIF plays at {speed:.3g}× real time (slowed)"]


def test_force_arrows_are_scaled_per_frame_and_drawn_above_the_particles():
    """One frame with a force 1e4 times the others' (an impact) does not shrink the arrows of the
    other frames to nothing: each frame's longest arrow is ARROW_SHARE of the picture, and the
    title gives its magnitude in N."""
    from constrained.output.animation import ARROW_SHARE, animation_parts

    traj = pendulum()
    forces = traj.constraint_forces.copy()
    forces[150] *= 1e4
    traj.constraint_forces = forces
    fig, draw, n = animation_parts(traj, None, True, len(traj.t))
    ax = fig.axes[0]
    size = max(np.ptp(traj.x[:, 0, 0]), np.ptp(traj.x[:, 0, 1]))
    dots = [line for line in ax.lines if line.get_marker() == "o"]
    for k in (0, 100, 150, 250):
        artists = draw(k)
        quiver = next(a for a in artists if hasattr(a, "U"))
        length = float(np.max(np.hypot(quiver.U, quiver.V)))
        assert length == pytest.approx(ARROW_SHARE * size, rel=1e-6)
        assert quiver.get_zorder() > max(d.get_zorder() for d in dots)
        assert artists.index(quiver) > max(artists.index(d) for d in dots)  # blitted after them
        title = next(a for a in artists if hasattr(a, "get_text")).get_text()
        magnitude = float(np.max(np.linalg.norm(traj.constraint_forces[k], axis=-1)))
        assert f"longest force arrow: {magnitude:.3g} N" in title


def test_animation_draws_the_curve_a_scene_holds_its_bead_on(tmp_path):
    """A bead on a helical wire (a curve: two surfaces): the GIF shows the wire — points on it
    near the motion, each within 1e-5 m of both surfaces."""
    import constrained as C
    from constrained.output.animation import animation_parts, save_animation

    system = C.System(
        [C.Particle("bead", 0.1, [0.5, 0.0, 0.0], [0.0, 1.0, 0.2])],
        [C.Curve("bead", ["x - 0.5*cos(z/0.1)", "y - 0.5*sin(z/0.1)"], name="helix")],
        [C.Gravity([0, 0, -G])],
    )
    traj = C.simulate(system, 1.0, t_eval=np.linspace(0, 1, 51), outputs={"constraint_forces"})
    fig, draw, n = animation_parts(traj, system, True, 20)
    ax = fig.axes[0]
    wire = next(line for line in ax.lines if line.get_label().startswith("curve: helix"))
    x, y, z = (np.asarray(c) for c in wire.get_data_3d())
    assert len(x) > 50
    np.testing.assert_allclose(x, 0.5 * np.cos(z / 0.1), atol=1e-5)  # (points stored to 1e-6 m)
    np.testing.assert_allclose(y, 0.5 * np.sin(z / 0.1), atol=1e-5)
    assert "curve: helix" in [t.get_text() for t in ax.get_legend().get_texts()]
    (gif,) = save_animation(traj, tmp_path / "helix.gif", system=system, max_frames=20)
    assert gif.read_bytes()[:6] == b"GIF89a"


def test_a_3d_animation_with_many_legend_entries_keeps_its_legend_inside_the_frame():
    """Two particles, a wire and a surface, and the force arrows: five legend entries, which
    legend() puts right of the axes — outside the GIF's fixed 640 px frame (cut off). The
    legend must lie in the frame and clear of the frame's title."""
    import constrained as C
    from constrained.output.animation import animation_parts

    system = C.System(
        [C.Particle("b", 0.05, [0.4, 0.0, 0.0], [0.0, 1.0, 0.2]), C.Particle("c", 0.1, [0.4, 0.0, -0.5])],
        [C.Curve("b", ["x - 0.4*cos(z/0.1)", "y - 0.4*sin(z/0.1)"]), C.Distance("b", "c", length=0.5),
         C.Surface("c", "z + 0.5 - 0.2*(x - 0.4)")],
        [C.Gravity([0, 0, -G])],
    )
    traj = C.simulate(system, 1.0, t_eval=np.linspace(0, 1, 31), outputs={"constraint_forces"})
    fig, draw, n = animation_parts(traj, system, True, 20)
    draw(n // 2)
    renderer = fig.canvas.get_renderer()
    fig.canvas.draw()
    frame = fig.bbox
    legends = [leg for leg in [*fig.legends, *(a.get_legend() for a in fig.axes)] if leg is not None]
    assert sum(len(leg.get_texts()) for leg in legends) >= 5
    boxes = [leg.get_window_extent(renderer) for leg in legends]
    titles = [t.get_window_extent(renderer) for a in fig.axes
              for t in (a.title, a._left_title, a._right_title) if t.get_text()]
    for box in boxes:
        assert frame.x0 - 1 <= box.x0 and box.x1 <= frame.x1 + 1, (box, frame)
        assert frame.y0 - 1 <= box.y0 and box.y1 <= frame.y1 + 1, (box, frame)
        assert not any(box.overlaps(title) for title in titles)


def test_gif_frames_keep_their_colours():
    """One palette for the whole GIF, each frame mapped through a table: a rendered frame comes
    back with every pixel within a few levels of its colour."""
    from constrained.output.animation import animation_parts
    from constrained.output.gif import PaletteMap, palette_from

    fig, draw, n = animation_parts(helix(), None, True, 10)
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    mapping = PaletteMap(palette_from([rgb]))
    back = mapping.palette[mapping(rgb)].astype(int)
    error = np.abs(back - rgb.astype(int)).max(axis=-1)
    assert np.percentile(error, 99) <= 16 and error.mean() < 2
    rgba = np.asarray(fig.canvas.buffer_rgba())
    assert np.array_equal(mapping(rgba), mapping(rgba[..., :3]))  # the 32-bit path agrees
