"""Every method's convergence order, measured, against the order it declares.

The problem is smooth and has a closed form: a particle on a circle of radius R (a distance
constraint and a plane) moving uniformly, x(t) = R (cos ωt, sin ωt, 0), with gravity pressing
it onto the plane so the multipliers are not trivial. Its error is a pure phase error.

- fixed-step methods: the error falls by 2^p when the step is halved;
- adaptive methods of a fixed order p: log(error) against log(steps) has slope −p (the steps
  are uniform on this problem);
- variable-order methods (SUNDIALS' BDF/Adams; ``order`` None): the error follows the
  tolerance, a slope of about 1 in log(error) against log(tolerance).
"""

import warnings

import numpy as np
import pytest

import constrained as C
from constrained.solvers import METHODS

R, OMEGA, T = 1.0, 2.0, 10.0
EXACT = np.array([R * np.cos(OMEGA * T), R * np.sin(OMEGA * T), 0.0])
TOLERANCES = [1e-4, 1e-5, 1e-6, 1e-7, 1e-8]


def circle() -> C.System:
    s = C.System(name="uniform circular motion")
    s.add_particle("p", 1.0, [R, 0, 0], [0, R * OMEGA, 0])
    s.add(C.Distance("p", point=[0, 0, 0], length=R), C.Plane("p", [0, 0, 1]), C.Gravity([0, 0, -9.81]))
    return s


def error_of(tr) -> float:
    return float(np.max(np.abs(tr.x[-1, 0] - EXACT)))


def run(method, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return C.simulate(circle(), T, method=method, outputs=[], **options)


def declared_order(method, **options) -> int | None:
    from constrained.manifold.manifold import Manifold

    model = C.assemble(circle())
    return METHODS[method](Manifold(model), **options).order


ADAPTIVE = [("projection", {}), ("projection", {"base": "RK45"}), ("projection", {"base": "Radau"}),
            ("dopri", {"compiled": False}), ("dopri", {"base": "DOPRI5", "compiled": False}),
            ("dopri", {"base": "Tsit5", "compiled": False}), ("baumgarte", {})]


@pytest.mark.parametrize("method, options", ADAPTIVE, ids=lambda v: str(v))
def test_adaptive_methods_converge_at_their_declared_order(method, options):
    p = declared_order(method, **options)
    assert isinstance(p, int) and p >= 5
    rows = []
    for tol in TOLERANCES:
        tr = run(method, rtol=tol, atol=tol, **options)
        rows.append((tr.stats["steps"], error_of(tr)))
    steps, errors = np.array(rows).T
    assert np.all(np.diff(errors) < 0), errors  # tighter tolerance, smaller error
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert 0.85 * p <= slope <= p + 2, (slope, p)


def test_rattle_is_second_order():
    assert declared_order("rattle", dt=0.01) == 2
    errors = [error_of(run("rattle", dt=dt, compiled=False)) for dt in (0.02, 0.01, 0.005)]
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    np.testing.assert_allclose(np.log2(ratios), 2.0, atol=0.1)


@pytest.mark.parametrize("method, options", [("idas", {}), ("ggl", {}), ("pantelides", {}),
                                             ("projection", {"base": "CVODES"})], ids=lambda v: str(v))
def test_variable_order_methods_follow_their_tolerance(method, options):
    assert declared_order(method, **options) is None
    errors = np.array([error_of(run(method, rtol=tol, atol=tol, **options)) for tol in TOLERANCES])
    slope = np.polyfit(np.log(TOLERANCES), np.log(errors), 1)[0]
    assert 0.6 <= slope <= 1.5, (slope, errors)
    assert errors[-1] < 1e-2 * errors[0]


def test_reduced_route_is_eighth_order():
    """On the circle the reduced equation is θ'' = 0, which every Runge–Kutta method solves
    exactly; the pendulum θ'' = −(g/L) sin θ shows the order, against SciPy at 1e-13."""
    from scipy.integrate import solve_ivp

    from constrained.run.reduced import ReducedModel

    g, th0, t_end = 9.81, 1.0, 5.0
    s = C.System(name="pendulum")
    s.add_particle("p", 1.0, [np.sin(th0), -np.cos(th0), 0.0])
    s.add(C.Distance("p", point=[0, 0, 0], length=1.0), C.Plane("p", [0, 0, 1]), C.Gravity([0, -g, 0]))
    rm = ReducedModel(s, ["th"], {"p": ["sin(th)", "-cos(th)", "0"]}, initial={"th": th0}, rates={"th": 0.0})
    assert declared_order("reduced", reduced_model=rm) == 8
    ref = solve_ivp(lambda t, y: [y[1], -g * np.sin(y[0])], (0, t_end), [th0, 0.0], method="DOP853",
                    rtol=1e-13, atol=1e-13).y[0, -1]
    exact = np.array([np.sin(ref), -np.cos(ref), 0.0])
    rows = []
    for tol in TOLERANCES:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tr = C.simulate(s, t_end, method="reduced", rtol=tol, atol=tol, reduced_model=rm, outputs=[])
        rows.append((tr.stats["nfev"], float(np.max(np.abs(tr.x[-1, 0] - exact)))))
    nfev, errors = np.array(rows).T
    slope = -np.polyfit(np.log(nfev), np.log(errors), 1)[0]
    assert 0.85 * 8 <= slope <= 10, slope
