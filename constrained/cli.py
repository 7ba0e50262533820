"""The ``constrained`` command: ``run`` and ``check`` a scene file.

Exit status: 0 success, 1 a run that had to stop (what it computed is saved), 2 bad input
or an unwritable output folder (one-paragraph message naming the file and the key, nothing
written), 130 interrupted. Outputs go through ``outputs.OutputSet``: one consistent set per run.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
from collections.abc import Sequence
from pathlib import Path

from ._version import __version__
from .errors import InconsistentStateError, InputError, RunInterrupted, SimulationError


class _LazyNumpy:
    """``np`` of this module: NumPy is imported on first use, so ``--help`` and ``--version``
    stay fast (numpy, CasADi, SciPy and matplotlib are imported only when a verb runs)."""

    def __getattr__(self, name):
        import numpy

        return getattr(numpy, name)


np = _LazyNumpy()


def _import_verb_modules() -> None:
    """Bind the scene and trajectory names the verb handlers use (imported when a verb runs)."""
    global _KEY_RE, SIMULATE_DEFAULTS, Scene, SceneError, check_expectations, expect_requirements
    global load_scene, QUANTITIES, Trajectory, atomic_write, check_regular_start
    global OutputSet, discard_uncommitted, user_path
    from .outputs import OutputSet, discard_uncommitted, user_path
    from .overrides import _KEY_RE
    from .scene import (
        SIMULATE_DEFAULTS,
        Scene,
        SceneError,
        check_expectations,
        check_regular_start,
        expect_requirements,
        load_scene,
    )
    from .trajectory import QUANTITIES, Trajectory, atomic_write

__all__ = ["main", "build_parser", "trajectory_csv"]

PROG = "constrained"
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
  derive  print T, V, L and Lagrange's equations; check hand-derived equations,
          Lagrangians and generalized forces (exit 1 when one is wrong)
            constrained derive scenarios/double_pendulum.toml --set parameters.g=9.81 \
              --equation "th2_ddot + th1_ddot*cos(th1-th2) - th1_dot**2*sin(th1-th2) + g*sin(th2) = 0"
  sweep   many runs of one scene on Dask: --vary KEY=SPEC (grid / random); summary.csv
            constrained sweep scenarios/kapitza_sweep.toml --vary "parameters.a=lin(0.002, 0.02, 12)" \
              --vary "parameters.nu=lin(20, 240, 12)" --summary "min:up=y_bob - a*cos(nu*t)"
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
    _verb(verbs, "check", "validate a scene; print DOF, redundancy and initial-state consistency",
          "Validate SCENE without simulating: particles, constraint rows, degrees of "
          "freedom, rank and redundancy, singular configuration, consistency of the initial state, "
          "and the terms the model assembles.",
          "check scenarios/double_pendulum.toml", quiet=True)
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
        "Simulate SCENE with each method at each tolerance; write DIR/bench.csv "
        "(method, rtol, dt, error, constraint_residual, velocity_residual, energy_drift, "
        "wall_time_s, steps, nfev, status), DIR/bench.md and DIR/bench.png.",
        "bench scenarios/double_pendulum.toml --set simulate.t_end=2 "
        "--methods projection,rattle --tolerances 1e-8,1e-10", out=OUT, quiet=True)
    bench.add_argument("--methods", help="comma-separated methods (default: all)")
    bench.add_argument("--tolerances", help="comma-separated rtol values (default: 1e-6,1e-8,1e-10,1e-12)")
    bench.add_argument("--repeats", type=int, default=3, help="timed repeats per row (median)")
    derive = _verb(
        verbs, "derive", "print Lagrange's equations; check hand-derived equations, Lagrangians, forces",
        "Without options print T, V, L, the momenta and Lagrange's equations of "
        "SCENE's [reduced] coordinates, in the names of its [parameters] (--latex: as LaTeX, "
        "through SymPy, the 'pretty' extra). With options check each candidate at random states "
        "and print one verdict line per check (OK or WRONG with where it disagrees); exit "
        "0 when all are right, 1 when one is wrong, 2 on bad input.",
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
    _add_sweep(verbs)
    _add_plot(verbs)
    _add_view(verbs)
    return parser


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
        out="output directory (default: out/<scene file stem>_sweep)", quiet=True)
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
    sw.add_argument("--plot", metavar="COLUMN", help="the column the figure shows")
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
    _import_verb_modules()
    handlers = {"run": _run, "check": _check, "crosscheck": _crosscheck, "bench": _bench,
                "statics": _statics, "derive": _derive, "sweep": _sweep, "path": _path, "plot": _plot,
                "view": _view}
    try:
        return handlers[args.verb](args)
    except InputError as exc:
        _say_error(str(exc))
        return 2
    except OSError as exc:  # writing the outputs: permissions, a full disk (nothing is left half-written)
        target = user_path(exc.filename) if exc.filename else (getattr(args, "out", None)
                                                               or "the output directory")
        _say_error(f"cannot write {target}: {exc.strerror or exc}; nothing was written (choose another "
                   "--out, or free space)")
        return 2
    except KeyboardInterrupt:
        _say_error("interrupted")
        return 130
    finally:
        discard_uncommitted()  # a verb that stopped early leaves its --out folder as it was


# --- run -------------------------------------------------------------------------------------


def _end_time(scene, file: str) -> float:
    """The scene's t_end, or the refusal naming simulate.t_end."""
    if scene.settings["t_end"] is None:
        raise SceneError("no end time: give t_end in [simulate], or pass --set simulate.t_end=...",
                         file=file, key="simulate.t_end")
    return scene.settings["t_end"]


