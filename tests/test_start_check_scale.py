"""The start check of a large scene's effects (session 14): one evaluation of F and V.

Every constraint row, and every effect's term and gradients, must be finite at the initial state:
a 1/r potential at r = 0 is refused at load time with the item's key. The effects were checked
one by one in SX (each term and its gradients in one Function): 0.43 s of CasADi Jacobians for
a 100 × 100 cloth's 19,602 springs. A large model (the vectorized build) whose effects are
potentials alone now evaluates F = −∂V/∂x and the energy once: finite, every term and gradient
is (a sum is finite only when its terms are); otherwise the item-by-item check names the culprit.
"""

from __future__ import annotations

import pytest

import constrained as C
from constrained.errors import SceneError
from constrained.model import regularity

N, LINK = 120, 0.01  # 360 coordinates: the vectorized build


def _scene(tmp_path, extra: str = "") -> str:
    lines = [f'[[particles]]\nname = "p{i}"\nmass = {0.01 + 0.001 * (i % 7)}\n'
             f"position = [{(i + 1) * LINK}, 0.0, 0.0]\n" for i in range(N)]
    lines.append('[[constraints]]\ntype = "distance"\na = "p0"\npoint = [0.0, 0.0, 0.0]\n'
                 f"length = {LINK}\n")
    lines += [f'[[constraints]]\ntype = "distance"\na = "p{i - 1}"\nb = "p{i}"\nlength = {LINK}\n'
              for i in range(1, N)]
    lines += [f'[[effects]]\ntype = "spring"\na = "p{i}"\nb = "p{i + 2}"\nk = 3.0\nrest = {2 * LINK}\n'
              for i in range(0, N - 2, 3)]
    lines.append('[[effects]]\ntype = "gravity"\ng = [0.0, -9.81, 0.0]\n')
    lines.append(extra)
    lines.append("[simulate]\nt_end = 0.01\n")
    path = tmp_path / "rope.toml"
    path.write_text("\n".join(lines))
    return path


def _count_item_checks(monkeypatch) -> list:
    calls = []
    original = regularity._start_check

    def counted(structure):
        calls.append(structure)
        return original(structure)

    monkeypatch.setattr(regularity, "_start_check", counted)
    return calls


def test_a_large_scene_of_finite_potentials_builds_no_per_effect_check(tmp_path, monkeypatch):
    calls = _count_item_checks(monkeypatch)
    scene = C.load_scene(_scene(tmp_path))
    assert scene.system.n_particles == N and calls == []


def test_a_potential_undefined_at_the_start_is_still_named(tmp_path, monkeypatch):
    calls = _count_item_checks(monkeypatch)
    # a 1/r attraction centred exactly on bead p57: infinite there
    extra = '[[effects]]\ntype = "central"\na = "p57"\npoint = [0.58, 0.0, 0.0]\nexpr = "-1e-6/r"\n'
    with pytest.raises(SceneError) as refused:
        C.load_scene(_scene(tmp_path, extra))
    springs = len(range(0, N - 2, 3))
    assert f"effects[{springs + 1}]" in str(refused.value)  # after the springs and gravity
    assert "undefined at the initial state" in str(refused.value)
    assert len(calls) == 1  # the item-by-item check, where something is not finite


def test_a_force_that_is_not_a_potential_keeps_the_per_effect_check(tmp_path, monkeypatch):
    calls = _count_item_checks(monkeypatch)
    C.load_scene(_scene(tmp_path, '[[effects]]\ntype = "damping"\ncoefficient = 0.01\n'))
    assert len(calls) == 1
