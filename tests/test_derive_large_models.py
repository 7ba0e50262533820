"""`derive` of models too large for SymPy to simplify in a bounded time (a chain of links in
spherical angles): the printout must end, with every printed formula equal to the model's, and
summarize what it cannot print instead of simplifying it for minutes (a 50-link chain took
10 minutes and ended in SymPy's RecursionError; 3 links took 40 s)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import sympy

import constrained as C
from constrained.analysis import printing
from constrained.analysis.derivation import describe, describe_conserved
from constrained.run.reduced import ReducedModel


def _chain_scene(tmp_path, links: int):
    """``links`` beads of 0.1 kg hanging in 3-D from the origin on rods of length l, in the polar
    and azimuthal angle of each rod: the map of bead k sums k + 1 terms."""
    lines = ["[parameters]", "l = 0.1", "g = 9.81"]
    for i in range(links):
        lines += ["[[particles]]", f"name = 'p{i}'", "mass = 0.1",
                  f"position = [{0.1 * (i + 1)!r}, 0.0, 0.0]", "velocity = [0.0, 0.0, 0.0]"]
    lines += ["[[constraints]]", "type = 'distance'", "a = 'p0'", "point = [0.0, 0.0, 0.0]", "length = 'l'"]
    for i in range(1, links):
        lines += ["[[constraints]]", "type = 'distance'", f"a = 'p{i - 1}'", f"b = 'p{i}'", "length = 'l'"]
    lines += ["[[effects]]", "type = 'gravity'", "g = [0.0, 0.0, '-g']", "[reduced]"]
    coordinates = [c for i in range(links) for c in (f"t{i}", f"f{i}")]
    x = y = z = "0"
    bead_map = []
    for i in range(links):
        x, y, z = (f"{x} + l*sin(t{i})*cos(f{i})", f"{y} + l*sin(t{i})*sin(f{i})", f"{z} - l*cos(t{i})")
        bead_map.append(f"p{i} = ['{x}', '{y}', '{z}']")
    lines += ["coordinates = [" + ", ".join(f"'{c}'" for c in coordinates) + "]",
              "initial = {" + ", ".join(f"t{i} = 1.5707963267948966, f{i} = 0.0" for i in range(links)) + "}",
              "rates = {" + ", ".join(f"{c} = 0.1" for c in coordinates) + "}",
              "map = {" + ", ".join(bead_map) + "}"]
    path = tmp_path / f"chain{links}.toml"
    path.write_text("\n".join(lines) + "\n")
    return C.load_scene(path)


def _value(formula: str, rm, q, q_dot) -> float:
    """A printed formula at the state (q, q̇), l = 0.1 m, g = 9.81 m/s²."""
    expr = sympy.sympify(formula.replace("^", "**"))
    values = {"l": 0.1, "g": 9.81}
    for j, c in enumerate(rm.coordinates):
        values[c], values[f"{c}_dot"] = q[j], q_dot[j]
    return float(expr.subs({s: values[str(s)] for s in expr.free_symbols}))


def test_a_ten_link_chain_is_described_without_simplifying_what_is_not_printed(tmp_path, monkeypatch):
    rm = ReducedModel.from_scene(_chain_scene(tmp_path, 10))
    simplified = []
    trigsimp = sympy.trigsimp
    monkeypatch.setattr(sympy, "trigsimp", lambda e, *a, **k: simplified.append(e) or trigsimp(e, *a, **k))
    lines = describe(rm).splitlines()
    assert lines[-1] == "… (truncated)" and len(lines) == 3  # T alone is 14,000 characters
    # the 20 momenta and 20 equations past the 4000 characters were not handed to SymPy at all
    assert len(simplified) <= 3
    # printed whole, T, V, L and the momenta are the model's at a random state
    lines = describe(rm, max_chars=10**7).splitlines()
    rng = np.random.default_rng(3)
    q, q_dot = rng.uniform(-1, 1, len(rm.coordinates)), rng.uniform(-1, 1, len(rm.coordinates))
    ex = rm.expressions
    model = ca.Function("TVLp", [rm.q, rm.q_dot, rm.t], [ca.vertcat(ex["T"], ex["V"], ex["L"], ex["p"])])
    names = ["T", "V", "L", *[f"p_{c}" for c in rm.coordinates]]
    values = dict(zip(names, np.asarray(model(q, q_dot, 0.0)).ravel(), strict=True))
    printed = dict(line.split(" = ", 1) for line in lines if line.split(" = ", 1)[0] in values)
    assert set(printed) == set(names)
    for name, formula in printed.items():
        assert abs(_value(formula, rm, q, q_dot) - values[name]) <= 1e-12 * max(1.0, abs(values[name])), name


def test_long_chain_lists_the_angular_momentum_about_its_vertical_and_its_energy(tmp_path):
    rm = ReducedModel.from_scene(_chain_scene(tmp_path, 10))
    text = describe_conserved(rm)
    (lz,) = [line.strip() for line in text.splitlines() if line.strip().startswith("L_z = ")]
    formula, _, why = lz[len("L_z = "):].partition("  (")
    assert why.startswith("rotation about the z axis through (0, 0, 0) is a symmetry")
    rng = np.random.default_rng(4)
    q, q_dot = rng.uniform(-1, 1, len(rm.coordinates)), rng.uniform(-1, 1, len(rm.coordinates))
    ex = rm.expressions
    xv = ca.Function("xv", [rm.q, rm.q_dot, rm.t], [ex["x"], ex["x_dot"]])
    x, v = (np.asarray(a).reshape(-1, 3) for a in xv(q, q_dot, 0.0))
    assert abs(_value(formula, rm, q, q_dot) - 0.1 * np.cross(x, v)[:, 2].sum()) < 1e-12  # Σ m (x × v)_z
    (h,) = [line for line in text.splitlines() if line.strip().startswith("h = ")]
    assert "h = T + V, the energy" in h


def test_a_polynomial_that_expands_beyond_bounds_is_not_expanded():
    x = ca.SX.sym("x")
    nested = x
    for _ in range(60):  # (x² + x)² … : 2^60 terms expanded, 122 operations as a graph
        nested = nested * nested + nested
    assert printing.pretty(nested) == "(an expression of 122 operations, too long to print)"
    small = x
    for _ in range(3):
        small = small * small + small
    assert printing.pretty(small) == "x^8 + 4*x^7 + 8*x^6 + 10*x^5 + 9*x^4 + 6*x^3 + 3*x^2 + x"