def _needs_reduced(file: str, verb: str):
    """The refusal of a verb that needs the scene's [reduced] coordinates."""
    raise SceneError(f"no [reduced] section: {verb} needs generalized coordinates "
                     "(coordinates, initial, rates, map)", file=file, key="reduced")


def _run(args) -> int:
    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    s = scene.settings
    _end_time(scene, file)
    check_regular_start(scene, loaded=True)
    out_dir = Path(args.out) if args.out else Path("out") / Path(file).stem
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} exists and is not a directory")
    quantities = _contract_quantities(scene.outputs["quantities"])
    kinds = list(scene.outputs["plots"])
    viewer = "viewer" in kinds  # an HTML page (constrained.viewer), not a matplotlib figure
    kinds = [k for k in kinds if k != "viewer"]
    from .figure_process import FigureProcess

    outs = OutputSet(out_dir, _run_files()).open()
    try:
        # The solvers detect non-finite values themselves and stop with a SimulationError;
        # NumPy's floating-point warnings on the way there would only repeat it, noisily.
        # The figures are drawn by a helper process that imports matplotlib during the run.
        # (started before the progress bar: no tqdm thread exists yet when it forks)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"), \
                (FigureProcess() if kinds else _no_figures()) as figures, \
                _progress(args.quiet, s["t_start"], s["t_end"]) as progress:
            result = scene.run(quantities=quantities, progress=progress)
            trajectory = result.trajectory
            written = _write_run_outputs(scene, trajectory, quantities, kinds, viewer, figures, outs,
                                         progress)
    except SimulationError as exc:  # RunInterrupted (Ctrl-C) too: exit status 130
        message = f"scene file {file}: {exc}"
        partial = exc.trajectory
        if partial is not None and len(partial.t):
            (path,) = outs.commit([partial.save(outs.path("trajectory.npz"), quantities=quantities)])
            message += f"; what was computed up to t = {partial.t[-1]:.6g} s is saved in {path}"
        _say_error(message)
        return 130 if isinstance(exc, RunInterrupted) else 1
    except InputError as exc:
        raise _scene_error(exc, file) from None

    written = outs.commit(written)
    if not args.quiet:
        _summary(scene, file, trajectory, written)
    return _report_expectations(scene, trajectory, args.quiet, result.expectations)


class _no_figures:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def _write_run_outputs(scene, trajectory, quantities, kinds, viewer, figures, outs, progress) -> list:
    """trajectory.npz, .csv, the figures and the viewer page of a run, into the run's output set
    (committed by the caller); the progress display counts the files."""
    count = 1 + ("csv" in scene.outputs["formats"]) + len(kinds) + bool(viewer)
    progress.stage("writing", count, unit="file")
    if kinds:  # the helper draws the figures while this process writes the data files
        figures.start(trajectory, kinds, outs.dir, system=scene.system)
    written = [trajectory.save(outs.path("trajectory.npz"), quantities=quantities)]
    progress.advance()
    if "csv" in scene.outputs["formats"]:
        path = outs.path("trajectory.csv")
        text = trajectory_csv(trajectory, quantities)
        atomic_write(path, lambda f: f.write(text.encode("utf-8")))
        written.append(path)
        progress.advance()
    if viewer:
        from .viewer import write_viewer

        page = outs.dir / "viewer.html"
        written.append(write_viewer(trajectory, page, system=scene.system, title=scene.name))
        progress.advance()
    if kinds:
        try:
            written.extend(figures.wait(progress.advance))
        except (ImportError, RuntimeError) as exc:  # no matplotlib, or the drawing process died
            _say(f"{PROG}: warning: plots skipped ({exc})", always=True)
    return written


