"""Scene files: loading, --set overrides, and one clear SceneError per kind of bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from constrained.defaults import DEFAULT_METHOD
from constrained.errors import InputError
from constrained.model.constraints import Distance, Plane
from constrained.model.effects import Gravity
from constrained.scene.load import SceneError, apply_overrides, load_scene

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
DOUBLE_PENDULUM = SCENARIOS / "double_pendulum.toml"

BASE = """\
[scene]
name = "two beads"

[[particles]]
name = "p1"
mass = 1.0
position = [1.0, 0.0, 0.0]

[[particles]]
name = "p2"
mass = 2.0
position = [1.0, -1.0, 0.0]

[[constraints]]
type = "distance"
a = "p1"
point = [0.0, 0.0, 0.0]
length = 1.0

[[constraints]]
type = "distance"
a = "p1"
b = "p2"
length = 1.0

[[effects]]
type = "gravity"
g = [0.0, -9.81, 0.0]
"""


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def expect_error(path: Path, key: str | None, *fragments: str, overrides=None) -> SceneError:
    """load_scene must refuse with a one-paragraph message naming the file and ``key``."""
    with pytest.raises(SceneError) as info:
        load_scene(path, overrides)
    err = info.value
    message = str(err)
    assert isinstance(err, InputError)
    assert err.file == str(path)
    assert f"scene file {path}" in message
    assert "\n" not in message
    if key is not None:
        assert err.key == key, message
        assert f"key {key}:" in message
    for fragment in fragments:
        assert fragment in message, message
    return err


# --- the shipped scene ------------------------------------------------------------------------


def test_double_pendulum_scene_loads():
    scene = load_scene(DOUBLE_PENDULUM)
    system = scene.system
    assert scene.name == "double pendulum"
    assert scene.path == DOUBLE_PENDULUM
    assert system.names == ["p1", "p2"]
    np.testing.assert_array_equal(system.masses, [1.0, 1.0])
    np.testing.assert_allclose(
        system.positions, [[0.9092974268, 0.4161468365, 0.0], [1.5077695709, 1.2172904521, 0.0]]
    )
    np.testing.assert_array_equal(system.velocities, np.zeros((2, 3)))
    assert [type(c) for c in system.constraints] == [Distance, Distance, Plane]
    assert system.constraints[0].point == [0.0, 0.0, 0.0] and system.constraints[0].b is None
    assert system.constraints[1].b == "p2"
    assert system.constraints[2].particles == ["p1", "p2"]
    assert len(system.effects) == 1 and isinstance(system.effects[0], Gravity)
    s = scene.settings
    assert s["t_end"] == 10.0 and s["rtol"] == 1e-10 and s["atol"] == 1e-10
    # no method named: a newcomer's first run takes the default (and its advertised speed)
    assert s["method"] == DEFAULT_METHOD == "dopri" and s["t_start"] == 0.0 and s["samples"] is None
    assert scene.outputs == {
        "quantities": ["multipliers", "constraint_forces", "energy", "constraint_residual"],
        "plots": ["trajectory", "energy", "constraint_residual"],
        "formats": ["npz"],
    }
    assert scene.reduced["coordinates"] == ["th1", "th2"]
    assert scene.reduced["initial"] == {"th1": 2.0, "th2": 2.5}
    assert scene.reduced["map"]["p2"][1] == "-cos(th1) - cos(th2)"
    assert scene.expect["energy_drift"] == 1e-9
    assert [c["kind"] for c in scene.expectations] == ["energy_drift", "constraint_residual", "closed_form"]


def test_defaults_of_a_minimal_scene(tmp_path):
    path = write(tmp_path, '[[particles]]\nname = "a"\nmass = 2\nposition = [0, 0, 1]\n', "ball.toml")
    scene = load_scene(path)
    assert scene.name == "ball"
    assert scene.settings["t_end"] is None
    assert scene.settings["rtol"] == 1e-8 and scene.settings["atol"] == 1e-10
    assert scene.settings["base"] == "DOP853" and scene.settings["max_initial_correction"] == 1e-3
    assert scene.outputs["quantities"] == [
        "multipliers",
        "constraint_forces",
        "energy",
        "constraint_residual",
    ]
    assert scene.outputs["plots"] == [] and scene.outputs["formats"] == ["npz"]
    assert scene.reduced is None
    np.testing.assert_array_equal(scene.system.velocities, [[0.0, 0.0, 0.0]])


def test_all_constraint_and_effect_types_build(tmp_path):
    text = (
        BASE
        + """
