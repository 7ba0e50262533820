"""Results as people expect them (issue 32): SciPy's success/status/message, arrays by name,
pandas and xarray tables with names and units, Jupyter displays, examples in help()."""

from __future__ import annotations

import html
import inspect
import re
import sys

import numpy as np
import pytest
from conftest import ROOT, SCENARIOS

import constrained as C

G = 9.81


def pendulum(length: float = 0.8, mass: float = 0.3) -> C.System:
    """A pendulum in the plane z = 0, released horizontally at rest."""
    return C.System(
        [C.Particle("bob", mass, [length, 0.0, 0.0])],
        [C.Distance("bob", point=[0, 0, 0], length=length, name="rod"), C.Plane("bob", [0, 0, 1])],
        [C.Gravity([0, -G, 0])],
        name="pendulum",
    )


# --- SciPy's habits ---------------------------------------------------------------------------


def test_a_finished_run_says_so_as_scipy_does():
    traj = C.simulate(pendulum(), 1.0)
    assert traj.success is True and traj.status is C.Status.COMPLETED
    assert traj.message == "the run reached t_end"


def test_a_terminal_event_ends_the_run_successfully_and_is_named():
    """The bob released horizontally crosses the bottom (x = 0) after a quarter period of the
    large swing; a terminal event there ends a successful run, as solve_ivp's status 1."""
    bottom = C.Event("bottom", lambda t, x, v: x[0], direction=-1, terminal=True)
    traj = C.simulate(pendulum(), 5.0, events=[bottom])
    assert traj.success and traj.status is C.Status.EVENT
    assert traj.message.startswith("the terminal event 'bottom' at t = ")
    assert float(traj.message.split("t = ")[1].split()[0]) == pytest.approx(traj.t[-1], rel=1e-5)
    assert abs(traj.x[-1, 0, 0]) < 1e-9


def test_a_failed_run_keeps_its_trajectory_with_the_reason():
    with pytest.raises(C.SimulationError) as caught:
        C.simulate(pendulum(), 5.0, max_steps=5)
    traj = caught.value.trajectory
    assert traj.success is False and traj.status is C.Status.STEP_LIMIT
    assert traj.message == str(caught.value) and "max_steps" in traj.message


def test_status_survives_a_saved_file(tmp_path):
    traj = C.simulate(pendulum(), 0.5)
    traj.save(tmp_path / "t.npz")
    back = C.Trajectory.load(tmp_path / "t.npz")
    assert back.success and back.status is C.Status.COMPLETED and back.message == traj.message


def test_arrays_by_name():
    traj = C.simulate(pendulum(), 0.5, outputs={"multipliers"})
    assert traj["x"] is traj.x and traj["t"] is traj.t and traj["multipliers"] is traj.multipliers
    assert traj.keys() == ["t", "x", "v", "multipliers"] and "x" in traj and "energy" not in traj
    with pytest.raises(KeyError, match="did not compute 'energy'"):
        traj["energy"]
    with pytest.raises(KeyError, match="no array 'X'"):
        traj["X"]


# --- tables: pandas and xarray -----------------------------------------------------------------


