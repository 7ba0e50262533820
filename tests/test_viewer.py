"""The interactive viewer (constrained.viewer, ``constrained view``): the page, in a real browser.

The browser checks run headless Chromium on the written page. The page carries a self-test
(URL hash ``#selftest``) that drives its own controls the way a reader does (moves the
slider, toggles the force arrows, picks another multiplier, turns the view) and writes what
it saw, pixel hashes and the errors the page met, into ``<pre id="selftest">``; Chromium's
``--dump-dom`` hands that back. Screenshots at two times are compared from outside too.

In CI (``CI`` set) a missing Chromium is a failure, never a skip (``.ci/run`` installs it).
"""

from __future__ import annotations

import base64
import html
import json
import os
import re
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.output import shapes, viewer
from constrained.run.trajectory import Trajectory

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenarios" / "double_pendulum.toml"
IN_CI = os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")
_BROWSERS = ("chromium", "chromium-browser", "google-chrome")
CHROMIUM = next((p for p in map(shutil.which, _BROWSERS) if p), None)


@pytest.fixture(scope="module")
def chromium() -> str:
    if CHROMIUM is None:
        if IN_CI:
            pytest.fail("chromium is not installed: the viewer tests need it in CI (.ci/run installs it)")
        pytest.skip("no chromium on this machine (the viewer's browser tests run in CI)")
    return CHROMIUM


def _browser(chromium: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--window-size=1280,800",
             "--no-first-run", "--disable-extensions"]
    return subprocess.run([chromium, *flags, *args], capture_output=True, text=True, timeout=timeout)


def selftest(chromium: str, page: Path) -> dict:
    """Load ``page#selftest`` in headless Chromium; the report the page wrote about itself."""
    # virtual time lets the page's timers run: it plays until its slider moves, then reports
    url = page.resolve().as_uri() + "#selftest"
    done = _browser(chromium, "--virtual-time-budget=6000", "--dump-dom", url)
    match = re.search(r'<pre id="selftest"[^>]*>(.*?)</pre>', done.stdout, re.S)
    assert match, f"the page wrote no self-test report (exit {done.returncode}): {done.stderr[-2000:]}"
    return json.loads(html.unescape(match.group(1)))


def screenshot(chromium: str, page: Path, fragment: str, png: Path) -> np.ndarray:
    from matplotlib.image import imread

    _browser(chromium, f"--screenshot={png}", page.resolve().as_uri() + "#" + fragment)
    assert png.is_file(), f"no screenshot of {page}#{fragment}"
    return imread(png)


def _embedded(page: Path) -> dict:
    text = page.read_text(encoding="utf-8")
    match = re.search(r'<script type="application/json" id="data">(.*?)</script>', text, re.S)
    assert match
    return json.loads(match.group(1))


def _f32(b64: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(b64), dtype="<f4")


@pytest.fixture(scope="module")
def dp_run(tmp_path_factory) -> Path:
    """The bundled double pendulum for 1 s, with ``plots = ["viewer"]`` asked by --set."""
    out = tmp_path_factory.mktemp("dp")
    assert main(["run", str(SCENE), "--out", str(out), "--set", "simulate.t_end=1",
                 "--set", 'outputs.plots=["viewer"]', "--quiet"]) == 0
    return out


# --------------------------------------------------------------------------------- in the browser