[parameters]
k = 3.0

[[constraints]]
type = "plane"
particles = "p2"
normal = [0, 0, 1]

[[constraints]]
type = "custom"
expr = "z_p1 - 0.1*sin(t)"
name = "lift"

[[effects]]
type = "spring"
a = "p1"
b = "p2"
k = "k"
rest = 0.5

[[effects]]
type = "central"
a = "p2"
point = ["cos(t)", 0, 0]
expr = "-1/r"

[[effects]]
type = "damping"
coefficient = 0.1

[[effects]]
type = "force"
particle = "p1"
expr = ["-vx_p1", "0", 1]

[[effects]]
type = "electromagnetic"
charges = { p1 = 1e-3 }
A = ["-y/2", "x/2", "0"]

[[effects]]
type = "potential"
expr = "k*z_p2**2"
"""
    )
    scene = load_scene(write(tmp_path, text))
    assert len(scene.system.constraints) == 4 and len(scene.system.effects) == 7
    assert scene.system.constraints[3].label == "lift"
    assert scene.system.parameters == {"k": 3.0}


# --- overrides -----------------------------------------------------------------------------


def test_overrides_by_name_index_and_section():
    scene = load_scene(
        DOUBLE_PENDULUM,
        [
            "simulate.t_end=2",
            "particles.p1.mass=2",
            "particles[1].position=[0,1,0]",
            "effects[0].g=[0, -1.62, 0]",
            "simulate.method=projection",
        ],
    )
    assert scene.settings["t_end"] == 2.0
    np.testing.assert_array_equal(scene.system.masses, [2.0, 1.0])
    np.testing.assert_array_equal(scene.system.positions[1], [0.0, 1.0, 0.0])
    assert scene.system.effects[0].g == [0.0, -1.62, 0.0]
    assert scene.raw["simulate"]["t_end"] == 2


def test_apply_overrides_copies_and_parses_toml_values():
    raw = {"particles": [{"name": "p1", "mass": 1.0}], "parameters": {"k": 1.0}}
    out = apply_overrides(
        raw,
        ["parameters.k=3", 'particles.p1.note="sin(t)"', "simulate.method=rattle", "x.y=[1, 0]"],
    )
    assert out["parameters"]["k"] == 3 and raw["parameters"]["k"] == 1.0
    assert out["particles"][0]["note"] == "sin(t)"
    assert out["simulate"]["method"] == "rattle"  # a bare word is a string
    assert out["x"]["y"] == [1, 0]
    assert "note" not in raw["particles"][0]


# --- bad input: each kind its own test ---------------------------------------------------


def test_unknown_key(tmp_path):
    path = write(tmp_path, BASE.replace("mass = 2.0", "mass = 2.0\nmas = 3"))
    expect_error(path, "particles[1].mas", "unknown key 'mas'", "mass, position, velocity")


def test_unknown_key_in_simulate(tmp_path):
    path = write(tmp_path, BASE + "\n[simulate]\nt_end = 1\nrtoll = 1e-6\n")
    expect_error(path, "simulate.rtoll", "unknown key 'rtoll'", "did you mean 'rtol'")


def test_unknown_top_level_table(tmp_path):
    path = write(tmp_path, BASE + "\n[simulation]\nt_end = 1\n")
    expect_error(path, "simulation", "unknown top-level table 'simulation'", "simulate")


def test_missing_mass(tmp_path):
    path = write(tmp_path, BASE.replace("mass = 2.0\n", ""))
    expect_error(path, "particles[1].mass", "missing required key 'mass'")


@pytest.mark.parametrize("mass", ["0", "-1", "0.0"])
def test_non_positive_mass(tmp_path, mass):
    path = write(tmp_path, BASE.replace("mass = 2.0", f"mass = {mass}"))
    expect_error(path, "particles[1].mass", "must be a finite positive number", f"got {mass}")


def test_non_numeric_mass(tmp_path):
    # a string is a formula of the parameters: an unknown name is refused, naming it
    path = write(tmp_path, BASE.replace("mass = 2.0", 'mass = "heavy"'))
    expect_error(path, "particles[1].mass", "unknown name 'heavy'")
    path = write(tmp_path, BASE.replace("mass = 2.0", "mass = true"))
    expect_error(path, "particles[1].mass", "the boolean true")


def test_duplicate_particle_name(tmp_path):
    path = write(tmp_path, BASE.replace('name = "p2"', 'name = "p1"'))
    expect_error(path, "particles[1].name", "duplicate particle name 'p1'")


def test_constraint_naming_unknown_particle(tmp_path):
    path = write(tmp_path, BASE.replace('b = "p2"', 'b = "p3"'))
    expect_error(path, "constraints[1].b", "unknown particle 'p3'", "p1, p2")


def test_effect_naming_unknown_particle(tmp_path):
    extra = '\n[[effects]]\ntype = "damping"\ncoefficient = 1\nparticles = ["p1", "q"]\n'
    path = write(tmp_path, BASE + extra)
    expect_error(path, "effects[1].particles[1]", "unknown particle 'q'")


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_non_finite_number(tmp_path, value):
    path = write(tmp_path, BASE.replace("position = [1.0, -1.0, 0.0]", f"position = [1.0, {value}, 0.0]"))
    expect_error(path, "particles[1].position[1]", "not finite")


def test_non_finite_number_where_a_formula_is_allowed(tmp_path):
    path = write(tmp_path, BASE.replace("length = 1.0\n\n[[effects]]", "length = nan\n\n[[effects]]"))
    expect_error(path, "constraints[1].length", "not finite")


def test_formula_with_unknown_name(tmp_path):
    path = write(tmp_path, BASE + '\n[[constraints]]\ntype = "custom"\nexpr = "z_p1 - zeta"\n')
    expect_error(path, "constraints[2].expr", "unknown name 'zeta'")


def test_formula_in_point_with_unknown_name(tmp_path):
    path = write(tmp_path, BASE.replace("point = [0.0, 0.0, 0.0]", 'point = [0.0, "w*t", 0.0]'))
    expect_error(path, "constraints[0].point[1]", "unknown name 'w'")


@pytest.mark.parametrize(
    ("formula", "fragment"),
    [
        ("x.__class__", "attribute access"),
        ("__import__('os')", "function '__import__' is not allowed"),
        ("open(1)", "function 'open' is not allowed"),
    ],
)
def test_formula_with_forbidden_construct(tmp_path, formula, fragment):
    text = BASE + f'\n[[constraints]]\ntype = "surface"\nparticles = "p2"\nexpr = "{formula}"\n'
    path = write(tmp_path, text)
    expect_error(path, "constraints[2].expr", fragment)


def test_wrong_vector_length(tmp_path):
    path = write(tmp_path, BASE.replace("position = [1.0, 0.0, 0.0]", "position = [1.0, 0.0]"))
    expect_error(path, "particles[0].position", "list of 3 numbers", "got 2 entries")


def test_wrong_vector_length_of_gravity(tmp_path):
    path = write(tmp_path, BASE.replace("g = [0.0, -9.81, 0.0]", "g = [0.0, -9.81]"))
    expect_error(path, "effects[0].g", "list of 3")


def test_unknown_constraint_type(tmp_path):
    path = write(tmp_path, BASE.replace('type = "distance"', 'type = "distanse"', 1))
    expect_error(path, "constraints[0].type", "unknown constraint type 'distanse'", "pin, plane")


def test_unknown_effect_type(tmp_path):
    path = write(tmp_path, BASE.replace('type = "gravity"', 'type = "gravitation"'))
    expect_error(path, "effects[0].type", "unknown effect type 'gravitation'", "spring")


def test_distance_needs_b_or_point(tmp_path):
    path = write(tmp_path, BASE.replace('b = "p2"', 'b = "p2"\npoint = [0, 0, 0]'))
    expect_error(path, "constraints[1]", "exactly one of 'b'")


def test_invalid_toml_gives_line_and_column(tmp_path):
    path = write(tmp_path, BASE.replace("mass = 1.0", "mass = = 1.0"))
    err = expect_error(path, None, "not valid TOML", "line 6, column 8")
    assert err.key is None


def test_missing_file(tmp_path):
    expect_error(tmp_path / "nothere.toml", None, "no such file")


def test_simulate_ranges(tmp_path):
    path = write(tmp_path, BASE + "\n[simulate]\nt_end = 1\nrtol = 1.5\n")
    expect_error(path, "simulate.rtol", "between 0 and 1")


def test_unknown_output_quantity(tmp_path):
    path = write(tmp_path, BASE + '\n[outputs]\nquantities = ["energy", "momentum"]\n')
    expect_error(path, "outputs.quantities[1]", "unknown quantity 'momentum'", "velocity_residual")


def test_reduced_map_must_cover_every_particle(tmp_path):
    text = BASE + (
        '\n[reduced]\ncoordinates = ["q"]\ninitial = { q = 0.0 }\nmap = { p1 = ["cos(q)", "sin(q)", 0] }\n'
    )
    expect_error(write(tmp_path, text), "reduced.map.p2", "not mapped")


# --- bad --set -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("override", "key", "fragment"),
    [
        ("simulate.t_end", "simulate.t_end", "expected KEY=VALUE"),
        ("simulate..t_end=1", "simulate..t_end", "not a key path"),
        ("particles.p9.mass=1", "particles.p9.mass", "no entry named 'p9'"),
        ("particles[7].mass=1", "particles[7].mass", "out of range"),
        ("simulate.tend=1", "simulate.tend", "unknown key 'tend'"),
        ("particles.p1.mass=-2", "particles[0].mass", "--set particles.p1.mass=-2"),
        ("sim.t_end=1", "sim", "unknown top-level table 'sim'"),
    ],
)
def test_bad_set_key(tmp_path, override, key, fragment):
    path = write(tmp_path, BASE)
    expect_error(path, key, fragment, overrides=[override])


# --- [expect] ---------------------------------------------------------------------------------

EXPECT_BASE = """
[[particles]]
name = "p"
mass = 1.0
position = [1.0, 0.0, 0.0]