def _run_files() -> list[str]:
    """The files ``run`` owns in its --out folder: a new run replaces all of them (figures drawn
    by ``plot`` from the earlier trajectory included)."""
    from .scene import OUTPUT_PLOTS  # not constrained.plot: that imports matplotlib (0.25 s)

    return ["trajectory.npz", "trajectory.csv", "animation.gif", "animation.mp4", "viewer.html",
            *(f"{kind}.png" for kind in OUTPUT_PLOTS if kind not in ("animation", "viewer"))]


def _report_expectations(scene: Scene, trajectory: Trajectory, quiet: bool, results=None) -> int:
    """Check the scene's [expect] section: one line per check; 1 when one fails, else 0."""
    if not scene.expectations:
        return 0
    if results is None:
        results = check_expectations(scene, trajectory)
    failed = [r for r in results if not r.ok]
    if not quiet:
        built = sum(r.by_construction for r in results)
        aside = f" ({built} of them hold by construction, see below)" if built else ""
        print(f"expect: {len(results) - len(failed)} of {len(results)} checks pass{aside}")
        for r in results:
            print("  " + r.line)
    elif failed:
        for r in failed:
            print(f"{PROG}: expect: {r.line}", file=sys.stderr)
    return 1 if failed else 0


class _progress:
    """The progress display of a run (tqdm, on stderr): a bar over simulated time, then one
    over the files written (figures, the animation frame by frame). It appears once the run
    has taken ~2 s (DELAY) in all, and only on a terminal and without --quiet. The solvers report
    the time they have reached through their ``progress`` callback — this object is that callback."""

    DELAY = 2.0
    #: seconds between redraws of the bar
    MININTERVAL = 0.2

    def __init__(self, quiet: bool, t_start: float, t_end: float, *, stream=None):
        import time

        self.stream = sys.stderr if stream is None else stream
        self.enabled = not quiet and self.stream.isatty()
        self.t_start, self.t_end = float(t_start), float(t_end)
        self.bar = None
        self.started = time.perf_counter()
        self.time = time.perf_counter
        # once the time loop runs (its first report), one line says how to stop it
        self.announce = not quiet

    def _open(self, total: float, desc: str, bar_format: str | None = None, unit: str = "it"):
        if not self.enabled:
            return
        try:
            from tqdm import tqdm
        except ImportError:
            return
        # the delay counts from the start of the run, not from this stage
        delay = max(0.0, self.DELAY - (self.time() - self.started))
        self.bar = tqdm(total=total, desc=desc, delay=delay, file=self.stream, leave=False,
                        unit=unit, bar_format=bar_format, mininterval=self.MININTERVAL, miniters=1)

    def __enter__(self):
        self._open(self.t_end - self.t_start, "simulating",
                   "{desc}: {percentage:3.0f}%|{bar}| t = {n:.4g} of {total:.4g} s "
                   "[{elapsed}<{remaining}]")
        return self

    def __call__(self, t: float) -> None:
        if self.announce:
            self.announce = False
            print(f"simulating to t = {self.t_end:g} s (Ctrl-C stops the run and saves what was "
                  "computed)", flush=True)
        if self.bar is not None:
            self.bar.update(min(t - self.t_start, self.bar.total) - self.bar.n)

    def stage(self, desc: str, total: float, unit: str = "it") -> None:
        """Close the current bar and open one for ``total`` units of a new stage."""
        self._close()
        self._open(total, desc, "{desc}: {n:.3g}/{total:.3g} " + unit + "s |{bar}| [{elapsed}<{remaining}]",
                   unit=unit)

    def advance(self, amount: float = 1.0) -> None:
        """``amount`` more units of the current stage are done."""
        if self.bar is not None:
            self.bar.update(amount)

    def _close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __exit__(self, *exc):
        self._close()
        return False