@pytest.mark.slow
def test_run_writes_viewer_html_that_works_in_chromium(dp_run, chromium):
    page = dp_run / "viewer.html"
    assert page.is_file()
    report = selftest(chromium, page)
    assert report["errors"] == [], report
    assert report["particles"] == 2 and report["constraints"] == 3  # two rods and the plane
    assert report["start"]["ink"] > 1000  # the picture is not blank
    assert report["start"]["ink"] < 0.5 * report["start"]["pixels"]  # nor flooded (face-on plane faded)
    assert report["slider_changes_picture"] and report["t_middle"] > report["t_start"]
    assert all(ink > 200 for ink in report["panels"])  # energy, residual, multiplier drawn
    for axes in report["axis_labels"]:  # numbers on the axes, each readable and distinct
        for labels in (axes["y"], axes["t"]):
            assert len(labels) >= 2 and len(set(labels)) == len(labels), axes
            assert all(re.fullmatch(r"-?[0-9.]+(e[-+]?[0-9]+)?", text) for text in labels), axes
        assert axes["t"][0] == "0" and float(axes["t"][-1]) == 1.0
    assert report["forces_toggle_changes_picture"]
    # arrows scaled per frame: drawn in every frame, not only near the run's largest force
    assert len(report["force_pixels"]) == 12 and min(report["force_pixels"]) > 40, report["force_pixels"]
    # at 1280 × 800 no panel title is cut, and each says its unit
    assert report["titles_cut"] == [], report["titles_cut"]
    energy, residual, multiplier = report["panel_titles"]
    assert "[J]" in energy and "[m]" in residual and "λ [N]" in multiplier
    # graph paper in the plane of the motion, with the x and y axes through the origin
    assert report["grid"]["lines"] >= 8 and sorted(report["grid"]["axes"]) == ["x", "y"]
    assert report["multiplier_choice_changes_panel"]
    assert report["play_advances"]
    assert report["rotation_changes_picture"]
    played = report["played"]  # the play button, pressed for real: time runs, the slider follows
    assert played["t"] > 0 and played["slider_moved"] and played["picture_changed"], report
    assert "pause" in played["button"] and "play" in report["paused"]["button"]


