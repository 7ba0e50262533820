"""The ``constrained`` command: ``run`` and ``check`` a scene file.

Exit status: 0 success, 1 a run that had to stop (what it computed is saved), 2 bad input
or an unwritable output folder (one-paragraph message naming the file and the key, nothing
written), 130 interrupted. Outputs go through ``outputs.OutputSet``: one consistent set per run.

This module is the parser and the dispatch, light to import (``--help``, ``--version``); the
verbs are constrained.cli_run and constrained.cli_verbs, imported when one runs.
"""

from __future__ import annotations

import argparse
import errno
import os
import re
import signal
import sys
import warnings
from collections.abc import Sequence

from .._version import __version__
from ..errors import InputError
from .text import LISTED, PROG, ReaderGone, _say_error

__all__ = ["main", "build_parser", "trajectory_csv"]  # noqa: F822 (trajectory_csv: __getattr__)

#: the kinds of ``constrained plot`` (constrained.plot.KINDS, spelled here so that --help does not
#: import matplotlib; tests/test_cli.py checks that the two agree)
PLOT_KINDS = ("trajectory", "energy", "constraint_residual", "constraint_forces", "multipliers",
              "phase", "action", "animation")

EPILOG = """\
verbs:
  run     simulate a scene; write DIR/trajectory.npz (and .csv, plots) as the scene asks
            constrained run scenarios/double_pendulum.toml --out out/dp --set simulate.t_end=2
  check   validate a scene and print DOF, rank, redundancy, initial-state consistency
            constrained check scenarios/double_pendulum.toml
  crosscheck  compare with Lagrange's equations in the [reduced] coordinates
            constrained crosscheck scenarios/double_pendulum.toml --set simulate.t_end=2
  statics equilibrium, multipliers, reactions, stability, virtual-work residual
            constrained statics scenarios/hanging_chain.toml --out out/chain
  plot    figures and animation (GIF) from a saved trajectory.npz
            constrained plot out/dp/trajectory.npz --kinds trajectory,animation
  view    one self-contained interactive HTML page of a run (works offline)
            constrained view out/dp/trajectory.npz --scene scenarios/double_pendulum.toml --out dp.html
  derive  print T, V, L, Lagrange's equations and the conserved quantities; check hand-derived
          equations, Lagrangians, generalized forces and constants of the motion (exit 1 when one
          is wrong)
            constrained derive scenarios/double_pendulum.toml --set parameters.g=9.81 \
              --equation "th2_ddot + th1_ddot*cos(th1-th2) - th1_dot**2*sin(th1-th2) + g*sin(th2) = 0"
  sweep   many runs of one scene on Dask: --vary KEY=SPEC (grid / random); summary.csv
            constrained sweep scenarios/kapitza_sweep.toml --vary "parameters.a=lin(0.002, 0.02, 12)" \
              --vary "parameters.nu=lin(20, 240, 12)" --summary "min:up=y_bob - a*cos(nu*t)"
  modes   normal modes about the equilibrium (or a steady motion in a rotating frame): frequencies,
          damping, stability, shapes; modes.json, modes.png, one mode as GIF and viewer page
            constrained modes scenarios/hanging_chain.toml --out out/chain_modes
  fit     fit [parameters] to measured data (CSV: t and observed columns) with exact Jacobians;
          estimates, standard errors, residual plots, the fitted run
            constrained fit scenarios/pendulum_fit.toml scenarios/data/pendulum_camera.csv --params l,b
  path    the motion between the scene's positions and --to in --time T, by making the
          discrete action stationary (IPOPT); minimum or saddle; path.npz, path.png
            constrained path scenarios/double_pendulum.toml --to "p1=[0,-1,0]; p2=[0,-2,0]" --time 1

--set KEY=VALUE overrides one scene key (repeatable): simulate.t_end=2,
particles.p1.mass=2 or particles[0].mass=2, parameters.k=3, effects[0].k=5.
VALUE is read as TOML (2, [1, 0, 0], "sin(t)"); a bare word is a string.

exit status: 0 done, 1 the run had to stop (partial trajectory saved),
2 bad input or an unwritable output folder (nothing written), 130 interrupted.
Each run replaces its own earlier files in --out DIR as one set (never a mix of two runs).
"""