def _contract_quantities(names: Sequence[str]) -> list[str]:
    """Scene output names -> contract array names besides t, x, v (always written)."""
    return [q for q in QUANTITIES if q in names]


def trajectory_csv(trajectory: Trajectory, quantities: Sequence[str]) -> str:
    """The trajectory as CSV text: ``t``, positions, velocities, then the requested quantities."""
    tr = trajectory
    names = tr.particle_names or [f"p{i}" for i in range(tr.n_particles)]
    header = ["t"]
    columns = [tr.t.reshape(-1, 1)]
    header += [f"{a}_{n}" for n in names for a in "xyz"]
    columns.append(tr.x.reshape(len(tr.t), -1))
    header += [f"v{a}_{n}" for n in names for a in "xyz"]
    columns.append(tr.v.reshape(len(tr.t), -1))
    for q in quantities:
        value = getattr(tr, q, None)
        if value is None:
            continue
        if q == "multipliers":
            labels = tr.constraint_labels or [str(k) for k in range(value.shape[1])]
            header += [f"lambda[{label}]" for label in labels]
            columns.append(value.reshape(len(tr.t), -1))
        elif q == "constraint_forces":
            header += [f"Fc{a}_{n}" for n in names for a in "xyz"]
            columns.append(value.reshape(len(tr.t), -1))
        else:
            header.append(q)
            columns.append(value.reshape(-1, 1))
    data = np.hstack(columns)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in data:
        w.writerow([repr(float(v)) for v in row])
    return buf.getvalue()


def _summary(scene: Scene, file: str, tr: Trajectory, written: list[Path]) -> None:
    s = scene.settings
    lines = [f"scene: {scene.name} ({file})"]
    dof = tr.info.get("degrees_of_freedom")
    if dof is None:
        dof = _degrees_of_freedom(scene)
    lines.append(
        f"particles {scene.system.n_particles}, constraint rows {len(tr.constraint_labels)}, "
        f"degrees of freedom {dof if dof is not None else '?'}"
    )
    lines.append(
        f"method {s['method']}, rtol {s['rtol']:g}, atol {s['atol']:g}, "
        f"t = {tr.t[0]:g} .. {tr.t[-1]:g} s, {len(tr.t)} samples"
    )
    corr = tr.info.get("initial_correction")
    if corr is not None:
        lines.append(f"initial-state correction: {_fmt_correction(corr)}")
    if tr.stats:
        stats = ", ".join(f"{k} {_fmt_value(v)}" for k, v in tr.stats.items() if np.isscalar(v))
        lines.append(f"solver: {stats}")
    from .events import report_lines

    lines += report_lines(tr.info, tr.events)
    if tr.energy is not None and len(tr.energy):
        drift = float(np.max(np.abs(tr.energy - tr.energy[0])))
        conserving = not set(tr.info.get("active_terms", ())) & {
            "rheonomic", "dissipation", "applied_force", "time_dependent_forces"}
        conserving = conserving and not any(r.energy_lost > 0 for r in tr.events)
        if conserving:
            text = f"energy drift: max |E - E0| = {drift:.3g} J"
            if tr.energy[0] != 0:
                text += f" (relative {drift / abs(float(tr.energy[0])):.3g})"
        else:  # damping, driving or applied forces change E: that is physics, not drift
            text = (f"energy change: E(end) - E0 = {float(tr.energy[-1] - tr.energy[0]):.6g} J "
                    "(not conserved in this scene: damping, driving, applied forces or impacts)")
        lines.append(text)
    if tr.constraint_residual is not None and len(tr.constraint_residual):
        lines.append(f"max constraint residual: {float(np.max(tr.constraint_residual)):.3g} m")
    if tr.velocity_residual is not None and len(tr.velocity_residual):
        lines.append(f"max velocity residual: {float(np.max(tr.velocity_residual)):.3g} m/s")
    lines.append("wrote: " + ", ".join(str(p) for p in written))
    print("\n".join(lines))


def _degrees_of_freedom(scene: Scene):
    try:
        from .analysis import constraint_report
    except ImportError:
        return None
    return constraint_report(scene.system).degrees_of_freedom


# --- crosscheck ------------------------------------------------------------------------------


