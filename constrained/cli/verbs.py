"""The verbs of ``constrained`` besides ``run``: ``crosscheck``, ``statics``, ``derive``,
``check``, ``bench``, ``sweep``, ``path``, ``plot`` and ``view``."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from ..errors import InconsistentStateError, InputError, RunInterrupted, SimulationError
from ..output.output_set import OutputSet
from ..run.trajectory import Trajectory
from ..scene.load import Scene, check_regular_start, load_scene
from .text import LISTED, PROG, _end_time, _needs_reduced, _say, _say_error, _say_stopped, _scene_error, _vec

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
    from ..analysis.crosscheck import cross_check, save_crosscheck_figure

    outs = OutputSet(out_dir, ["crosscheck.png"]).open()
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            check = cross_check(scene, t_end)
    except RunInterrupted as exc:
        _say_stopped(f"scene file {file}: {exc}")
        return 130
    except SimulationError as exc:
        _say_error(f"scene file {file}: {exc}")
        return 1
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
    from ..analysis.statics import equilibrium
    from ..analysis.statics_report import format_equilibrium, save_equilibrium_figure, write_equilibrium_json

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
    """describe(scene) and its conserved quantities, or one verdict line per candidate check; 1 when
    a candidate is wrong."""
    from ..analysis.derivation import (
        check_constant_of_motion,
        check_equations,
        check_generalized_forces,
        check_lagrangian,
        describe,
        describe_conserved,
    )
    from ..run.reduced import ReducedModel

    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    if scene.reduced is None:
        _needs_reduced(file, "derive")
    try:
        rm = ReducedModel.from_scene(scene)
    except InputError as exc:
        raise _scene_error(exc, file) from None
    if not (args.equation or args.lagrangian or args.force or args.conserved):
        if not args.quiet:
            try:
                print(describe(rm, latex=args.latex))
                print(describe_conserved(rm, latex=args.latex))
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
        for text in args.conserved:
            checks.append(check_constant_of_motion(rm, text))
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


def _more(n: int, shown: int | None, what: str) -> list[str]:
    """The line saying how many of ``n`` were not listed (none when all were)."""
    return [] if shown is None or n <= shown else [f"  … {n - shown} more {what} (--all lists them)"]


def _check(args) -> int:
    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    check_regular_start(scene, loaded=True)
    from ..manifold.constraint_report import constraint_report
    from ..model.structure import assemble

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
    shown = None if args.list_all else LISTED
    out.append(f"particles ({sysm.n_particles}):")
    for p in sysm.particles[:shown]:
        given = f" ({p.formulas['mass']})" if "mass" in p.formulas else ""
        out.append(
            f"  {p.name}: mass {p.mass:g} kg{given}, position {_vec(p.position)} m, "
            f"velocity {_vec(p.velocity)} m/s"
        )
    out += _more(sysm.n_particles, shown, "particles")
    labels = list(getattr(report, "labels", None) or getattr(model, "constraint_labels", []))
    out.append(f"constraints ({len(sysm.constraints)} given, {len(labels)} scalar rows):")
    for k, label in enumerate(labels[:shown]):
        out.append(f"  [{k}] {label}")
    out += _more(len(labels), shown, "rows")
    generic = getattr(report, "generic_rank", None)
    rank_text = f"rank {report.rank}"
    if generic is not None and generic != report.rank:
        rank_text += f" (generic rank {generic})"
    out.append(
        f"coordinates {report.n_coordinates}, constraint rows {report.n_constraints}, "
        f"{rank_text}, degrees of freedom {report.degrees_of_freedom}"
        + (f" ({report.generic_degrees_of_freedom} away from this configuration)" if report.singular else "")
    )
    velocity = list(getattr(report, "velocity_labels", []))
    if velocity:  # velocity constraints: rows of their own, after those of f
        rows = f"{len(velocity)} row{'s' if len(velocity) > 1 else ''}"
        out.append(f"velocity constraints ({rows} a(x, t)·v + b = 0, no position level):")
        out += [f"  [{len(labels) + k}] {label}" for k, label in enumerate(velocity)]
        out.append(f"rank [J; A] {report.velocity_rank}, velocity degrees of freedom "
                   f"{report.velocity_degrees_of_freedom} (configuration: {report.degrees_of_freedom})")
    redundant = list(report.redundant)
    out.append("redundant constraints: " + ("; ".join(redundant[:shown]) if redundant else "none")
               + (f"; … {len(redundant) - shown} more (--all lists them)"
                  if shown is not None and len(redundant) > shown else ""))
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
    out.append(_symmetries_line(model))
    if not args.quiet:
        print("\n".join(out))
    return 0


#: Above this many coordinates ``check`` does not search the rigid motions that are symmetries
#: (the search projects 12 sampled states onto the constraints).
SYMMETRY_SEARCH_UP_TO = 300


def _symmetries_line(model) -> str:
    """The rigid motions that are symmetries of the scene (``rigid_symmetries``), whose Noether
    charges are conserved: what a scene's ``[expect] conserved`` can name."""
    head = "symmetries (rigid motions)"
    if model.n_coordinates > SYMMETRY_SEARCH_UP_TO:
        return (f"{head}: not searched ({model.n_coordinates} coordinates, more than "
                f"{SYMMETRY_SEARCH_UP_TO}; constrained.rigid_symmetries(scene) searches them)")
    from ..analysis.conservation.rigid_motions import rigid_symmetries

    try:
        found = rigid_symmetries(model)
    except InputError as exc:
        return f"{head}: not searched ({exc})"
    if not found:
        return f"{head}: none"
    return (f"{head}, their Noether charges conserved: "
            + "; ".join(f"{s.name} ({s.description})" for s in found))


