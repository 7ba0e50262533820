"""Shortcuts of a run's fixed cost (reading, assembling, checking a large scene) against the
long way they replace: the same expressions, numbers and refusals, on friendly and unfriendly
systems (uneven masses, time-dependent and velocity-dependent forces, no effects at all)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import structure_reference

import constrained as C
from constrained.model import lifting
from constrained.model.effects import forces
from constrained.model.structure import Structure


def _rope(n: int, *, effects=()) -> C.System:
    s = C.System(name="rope", parameters={"w": 2.0})
    for i in range(n):
        s.add_particle(f"p{i}", 0.01 * (1 + 0.5 * np.cos(i)), [0.01 * (i + 1), 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.01))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=0.01 * (1 + 0.1 * i)))
    s.add(*effects)
    return s


EFFECTS = {
    "none": (),
    "gravity": (C.Gravity([0, -9.81, 0]),),
    "springs": (C.Gravity([0, -9.81, 0]), C.Spring("p0", "p3", k=2.0, rest=0.0),
                C.Spring("p1", "p4", k=1.0, rest=0.02)),
    "time-dependent potential": (C.Spring("p0", "p3", k="1 + sin(w*t)", rest=0.02),),
    "potential of t alone": (C.Potential("sin(t)"), C.Gravity([0, -9.81, 0])),
    "damping": (C.Gravity([0, -9.81, 0]), C.Damping(0.1, ["p1", "p2"])),
    "applied force": (C.Force("p2", ["0", "-0.1*t", "0"]),),
}


def _function(e, F) -> str:
    return ca.Function("F", [e.x, e.v, e.t, e.p], [F]).serialize()


@pytest.mark.parametrize("name", EFFECTS)
def test_deferred_forces_are_the_eager_forces(name):
    """``forces(..., deferred=True)``: F and V built when asked are the expressions built at once,
    and the active terms (time-dependent forces among them) are the same."""
    e = Structure(_rope(6, effects=EFFECTS[name])).expressions
    eager = forces(e.slots, e.x, e.v, e.t)
    F, V, *deferred = forces(e.slots, e.x, e.v, e.t, deferred=True)
    assert _function(e, F()) == _function(e, eager[0])
    assert F() is F() and V() is V()  # (built once)
    for a, b in zip([V(), *deferred[:2]], eager[1:4], strict=True):
        assert _function(e, a) == _function(e, b)
    assert deferred[2] == eager[4]
    of_t = ("time-dependent potential", "potential of t alone", "applied force")
    assert ("time_dependent_forces" in eager[4]) == (name in of_t)


@pytest.mark.parametrize("name", EFFECTS)
def test_the_structures_dynamics_and_flags_follow_the_effects(name):
    """The Structure's dynamics (F from the deferred build) gives the forces of the effects."""
    system = _rope(6, effects=EFFECTS[name])
    structure = Structure(system)
    e = structure.expressions
    x, v = np.asarray(system.positions, float).ravel(), np.linspace(-0.1, 0.1, 18)
    p = np.r_[2.0, lifting.numbers(system)]
    F = np.asarray(structure.function("dynamics")(x, v, 0.3, p)[0]).ravel()
    reference = ca.Function("F", [e.x, e.v, e.t, e.p], [forces(e.slots, e.x, e.v, e.t)[0]])
    assert np.array_equal(F, np.asarray(reference(x, v, 0.3, p)).ravel())
    assert np.any(F != 0) == (name != "none")
    assert structure.forces_depend_on_velocity == (name == "damping")


def _net(n: int) -> C.System:
    """Springs of every kind: plain numbers between particles (equal and uneven masses, some of
    the same period), to a point, of a formula of t, of zero stiffness, of a parameter."""
    s = C.System(name="net", parameters={"kk": 40.0})
    for i in range(n):
        s.add_particle(f"p{i}", 0.01 * (1 + i % 3), [0.01 * i, 0.001 * (i % 2), 0.0])
    for i in range(n - 1):
        s.add(C.Spring(f"p{i}", f"p{i + 1}", k=[1.0, 1e6, 50.0, 0.0][i % 4], rest=0.011 * (i % 2)))
    s.add(C.Spring("p0", point=[0, 1, 0], k=1e5, rest=0.5), C.Spring("p2", "p5", k="kk", rest=0.03),
          C.Spring("p1", "p3", k="1e4*(2 + sin(t))", rest=0.02), C.Gravity([0, -9.81, 0]))
    return s