def _crosscheck(args) -> int:
    """Both routes from the [reduced] start; table on stdout, DIR/crosscheck.png."""
    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    if scene.reduced is None:
        _needs_reduced(file, "crosscheck")
    t_end = _end_time(scene, file)
    out_dir = Path(args.out) if args.out else Path("out") / Path(file).stem
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} exists and is not a directory")
    from .crosscheck import cross_check
    from .reduced import save_crosscheck_figure

    outs = OutputSet(out_dir, ["crosscheck.png"]).open()
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            check = cross_check(scene, t_end)
    except SimulationError as exc:
        _say_error(f"scene file {file}: {exc}")
        return 130 if isinstance(exc, RunInterrupted) else 1
    except InputError as exc:
        raise _scene_error(exc, file) from None
    written = []
    try:
        written.append(save_crosscheck_figure(check, outs.path("crosscheck.png")))
    except ImportError as exc:
        _say(f"{PROG}: warning: figure skipped ({exc})", always=True)
    written = outs.commit(written)
    if args.quiet:
        return 0
    print(f"scene: {scene.name} ({file}), coordinates {', '.join(check.reduced_model.coordinates)}, "
          f"t = {check.t[0]:g} .. {check.t[-1]:g} s, rtol {check.settings['rtol']:g}")
    print(check.table())
    if written:
        print("wrote: " + ", ".join(str(p) for p in written))
    return 0


# --- statics ---------------------------------------------------------------------------------


def _statics(args) -> int:
    """Equilibrium near the scene's positions: report on stdout, DIR/equilibrium.json, statics.png."""
    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    check_regular_start(scene, loaded=True)
    out_dir = Path(args.out) if args.out else Path("out") / Path(file).stem
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} exists and is not a directory")
    from .statics import equilibrium
    from .statics_report import format_equilibrium, save_equilibrium_figure, write_equilibrium_json

    outs = OutputSet(out_dir, ["equilibrium.json", "statics.png"]).open()
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            eq = equilibrium(scene.system, t=scene.settings["t_start"])
    except InputError as exc:
        raise _scene_error(exc, file) from None
    written = [write_equilibrium_json(eq, outs.path("equilibrium.json"))]
    try:
        written.append(save_equilibrium_figure(eq, scene.system, outs.path("statics.png")))
    except ImportError as exc:
        _say(f"{PROG}: warning: figure skipped ({exc})", always=True)
    written = outs.commit(written)
    if not args.quiet:
        print(format_equilibrium(eq, title=f"scene: {scene.name} ({file})"))
        print("wrote: " + ", ".join(str(p) for p in written))
    return 0


# --- derive ----------------------------------------------------------------------------------


def _derive(args) -> int:
    """describe(scene), or one verdict line per candidate check; 1 when a candidate is wrong."""
    from .derivation import check_equations, check_generalized_forces, check_lagrangian, describe
    from .reduced import ReducedModel

    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    if scene.reduced is None:
        _needs_reduced(file, "derive")
    try:
        rm = ReducedModel.from_scene(scene)
    except InputError as exc:
        raise _scene_error(exc, file) from None
    if not (args.equation or args.lagrangian or args.force):
        if not args.quiet:
            try:
                print(describe(rm, latex=args.latex))
            except InputError as exc:  # --latex without SymPy
                raise InputError(f"derive {file}: {exc}") from None
        return 0
    checks = []
    try:
        if args.equation:
            checks += check_equations(rm, args.equation)
        for text in args.lagrangian:
            checks.append(check_lagrangian(rm, text))
        if args.force:
            checks += check_generalized_forces(rm, args.force)
    except InputError as exc:
        raise InputError(f"derive {file}: {exc}") from None
    if not args.quiet:
        print(f"scene: {scene.name} ({file}), coordinates {', '.join(rm.coordinates)}")
    for check in checks:
        if not args.quiet:
            print(f"{'OK' if check.ok else 'WRONG'}: {check.message}")
        elif not check.ok:  # --quiet: only the failing checks, on stderr
            print(f"{PROG}: WRONG: {check.message}", file=sys.stderr)
    return 0 if all(c.ok for c in checks) else 1


# --- check -----------------------------------------------------------------------------------