def _projection_preview(model, scene: Scene) -> str:
    """What the start-up projection of ``run`` would do to the initial state."""
    from ..run.start import consistent_state
    from ..run.unilateral import has_one_sided, start_report

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


# --- bench -----------------------------------------------------------------------------------


def _bench(args) -> int:
    """Work-precision measurement of one scene: DIR/bench.csv, bench.md, bench.png."""
    from ..analysis.bench import DEFAULT_METHODS, DEFAULT_TOLERANCES, check_tolerances, work_precision

    methods = tuple(m.strip() for m in args.methods.split(",")) if args.methods else DEFAULT_METHODS
    if not all(methods):
        raise InputError(f"--methods has an empty name in {args.methods!r}: give e.g. --methods dopri,idas")
    if len(set(methods)) < len(methods):
        raise InputError(f"--methods names a method twice in {args.methods!r}: each is measured once")
    try:
        tolerances = (tuple(float(x) for x in args.tolerances.split(",") if x.strip())
                      if args.tolerances is not None else DEFAULT_TOLERANCES)
    except ValueError:
        raise InputError(f"--tolerances must be comma-separated numbers, got {args.tolerances!r}") from None
    try:
        tolerances = check_tolerances(tolerances)
    except InputError as exc:
        raise InputError(f"--tolerances: {exc}") from None
    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    t_end = _end_time(scene, file)
    check_regular_start(scene, loaded=True)
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
            from ..scene.load import closed_form_error, closed_form_positions

            closed = [c["lhs"] for c in closed_form_positions(scene)]
            kwargs = {}
            if closed:
                kwargs = dict(error_of=lambda tr: closed_form_error(scene, tr)[0],
                              reference_note=f"the scene's closed form for {', '.join(closed)}")
            result = work_precision(scene.system, t_end, methods=methods, tolerances=tolerances,
                                    repeats=args.repeats, name=scene.name, progress=progress, **kwargs)
    except InputError as exc:
        raise _scene_error(exc, file) from None
    except SimulationError as exc:  # the reference run failed: nothing to measure against
        _say_error(f"scene file {file}: {exc}")
        return 1
    if result.interrupted and not result.rows:  # (nothing measured: no empty table, no empty figure)
        _say(f"{PROG}: interrupted (Ctrl-C) before any row was measured; nothing was written", always=True)
        return 130
    written = outs.commit(result.write(outs.dir))
    if not args.quiet:
        print(result.markdown())
        print("wrote: " + ", ".join(str(p) for p in written))
    if result.interrupted:
        _say(f"{PROG}: interrupted (Ctrl-C): kept the {len(result.rows)} row(s) measured before in "
             + ", ".join(str(p) for p in written), always=True)
        return 130
    return 0


# --- sweep -----------------------------------------------------------------------------------


def _sweep(args) -> int:
    """Parameter sweep / ensemble: DIR/summary.csv (.parquet), DIR/runs/, DIR/sweep.png."""
    from ..sweeps.sweep import sweep

    result = sweep(args.scene, args.vary, design_file=args.design, samples=args.samples, seed=args.seed,
                   scheduler=args.scheduler, out_dir=args.out, overrides=args.overrides, summary=args.summary,
                   save_trajectories=args.trajectories, progress=not args.quiet, limit=args.limit,
                   workers=args.workers, plot=args.plot, boundary=args.boundary, batch=not args.per_run,
                   chunk_size=args.chunk_size)
    for warning in result.warnings:
        _say(f"{PROG}: warning: {warning}", always=True)
    if result.failed:
        _say(f"{PROG}: warning: {result.failed} of {result.finished} runs failed (their errors are in "
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
            print(f"{result.total - result.finished} runs still missing: run the same command again")
        print("wrote: " + ", ".join(str(p) for p in result.paths))
    return 0


# --- path ------------------------------------------------------------------------------------


def _path(args) -> int:
    """Stationary path from the scene's positions to --to in --time: DIR/path.npz, path.png."""
    from ..analysis.action import end_configuration, save_path_figure, stationary_path

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
        if isinstance(exc, RunInterrupted):  # asked for: one line, not an error
            _say_stopped(message)
            return 130
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
    from ..output.plot import FIGURES, KINDS, save_figures

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
    from ..output.figure_style import finite_samples, nonfinite_quantities

    try:
        trajectory, dropped = finite_samples(trajectory)
    except InputError as exc:
        raise InputError(f"plot: {results}: {exc}") from None
    if dropped and not args.quiet:
        print(f"note: {dropped} of {dropped + len(trajectory.t)} samples of {results} have times, positions "
              "or velocities that are not finite; the figures leave them out")
    for name, bad, total in [] if args.quiet else nonfinite_quantities(trajectory):  # (no NaN unsaid)
        print(f"note: {name}: {bad} of {total} samples of {results} are not finite; its figure leaves them "
              "out" + (" (it is empty)" if bad == total else ""))
    system = load_scene(args.scene, equations=False).system if args.scene else None
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
            print("skipped (nothing in the file to draw them from): " + "; ".join(skipped))
    return 0 if written or not args.kinds else 1


def _view(args) -> int:
    """``view``: the interactive page of a saved run (constrained.viewer)."""
    from ..output.viewer import view_command

    if args.overrides and not args.scene:
        raise InputError("view: --set changes the scene; give it with --scene")
    scene = load_scene(args.scene, args.overrides, equations=False) if args.scene else None
    path = view_command(args.results, scene=scene, out=args.out)
    if not args.quiet:
        print(f"wrote: {path}")
    return 0
