"""Compiled evaluation: machine code gives the virtual machine's results; settings are honoured."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import double_pendulum

import constrained as C
from constrained.codegen import compiled
from constrained.manifold.manifold import Manifold


def chain(n: int) -> C.System:
    s = C.System(name=f"chain of {n}")
    for i in range(n):
        s.add_particle(f"p{i}", 1.0 + 0.1 * i, [(i + 1) * np.sin(0.5), -(i + 1) * np.cos(0.5), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=1.0))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=1.0))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    return s


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))


needs_cc = pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler on this machine")


@needs_cc
def test_compiled_rattle_matches_the_virtual_machine():
    t = np.linspace(0, 2, 11)
    vm = C.simulate(double_pendulum(), 2.0, method="rattle", dt=1e-3, t_eval=t, compiled=False)
    mc = C.simulate(double_pendulum(), 2.0, method="rattle", dt=1e-3, t_eval=t, compiled=True)
    assert vm.stats["evaluation"] == "virtual machine" and mc.stats["evaluation"] == "compiled"
    np.testing.assert_allclose(mc.x, vm.x, atol=1e-12, rtol=0)
    np.testing.assert_allclose(mc.v, vm.v, atol=1e-12, rtol=0)


@needs_cc
def test_compiled_projection_matches_the_virtual_machine_on_a_chain():
    t = np.linspace(0, 0.5, 6)
    vm = C.simulate(chain(12), 0.5, rtol=1e-9, atol=1e-11, t_eval=t, compiled=False)
    mc = C.simulate(chain(12), 0.5, rtol=1e-9, atol=1e-11, t_eval=t, compiled=True)
    assert mc.stats["evaluation"] == "compiled"
    np.testing.assert_allclose(mc.x, vm.x, atol=1e-12, rtol=0)
    np.testing.assert_allclose(mc.multipliers, vm.multipliers, atol=1e-9, rtol=0)
    assert len(list((compiled.cache_dir()).glob("*.so"))) >= 1  # cached on disk


def test_the_environment_turns_compilation_off(monkeypatch):
    monkeypatch.setenv("CONSTRAINED_COMPILE", "0")
    tr = C.simulate(double_pendulum(), 0.1, method="rattle", dt=1e-3, compiled=True)
    assert tr.stats["evaluation"] == "virtual machine"


def test_without_a_compiler_the_virtual_machine_is_used(monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    model = C.assemble(double_pendulum())
    assert Manifold(model, compiled=True).evaluation == "virtual machine"
    assert "no C compiler" in compiled.last_error
    # the run still goes, in the virtual machine
    tr = C.simulate(double_pendulum(), 0.2, method="rattle", dt=1e-3, compiled=True, model=model)
    assert tr.stats["evaluation"] == "virtual machine"
    assert np.max(tr.constraint_residual) <= 1e-10


def test_bad_compiled_setting_is_refused():
    with pytest.raises(C.InputError, match="compiled must be"):
        C.simulate(double_pendulum(), 0.1, compiled="sometimes")


@needs_cc
def test_cvodes_base_runs_on_a_compiled_model():
    t = np.linspace(0, 0.3, 4)
    kw = dict(method="projection", base="CVODES", rtol=1e-9, atol=1e-11, t_eval=t)
    vm = C.simulate(chain(12), 0.3, compiled=False, **kw)
    mc = C.simulate(chain(12), 0.3, compiled=True, **kw)
    assert mc.stats["evaluation"] == "compiled"
    np.testing.assert_allclose(mc.x, vm.x, atol=1e-12, rtol=0)


@needs_cc
def test_generated_helpers_are_not_exported_so_they_can_be_inlined(tmp_path):
    """CasADi's generated helpers (``NAME_sq``, ``NAME_copy``, …) are global functions; built
    into a shared library with default visibility, every call of them went through the PLT
    and none was inlined (a pair kernel ran 2x slower). The library exports the entry points
    CasADi loads and nothing of the helpers, and evaluates as the virtual machine does."""
    import ctypes

    import casadi as ca

    x = ca.SX.sym("x", 3)
    f = ca.Function("visibility_probe", [x], [ca.dot(x, x) ** 2, ca.sqrt(x[0] ** 2 + x[1] ** 2)])
    (machine,) = compiled.compile_functions([f])
    assert machine.class_name() == "External"
    (library,) = list((tmp_path / "cache").glob("visibility_probe_*.so"))
    lib = ctypes.CDLL(str(library))
    assert hasattr(lib, "visibility_probe") and hasattr(lib, "visibility_probe_n_in")
    assert not hasattr(lib, "visibility_probe_sq")  # the helper: hidden, inlined
    point = [0.3, -1.2, 2.0]
    for got, want in zip(machine(point), f(point), strict=True):
        assert float(got) == pytest.approx(float(want), rel=1e-15)