[[constraints]]
type = "distance"
a = "p"
point = [0.0, 0.0, 0.0]
length = 1.0
"""


def test_expect_section_is_normalized(tmp_path):
    text = EXPECT_BASE + """
[expect]
energy_drift = 1e-8
closed_form = { "x_p" = ["cos(t)", 1e-6] }
final = { "Fx_p" = [0, 1e-9] }
bounds = { "z_p" = [-inf, 0.5] }
conserved = { Lz = { axis = [0, 0, 1], tol = 1e-9 } }
"""
    scene = load_scene(write(tmp_path, text))
    kinds = [c["kind"] for c in scene.expectations]
    assert kinds == ["energy_drift", "final", "closed_form", "bounds", "conserved"]
    assert scene.expectations[3]["lo"] == float("-inf")
    assert scene.expectations[4]["rotation"] == ([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    "body, key, fragment",
    [
        ("energy_drfit = 1e-8", "expect.energy_drfit", "did you mean 'energy_drift'"),
        ("energy_drift = -1", "expect.energy_drift", "tolerance >= 0"),
        ('closed_form = { "x_q" = ["t", 1e-6] }', "expect.closed_form.x_q", "unknown name 'x_q'"),
        ('closed_form = { "x_p" = ["t"] }', "expect.closed_form.x_p", "[value or formula, tolerance]"),
        ('final = { "x_p" = ["__import__(1)", 1] }', "expect.final.x_p[0]", "not allowed"),
        ('bounds = { "x_p" = [1, 0] }', "expect.bounds.x_p", "is above highest"),
        ("conserved = { L = { tol = 1e-9 } }", "expect.conserved.L", "give 'axis'"),
        ("conserved = { L = { axis = [0, 0, 1], tol = 1e-9, pivot = 1 } }", "expect.conserved.L.pivot",
         "unknown key 'pivot'"),
    ],
)
def test_bad_expect_names_file_and_key(tmp_path, body, key, fragment):
    path = write(tmp_path, EXPECT_BASE + "\n[expect]\n" + body + "\n")
    err = expect_error(path, key, fragment)
    assert str(path) in str(err)


def test_pairwise_effect_is_checked_where_it_is_written(tmp_path):
    text = """