class _Parser(argparse.ArgumentParser):
    """argparse with one-paragraph errors (``constrained: error: ...``) and exit status 2."""

    def error(self, message: str):
        verb = self.prog.split()[-1] if " " in self.prog else None
        where = f"{verb}: " if verb else ""
        missing = re.fullmatch(r"argument (--[\w-]+): expected one argument", message)
        if missing:  # argparse reads a value such as -k*x as an option
            option = missing.group(1)
            message += f"; a value that starts with '-' must be attached with '=', e.g. {option}=-k*x"
        _say_error(f"{where}{message} (see '{PROG} --help')")
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``constrained`` command."""
    parser = _Parser(
        prog=PROG,
        description="Simulate particles under holonomic constraints (constraint forces as "
        "Lagrange multipliers).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    verbs = parser.add_subparsers(dest="verb", metavar="VERB", required=True, parser_class=_Parser)

    OUT = "output directory (default: out/<scene file stem>)"
    WITH_REDUCED = "scene file (TOML) with a [reduced] section"

    _verb(verbs, "run", "simulate a scene and write its trajectory and plots",
          "Simulate SCENE and write DIR/trajectory.npz (plus trajectory.csv and the "
          "plots the scene's [outputs] asks for).",
          "run scenarios/double_pendulum.toml --out out/dp --set simulate.t_end=2", out=OUT, quiet=True)
    check = _verb(verbs, "check", "validate a scene; print DOF, redundancy and initial-state consistency",
                  "Validate SCENE without simulating: particles, constraint rows, degrees of "
                  "freedom, rank and redundancy, singular configuration, consistency of the initial "
                  "state, and the terms the model assembles. A large scene's particles and rows are "
                  f"listed up to {LISTED} each (--all: every one).",
                  "check scenarios/double_pendulum.toml", quiet=True)
    check.add_argument("--all", action="store_true", dest="list_all",
                       help="list every particle and constraint row, however many")
    _verb(verbs, "crosscheck",
          "compare the Cartesian route with Lagrange's equations in the [reduced] coordinates",
          "Run SCENE both ways from the same start (the [reduced] initial values mapped "
          "to x, v): the Cartesian route with multipliers, and Lagrange's equations in the "
          "generalized coordinates. Print the largest differences and energies; write "
          "DIR/crosscheck.png (position difference against time).",
          "crosscheck scenarios/double_pendulum.toml --set simulate.t_end=2",
          scene_help=WITH_REDUCED, out=OUT, quiet=True)
    _verb(verbs, "statics", "find the static equilibrium near the initial positions; reactions and stability",
          "Solve F(x) + Jᵀλ = 0, f(x) = 0 near the scene's initial positions (Newton on "
          "the KKT conditions): print positions, multipliers, constraint forces, support reactions, "
          "stability (tangent-space eigenvalues of the Hessian of V − λ·f, soft modes) and the "
          "virtual-work residual; write DIR/equilibrium.json and DIR/statics.png.",
          "statics scenarios/lever.toml --out out/lever", out=OUT, quiet=True)
    bench = _verb(
        verbs, "bench", "work-precision table and figure: error and drift against wall time per method",
        "Simulate SCENE with each method at each tolerance, once to warm up, then timed; write "
        "DIR/bench.csv (method, rtol, dt, error, constraint_residual, velocity_residual, energy_drift, "
        "wall_time_s, compile_time_s (the first run's one-time cost, not in wall_time_s), steps, nfev, "
        "status), DIR/bench.md and DIR/bench.png.",
        "bench scenarios/double_pendulum.toml --set simulate.t_end=2 "
        "--methods projection,rattle --tolerances 1e-8,1e-10", out=OUT, quiet=True)
    bench.add_argument("--methods", help="comma-separated methods (default: all)")
    bench.add_argument("--tolerances", help="comma-separated rtol values (default: 1e-6,1e-8,1e-10,1e-12)")
    bench.add_argument("--repeats", type=int, default=3, help="timed repeats per row, after a warm-up")
    derive = _verb(
        verbs, "derive", "print Lagrange's equations; check hand-derived equations, Lagrangians, forces, "
        "constants of the motion",
        "Without options print T, V, L, the momenta and Lagrange's equations of "
        "SCENE's [reduced] coordinates, in the names of its [parameters], and the conserved quantities "
        "found (momenta of cyclic coordinates, the energy function h when ∂L/∂t = 0 and nothing does "
        "work), or why there are none (--latex: as LaTeX, through SymPy, the 'pretty' extra). With "
        "options check each candidate at random states, "
        "and again at other values of the [parameters] it names (a slip such as l1 for l2 is "
        "invisible at l1 = l2), and print one verdict line per check (OK or WRONG with where it "
        "disagrees); exit 0 when all are right, 1 when one is wrong, 2 on bad input (also a "
        "candidate that is not finite at a sampled state).",
        "derive scenarios/double_pendulum.toml --set parameters.g=9.81 "
        "--set parameters.m=1 --set parameters.l=1 \\\n    --lagrangian \"0.5*m*l**2*(2*th1_dot**2 + "
        "th2_dot**2 + 2*th1_dot*th2_dot*cos(th1-th2)) + m*g*l*(2*cos(th1) + cos(th2))\"",
        scene_help=WITH_REDUCED, quiet=True)
    derive.add_argument("--latex", action="store_true",
                        help="print the equations as LaTeX (needs SymPy: the 'pretty' extra)")
    derive.add_argument("--equation", action="append", default=[], metavar="EQ",
                        help="an equation of motion 'lhs = rhs' in q, q_dot, q_ddot, t (repeatable)")
    derive.add_argument("--lagrangian", action="append", default=[], metavar="L",
                        help="a candidate Lagrangian in q, q_dot, t (repeatable)")
    derive.add_argument("--force", action="append", default=[], metavar="Q",
                        help="a candidate generalized force, one per coordinate in coordinate order "
                        "(repeat once per coordinate; write --force=-k*x when the formula starts with '-')")
    derive.add_argument("--conserved", action="append", default=[], metavar="C",
                        help="a candidate constant of the motion in q, q_dot, t (or 'NAME = formula'): "
                        "OK when dC/dt = 0 along the equations of motion (repeatable; write "
                        "--conserved=-C when the formula starts with '-')")
    _add_sweep(verbs)
    _add_modes_and_fit(verbs)
    _add_plot(verbs)
    _add_view(verbs)
    return parser


def _add_modes_and_fit(verbs) -> None:
    """The ``modes`` and ``fit`` verbs (constrained.cli_verbs_fit)."""
    m = _verb(
        verbs, "modes", "normal modes about an equilibrium or a steady motion; one mode animated",
        "Linearize SCENE on its constraints about the equilibrium near its positions (statics; with "
        "--at start: its initial state, which must be at rest, or steady in the --rotating frame) and "
        "solve M q'' + (G + D) q' + K q = 0: frequencies, damping ratios, stability and mode shapes as "
        "particle displacements. Write DIR/modes.json, DIR/modes.png (the shapes) and the chosen mode as "
        "DIR/mode<K>.gif and the viewer page DIR/mode<K>.html. With a [reduced] section the roots are "
        "compared with those of Lagrange's equations linearized at the same state.",
        "modes scenarios/bead_on_rotating_hoop.toml --rotating 0,0,4 "
        "--set 'particles.bead.position=[0.8,0,-0.6]'",
        out="output directory (default: out/<scene file stem>_modes)", quiet=True)
    m.add_argument("--at", choices=("equilibrium", "start"), default="equilibrium",
                   help="about the equilibrium near the scene's positions (default), or its initial state")
    m.add_argument("--rotating", metavar="WX,WY,WZ",
                   help="angular velocity (rad/s) of a frame in which the state is at rest (a steady motion)")
    m.add_argument("--frame-point", metavar="X,Y,Z", help="a point on the frame's axis (default the origin)")
    m.add_argument("--mode", type=int, metavar="K",
                   help="the mode to animate (default: the slowest oscillation)")
    m.add_argument("--amplitude", type=float, metavar="A",
                   help="the animated mode's largest displacement in metres (default 5%% of the system's "
                   "size)")
    m.add_argument("--no-animation", action="store_true", help="skip the GIF and the viewer page")
    m.add_argument("--count", type=int, metavar="K",
                   help="only the lowest K modes (a large model: a sparse solve, no dense tangent basis)")
    f = _verb(
        verbs, "fit", "fit [parameters] to measured data with exact Jacobians; standard errors, residuals",
        "Fit the [parameters] named by --params so that the run of SCENE reproduces DATA (a CSV file: a "
        "column t and one column per observable, named by its formula, e.g. x_bob, or by --observe; "
        "optional sigma_NAME columns give each value's standard deviation). Least squares (SciPy, "
        "trust region) with the Jacobian from CasADi AD through the run's steps. Print the estimates and "
        "their standard errors; write DIR/fit.json, DIR/fit.csv, DIR/fit.png, DIR/residuals.png and the "
        "fitted run DIR/trajectory.npz. Several DATA files: one fit each (here or on Dask), DIR/fits.csv. "
        "Exit 1 when a fit does not converge (its results are written).",
        "fit scenarios/pendulum_fit.toml scenarios/data/pendulum_camera.csv --params l,b --out out/fit",
        out="output directory (default: out/<scene file stem>_fit)", quiet=True)
    f.add_argument("data", nargs="+", metavar="DATA", help="CSV file(s) of measurements")
    f.add_argument("--params", required=True, metavar="P1,P2", help="comma-separated [parameters] to fit")
    f.add_argument("--observe", action="append", default=[], metavar="NAME=FORMULA",
                   help="the formula of a data column that is not a formula itself, e.g. "
                   "'theta=atan2(x_bob, -y_bob)' (repeatable)")
    f.add_argument("--sigma", type=float, metavar="S",
                   help="standard deviation of every value without a sigma_NAME column (default: estimated "
                   "from the residuals)")
    f.add_argument("--start", action="append", default=[], metavar="NAME=VALUE",
                   help="start values (default: the scene's), e.g. l=0.5,b=0.1")
    f.add_argument("--bounds", action="append", default=[], metavar="NAME=LOW:HIGH",
                   help="bounds of a fitted parameter (repeatable), e.g. l=0.1:5")
    f.add_argument("--max-runs", type=int, default=100, metavar="N", help="runs allowed (default 100)")
    f.add_argument("--scheduler", default="sequential", metavar="ADDRESS",
                   help="several DATA files: 'sequential' (default), 'local' (a local Dask cluster) or "
                   "tcp://HOST:PORT")
    f.add_argument("--workers", type=int, metavar="N", help="worker processes of the local cluster")


def _add_plot(verbs) -> None:
    """The ``plot`` verb: figures (and the animation) from a saved trajectory.npz."""

    p = verbs.add_parser(
        "plot", help="figures and animation from a saved trajectory.npz",
        description="Draw figures from RESULTS (a trajectory.npz written by 'run', or the directory "
        f"holding it) into DIR (default: beside RESULTS). Kinds: {', '.join(PLOT_KINDS)} "
        "(animation.gif; also .mp4 when ffmpeg is on PATH). Kinds whose data the file lacks are "
        "skipped with a note.",
        epilog=f"example:\n  {PROG} plot out/dp/trajectory.npz --kinds trajectory,animation "
        "--scene scenarios/double_pendulum.toml",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results", metavar="RESULTS", help="trajectory.npz, or a directory holding one")
    p.add_argument("--out", metavar="DIR", help="output directory (default: the folder of RESULTS)")
    p.add_argument("--kinds", help="comma-separated kinds (default: all PNG figures; also: animation)")
    p.add_argument("--scene", metavar="SCENE", help="the scene file, to draw its rods in the animation")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


def _add_view(verbs) -> None:
    """The ``view`` verb (constrained.viewer): an interactive HTML page of a saved run."""
    p = verbs.add_parser(
        "view", help="one self-contained interactive HTML page of a saved trajectory.npz",
        description="Write one HTML page (no network needed) showing RUN: particles, trails, "
        "constraint-force arrows, a time slider, play/pause and speed, and linked panels of energy, "
        "constraint residual and a chosen multiplier. With --scene the constraints are drawn too.",
        epilog=f"example:\n  {PROG} view out/dp/trajectory.npz --scene scenarios/double_pendulum.toml "
        "--out out/dp/viewer.html", formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results", metavar="RUN", help="trajectory.npz, or a directory holding one")
    p.add_argument("--scene", metavar="SCENE", help="the scene file of the run, to draw its constraints")
    p.add_argument("--out", metavar="FILE", help="the page to write (default: viewer.html beside RUN)")
    _add_set(p)
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


def _add_sweep(verbs) -> None:
    """The ``sweep`` verb (constrained.sweep): many runs of one scene on Dask."""
    sw = _verb(
        verbs, "sweep", "run a parameter sweep or an ensemble (batched, here or on Dask); one row per run",
        "Run SCENE once per point of the design given by --vary KEY=SPEC (a full grid; "
        "random specs draw --samples points) and/or the rows of --design FILE.csv|.parquet (one "
        "column per scene key). SPEC: [1, 2, 3], lin(a, b, n), log(a, b, n), "
        "uniform(a, b), normal(mu, sigma), loguniform(a, b). Variants that differ only in "
        "[parameters] run batched (many per simulate_many call); the others one run each. "
        "Writes DIR/chunks/<id>.parquet as chunks finish, DIR/summary.csv (and .parquet), "
        "DIR/sweep.png; run again, it skips finished variants. "
        "A run that fails is recorded with its error; the others go on.",
        "sweep scenarios/kapitza_sweep.toml --vary 'parameters.a=lin(0.002, 0.02, 12)' "
        "--vary 'parameters.nu=lin(20, 240, 12)' \\\n    --summary 'min:up=y_bob - a*cos(nu*t)' "
        "--boundary 'a**2*nu**2 - 2*g*l' --out out/kapitza",
        out="output directory (default: out/<scene file stem>_sweep, the word not doubled)", quiet=True)
    sw.add_argument("--vary", action="append", default=[], metavar="KEY=SPEC",
                    help="a scene key (--set syntax) and its values (repeatable: a grid)")
    sw.add_argument("--design", metavar="FILE",
                    help="a .csv or .parquet file of variants: one column per scene key (parameters.m1, "
                    "...), one row per variant, numbers only")
    sw.add_argument("--samples", type=int, metavar="N", help="random draws of the random specs")
    sw.add_argument("--seed", type=int, default=0, help="seed of the random specs (default 0)")
    sw.add_argument("--scheduler", metavar="ADDRESS",
                    help="tcp://HOST:PORT of a running Dask scheduler, 'local' (a local Dask cluster, one "
                    "worker process per core) or 'sequential' (this process, no Dask); default: this "
                    "process or a local cluster, chosen by the estimated work")
    sw.add_argument("--per-run", action="store_true",
                    help="run every variant on its own (no batching)")
    sw.add_argument("--chunk-size", type=int, metavar="N",
                    help="variants per batched chunk: one simulate_many call, one file (default 500)")
    sw.add_argument("--workers", type=int, metavar="N", help="worker processes of the local cluster")
    sw.add_argument("--summary", action="append", default=[], metavar="[RED:]NAME=FORMULA",
                    help="a summary column: a formula in t, x_P, vx_P, ..., parameters, at t_end or "
                    "reduced over the run with max:, min:, max_abs:, mean: (repeatable)")
    sw.add_argument("--trajectories", action="store_true", help="also write DIR/runs/<id>.npz")
    sw.add_argument("--plot", metavar="COLUMN", help="the column the figure shows (default: the first "
                    "--summary, else the position coordinate that varies most across the runs)")
    sw.add_argument("--boundary", metavar="FORMULA",
                    help="2-D map: draw the zero contour of a formula in the varied keys' last names "
                    "and the parameters, e.g. 'a**2*nu**2 - 2*g*l'")
    sw.add_argument("--limit", type=int, metavar="N", help="compute at most N missing runs, then stop")
    path = _verb(
        verbs, "path", "the motion between two configurations in a given time (stationary action)",
        "Find the path from SCENE's initial positions (at simulate.t_start) to the positions "
        "--to at time t_start + T by making the discrete action stationary (IPOPT), the "
        "constraints held at every node. Print the action, convergence and whether it is a "
        "minimum or a saddle (beyond a conjugate point); write DIR/path.npz and DIR/path.png "
        "(the path and the action against iteration). Exit 1 with the last iterate saved when "
        "IPOPT does not converge.",
        "path scenarios/double_pendulum.toml --to \"p1=[0,-1,0]; p2=[0,-2,0]\" --time 1 --out out/dp_path",
        out="output directory (default: out/<scene file stem>_path)", quiet=True)
    path.add_argument("--to", required=True, metavar="FILE_OR_POSITIONS",
                      help="end configuration: a trajectory .npz (its last positions) or "
                      "'p1=[x,y,z]; p2=[x,y,z]' naming every particle")
    path.add_argument("--time", required=True, type=float, metavar="T", help="duration T in seconds (> 0)")
    path.add_argument("--nodes", type=int, default=200, metavar="K", help="time intervals (default 200)")
    path.add_argument("--quadrature", choices=("midpoint", "trapezoid"), default="midpoint",
                      help="discrete Lagrangian (default midpoint)")
    path.add_argument("--max-iter", type=int, default=200, metavar="N", help="IPOPT iterations (default 200)")
    path.add_argument("--minimize", action="store_true",
                      help="minimize the action instead of solving for a stationary point near the "
                      "straight path (finds minima only)")


def _verb(verbs, name: str, help: str, description: str, example: str, *,
          scene_help: str = "scene file (TOML)", out: str | None = None, quiet: bool = False):
    """A verb taking SCENE, ``--set`` and, where asked, ``--out DIR`` and ``--quiet``."""
    p = verbs.add_parser(name, help=help, description=description,
                         epilog=f"example:\n  {PROG} {example}",
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help=scene_help)
    if out:
        p.add_argument("--out", metavar="DIR", help=out)
    _add_set(p)
    if quiet:
        p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def _add_set(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a scene key, e.g. simulate.t_end=2 (repeatable)",
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, already reported)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    global _as_command
    _as_command = args.as_command = argv is None
    if _as_command and not isinstance(sys.stdout, ReaderGone):
        sys.stdout = ReaderGone(sys.stdout)
    code = _dispatch(args)
    if code == 130:  # Ctrl-C handled here: the exit status is 130, not a death by SIGINT
        from ..interrupt import forget_handled_keyboard_interrupt

        _ignore_further_ctrl_c()

        forget_handled_keyboard_interrupt()
    if _as_command:
        _end_command(code)
    return code


def _end_command(code: int) -> None:
    """The command's end without the interpreter's teardown, which frees a large model's
    millions of objects one by one (0.1 s of CPU after a 10,000-bead rope's run): everything
    the command wrote is committed by then (atomic renames), and the streams are flushed here."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # (a closed pipe: nothing more can be said)
            pass
    os._exit(code if isinstance(code, int) else 0)


#: Whether ``main`` runs as the command (its arguments from sys.argv), not called in-process.
_as_command = False


def _ignore_further_ctrl_c() -> None:
    """Once the command has handled Ctrl-C and is ending: a second Ctrl-C (often pressed right
    after the first) is the same request; it would otherwise interrupt the cleanup or the
    interpreter's exit and end the process by SIGINT instead of with status 130. Not when
    ``main`` is called in-process (tests, notebooks): their Ctrl-C stays theirs."""
    if _as_command:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _dispatch(args) -> int:
    """The verb's exit status; bad input, an unwritable output and Ctrl-C as the epilog says."""
    discard_uncommitted = user_path = None
    try:
        from ..errors import InitialStateWarning
        from ..output.output_set import discard_uncommitted, user_path
        from . import run as cli_run  # the verbs' imports (NumPy, CasADi, ...) only when one runs
        from . import verbs as cli_verbs
        from . import verbs_fit

        handlers = {"run": cli_run._run, "check": cli_verbs._check, "crosscheck": cli_verbs._crosscheck,
                    "bench": cli_verbs._bench, "statics": cli_verbs._statics, "derive": cli_verbs._derive,
                    "sweep": cli_verbs._sweep, "path": cli_verbs._path, "plot": cli_verbs._plot,
                    "view": cli_verbs._view, "modes": verbs_fit._modes, "fit": verbs_fit._fit}
        with warnings.catch_warnings():  # every verb reports a corrected start in its own words
            warnings.simplefilter("ignore", InitialStateWarning)
            return handlers[args.verb](args)
    except InputError as exc:
        _say_error(str(exc))
        return 2
    except OSError as exc:  # writing the outputs: permissions, a full disk (nothing is left half-written)
        target = user_path(exc.filename) if exc.filename and user_path else (getattr(args, "out", None)
                                                                             or "the output directory")
        hint = {errno.ENOSPC: "free space", errno.EDQUOT: "free space", errno.EFBIG: "free space",
                errno.EACCES: "choose another --out", errno.EROFS: "choose another --out",
                errno.EPERM: "choose another --out", None: ""}.get(exc.errno,
                                                                   "choose another --out, or free space")
        _say_error(f"cannot write {target}: {exc.strerror or exc}; nothing was written"
                   + (f" ({hint})" if hint else ""))
        return 2
    except KeyboardInterrupt as exc:  # asked for: one line, not called an error (with what was kept)
        _ignore_further_ctrl_c()
        print(f"{PROG}: {exc if str(exc) else 'interrupted (Ctrl-C)'}", file=sys.stderr)
        return 130
    finally:
        if discard_uncommitted is not None:
            discard_uncommitted()  # a verb that stopped early leaves its --out folder as it was


def __getattr__(name: str):
    """``trajectory_csv`` and the run's ``_progress`` (constrained.cli_run), imported on use."""
    if name in ("trajectory_csv", "_progress"):
        from . import run as cli_run

        return getattr(cli_run, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if __name__ == "__main__":
    raise SystemExit(main())
