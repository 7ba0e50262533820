"""Start-up cost, --version/--quiet on every verb, and the progress display of `run` (issue 19)."""

from __future__ import annotations

import io
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from interrupting import env as _env

import constrained as C
from constrained.cli.main import PLOT_KINDS, build_parser, main

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
HEAVY = ("casadi", "matplotlib", "scipy")




def _imported(code: str) -> set[str]:
    """Top-level package names a fresh interpreter imports to run ``code`` (-X importtime)."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-c", code], capture_output=True, text=True,
                          env=_env(), cwd=ROOT, check=True)
    names = re.findall(r"^import time:\s+\d+ \|\s+\d+ \|\s*(\S+)$", proc.stderr, flags=re.M)
    assert names, proc.stderr[:500]
    return {n.split(".")[0] for n in names} | set(names)


def test_import_constrained_imports_nothing_heavy():
    names = _imported("import constrained")
    assert "constrained" in names
    assert not [h for h in HEAVY if h in names], sorted(h for h in HEAVY if h in names)


def test_cli_help_imports_nothing_heavy():
    names = _imported("import sys; from constrained.cli.main import main; "
                      "sys.argv = ['constrained', '--help']\ntry:\n    main()\nexcept SystemExit:\n    pass")
    assert "constrained.cli.main" in names
    assert not [h for h in (*HEAVY, "numpy") if h in names]


def test_a_small_dopri_run_imports_no_scipy():
    """The first call in a new process (docs/performance.md, "Fresh call"): a lean dopri run of
    the double pendulum needs NumPy, CasADi and constrained only (the redundancy test at its
    start once imported scipy.sparse to ask whether J was a SciPy matrix: 0.2 s)."""
    names = _imported("import constrained as C\nsc = C.load_scene('scenarios/double_pendulum.toml')\n"
                      "C.simulate(sc.system, 2.0, t_eval=[0, 2], outputs=set())")
    assert "casadi" in names and "scipy" not in names, sorted(n for n in names if n.startswith("scipy"))[:5]


def test_public_names_still_resolve_lazily():
    # every name of __all__ is reachable, simulate is the function even after its module loaded
    for name in C.__all__:
        assert getattr(C, name) is not None, name
    import constrained.run.simulate  # noqa: F401  (the submodule of the same name)

    assert callable(C.simulate) and C.simulate.__name__ == "simulate"
    with pytest.raises(AttributeError):
        C.no_such_name  # noqa: B018


def test_version_flag_prints_the_package_version(capsys):
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert C.__version__ == version
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"constrained {version}"
    proc = subprocess.run([sys.executable, "-m", "constrained.cli", "--version"], capture_output=True,
                          text=True, env=_env(), cwd=ROOT)
    assert proc.returncode == 0 and proc.stdout.strip() == f"constrained {version}"


def test_every_verb_takes_quiet():
    parser = build_parser()
    verbs = parser._subparsers._group_actions[0].choices
    missing = [name for name, sub in verbs.items()
               if not any("--quiet" in a.option_strings for a in sub._actions)]
    assert not missing, f"verbs without --quiet: {missing}"


@pytest.mark.parametrize("argv", [
    ["check", str(SCENARIOS / "four_bar_linkage.toml")],
    ["derive", str(SCENARIOS / "simple_pendulum.toml")],
])
def test_quiet_check_and_derive_print_nothing(argv, capsys):
    assert main(argv) == 0
    assert capsys.readouterr().out.strip()  # loud without --quiet
    assert main([*argv, "--quiet"]) == 0
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""


def test_quiet_derive_still_reports_a_wrong_equation(capsys):
    code = main(["derive", str(SCENARIOS / "simple_pendulum.toml"), "--quiet", "--equation", "th_ddot = 0"])
    out = capsys.readouterr()
    assert code == 1 and out.out == "" and "WRONG" in out.err


def test_quiet_crosscheck_writes_the_figure_and_prints_nothing(tmp_path, capsys):
    assert main(["crosscheck", str(SCENARIOS / "simple_pendulum.toml"), "--set", "simulate.t_end=0.5",
                 "--out", str(tmp_path), "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    assert (tmp_path / "crosscheck.png").stat().st_size > 1000


def test_plot_kinds_of_the_cli_match_the_plot_module():
    from constrained.output.plot import KINDS

    assert tuple(PLOT_KINDS) == tuple(KINDS)


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_bar_appears_on_a_terminal_after_the_delay_and_covers_writing(monkeypatch):
    """The bar is tqdm's, shown only on a terminal; its delay counts from the start of the run
    and the writing stage (figures, animation frames) has a bar of its own."""
    from constrained.cli import main as cli

    terminal = _Terminal()
    monkeypatch.setattr(cli._progress, "DELAY", 0.0)
    monkeypatch.setattr(cli._progress, "MININTERVAL", 0.0)
    with cli._progress(False, 0.0, 2.0, stream=terminal) as progress:
        progress(1.0)
        progress(2.0)
        progress.stage("writing", 3, unit="file")
        for _ in range(3):
            progress.advance()
    text = terminal.getvalue()
    assert "simulating" in text and "t = 2 of 2 s" in text
    assert "writing" in text and "3/3 files" in text

    quiet, pipe = _Terminal(), io.StringIO()  # --quiet, or not a terminal: nothing
    for stream, is_quiet in ((quiet, True), (pipe, False)):
        with cli._progress(is_quiet, 0.0, 1.0, stream=stream) as progress:
            progress(1.0)
            progress.stage("writing", 1)
            progress.advance()
        assert stream.getvalue() == ""


def test_progress_waits_for_the_delay(monkeypatch):
    from constrained.cli import main as cli

    terminal = _Terminal()
    with cli._progress(False, 0.0, 1.0, stream=terminal) as progress:  # DELAY = 2 s: a quick run
        progress(0.5)
        progress(1.0)
    assert terminal.getvalue() == ""


def test_run_leaves_matplotlib_to_the_figure_process(tmp_path):
    """The figures of a run are drawn by a forked helper that imports matplotlib while the run
    simulates; the run itself must not import it too (0.25 s on its critical path)."""
    scene, out = str(SCENARIOS / "double_pendulum.toml"), str(tmp_path / "out")
    code = ("import sys\nfrom constrained.cli.main import main\n"
            f"code = main(['run', {scene!r}, '--out', {out!r}, '--quiet', '--set', 'simulate.t_end=0.2',"
            " '--set', 'expect.energy_drift=1e-6'])\n"
            "print(code, 'matplotlib' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), cwd=ROOT,
                          timeout=300)
    assert proc.stdout.split()[-2:] == ["0", "False"], proc.stdout + proc.stderr
    assert sorted(p.name for p in (tmp_path / "out").glob("*.png")) == [
        "constraint_residual.png", "energy.png", "trajectory.png"]
