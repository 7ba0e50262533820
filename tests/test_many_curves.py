"""Figures of large models (session 14): `constrained plot` of a 3,000-bead rope's 0.2 s took
11 s, one matplotlib artist per path, per multiplier and per force (three per path with its
start and end markers). From MANY_CURVES curves they are one collection and one scatter per
kind of marker: the same curves, colours and legend."""

from __future__ import annotations

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.legend import Legend
from mpl_toolkits.mplot3d.art3d import Line3DCollection

import constrained as C
from constrained.output import plot
from constrained.output.figure_style import MANY_CURVES, MAX_LEGEND

N = MANY_CURVES + 6


def _rope(n: int = N, planar: bool = True) -> C.Trajectory:
    s = C.System(name="rope")
    for i in range(n):
        s.add_particle(f"p{i}", 0.01, [0.01 * (i + 1), 0.0, 0.0], [0.0, 0.0, 0.0 if planar else 0.05])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.01))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=0.01))
    if planar:
        s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1], 0.0))
    s.add(C.Gravity([0, -9.81, 0]))
    return C.simulate(s, 0.02, rtol=1e-6, atol=1e-6, outputs={"multipliers", "constraint_forces"})


def _collection(ax, kind):
    found = [c for c in ax.collections if isinstance(c, kind)]
    assert len(found) == 1
    return found[0]


def test_many_paths_are_one_collection_with_their_data_and_legend():
    tr = _rope()
    fig = plot.trajectory_figure(tr)
    ax = fig.axes[0]
    paths = _collection(ax, LineCollection).get_segments()
    assert len(paths) == N and not [line for line in ax.lines if len(line.get_xdata()) > 1]
    np.testing.assert_array_equal(paths[7], tr.x[:, 7, :2])  # (the x–y plane: raw coordinates)
    x0, x1 = ax.get_xlim()
    assert x0 <= tr.x[:, :, 0].min() and x1 >= tr.x[:, :, 0].max()  # the view holds every path
    legends = [c for c in ax.get_children() if isinstance(c, Legend)]
    names = next([t.get_text() for t in lg.get_texts()] for lg in legends
                 if lg.get_texts()[0].get_text() == "p0")
    assert names[1] == "p1" and names[MAX_LEGEND] == f"… ({N - MAX_LEGEND} more)"


def test_many_paths_in_3d_and_many_multipliers():
    tr = _rope(planar=False)
    fig = plot.trajectory_figure(tr)
    fig.canvas.draw()  # (a 3D collection's segments are its projection, made when drawn)
    assert len(_collection(fig.axes[0], Line3DCollection).get_segments()) == N
    ax = plot.multipliers_figure(tr).axes[0]
    curves = _collection(ax, LineCollection).get_segments()
    lam = tr.multipliers.reshape(len(tr.t), -1)
    assert len(curves) == lam.shape[1] == N
    np.testing.assert_array_equal(curves[3][:, 1], lam[:, 3])
    lo, hi = ax.get_ylim()
    assert lo <= lam.min() and hi >= lam.max()
    forces = _collection(plot.constraint_forces_figure(tr).axes[0], LineCollection).get_segments()
    np.testing.assert_allclose(forces[5][:, 1], np.linalg.norm(tr.constraint_forces[:, 5], axis=1))


def test_a_few_curves_keep_one_line_each():
    tr = _rope(n=5)
    ax = plot.trajectory_figure(tr).axes[0]
    assert not ax.collections and len([line for line in ax.lines if len(line.get_xdata()) > 1]) == 5


def test_an_animation_of_many_particles_moves_a_few_artists_with_every_particle():
    """A frame of a 3,000-bead rope's GIF updated 9,000 artists (51 s for 65 frames): from
    MANY_CURVES particles the trails and dots are one artist per colour and the rods one."""
    from constrained.output.animation import animation_parts, resample

    tr = _rope()
    fig, draw, n_frames = animation_parts(tr, None, forces=False, max_frames=12)
    k = n_frames - 1
    changed = draw(k)
    assert len(changed) <= 25  # (10 trails, 10 dots, the rods, the title: not 3 per particle)
    times = np.linspace(tr.t[0], tr.t[-1], n_frames)
    q = resample(tr.t, tr.x, times)[k, :, :2]
    dots = {tuple(np.round(p, 12)) for line in fig.axes[0].lines if line.get_marker() == "o"
            for p in np.column_stack(line.get_data())}
    assert dots >= {tuple(np.round(p, 12)) for p in q}  # every particle's dot where it is


def test_a_system_without_constraints_has_no_constraint_figures():
    """Helper's finding (session 14): `constrained plot` drew empty multiplier and
    constraint-force figures for a free particle; they are skipped, saying why."""
    import pytest

    from constrained.errors import InputError

    s = C.System(name="free particle")
    s.add_particle("b", 1.0, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    s.add(C.Gravity([0.0, -9.81, 0.0]))
    tr = C.simulate(s, 0.5)
    for figure in (plot.multipliers_figure, plot.constraint_forces_figure):
        with pytest.raises(InputError, match="no constraints"):
            figure(tr)
    assert plot.trajectory_figure(tr).axes  # the others are drawn