def _check(args) -> int:
    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    check_regular_start(scene, loaded=True)
    from .analysis import constraint_report
    from .model import assemble

    try:
        model = assemble(scene.system)
        report = constraint_report(scene.system)
    except InputError as exc:
        raise _scene_error(exc, file) from None

    sysm = scene.system
    out = [f"scene: {scene.name} ({file})"]
    if scene.description:
        out.append(f"  {scene.description}")
    values = sysm.parameter_values
    if sysm.parameters:  # inputs of the model's functions: --set parameters.NAME=VALUE
        out.append("parameters: " + ", ".join(f"{k} = {v:g}" for k, v in sysm.parameters.items()))
    if sysm.definitions:
        out.append("definitions: " + ", ".join(f"{k} = {f} = {values[k]:g}"
                                               for k, f in sysm.definitions.items()))
    out.append(f"particles ({sysm.n_particles}):")
    for p in sysm.particles:
        given = f" ({p.formulas['mass']})" if "mass" in p.formulas else ""
        out.append(
            f"  {p.name}: mass {p.mass:g} kg{given}, position {_vec(p.position)} m, "
            f"velocity {_vec(p.velocity)} m/s"
        )
    labels = list(getattr(report, "labels", None) or getattr(model, "constraint_labels", []))
    out.append(f"constraints ({len(sysm.constraints)} given, {len(labels)} scalar rows):")
    for k, label in enumerate(labels):
        out.append(f"  [{k}] {label}")
    generic = getattr(report, "generic_rank", None)
    rank_text = f"rank {report.rank}"
    if generic is not None and generic != report.rank:
        rank_text += f" (generic rank {generic})"
    out.append(
        f"coordinates {report.n_coordinates}, constraint rows {report.n_constraints}, "
        f"{rank_text}, degrees of freedom {report.degrees_of_freedom}"
        + (f" ({report.generic_degrees_of_freedom} away from this configuration)" if report.singular else "")
    )
    redundant = list(report.redundant)
    out.append("redundant constraints: " + ("; ".join(redundant) if redundant else "none"))
    out.append(
        "configuration: "
        + ("SINGULAR (the constraint Jacobian loses rank here)" if report.singular else "regular")
    )
    if labels:
        text = f"initial state: max constraint residual {report.max_residual:.3g}"
        if report.worst is not None and report.max_residual > 0:
            text += f" (worst: {report.worst})"
        out.append(text)
        preview = _projection_preview(model, scene)
        out.append(preview)
        if preview.startswith("projection: FAILS"):  # incompatible constraints: refuse the scene
            if not args.quiet:
                print("\n".join(out))
            _say_error(f"scene file {file}: refused: {preview.removeprefix('projection: FAILS, ')}")
            return 2
    else:
        out.append("initial state: no constraints")
    terms = sorted(getattr(model, "active_terms", ()))
    out.append("model terms: " + (", ".join(terms) if terms else "none"))
    if not args.quiet:
        print("\n".join(out))
    return 0


def _projection_preview(model, scene: Scene) -> str:
    """What the start-up projection of ``run`` would do to the initial state."""
    from .start import consistent_state
    from .unilateral import has_one_sided, start_report

    sysm, s = scene.system, scene.settings
    if has_one_sided(model):  # only the rows touching at the start are held: no projection onto all
        return start_report(model, sysm.positions, s["t_start"], sysm.size(), s["max_initial_correction"])
    try:
        _, _, corr = consistent_state(
            model,
            sysm.positions,
            sysm.velocities,
            s["t_start"],
            max_correction=math.inf,
            size=sysm.size(),
        )
    except InconsistentStateError as exc:
        return f"projection: FAILS, run would refuse this start: {exc}"
    limit = s["max_initial_correction"] * sysm.size()
    verdict = "within" if corr["position"] <= limit else "MORE than"
    return (
        f"projection would move positions by {corr['position']:.3g} m ({verdict} the allowed "
        f"{limit:.3g} m = simulate.max_initial_correction x system size) and velocities by "
        f"{corr['velocity']:.3g} m/s"
    )


def _fmt_correction(corr) -> str:
    if isinstance(corr, dict) and "position" in corr:
        text = f"positions moved by {corr['position']:.3g} m"
        if "velocity" in corr:
            text += f", velocities by {corr['velocity']:.3g} m/s"
        if corr.get("worst_constraint") and corr.get("max_residual_before"):
            text += (
                f" (largest violation before: {corr['max_residual_before']:.3g} in "
                f"'{corr['worst_constraint']}')"
            )
        return text
    return _fmt_value(corr)


# --- messages --------------------------------------------------------------------------------