[[particles]]
name = "a"
mass = 1.0
position = [1.0, 0.0, 0.0]

[[particles]]
name = "b"
mass = 1.0
position = [0.0, 1.0, 0.0]

[[effects]]
type = "pairwise"
particles = ["a", "a"]
expr = "1/r"
"""
    path = tmp_path / "pairs.toml"
    path.write_text(text)
    with pytest.raises(SceneError, match=r"effects\[0\].particles.*twice"):
        load_scene(path)
    path.write_text(text.replace('["a", "a"]', '["a", "c"]'))
    with pytest.raises(SceneError, match=r"effects\[0\].*'c'"):
        load_scene(path)
    path.write_text(text.replace('["a", "a"]', '["a", "b"]').replace("1/r", "1/q"))
    with pytest.raises(SceneError, match=r"effects\[0\].expr"):
        load_scene(path)


def test_a_scene_read_again_is_checked_by_content_and_shares_nothing(tmp_path):
    """load_scene keeps validated scenes by file content: an edited file is read anew, and a
    caller changing its scene does not change the next caller's."""
    from conftest import pendulum_toml

    path = tmp_path / "p.toml"
    path.write_text(pendulum_toml(1.0))
    first = load_scene(path)
    first.system.particles[0].mass = 7.0
    first.system.add_particle("extra", 1.0, [0.0, 0.0, 5.0])
    first.settings["t_end"] = 99.0
    second = load_scene(path)
    assert second.system.particles[0].mass == 1.0 and second.system.n_particles == 1
    assert second.settings["t_end"] == 1.0
    path.write_text(pendulum_toml(2.5).replace("mass = 1.0", "mass = 3.0"))
    third = load_scene(path)
    assert third.settings["t_end"] == 2.5 and third.system.particles[0].mass == 3.0
    path.write_text(pendulum_toml(1.0).replace("length = 1.0", "length = -1.0"))
    with pytest.raises(InputError, match="length"):
        load_scene(path)


def test_reading_a_scene_leaves_the_garbage_collector_as_it_found_it(tmp_path):
    """load_scene pauses Python's cyclic collector while it builds (constrained.bulk) and turns
    it back on afterwards, also when the scene is refused; a caller that had it off keeps it
    off; nested pauses end with the outer one."""
    import gc

    from constrained.bulk import collector_paused

    bad = tmp_path / "bad.toml"
    bad.write_text('[[particles]]\nname = "p"\nmass = -1.0\nposition = [0, 0, 0]\n')
    assert gc.isenabled()
    load_scene(SCENARIOS / "simple_pendulum.toml")
    assert gc.isenabled()
    with pytest.raises(SceneError):
        load_scene(bad)
    assert gc.isenabled()
    with collector_paused():
        with collector_paused():
            assert not gc.isenabled()
        assert not gc.isenabled()
    assert gc.isenabled()
    gc.disable()
    try:
        load_scene(SCENARIOS / "double_pendulum.toml")
        assert not gc.isenabled()
    finally:
        gc.enable()
