"""Parameters are inputs of the CasADi functions, not constants.

A Model for other parameter values (``Model.with_parameters``, ``simulate(parameters=…)``)
shares the structure (counted: ``Structure.builds`` does not grow) and gives exactly what
the scene gives with those numbers written into its formulas (``literal_scene``)."""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.errors import InputError
from constrained.model.structure import Model, Structure, assemble
from constrained.scene.load import SceneError, build_scene

PARAMETRIC_SCENE = Path(__file__).resolve().parent.parent / "scenarios" / "double_pendulum_parametric.toml"

DOUBLE_PENDULUM = """
[scene]
name = "parametric double pendulum"

[parameters]
m1 = 1.0
m2 = 1.5
l1 = 1.0
l2 = 0.8
g = 9.81
th1 = 2.0
th2 = 2.5

[definitions]
y2 = "y1 - l2*cos(th2)"     # uses a definition written after it
y1 = "-l1*cos(th1)"

[[particles]]
name = "p1"
mass = "m1"
position = ["l1*sin(th1)", "y1", 0]

[[particles]]
name = "p2"
mass = "m2"
position = ["l1*sin(th1) + l2*sin(th2)", "y2", 0.0]

[[constraints]]
type = "distance"
a = "p1"
point = [0, 0, 0]
length = "l1"

[[constraints]]
type = "distance"
a = "p1"
b = "p2"
length = "l2"

[[constraints]]
type = "plane"
particles = ["p1", "p2"]
normal = [0, 0, 1]

[[effects]]
type = "gravity"
g = [0, "-g", 0]

[simulate]
t_end = 1.0
rtol = 1e-10
atol = 1e-12

[reduced]
coordinates = ["q1", "q2"]
initial = { q1 = 2.0, q2 = 2.5 }
[reduced.map]
p1 = ["l1*sin(q1)", "-l1*cos(q1)", "0"]
p2 = ["l1*sin(q1) + l2*sin(q2)", "-l1*cos(q1) - l2*cos(q2)", "0"]
"""

# Every kind of number an item takes, as a parameter: spring constant and rest length,
# damping coefficient, field amplitude and charge, a moving anchor's amplitude, a plane's
# offset, a pairwise potential's strength, an applied force's size.
EVERYTHING = """
[parameters]
k = 40.0
rest = 0.3
c = 0.2
E0 = 1.5
q = 0.7
A = 0.1
h = 0.05
G = 0.3
F0 = 0.4
m = 2.0

[definitions]
w = "sqrt(k/m)"

[[particles]]
name = "a"
mass = "m"
position = [1.0, 0.2, "h"]
velocity = [0.0, "0.1*w", 0.0]

[[particles]]
name = "b"
mass = 1.0
position = [0.0, -1.0, "h"]

[[constraints]]
type = "plane"
particles = ["a", "b"]
normal = [0, 0, 1]
offset = "h"

[[effects]]
type = "spring"
a = "a"
point = ["A*sin(w*t)", 0, 0]
k = "k"
rest = "rest"

[[effects]]
type = "damping"
coefficient = "c"

[[effects]]
type = "electromagnetic"
charges = { a = "q" }
phi = "-E0*x"
A = ["0", "0.5*E0*x", "0"]

[[effects]]
type = "pairwise"
expr = "-G*m/r"

[[effects]]
type = "force"
particle = "b"
expr = ["F0*cos(t)", "0", "0"]
"""


def scene(text=DOUBLE_PENDULUM, **values):
    """The scene from its text, with [parameters] changed as by --set."""
    sc = build_scene(tomllib.loads(text))
    if values:
        sc = sc.with_overrides([f"parameters.{k}={v!r}" for k, v in values.items()])
    return sc


def literal_scene(text=DOUBLE_PENDULUM, **values):
    """The reference: the scene with every parameter's value (``values`` over the file's)
    written as a number into each formula, as if the scene had no parameters."""
    raw = tomllib.loads(text)
    numbers = {**raw.get("parameters", {}), **values}

    def substitute(match):
        formula = match.group(0)
        for name, value in numbers.items():
            formula = re.sub(rf"\b{name}\b", f"({value!r})", formula)
        return formula

    raw = tomllib.loads(re.sub(r'"[^"\n]*"', substitute, text))
    raw.setdefault("parameters", {}).update(values)
    return build_scene(raw)