def _scene_error(exc: InputError, file: str) -> SceneError:
    """An InputError raised after loading (simulate, assemble) -> SceneError naming the file
    (a SceneError already names it and passes through)."""
    if isinstance(exc, SceneError):
        return exc
    where = getattr(exc, "where", None)
    reason = getattr(exc, "reason", None) or str(exc)
    key = None
    if where in SIMULATE_DEFAULTS:
        key = f"simulate.{where}"
    elif where and _KEY_RE.fullmatch(where):
        key = where
    elif where:
        reason = f"{where}: {reason}"
    if key is None and isinstance(exc, InconsistentStateError):
        key = "particles"
    return SceneError(reason, file=file, key=key)


def _say_error(message: str) -> None:
    print(f"{PROG}: error: " + " ".join(str(message).split()), file=sys.stderr)


def _say(message: str, *, always: bool = False) -> None:
    print(message, file=sys.stderr if always else sys.stdout)


def _vec(v) -> str:
    return "(" + ", ".join(f"{float(c):.6g}" for c in v) + ")"


def _fmt_value(v) -> str:
    if isinstance(v, float | np.floating):
        return f"{float(v):.3g}"
    return str(v)



# --- bench -----------------------------------------------------------------------------------


def _bench(args) -> int:
    """Work-precision measurement of one scene: DIR/bench.csv, bench.md, bench.png."""
    from .bench import DEFAULT_METHODS, DEFAULT_TOLERANCES, work_precision

    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    t_end = _end_time(scene, file)
    check_regular_start(scene, loaded=True)
    methods = tuple(m.strip() for m in args.methods.split(",")) if args.methods else DEFAULT_METHODS
    try:
        tolerances = (tuple(float(x) for x in args.tolerances.split(","))
                      if args.tolerances else DEFAULT_TOLERANCES)
    except ValueError:
        raise InputError(f"--tolerances must be comma-separated numbers, got {args.tolerances!r}") from None
    out_dir = Path(args.out) if args.out else Path("out") / Path(file).stem
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} exists and is not a directory")

    def progress(method, opts):
        if not args.quiet:
            setting = ", ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}"
                                for k, v in opts.items() if k not in ("atol", "base"))
            print(f"  {method} ({setting})", flush=True)

    outs = OutputSet(out_dir, ["bench.csv", "bench.md", "bench.png"]).open()
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            from .scene import closed_form_error, closed_form_positions

            closed = [c["lhs"] for c in closed_form_positions(scene)]
            kwargs = {}
            if closed:
                kwargs = dict(error_of=lambda tr: closed_form_error(scene, tr)[0],
                              reference_note=f"the scene's closed form for {', '.join(closed)}")
            result = work_precision(scene.system, t_end, methods=methods, tolerances=tolerances,
                                    repeats=args.repeats, name=scene.name, progress=progress, **kwargs)
    except InputError as exc:
        raise _scene_error(exc, file) from None
    written = outs.commit(result.write(outs.dir))
    if not args.quiet:
        print(result.markdown())
        print("wrote: " + ", ".join(str(p) for p in written))
    return 0


# --- sweep -----------------------------------------------------------------------------------


def _sweep(args) -> int:
    """Parameter sweep / ensemble: DIR/summary.csv (.parquet), DIR/runs/, DIR/sweep.png."""
    from .sweep import sweep

    result = sweep(args.scene, args.vary, design_file=args.design, samples=args.samples, seed=args.seed,
                   scheduler=args.scheduler, out_dir=args.out, overrides=args.overrides, summary=args.summary,
                   save_trajectories=args.trajectories, progress=not args.quiet, limit=args.limit,
                   workers=args.workers, plot=args.plot, boundary=args.boundary, batch=not args.per_run,
                   chunk_size=args.chunk_size)
    for warning in result.warnings:
        _say(f"{PROG}: warning: {warning}", always=True)
    if result.failed:
        _say(f"{PROG}: warning: {result.failed} of {len(result.rows)} runs failed (their errors are in "
             f"the status column)", always=True)
    if not args.quiet:
        print(f"sweep: {result.total} runs ({result.computed} computed, {result.skipped} already done, "
              f"{result.failed} failed) on {result.workers} worker(s) in {result.wall_time_s:.1f} s")
        if result.computed:
            print(f"paths: {result.batched} batched (simulate_many per chunk), {result.per_run} one run each")
            print(f"ran {result.where.mode}: {result.where.reason}")
            for note in result.notes:
                print(f"note: {note}")
        if not result.complete:
            print(f"{result.total - len(result.rows)} runs still missing: run the same command again")
        print("wrote: " + ", ".join(str(p) for p in result.paths))
    return 0