@pytest.mark.slow
def test_view_verb_screenshots_change_with_time(dp_run, chromium, tmp_path, capsys):
    page = tmp_path / "dp.html"
    assert main(["view", str(dp_run / "trajectory.npz"), "--scene", str(SCENE), "--out", str(page)]) == 0
    assert f"wrote: {page}" in capsys.readouterr().out
    a = screenshot(chromium, page, "t=0", tmp_path / "a.png")
    b = screenshot(chromium, page, "t=0.6", tmp_path / "b.png")
    assert a.shape == b.shape and a.shape[0] >= 600
    assert a[..., :3].std() > 0.05  # a picture, not a blank page
    changed = np.any(np.abs(a[..., :3] - b[..., :3]) > 0.1, axis=-1)
    assert changed.sum() > 500  # the pendulum moved (and the cursors and the clock)
    assert changed[:, : a.shape[1] // 2].sum() > 200  # in the picture of the scene itself


@pytest.mark.slow
def test_view_without_scene_draws_what_the_file_has(dp_run, chromium, tmp_path):
    page = tmp_path / "bare.html"
    assert main(["view", str(dp_run), "--out", str(page), "--quiet"]) == 0
    data = _embedded(page)
    assert "constraints" not in data and data["n"] == 2
    report = selftest(chromium, page)
    assert report["errors"] == [] and report["constraints"] == 0
    assert report["start"]["ink"] > 500 and report["slider_changes_picture"]
    assert "give --scene" in page.read_text(encoding="utf-8")
    report = selftest(chromium, dp_run / "viewer.html")  # the legend of the page with the scene
    assert "plane n=(0, 0, 1), offset 0 (the picture's own plane)" in report["legend"]
    assert "distance p1–p2 = 1 m" in report["legend"] and "give --scene" not in report["legend"]


def test_page_is_self_contained(dp_run):
    text = (dp_run / "viewer.html").read_text(encoding="utf-8")
    assert not re.search(r"<script[^>]*\bsrc=|<link\b|@import|url\(|https?://", text, re.I)
    assert text.count("<canvas") == 4  # the scene and three panels
    for control in ('id="slider"', 'id="play"', 'id="speed"', 'id="forces"', 'id="trail"', 'id="lam-select"'):
        assert control in text


def _zoo() -> tuple[C.System, Trajectory]:
    """Every drawable constraint kind, moving ones included, and a trajectory to go with it."""
    s = C.System(name="zoo", parameters={"w": 2.0})
    for name in ("a", "b", "c", "d"):
        s.add_particle(name, 1.0, [0.0, 0.0, 0.0])
    s.add(C.Surface("a", "x**2 + y**2 + z**2 - 1"),
          C.Plane("a", ["-sin(w*t)", "cos(w*t)", "0"]),
          C.Distance("b", point=["0.2*sin(t)", "0", "1"], length=1.0),
          C.Distance("a", "b", length=1.0),
          C.Pin("c", ["cos(t)", "sin(t)", "0.5"]),
          C.Curve("d", ["x**2 + y**2 + z**2 - 1", "z - 0.2"]),
          C.Surface("d", "x**2 + y**2 - (0.9 + 0.05*t)**2"),
          C.Custom("x_a - x_b"),
          C.Surface("c", "x**2 + y**2 + z**2 - 1"))  # the sphere again: drawn once
    t = np.linspace(0.0, 2.0, 60)
    th = 0.5 * np.sin(3 * t)
    a = np.stack([np.sin(th) * np.cos(2 * t), np.sin(th) * np.sin(2 * t), -np.cos(th)], axis=1)
    b = np.stack([0.2 * np.sin(t), np.zeros_like(t), np.ones_like(t) * 0.1], axis=1)
    c = np.stack([np.cos(t), np.sin(t), 0.5 * np.ones_like(t)], axis=1)
    r = np.sqrt(1 - 0.2**2)
    d = np.stack([r * np.cos(t), r * np.sin(t), 0.2 * np.ones_like(t)], axis=1)
    x = np.stack([a, b, c, d], axis=1)
    lam = np.stack([np.sin(t + k) for k in range(8)], axis=1)
    return s, Trajectory(t=t, x=x, v=np.zeros_like(x), multipliers=lam, energy=np.cos(t),
                         constraint_residual=np.abs(np.sin(5 * t)) * 1e-12,
                         particle_names=["a", "b", "c", "d"])


@pytest.mark.slow
def test_every_constraint_kind_is_drawn_and_moves(chromium, tmp_path):
    system, traj = _zoo()
    data = viewer.page_data(traj, system=system, title="zoo")
    kinds = [c["kind"] for c in data["constraints"]]
    assert kinds == ["surface", "plane", "rod", "rod", "pin", "curve", "surface", "undrawn", "surface"]
    sphere, plane, anchor, pair, pin, curve, cylinder, custom, again = data["constraints"]
    assert again["same_as"] == 0 and "points" not in again
    frames = data["frames"]
    times = _f32(data["t"])
    # the fixed sphere: points on it, near the motion
    pts = np.array(sphere["points"])
    assert len(pts) > 50 and np.allclose(np.linalg.norm(pts, axis=1), 1.0, atol=1e-5)
    # the turning plane: 4 corners per frame, each on n(t)·x = 0
    corners = _f32(plane["moving"]).reshape(frames, 4, 3)
    normal = np.stack([-np.sin(2 * times), np.cos(2 * times), 0 * times], axis=1)
    assert np.allclose(np.einsum("fkc,fc->fk", corners, normal), 0.0, atol=1e-5)
    # the moving anchor and the pin follow their formulas of t
    anchor_x = _f32(anchor["point"]["moving"]).reshape(frames, 3)[:, 0]
    assert np.allclose(anchor_x, 0.2 * np.sin(times), atol=1e-6)
    assert pair["a"] == 0 and pair["b"] == 1 and "point" not in pair
    assert np.allclose(_f32(pin["point"]["moving"]).reshape(frames, 3)[:, 1], np.sin(times), atol=1e-6)
    # the curve: on both surfaces
    cpts = np.array(curve["points"])
    assert len(cpts) > 10
    assert np.allclose(np.linalg.norm(cpts, axis=1), 1.0, atol=1e-5)
    assert np.allclose(cpts[:, 2], 0.2, atol=1e-6)
    # the growing cylinder: a cloud per key time, on the cylinder of that time
    keys = np.array(cylinder["keys"])
    cloud = _f32(cylinder["moving"]).reshape(len(keys), cylinder["count"], 3)
    assert 2 < len(keys) <= shapes.CLOUD_KEYS
    for k, frame in enumerate(keys):
        p = cloud[k][np.isfinite(cloud[k, :, 0])]
        assert len(p) > 10
        assert np.allclose(np.hypot(p[:, 0], p[:, 1]), 0.9 + 0.05 * times[frame], atol=1e-5)
    assert "not drawn" in custom["label"]
    traj.particle_names = []  # a file without names: the scene's names (same count) are used
    page = viewer.write_viewer(traj, tmp_path / "zoo.html", system=system, title="__DATA__ zoo <&>")
    assert "<h1>__DATA__ zoo &lt;&amp;&gt;</h1>" in page.read_text(encoding="utf-8")
    assert _embedded(page)["names"] == ["a", "b", "c", "d"]
    report = selftest(chromium, page)
    assert report["errors"] == [] and report["constraints"] == 9
    assert report["slider_changes_picture"] and report["rotation_changes_picture"]


@pytest.mark.slow
def test_large_run_is_decimated_and_the_page_stays_small(chromium, tmp_path):
    """1e5 samples of 300 particles: frames and series decimated, spikes kept, page bounded."""
    T, N, C_ = 100_000, 300, 300
    t = np.linspace(0.0, 100.0, T)
    phase = np.linspace(0, 2 * np.pi, N, endpoint=False, dtype=np.float32)
    x = np.empty((T, N, 3), dtype=np.float32)
    tt = t.astype(np.float32)[:, None]
    x[..., 0] = np.cos(tt + phase)
    x[..., 1] = np.sin(tt + phase)
    x[..., 2] = 0.1 * np.sin(3 * tt + phase)
    residual = np.full(T, 1e-14)
    residual[54_321] = 3e-9  # one spike: the decimated panel must still show it
    lam = np.sin(t[:, None] + np.arange(C_)[None, :]).astype(np.float32)
    run = tmp_path / "big.npz"
    np.savez(run, t=t, x=x, v=np.zeros((T, N, 3), dtype=np.float16), multipliers=lam,
             energy=1.0 + 1e-9 * np.sin(t), constraint_residual=residual,
             meta=np.array(json.dumps({"particle_names": [f"q{i}" for i in range(N)]})))
    del x, lam
    page = tmp_path / "big.html"
    assert main(["view", str(run), "--out", str(page), "--quiet"]) == 0
    size = page.stat().st_size
    assert size < 8_000_000, f"the page is {size / 1e6:.1f} MB"
    data = _embedded(page)
    assert data["samples"] == T and data["n"] == N
    assert viewer.MIN_FRAMES <= data["frames"] <= viewer.MAX_POINT_FRAMES // N
    res = data["series"]["constraint_residual"]
    assert len(_f32(res["t"])) <= viewer.MAX_SERIES_POINTS
    assert np.isclose(_f32(res["y"]).max(), 3e-9, rtol=1e-6)
    lam_series = data["series"]["multipliers"]
    points = len(_f32(lam_series["t"]))
    assert points * C_ <= viewer.MAX_SERIES_VALUES and lam_series["count"] == C_
    assert len(_f32(lam_series["y"])) == points * C_
    drift = _f32(data["series"]["energy"]["y"])  # E − E(t0): the 1e-9 drift survives float32
    assert 1.5e-9 < drift.max() - drift.min() < 2.5e-9
    report = selftest(chromium, page)
    assert report["errors"] == [] and report["particles"] == N
    assert report["slider_changes_picture"]
    assert report["draw_ms"] < 250, report["draw_ms"]  # smooth: a picture (trails included) per frame


# --------------------------------------------------------------------------------- pieces


def test_envelope_keeps_extremes_and_bounds_points():
    t = np.linspace(0, 1, 10_001)
    y = np.sin(40 * t)
    y[7777] = 5.0
    tt, yy = viewer.envelope(t, y, 500)
    assert len(tt) == len(yy) <= 500
    assert np.all(np.diff(tt) >= 0)
    assert yy.max() == 5.0 and np.isclose(yy.min(), y.min())
    tt, yy = viewer.envelope(t[:100], y[:100], 500)  # short series pass through
    assert np.array_equal(yy, y[:100])


def test_frame_budget():
    t = np.linspace(0, 1, 100_000)
    assert len(viewer.frame_indices(t, 2)) == viewer.MAX_FRAMES
    assert len(viewer.frame_indices(t, 1000)) <= viewer.MAX_POINT_FRAMES // 1000
    assert len(viewer.frame_indices(t, 10**6)) == viewer.MIN_FRAMES
    assert np.array_equal(viewer.frame_indices(t[:50], 3), np.arange(50))


def test_view_basis():
    circle = np.stack([np.cos(np.linspace(0, 3, 50)), np.sin(np.linspace(0, 3, 50)), np.zeros(50)], axis=1)
    basis, names, planar = viewer.view_basis(circle[:, None, :])
    assert planar and names[:2] == ["x", "y"] and np.allclose(basis, np.eye(3))
    # a vertical plane y = 0 under gravity along −z: x to the right, z up the screen
    upright = circle[:, [0, 2, 1]]
    basis, names, planar = viewer.view_basis(upright[:, None, :], up=[0, 0, 1])
    assert planar and np.allclose(basis[1], [0, 0, 1]) and np.isclose(abs(basis[0][0]), 1)
    # 3-D: up stays up, the frame is right-handed and orthonormal
    s = np.linspace(0, 9, 80)
    helix = np.stack([np.cos(s), np.sin(s), s / 9], axis=1)
    basis, _, planar = viewer.view_basis(helix[:, None, :], up=[0, 0, 1])
    assert not planar and basis[1][2] > 0.8
    assert np.allclose(basis @ basis.T, np.eye(3)) and np.isclose(np.linalg.det(basis), 1.0)


def test_view_basis_of_two_positions_on_no_coordinate_plane():
    """A free particle's 0.05 s saved at its two ends (an IndexError refused the run's outputs)."""
    two = np.array([[[0.0, 0.0, 0.0]], [[0.05, 0.1, -0.02]]])
    for up in (None, [0, 0, 1]):
        basis, _, planar = viewer.view_basis(two, up=up)
        assert planar and np.allclose(basis @ basis.T, np.eye(3)) and np.isclose(np.linalg.det(basis), 1.0)
        line = two[1, 0] - two[0, 0]
        assert abs(basis[2] @ line) < 1e-12 * np.linalg.norm(line)  # seen across the motion's line


def test_floor_grid_lies_under_the_motion_and_names_its_axes():
    # 3-D under gravity along −y: a level floor (y = the lowest point), lines along x and z
    s = np.linspace(0, 9, 80)
    helix = np.stack([np.cos(s), s / 9 - 0.3, np.sin(s)], axis=1)[:, None, :]
    basis, _, planar = viewer.view_basis(helix, up=[0, 1, 0])
    grid = viewer.floor_grid(helix, basis, planar, up=[0, 1, 0])
    ends = np.array(grid["lines"]).reshape(-1, 3)
    assert np.allclose(ends[:, 1], -0.3) and grid["normal"] == [0.0, 1.0, 0.0]
    step = grid["step"]
    assert np.allclose(np.round(ends[:, [0, 2]] / step), ends[:, [0, 2]] / step)  # whole steps
    assert ends[:, 0].min() <= -1 + 1e-9 and ends[:, 0].max() >= 1 - 1e-9  # the motion's extent
    assert sorted(a[2] for a in grid["axes"]) == ["x", "z"]
    assert {n[1] for n in grid["names"]} == {"x [m]", "z [m]"}
    for point, text in grid["ticks"]:  # each number is the coordinate (x or z) where it stands
        assert np.isclose(float(text), point[0], atol=1e-9) or np.isclose(float(text), point[2], atol=1e-9)
    # planar, in the vertical plane z = 0.5: graph paper in that plane
    circle = np.stack([np.cos(s), np.sin(s), np.full_like(s, 0.5)], axis=1)[:, None, :]
    basis, _, planar = viewer.view_basis(circle)
    grid = viewer.floor_grid(circle, basis, planar)
    assert planar and np.allclose(np.array(grid["lines"]).reshape(-1, 3)[:, 2], 0.5)


# --------------------------------------------------------------------------------- bad input


def _truncated(dp_run: Path, tmp_path: Path) -> Path:
    data = (dp_run / "trajectory.npz").read_bytes()
    path = tmp_path / "truncated.npz"
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(zipfile.BadZipFile):
        zipfile.ZipFile(path)
    return path


@pytest.mark.parametrize("case", ["missing", "truncated", "not npz", "no x", "scene missing", "scene bad key",
                                  "scene other particles", "set without scene", "out is a directory",
                                  "out under a file"])
def test_view_bad_input_exits_2_with_one_line(case, dp_run, tmp_path, capsys):
    run = dp_run / "trajectory.npz"
    out = tmp_path / "page.html"
    args: list[str] = []
    if case == "missing":
        run = tmp_path / "nothere.npz"
    elif case == "truncated":
        run = _truncated(dp_run, tmp_path)
    elif case == "not npz":
        run = tmp_path / "text.npz"
        run.write_text("t,x\n0,1\n")
    elif case == "no x":
        run = tmp_path / "nox.npz"
        np.savez(run, t=np.arange(3.0))
    elif case == "scene missing":
        args = ["--scene", str(tmp_path / "nothere.toml")]
    elif case == "scene bad key":
        bad = tmp_path / "bad.toml"
        bad.write_text(SCENE.read_text().replace("[simulate]", "[simulate]\nfrobnicate = 3", 1))
        args = ["--scene", str(bad)]
    elif case == "scene other particles":
        args = ["--scene", str(ROOT / "scenarios" / "simple_pendulum.toml")]
    elif case == "set without scene":
        args = ["--set", "simulate.t_end=1"]
    elif case == "out is a directory":
        out = tmp_path / "adir"
        out.mkdir()
    elif case == "out under a file":
        (tmp_path / "afile").write_text("x")
        out = tmp_path / "afile" / "page.html"
    capsys.readouterr()
    assert main(["view", str(run), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err and "\n" not in err and "Traceback" not in err, err
    assert err.startswith("constrained: ")
    if case == "scene other particles":
        assert "simple_pendulum.toml" in err and "(bob)" in err and "p1, p2" in err, err
    if case not in ("out is a directory",):
        assert not out.exists()
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".part")]


def test_bad_input_leaves_an_existing_page_alone(dp_run, tmp_path):
    page = tmp_path / "page.html"
    page.write_text("the page from before")
    assert main(["view", str(_truncated(dp_run, tmp_path)), "--out", str(page), "--quiet"]) == 2
    assert page.read_text() == "the page from before"
    assert main(["view", str(dp_run), "--out", str(page), "--quiet"]) == 0
    assert page.read_text(encoding="utf-8").startswith("<!DOCTYPE html>")


def test_scene_outputs_plots_knows_viewer(tmp_path):
    scene = C.load_scene(SCENE, ['outputs.plots=["viewer", "energy"]'])
    assert scene.outputs["plots"] == ["viewer", "energy"]
    with pytest.raises(C.InputError, match="viewr"):
        C.load_scene(SCENE, ['outputs.plots=["viewr"]'])