def random_states(model, n=5, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        yield (rng.standard_normal(model.n_coordinates), rng.standard_normal(model.n_coordinates),
               rng.uniform(0, 2))


FUNCTIONS = {  # name -> which of (x, v, t) it takes
    "constraint": "xt", "jacobian": "xt", "velocity_terms": "xt", "dynamics": "xvt",
    "energy": "xvt", "potential": "xt", "kinetic": "v",
}


def assert_same_functions(a, b, rtol=1e-14):
    """Every public Function of Models a and b gives the same values (to round-off)."""
    for x, v, t in random_states(a):
        args = {"x": x, "v": v, "t": t}
        for name, takes in FUNCTIONS.items():
            fa, fb = getattr(a, name), getattr(b, name)
            out_a = fa.call([args[k] for k in takes])
            out_b = fb.call([args[k] for k in takes])
            for oa, ob in zip(out_a, out_b, strict=True):
                np.testing.assert_allclose(np.asarray(oa), np.asarray(ob), rtol=rtol, atol=1e-14,
                                           err_msg=name)


@pytest.mark.parametrize("text, values", [
    (DOUBLE_PENDULUM, {"m1": 1.3}), (DOUBLE_PENDULUM, {"l1": 1.2, "th1": 1.0}),
    (DOUBLE_PENDULUM, {"g": 3.7}),
    (EVERYTHING, {"k": 55.0}), (EVERYTHING, {"rest": 0.1, "c": 0.0}), (EVERYTHING, {"E0": -2.0}),
    (EVERYTHING, {"q": 1.1, "A": 0.3}), (EVERYTHING, {"h": -0.2, "m": 0.5}),
    (EVERYTHING, {"G": 1.0, "F0": 0.0}),
])
def test_with_parameters_equals_rebuilding_and_builds_nothing(text, values):
    model = assemble(scene(text).system)
    before = Structure.builds
    changed = model.with_parameters(values)
    assert Structure.builds == before
    assert changed.structure is model.structure
    rebuilt = assemble(literal_scene(text, **values).system)
    assert rebuilt.structure is not model.structure
    constants = Model(rebuilt.system, structure=Structure(rebuilt.system, lift=False), numbers=np.zeros(0))
    assert all(constants.structure.fixed(name) is not None for name in FUNCTIONS)  # numbers only, no p
    assert_same_functions(rebuilt, constants)  # plain numbers as inputs = plain numbers as constants
    assert changed.parameters == rebuilt.parameters
    np.testing.assert_array_equal(changed.masses, rebuilt.masses)
    np.testing.assert_array_equal(changed.system.positions, rebuilt.system.positions)
    np.testing.assert_array_equal(changed.system.velocities, rebuilt.system.velocities)
    assert_same_functions(changed, rebuilt)
    # the parametric Functions (p last) are what the bound ones evaluate
    for x, v, t in random_states(model, 2):
        F, J, gamma = model.structure.functions["dynamics"](x, v, t, changed.parameter_vector)
        F2, J2, gamma2 = changed.dynamics(x, v, t)
        np.testing.assert_allclose(np.asarray(F), np.asarray(F2), rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(np.asarray(gamma), np.asarray(gamma2), rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("values", [{"m1": 1.3}, {"l1": 1.2, "th1": 1.0}, {"g": 3.7}])
@pytest.mark.parametrize("method", ["projection", "dopri"])
def test_a_run_with_new_parameters_ends_where_the_rebuilt_scene_does(values, method):
    system = scene().system
    model = assemble(system)
    before = Structure.builds
    run = C.simulate(system, 1.0, method=method, rtol=1e-10, atol=1e-12, model=model,
                     parameters=values)
    assert Structure.builds == before, "a Model passed back in with new parameters rebuilt"
    reference = C.simulate(literal_scene(**values).system, 1.0, method=method, rtol=1e-10, atol=1e-12)
    assert len(run.t) == len(reference.t)
    np.testing.assert_allclose(run.x[-1], reference.x[-1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(run.energy, reference.energy, rtol=1e-12, atol=1e-12)
    # the start follows the parameters: rods of the new lengths, at the new angle
    l1 = values.get("l1", 1.0)
    assert np.linalg.norm(run.x[0, 0]) == pytest.approx(l1, abs=1e-12)


def test_a_fresh_simulate_builds_the_structure_once():
    system = scene().system
    system.add(C.Spring("p1", "p2", k=123.456))  # a structure no other test has
    before = Structure.builds
    C.simulate(system, 0.2, parameters={"m2": 2.0})
    assert Structure.builds == before + 1


def test_assemble_reuses_the_structure_of_an_equal_system():
    """A scene loaded again (another System object, other values, another start) gets the
    Structure built before; any structural change builds a new one."""
    first = assemble(scene().system)
    before = Structure.builds
    again = assemble(scene(m1=2.0, th1=0.3).system)
    assert Structure.builds == before and again.structure is first.structure
    reference = assemble(scene(m1=2.0, th1=0.3).system, reuse=False)
    assert Structure.builds == before + 1
    assert_same_functions(again, reference)
    changed = [
        DOUBLE_PENDULUM.replace('length = "l2"', 'length = "l2 + 0"'),   # a formula
        DOUBLE_PENDULUM.replace('mass = "m2"', "mass = 1.5"),            # a formula -> a number
        DOUBLE_PENDULUM.replace('name = "p2"', 'name = "q2"').replace('b = "p2"', 'b = "q2"')
        .replace('particles = ["p1", "p2"]', 'particles = ["p1", "q2"]').replace("p2 = [", "q2 = ["),
        DOUBLE_PENDULUM.replace("[parameters]", "[parameters]\nunused = 1.0"),  # parameter names
    ]
    for k, text in enumerate(changed):
        model = assemble(scene(text).system)
        assert model.structure is not first.structure, k
    assert Structure.builds == before + 1 + len(changed)


def test_a_spring_period_follows_its_constant():
    """A mass on a spring with k from [parameters]: the period is 2π √(m/k) for every k."""
    text = """
[parameters]
k = 4.0
m = 1.0
[[particles]]
name = "p"
mass = "m"
position = [0.1, 0, 0]
[[effects]]
type = "spring"
a = "p"
point = [0, 0, 0]
k = "k"
"""
    system = scene(text).system
    model = assemble(system)
    for k in (4.0, 9.0, 25.0):
        period = 2 * math.pi * math.sqrt(1.0 / k)
        run = C.simulate(system, period, model=model, parameters={"k": k}, rtol=1e-11, atol=1e-13,
                         t_eval=[0.0, period / 2, period])
        np.testing.assert_allclose(run.x[1, 0], [-0.1, 0, 0], atol=1e-8)  # half a period: opposite
        np.testing.assert_allclose(run.x[2, 0], [0.1, 0, 0], atol=1e-8)


def test_masses_given_by_formulas_follow_their_parameters():
    model = assemble(scene().system)
    heavier = model.with_parameters({"m1": 3.0, "m2": 0.5})
    np.testing.assert_array_equal(heavier.masses, np.repeat([3.0, 0.5], 3))
    # gravity pulls each particle with m_i g (F is −∂V/∂x with V = −Σ m_i g·x_i)
    F = np.asarray(heavier.dynamics(np.ones(6), np.zeros(6), 0.0)[0]).ravel()
    np.testing.assert_allclose(F, [0, -3.0 * 9.81, 0, 0, -0.5 * 9.81, 0], rtol=1e-15)
    assert model.masses[0] == 1.0  # the first model is unchanged


def test_bad_parameter_values_are_refused_with_the_cause():
    model = assemble(scene().system)
    with pytest.raises(InputError, match=r"unknown parameter 'mass1' \(parameters: m1, m2, l1"):
        model.with_parameters({"mass1": 2.0})
    with pytest.raises(InputError, match="'y1' is a definition"):
        model.with_parameters({"y1": 2.0})
    with pytest.raises(InputError, match="must be a finite number, got nan"):
        model.with_parameters({"m1": float("nan")})
    with pytest.raises(InputError, match="must be a finite number"):
        model.with_parameters({"m1": "heavy"})
    with pytest.raises(InputError, match=r"mass must be a finite positive number, got -1.0 "
                                         r"\(the formula 'm1'\)"):
        model.with_parameters({"m1": -1.0})
    with pytest.raises(InputError, match="unknown parameter"):
        C.simulate(scene().system, 0.1, parameters={"nope": 1.0})


def test_definitions_are_ordered_and_a_cycle_is_refused():
    system = scene().system
    assert system.parameter_values["y2"] == pytest.approx(-math.cos(2.0) - 0.8 * math.cos(2.5), abs=0)
    cyclic = DOUBLE_PENDULUM.replace('y1 = "-l1*cos(th1)"', 'y1 = "-l1*cos(th1) + 0*z3"\nz3 = "y2"')
    with pytest.raises(SceneError, match=r"the definitions form a cycle: (y1 -> z3 -> y2 -> y1|"
                                         r"y2 -> y1 -> z3 -> y2|z3 -> y2 -> y1 -> z3)") as info:
        scene(cyclic)
    assert info.value.key.startswith("definitions.")
    with pytest.raises(SceneError, match="definitions.y1.*unknown name 'l3'"):
        scene(DOUBLE_PENDULUM.replace('"-l1*cos(th1)"', '"-l3*cos(th1)"'))
    with pytest.raises(SceneError, match="the definition name 'g' is taken"):
        scene(DOUBLE_PENDULUM.replace("[definitions]", '[definitions]\ng = "2"'))


def test_python_api_particles_take_formulas():
    system = C.System(parameters={"l": 2.0, "a": 0.5, "m": 3.0}, definitions={"s": "l*sin(a)"})
    system.add_particle(C.Particle("bob", "m", ["s", "-l*cos(a)", 0.0]))
    np.testing.assert_allclose(system.positions, [[2 * math.sin(0.5), -2 * math.cos(0.5), 0]], rtol=1e-15)
    system.set_parameter("l", 1.0)  # the particle follows
    np.testing.assert_allclose(system.positions[0, :2], [math.sin(0.5), -math.cos(0.5)], rtol=1e-15)
    moved = system.with_parameters({"a": 0.0, "m": 4.0})
    np.testing.assert_allclose(moved.positions, [[0.0, -1.0, 0.0]], atol=0)
    assert moved.masses[0] == 4.0 and system.masses[0] == 3.0
    kept = moved.with_state(np.zeros((1, 3)))
    assert kept.particles[0].formulas == {"mass": "m"}  # the mass stays a formula


def test_describe_prints_parameter_names():
    from constrained.analysis.derivation import describe

    text = describe(scene())
    assert "g*" in text and "l1" in text and "m2" in text and "9.81" not in text
    # the same equations as the numbers give: Lagrange's equations hold for each parameter set
    checks = C.check_equations(scene(g=2.0), ["(m1 + m2)*l1*q1_ddot + m2*l2*q2_ddot*cos(q1 - q2) + "
                                              "m2*l2*q2_dot**2*sin(q1 - q2) + (m1 + m2)*g*sin(q1) = 0"])
    assert checks[0].ok, checks[0].message


def test_describe_gives_latex_through_sympy():
    pytest.importorskip("sympy")
    from constrained.analysis.derivation import describe

    tex = describe(scene(), latex=True)
    assert r"\ddot{q_{1}}" in tex and "m_{2}" in tex and r"\cos" in tex


def test_scene_run_with_parameters_equals_the_overridden_scene():
    sc = scene()
    model = assemble(sc.system)
    before = Structure.builds
    run = sc.run(parameters={"l2": 0.5, "m1": 2.0}, model=model, quantities=["energy"])
    assert Structure.builds == before
    reference = sc.run(["parameters.l2=0.5", "parameters.m1=2.0"], quantities=["energy"])
    np.testing.assert_array_equal(run.trajectory.x, reference.trajectory.x)
    np.testing.assert_array_equal(run.trajectory.energy, reference.trajectory.energy)
    x = run.trajectory.x[-1]
    assert np.linalg.norm(x[1] - x[0]) == pytest.approx(0.5, abs=1e-9)


def test_cli_derive_prints_names_and_latex(capsys, tmp_path, monkeypatch):
    from constrained.cli.main import main

    path = tmp_path / "dp.toml"
    path.write_text(DOUBLE_PENDULUM)
    assert main(["derive", str(path), "--set", "parameters.g=2"]) == 0
    out = capsys.readouterr().out
    assert "equation for q1:" in out and "g*" in out and "m1" in out
    monkeypatch.setitem(__import__("sys").modules, "sympy", None)  # SymPy not installed
    assert main(["derive", str(path), "--latex"]) == 2
    assert "LaTeX output needs SymPy" in capsys.readouterr().err


def test_cli_check_lists_parameters_and_definitions(capsys, tmp_path):
    from constrained.cli.main import main

    path = tmp_path / "dp.toml"
    path.write_text(DOUBLE_PENDULUM)
    main(["check", str(path), "--set", "parameters.th1=0.5"])
    out = capsys.readouterr().out
    assert "parameters: m1 = 1, m2 = 1.5, l1 = 1, l2 = 0.8, g = 9.81, th1 = 0.5, th2 = 2.5" in out
    assert f"y1 = -l1*cos(th1) = {-math.cos(0.5):g}" in out
    assert "mass 1.5 kg (m2)" in out


def test_scene_with_parameters_is_the_overridden_scene():
    sc = scene()
    changed = sc.with_parameters({"th2": 1.0})
    assert changed.system.parameters == scene(th2=1.0).system.parameters
    np.testing.assert_array_equal(changed.system.positions, scene(th2=1.0).system.positions)
    # later overrides start from the new values, as after --set
    again = changed.with_overrides(["simulate.t_end=0.5"])
    assert again.system.parameters["th2"] == 1.0 and sc.system.parameters["th2"] == 2.5


def test_models_with_equal_values_share_their_functions():
    model = assemble(scene().system)
    a, b = model.with_parameters({"g": 2.0}), model.with_parameters({"g": 2.0})
    assert a is not b and a.dynamics is b.dynamics  # the same bound Function object
    assert model.with_parameters({"g": 3.0}).dynamics is not a.dynamics
    numbers = assemble(literal_scene().system)  # its Functions do not depend on p at all
    assert numbers.with_parameters({"g": 2.0}).dynamics is numbers.dynamics


def test_simulate_starts_from_the_given_system_for_the_new_values():
    """The Model carries the equations; the start is the system's (its own state), with
    formulas evaluated for the new values."""
    system = scene().system
    model = assemble(system)
    moved = system.with_state(np.array([[0.0, -1.0, 0.0], [0.0, -1.8, 0.0]]))  # hanging, at rest
    run = C.simulate(moved, 0.5, model=model, parameters={"g": 1.0}, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(run.x[-1], [[0.0, -1.0, 0.0], [0.0, -1.8, 0.0]], atol=1e-9)


def test_parameter_overrides_of_a_scene_read_before_match_reading_it_anew(tmp_path):
    """load_scene with only ``parameters.NAME=VALUE`` overrides takes the scene read before
    and sets the values (no second validation): the same system as reading the file with
    those numbers, and the same refusals (a start made irregular by the values)."""
    path = tmp_path / "dp.toml"
    path.write_text(PARAMETRIC_SCENE.read_text())
    quick = C.load_scene(path, ["parameters.m1=1.7", "parameters.l2=0.6"])
    text = PARAMETRIC_SCENE.read_text().replace("m1 = 1.0", "m1 = 1.7").replace("l2 = 1.0", "l2 = 0.6")
    fresh_path = tmp_path / "dp_numbers.toml"
    fresh_path.write_text(text)
    fresh = C.load_scene(fresh_path)
    np.testing.assert_array_equal(quick.system.positions, fresh.system.positions)
    np.testing.assert_array_equal(quick.system.masses, fresh.system.masses)
    assert quick.system.parameters == fresh.system.parameters
    with pytest.raises(SceneError, match="mass"):
        C.load_scene(path, ["parameters.m1=-1"])


def test_a_fresh_call_with_every_output_builds_no_kkt_graph_again(monkeypatch):
    """The call README.md's speed sentence is about: the scene read again (a new Model of the
    same structure, new values) and simulated with every derived quantity. The multipliers'
    KKT graph is built once per structure: the second call builds no acceleration graph, and
    its multipliers equal a run on a model assembled from scratch."""
    import constrained.manifold.manifold as manifold

    path = Path(__file__).resolve().parents[1] / "scenarios" / "double_pendulum_parametric.toml"
    C.simulate(C.load_scene(path).system, 0.5)

    def refuse(*args, **kwargs):
        raise AssertionError("the KKT graph was built again")

    scene = C.load_scene(path, ["parameters.m1=1.3", "parameters.l2=0.7"])
    with monkeypatch.context() as patch:
        patch.setattr(manifold, "acceleration_graph", refuse)
        tr = C.simulate(scene.system, 0.5)
    fresh = C.simulate(scene.system, 0.5, model=assemble(scene.system, reuse=False), t_eval=tr.t)
    assert np.all(np.isfinite(tr.multipliers))
    assert np.allclose(tr.multipliers, fresh.multipliers, rtol=1e-8, atol=1e-10)
    assert np.allclose(tr.action, fresh.action, rtol=1e-8, atol=1e-12)
    assert np.allclose(tr.constraint_forces, fresh.constraint_forces, rtol=1e-8, atol=1e-10)
    # and Jᵀλ is J's transpose times λ at each sample (J of the model at those values)
    model = assemble(scene.system, reuse=False)
    for k in (0, len(tr.t) // 2, len(tr.t) - 1):
        J = np.asarray(model.jacobian(tr.x[k].ravel(), tr.t[k])[1])
        assert np.allclose(tr.constraint_forces[k].ravel(), J.T @ tr.multipliers[k], rtol=1e-10, atol=1e-12)
