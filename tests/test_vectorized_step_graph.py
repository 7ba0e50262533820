"""What dopri's step graph on the vectorized build is made of, built cheaper (issue 28) with the
same numbers: the potential terms' forces summed in one C loop (``vectorized.sums``: the bits of
``columns.Summation``, the same additions in the same order, signed zeros included), in the
build's F and in a dopri run of a cloth with springs; the step's short circuit at the output
time built as a Switch directly (``dopri.skipping``)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import test_vectorized as tv

import constrained as C
from constrained.codegen import compiled
from constrained.manifold.vectorized import build as vb
from constrained.manifold.vectorized.columns import Summation
from constrained.manifold.vectorized.sums import summation_loop
from constrained.model.structure import assemble
from constrained.solvers import dopri

needs_compiler = pytest.mark.skipif(not compiled.enabled(), reason="no C compiler")


def _same_bits(a, b):
    a, b = np.asarray(a, float).ravel(), np.asarray(b, float).ravel()
    assert np.array_equal(a, b, equal_nan=True)
    assert np.array_equal(np.signbit(a), np.signbit(b))  # (−0.0 where the Summation gives it)


@needs_compiler
@pytest.mark.parametrize("negated", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_loop_adds_what_the_summation_adds_bit_for_bit(seed, negated):
    """Streams of uneven lengths (one of a single entry), a target named twice in one stream,
    targets nobody names, values of every scale and signed zeros: the columns' bits."""
    rng = np.random.default_rng(seed)
    n_targets = 40
    lengths = [17, 1, 9, 30, 6]
    targets = [rng.integers(0, n_targets - 5, k) for k in lengths]  # (the last five: nobody's)
    targets[3][:10] = np.arange(0, 30, 3)  # (evenly stepping: no table read)
    loop = summation_loop(lengths, targets, n_targets, negated=negated)
    assert loop is not None
    streams = [ca.MX.sym(f"s{j}", k) for j, k in enumerate(lengths)]
    total = Summation(lengths, targets, n_targets)(streams)
    columns = ca.Function("columns", streams, [-total if negated else total])
    for trial in range(4):
        values = [rng.standard_normal(k) * 10.0 ** rng.integers(-8, 9, k) for k in lengths]
        for v in values:
            v[rng.random(len(v)) < 0.3] = 0.0
            v[rng.random(len(v)) < 0.3] *= -0.0 if trial % 2 else 1.0
        _same_bits(loop(*values), columns(*values))


def _sprung_cloth(k: int) -> C.System:
    """``test_vectorized.cloth`` with shear springs of uneven stiffness both ways and uneven masses."""
    s = tv.cloth(k)
    for i in range(k - 1):
        for j in range(k - 1):
            stiffness = 0.5 + 0.1 * np.sin(i + 3 * j)
            s.add(C.Spring(f"q{i}_{j}", f"q{i + 1}_{j + 1}", k=stiffness, rest=0.014),
                  C.Spring(f"q{i + 1}_{j}", f"q{i}_{j + 1}", k=2 * stiffness, rest=0.0142))
    return s


SYSTEMS = {"sprung cloth": lambda: _sprung_cloth(6), "rope with extras": tv.SYSTEMS["rope with extras"],
           "cloth": tv.SYSTEMS["cloth"]}


@needs_compiler
@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_the_builds_forces_are_the_columns_bit_for_bit(name, monkeypatch):
    """F of the build (springs and gravity; the rest's spring, damping and pair force added)
    with the loop and with the Summation."""
    system = SYSTEMS[name]()
    model = assemble(system, reuse=False)
    b = vb.vectorized_build(model.structure)
    assert b.force_sum() is not None
    x, v, t = tv._state(model, system)
    forces = {}
    for label in ("loop", "columns"):
        if label == "columns":
            monkeypatch.setattr(vb.VectorizedBuild, "force_sum", lambda self: None)
        X, V, T = ca.MX.sym("x", model.n_coordinates), ca.MX.sym("v", model.n_coordinates), ca.MX.sym("t")
        P = ca.MX.sym("p", len(model.parameter_vector))
        F = b.evaluate(X, V, T, P, (), forces_too=True)["F"]
        names = {f.name() for f in ca.Function("F", [X, V, T, P], [F]).find_functions()}
        assert any(n.startswith("sums_") for n in names) == (label == "loop")
        forces[label] = ca.Function("F", [X, V, T, P], [F])(x, v, t, model.parameter_vector)
    _same_bits(forces["loop"], forces["columns"])


@needs_compiler
def test_a_dopri_run_of_a_sprung_cloth_is_the_same_with_the_loop_and_without(monkeypatch):
    """A 10 x 10 cloth with springs (300 coordinates: the step in the virtual machine, its
    forces varying with x): the same trajectory to the last bit."""
    runs, steps = {}, []
    original = dopri.Dopri._step_function

    def keep(self, *args, **kwargs):
        steps.append(original(self, *args, **kwargs))
        return steps[-1]
    monkeypatch.setattr(dopri.Dopri, "_step_function", keep)
    for label in ("loop", "columns"):
        if label == "columns":
            monkeypatch.setattr(vb.VectorizedBuild, "force_sum", lambda self: None)
        system = _sprung_cloth(10)
        runs[label] = C.simulate(system, 0.003, model=assemble(system, reuse=False), rtol=1e-6, atol=1e-8)
        assert runs[label].stats["evaluation"] == "virtual machine"
        names = {f.name() for f in steps[-1].find_functions()}
        assert any(n.startswith("sums_") for n in names) == (label == "loop")
    a, b = runs["loop"], runs["columns"]
    assert a.stats["steps"] == b.stats["steps"] > 1
    _same_bits(a.x, b.x)
    _same_bits(a.v, b.v)


@pytest.mark.parametrize("direct", [False, True])
def test_the_direct_switch_is_the_short_circuit(direct):
    """``skipping``: S where done, else the attempt's S, and the attempt not evaluated where
    done (its NaN for a state it cannot take is never seen) — as ``ca.if_else``'s short circuit."""
    S = ca.MX.sym("s", 4)
    attempt = ca.Function("attempt", [S], [ca.vertcat(S[0] + S[1], ca.sqrt(S[1]) * 3, S[2] - 1, 1 / S[3])])
    S2 = ca.MX.sym("s", 4)
    step = dopri.skipping("step", S2, S2[2] >= S2[3], attempt, direct=direct)
    short = dopri.skipping("step", S2, S2[2] >= S2[3], attempt, direct=False)
    for state in ([1.0, 4.0, 0.5, 2.0], [1.0, -4.0, 3.0, 2.0], [2.0, 9.0, -1.0, 0.0], [0.0, -1.0, 0.0, 0.0]):
        out = np.array(step(state)).ravel()
        _same_bits(out, np.array(short(state)).ravel())
        if state[2] >= state[3]:
            _same_bits(out, state)
        assert not np.isnan(out).any()  # (the attempt's sqrt(−1) and 1/0 never taken)
    chain = step.mapaccum("chain", 3)
    _same_bits(chain([1.0, 4.0, 0.5, 2.0]), short.mapaccum("chain", 3)([1.0, 4.0, 0.5, 2.0]))
