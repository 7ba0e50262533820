"""A fit over a span where the run is chaotic: SciPy's trust region shrinks to nothing because
no step follows the linearization, and it reports `xtol` convergence at the start. The fit must
say it did not converge and why, not hand back the start with a standard error of 1e-11."""

from __future__ import annotations

import warnings

import numpy as np
from conftest import SCENARIOS

import constrained as C
from constrained.errors import LinearRangeWarning


def _double_pendulum_data(t_end: float) -> tuple[C.Scene, C.Measurements]:
    """The second bob of the double pendulum (g = 9.81, started at 2 and 2.5 rad: chaotic) every
    0.05 s, with 1 mm of noise."""
    scene = C.load_scene(SCENARIOS / "double_pendulum_parametric.toml")
    t = np.arange(0.0, t_end + 1e-9, 0.05)
    run = C.simulate(scene.system, t_end, t_eval=t, rtol=1e-12, atol=1e-13)
    noise = 1e-3 * np.random.default_rng(1).standard_normal((len(t), 2))
    return scene, C.Measurements(t, ("x_p2", "y_p2"), run.x[:, 1, :2] + noise, source="bob p2")


def test_a_fit_over_thirty_chaotic_seconds_is_not_converged_and_says_to_shorten_the_span():
    scene, data = _double_pendulum_data(30.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LinearRangeWarning)
        result = C.fit(scene.system, data, ["g"], start={"g": 9.7})
    assert not result.success  # it stayed at its start, 0.11 m/s² from the truth, with metres of misfit
    assert abs(result.estimates[0] - 9.81) > 1e3 * result.standard_errors[0]
    assert np.sqrt(np.nanmean(result.residuals**2)) > 100 * 1e-3
    assert "the sensitivities grew by g:" in result.message and "(chaotic)" in result.message
    assert "fit over a shorter span" in result.message and "NOT converged" in result.table()


def test_the_same_pendulum_over_five_seconds_fits_g_within_its_error():
    scene, data = _double_pendulum_data(5.0)
    result = C.fit(scene.system, data, ["g"], start={"g": 9.7})
    assert result.success, result.message
    assert abs(result.estimates[0] - 9.81) < 4 * result.standard_errors[0]
    assert np.sqrt(np.nanmean(result.residuals**2)) < 2e-3  # the noise, 1 mm
