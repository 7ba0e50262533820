"""Rods too short for the positions to resolve (session 18).

A rod of length 1e-320 (a subnormal), 5e-324 or 1e-20 m among coordinates of metres holds its two
ends on one point as far as doubles can tell: the rod's direction, and so its force, is 0/0. A
generated scene with such a rod ended, with `rodas`, in NumPy's bare "SVD did not converge"
traceback, and with `dopri` in a stop blaming a taut self-stressed set. It is now refused at
the scene's start check (`check` and `run`, exit 2, the rod's key `constraints[k].length`) and by
`simulate` from Python; a NaN Jacobian in the dense Schur solve gives NaN, not LAPACK's error.
"""

from __future__ import annotations

import numpy as np
import pytest

import constrained as C
from constrained.cli.main import main
from constrained.errors import InconsistentStateError
from constrained.manifold import dense
from constrained.scene.load import load_scene

LINK = 0.1


def _chain(n: int, short: int, length: float, *, gap: float | None = None) -> str:
    """A horizontal chain of n beads in z = 0, p0 pinned, rods of LINK but rod ``short`` of
    ``length``; the beads are LINK apart (``gap``: rod ``short``'s beads that far apart)."""
    lines, x = [], 0.0
    for i in range(n):
        if i:
            x += gap if (gap is not None and i - 1 == short) else LINK
        lines.append(f'[[particles]]\nname = "p{i}"\nmass = 1.0\nposition = [{x!r}, 0.0, 0.0]\n')
    lines.append('[[constraints]]\nname = "pivot"\ntype = "pin"\na = "p0"\npoint = [0, 0, 0]\n')
    lines += [f'[[constraints]]\nname = "rod{i}"\ntype = "distance"\na = "p{i}"\nb = "p{i + 1}"\n'
              f"length = {(length if i == short else LINK)!r}\n" for i in range(n - 1)]
    beads = ", ".join(f'"p{i}"' for i in range(n))
    lines.append(f'[[constraints]]\nname = "plane"\ntype = "plane"\nparticles = [{beads}]\n'
                 "normal = [0, 0, 1]\n")
    lines.append('[[effects]]\ntype = "gravity"\ng = [0, -9.81, 0]\n')
    lines.append("[simulate]\nt_end = 0.05\nmax_initial_correction = 1000.0\n")
    return "\n".join(lines)


@pytest.mark.parametrize("n, length", [(2, 1e-320), (2, 5e-324), (30, 1e-310), (30, 1e-20),
                                       (400, 1e-320)])
@pytest.mark.parametrize("verb", ["check", "run"])
def test_a_rod_too_short_to_resolve_is_refused_naming_its_length(tmp_path, capsys, n, length, verb):
    short = n // 2 if n > 2 else 0
    scene = tmp_path / "chain.toml"
    scene.write_text(_chain(n, short, length))
    extra = ["--out", str(tmp_path / "out"), "--quiet"] if verb == "run" else []
    assert main([verb, str(scene), *extra]) == 2
    err = capsys.readouterr().err
    assert f"key constraints[{short + 1}].length: a rod of length {length:.3g} m" in err
    assert f"'p{short}' and 'p{short + 1}' on one point" in err and "Traceback" not in err


@pytest.mark.parametrize("method", ["dopri", "rodas", "baumgarte"])
def test_simulate_refuses_the_rod_naming_it(tmp_path, method):
    (tmp_path / "chain.toml").write_text(_chain(30, 15, 1e-20))
    system = load_scene(tmp_path / "chain.toml", equations=False).system
    with pytest.raises(InconsistentStateError, match="constraint 'rod15': a rod of length 1e-20 m"):
        C.simulate(system, 0.05, method=method, max_initial_correction=1000.0)


def test_beads_starting_a_subnormal_apart_are_refused_too(tmp_path, capsys):
    scene = tmp_path / "chain.toml"
    scene.write_text(_chain(2, 0, 1e-320, gap=1e-320))  # p1 at x = 1e-320: its rod's |d|² is 0
    assert main(["check", str(scene)]) == 2
    assert "constraints[1].length: a rod of length 1e-320 m" in capsys.readouterr().err


def test_a_short_rod_the_positions_resolve_still_runs(tmp_path):
    """A 1 µm rod between beads of a 3 m chain: resolved to 1e-10 of its length; it holds."""
    (tmp_path / "chain.toml").write_text(_chain(30, 15, 1e-6, gap=1e-6))
    trajectory, _ = load_scene(tmp_path / "chain.toml").run()
    x = trajectory.x[-1]
    assert np.linalg.norm(x[16] - x[15]) == pytest.approx(1e-6, rel=1e-6)


def test_a_jacobian_that_is_not_finite_gives_nan_not_a_lapack_error():
    J = np.array([[np.nan, 0.0, 0.0], [0.0, 1.0, 0.0]])
    y = dense.schur_solve(J, np.ones(3), np.ones(2))
    assert y.shape == (2,) and np.all(np.isnan(y))