@pytest.mark.parametrize("limit", [0.0, 0.006, 0.05, 1.0, np.inf])
def test_stiff_springs_kept_by_period_are_the_whole_list_filtered(limit):
    """``stiff_springs(..., keep=...)`` (springs of plain numbers measured at once) is the whole
    list (each spring measured on its own) filtered by the same test: the same elements, every
    field equal, in the same order."""
    from constrained.model.structure import assemble
    from constrained.solvers.stiffness import stiff_springs

    system = _net(30)
    model = assemble(system)
    x = np.asarray(system.positions, float).ravel() * 1.01
    keep = lambda period: period * 10 < limit  # noqa: E731
    whole = [e for e in stiff_springs(model, x, 0.3) if keep(e.period)]
    kept = stiff_springs(model, x, 0.3, keep=keep)
    assert kept == whole
    assert len(whole) == {0.0: 0, 0.006: 4, 0.05: 9, 1.0: 16, np.inf: 25}[limit]


def _mixed() -> C.System:
    """Masses of numbers, of a parameter and of a formula; items with zeros, formulas, points."""
    s = C.System(name="mixed", parameters={"m": 0.3, "L": 0.5})
    s.add_particle("a", 1.0, [0.5, 0, 0])
    s.add_particle("b", "m", [1.0, 0, 0])
    s.add_particle("c", "2*m + 0.1", [1.5, 0, 0.0])
    s.add_particle("d", 0.25, [2.0, 0, 0])
    s.add(C.Distance("a", point=[0, 0, 0], length=0.5), C.Distance("a", "b", length="L"),
          C.Distance("b", "c", length=0.5), C.Plane(["a", "b", "c", "d"], [0, 0, 1], 0.0),
          C.Spring("c", "d", k=3.0, rest=0.0), C.Gravity([0, -9.81, 0]), C.Damping(0.1, ["d"]))
    return s


@pytest.mark.parametrize("make", [_mixed, lambda: _rope(8, effects=EFFECTS["springs"])],
                         ids=["mixed", "rope"])
def test_lifting_from_the_fingerprints_walk_is_lifting_anew(make):
    """``lift(system, walked)`` with the walk ``structure_data`` made for the fingerprint gives the
    lifted copy ``lift(system)`` gives: the same masses, fields and numbers."""
    system = make()
    walked: list = []
    _, values = structure_reference.structure_data(system, walked)
    reused, numbers = lifting.lift(system, tuple(walked))
    anew, reference = lifting.lift(system)
    assert np.array_equal(numbers, reference) and numbers.tolist() == values
    assert [p.mass for p in reused.particles] == [p.mass for p in anew.particles]
    for ours, theirs in zip((*reused.constraints, *reused.effects), (*anew.constraints, *anew.effects),
                            strict=True):
        assert type(ours) is type(theirs) and vars(ours) == vars(theirs)
    assert any(isinstance(p.mass, lifting.Number) for p in anew.particles)
    model_reused = Structure(system, walked=tuple(walked))
    model_anew = Structure(system)
    assert model_reused.constraint_labels == model_anew.constraint_labels
    assert _function(model_anew.expressions, model_anew.expressions.rows[1]) == _function(
        model_reused.expressions, model_reused.expressions.rows[1])


@pytest.mark.parametrize("n", [6, 150])
def test_residual_functions_built_when_asked_give_the_residuals_in_metres(n):
    """A large model's residual Functions: the row scales at once, the position and velocity
    residuals when first asked for; they are max |f_i| / s_i and max |J_i v| / s_i."""
    from constrained.manifold import residual
    from constrained.manifold.manifold import constraint_values, sparse_jacobian
    from constrained.model.structure import assemble

    system = _rope(n, effects=EFFECTS["gravity"])
    model = assemble(system)
    x = np.asarray(system.positions, float).ravel() * (1 + 1e-3 * np.sin(np.arange(3 * n)))
    v = np.cos(np.arange(3 * n))
    functions = residual.functions(model)
    large = n == 150
    assert (dict.get(functions, "position") is None) == large  # (not built yet)
    s = residual.row_scales(model, x, 0.0)
    f = np.asarray(constraint_values(model)(x, 0.0)[0]).ravel()
    J = np.asarray(ca.DM(sparse_jacobian(model)(x, 0.0)).full())
    assert residual.position_residual(model, x) == pytest.approx(np.max(np.abs(f) / s), rel=1e-12)
    velocity = residual.velocity_residual_along(model, x[None], v[None], np.zeros(1))[0]
    assert velocity == pytest.approx(np.max(np.abs(J @ v) / s), rel=1e-12)
    assert dict.get(functions, "position") is not None
    with pytest.raises(KeyError):
        functions["no such function"]