def test_to_pandas_names_particles_and_units_and_holds_the_physics():
    """The columns x_bob, y_bob hold the rod's length; the rod's multiplier λ (N: a distance row is
    in metres) gives the tension −λ = m (g cos θ + v²/L) (radial balance), with cos θ = −y/L."""
    pd = pytest.importorskip("pandas")
    L, m = 0.8, 0.3
    traj = C.simulate(pendulum(L, m), 1.0, t_eval=np.linspace(0, 1, 21))
    df = traj.to_pandas()
    assert isinstance(df, pd.DataFrame) and df.index.name == "t" and len(df) == 21
    assert {"x_bob", "y_bob", "z_bob", "vx_bob", "Fx_bob", "lambda[rod]", "energy"} <= set(df.columns)
    units = df.attrs["units"]
    assert units["t"] == "s" and units["x_bob"] == "m" and units["vy_bob"] == "m/s"
    assert units["Fy_bob"] == "N" and units["lambda[rod]"] == "N" and units["energy"] == "J"
    np.testing.assert_allclose(np.hypot(df["x_bob"], df["y_bob"]), L, atol=1e-9)
    speed2 = df["vx_bob"] ** 2 + df["vy_bob"] ** 2
    tension = m * (G * (-df["y_bob"] / L) + speed2 / L)
    np.testing.assert_allclose(-df["lambda[rod]"], tension, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(df["x_bob"].to_numpy(), traj.x[:, 0, 0])


def test_to_xarray_has_named_coordinates_and_units():
    xr = pytest.importorskip("xarray")
    traj = C.simulate(pendulum(), 0.5, t_eval=np.linspace(0, 0.5, 11))
    ds = traj.to_xarray()
    assert isinstance(ds, xr.Dataset)
    assert list(ds["particle"].values) == ["bob"] and list(ds["axis"].values) == ["x", "y", "z"]
    assert list(ds["constraint"].values) == traj.constraint_labels
    assert ds["x"].attrs["units"] == "m" and ds["t"].attrs["units"] == "s"
    assert ds["multipliers"].attrs["units"] == "N" and ds["energy"].attrs["units"] == "J"
    np.testing.assert_array_equal(ds["x"].sel(particle="bob", axis="y").values, traj.x[:, 0, 1])
    assert ds.attrs["message"] == "the run reached t_end"


@pytest.mark.parametrize("method, module", [("to_pandas", "pandas"), ("to_xarray", "xarray")])
def test_a_missing_optional_library_says_how_to_install_it(monkeypatch, method, module):
    traj = C.simulate(pendulum(), 0.2)
    monkeypatch.setitem(sys.modules, module, None)  # import fails as if not installed
    with pytest.raises(ImportError) as caught:
        getattr(traj, method)()
    text = str(caught.value)
    assert f"Trajectory.{method} needs {module}" in text
    assert "pip install 'constrained-particles[data]'" in text and f"pip install {module}" in text


# --- Jupyter -------------------------------------------------------------------------------------


def _text(markup: str) -> str:
    return html.unescape(re.sub(r"<[^>]+>", " ", markup))


def test_notebook_display_of_a_trajectory_scene_system_and_run():
    scene = C.load_scene(SCENARIOS / "double_pendulum.toml")
    system_html = scene.system._repr_html_()
    assert "particle p1" in _text(system_html) and "1 kg" in _text(system_html)
    assert "distance p1–p2 = 1 m" in _text(system_html) and "gravity" in _text(system_html)
    scene_html = _text(scene._repr_html_())
    assert "double_pendulum.toml" in scene_html and "t_end = 10.0" in scene_html
    assert "energy_drift" in scene_html and "method = dopri" in scene_html
    run = scene.run(["simulate.t_end=0.5"])
    run_html = run._repr_html_()
    assert "3 of 3 checks pass" in _text(run_html) and "completed: the run reached t_end" in _text(run_html)
    frame = re.search(r'<iframe srcdoc="([^"]*)"', run_html)
    assert frame, run_html[:300]
    page = html.unescape(frame.group(1))  # the viewer page, with the scene's constraints drawn
    assert page.startswith("<!DOCTYPE html>") and '"constraints":' in page
    traj_html = run.trajectory._repr_html_()
    assert "<iframe" in traj_html and "max constraint residual [m]" in _text(traj_html)


def test_a_view_that_fails_is_a_note_not_a_traceback(monkeypatch):
    from constrained import notebook

    def broken(obj, **options):
        raise RuntimeError("no canvas here")

    monkeypatch.setitem(notebook.VIEWS, "viewer", broken)
    markup = C.simulate(pendulum(), 0.2)._repr_html_()
    assert "viewer not shown: RuntimeError: no canvas here" in markup and "status" in _text(markup)


@pytest.mark.slow
def test_the_inline_viewer_draws_in_a_browser(tmp_path):
    """The notebook's cell, as a page: the iframe's viewer draws the pendulum (ink where the
    frame is, at 1280 × 800)."""
    from test_viewer import CHROMIUM, IN_CI, screenshot

    if CHROMIUM is None:
        if IN_CI:
            pytest.fail("chromium is not installed")
        pytest.skip("no chromium on this machine")
    run = C.load_scene(SCENARIOS / "double_pendulum.toml").run(["simulate.t_end=1"])
    page = tmp_path / "cell.html"
    page.write_text(f"<!DOCTYPE html><html><body style='margin:0'>{run._repr_html_()}</body></html>",
                    encoding="utf-8")
    image = screenshot(CHROMIUM, page, "", tmp_path / "cell.png")
    table_height = 0.35  # the summary table first, then the frame below it
    frame = image[int(table_height * image.shape[0]):, :, :3]
    assert np.mean(np.any(frame < 0.9, axis=-1)) > 0.02  # the viewer drew something


# --- help() shows an example ------------------------------------------------------------------------


@pytest.mark.parametrize("obj", [C.load_scene, C.System, C.Trajectory],
                         ids=["load_scene", "System", "Trajectory"])
def test_help_shows_an_example_that_runs(obj, monkeypatch):
    doc = inspect.getdoc(obj)
    head, _, block = doc.partition("::\n")
    assert "Example" in head and block, doc
    lines = []
    for line in block.splitlines():
        if line.strip() and not line.startswith("    "):
            break
        lines.append(line[4:])
    code = "\n".join(lines)
    assert "import constrained as C" in code
    monkeypatch.chdir(ROOT)  # the examples name scenarios/ as a user in a checkout does
    namespace: dict = {}
    exec(compile(code, f"<example of {obj.__name__}>", "exec"), namespace)  # noqa: S102