# --- path ------------------------------------------------------------------------------------


def _path(args) -> int:
    """Stationary path from the scene's positions to --to in --time: DIR/path.npz, path.png."""
    from .action import end_configuration, save_path_figure, stationary_path

    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    if not math.isfinite(args.time) or args.time <= 0:
        raise InputError(f"path {file}: --time must be a positive number of seconds, got {args.time:g}")
    if args.nodes < 2:
        raise InputError(f"path {file}: --nodes must be at least 2, got {args.nodes}")
    if args.max_iter < 1:
        raise InputError(f"path {file}: --max-iter must be at least 1, got {args.max_iter}")
    out_dir = Path(args.out) if args.out else Path("out") / f"{Path(file).stem}_path"
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} exists and is not a directory")
    t0 = scene.settings["t_start"]
    outs = OutputSet(out_dir, ["path.npz", "path.png"]).open()
    try:
        x_end = end_configuration(args.to, scene.system)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            result = stationary_path(scene.system, scene.system.positions, x_end, args.time,
                                     nodes=args.nodes, quadrature=args.quadrature, t0=t0,
                                     method="minimize" if args.minimize else "stationary",
                                     max_iter=args.max_iter)
    except SimulationError as exc:
        message = f"scene file {file}: {exc}"
        if exc.trajectory is not None:
            staged = exc.trajectory.save(outs.path("path.npz"))
            if getattr(exc, "path", None) is not None:
                try:
                    save_path_figure(exc.path, outs.path("path.png"))
                except ImportError:
                    pass
            (saved,) = outs.commit([staged])
            message += f"; the last iterate is saved in {saved}"
        _say_error(message)
        return 1
    except InputError as exc:
        raise _scene_error(exc, file) from None
    written = [result.trajectory.save(outs.path("path.npz"))]
    try:
        written.append(save_path_figure(result, outs.path("path.png")))
    except ImportError as exc:
        _say(f"{PROG}: warning: figure skipped ({exc})", always=True)
    written = outs.commit(written)
    if not args.quiet:
        print(f"scene: {scene.name} ({file}), from the scene's positions at t = {t0:g} s to --to at "
              f"t = {t0 + args.time:g} s")
        print(result.summary())
        print("wrote: " + ", ".join(str(p) for p in written))
    return 0


# --- plot ------------------------------------------------------------------------------------


def _plot(args) -> int:
    """Figures of a saved trajectory: DIR/<kind>.png and DIR/animation.gif."""
    from .plot import FIGURES, KINDS, save_figures

    results = Path(args.results)
    if results.is_dir():
        results = results / "trajectory.npz"
    if not results.exists():
        raise InputError(f"plot: no such file {results} (give a trajectory.npz written by 'run')")
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()] if args.kinds else list(FIGURES)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise InputError(f"plot: unknown kind(s) {', '.join(unknown)} (known: {', '.join(KINDS)})")
    try:
        trajectory = Trajectory.load(results)
    except InputError as exc:
        raise InputError(f"plot: {exc}") from None
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"plot: cannot read {results} as a trajectory ({exc})") from None
    system = load_scene(args.scene).system if args.scene else None
    out_dir = Path(args.out) if args.out else results.parent
    outs = OutputSet(out_dir).open()
    written, skipped = [], []
    for kind in kinds:
        try:
            written.extend(save_figures(trajectory, [kind], outs.dir, system=system))
        except InputError as exc:
            if args.kinds:  # asked for by name: say why not
                skipped.append(f"{kind} ({exc})")
            else:
                skipped.append(kind)
    if written:
        written = outs.commit(written)
    if not args.quiet:
        if written:
            print("wrote: " + ", ".join(str(p) for p in written))
        if skipped:
            print("skipped (data not in the file): " + "; ".join(skipped))
    return 0 if written or not args.kinds else 1


def _view(args) -> int:
    """``view``: the interactive page of a saved run (constrained.viewer)."""
    from .viewer import view_command

    if args.overrides and not args.scene:
        raise InputError("view: --set changes the scene; give it with --scene")
    scene = load_scene(args.scene, args.overrides) if args.scene else None
    path = view_command(args.results, scene=scene, out=args.out)
    if not args.quiet:
        print(f"wrote: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
