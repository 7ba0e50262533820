"""The verbs of small oscillations and measurements: ``modes`` (normal modes about an
equilibrium or a steady motion, their figure, one mode animated) and ``fit`` ([parameters]
fitted to measured data, with standard errors, figures and the fitted run)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError, RunInterrupted, SimulationError
from ..output.output_set import OutputSet
from ..scene.load import check_regular_start, load_scene
from .text import PROG, _say, _say_error, _say_stopped, _scene_error


def _triple(text: str | None, option: str) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        values = tuple(float(c) for c in text.replace(";", ",").split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(c) for c in values):
        raise InputError(f"{option} must be three numbers X,Y,Z, got {text!r}")
    return values


def _out_dir(args, suffix: str) -> Path:
    out = Path(args.out) if args.out else Path("out") / f"{Path(args.scene).stem}_{suffix}"
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    return out


# --- modes -----------------------------------------------------------------------------------


def _modes(args) -> int:
    """Normal modes: report on stdout, DIR/modes.json, modes.png, mode<K>.gif and mode<K>.html."""
    from ..analysis.linearization import RotatingFrame
    from ..analysis.modes import modes

    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    check_regular_start(scene, loaded=True)
    omega, point = _triple(args.rotating, "--rotating"), _triple(args.frame_point, "--frame-point")
    if point is not None and omega is None:
        raise InputError("--frame-point needs --rotating (the frame's angular velocity)")
    if args.amplitude is not None and not (math.isfinite(args.amplitude) and args.amplitude > 0):
        raise InputError(f"--amplitude must be a positive length in metres, got {args.amplitude:g}")
    if args.count is not None and args.count < 1:
        raise InputError(f"--count must be a positive number of modes, got {args.count}")
    frame = None if omega is None else RotatingFrame(omega, point or (0.0, 0.0, 0.0))
    system, t0 = scene.system, scene.settings["t_start"]
    at_start = args.at == "start"
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            result = modes(system, x=system.positions if at_start else None,
                           v=system.velocities if at_start else None, t=t0, frame=frame, count=args.count)
    except InputError as exc:
        if exc.where in ("x", "v"):  # the state of the scene: its particles
            exc = InputError(exc.reason, where="particles")
        raise _scene_error(exc, file) from None
    k = (_first_oscillation(result) if args.mode is None else args.mode) - 1  # (--mode 0 is no default)
    if not 0 <= k < max(len(result.modes), 1):
        raise InputError(f"--mode {args.mode}: the modes are numbered from 1 and the state has "
                         f"{len(result.modes)} mode(s)")
    names = ["modes.json", "modes.png"]
    animate = bool(result.modes) and not args.no_animation
    if animate:
        names += [f"mode{k + 1}.gif", f"mode{k + 1}.html"]
    outs = OutputSet(_out_dir(args, "modes"), names).open()
    import json

    from ..run.trajectory import atomic_write

    text = json.dumps(result.to_dict(), indent=2)
    atomic_write(outs.path("modes.json"), lambda f: f.write(text.encode("utf-8")))
    written = [outs.path("modes.json")]
    check = _reduced_check(scene, result) if scene.reduced is not None else None
    try:
        from ..output.mode_figure import save_mode_shapes

        titles = [_title(i, m) for i, m in enumerate(result.modes)]
        written.append(save_mode_shapes(result.x, result.shapes, titles, outs.path("modes.png"),
                                        system=system, names=list(system.names)))
        if animate:
            from ..output.animation import save_animation
            from ..output.viewer import write_viewer

            traj = result.trajectory(k, amplitude=args.amplitude, system=system)
            drawn = None if getattr(_model(system), "rheonomic", False) else system
            written += save_animation(traj, outs.path(f"mode{k + 1}.gif"), system=drawn, forces=False)
            written.append(write_viewer(traj, outs.path(f"mode{k + 1}.html"), system=drawn,
                                        title=f"{scene.name}: {_title(k, result.modes[k])}"))
    except ImportError as exc:
        _say(f"{PROG}: warning: figures skipped ({exc})", always=True)
    written = outs.commit(written)
    if not args.quiet:
        print(f"scene: {scene.name} ({file})")
        print(result.table())
        if check is not None:
            print(check)
        print("wrote: " + ", ".join(str(p) for p in written))
    return 0


def _model(system):
    from ..model.structure import assemble

    return assemble(system)


def _first_oscillation(result) -> int:
    return next((i + 1 for i, m in enumerate(result.modes) if m.kind == "oscillatory"), 1)


def _title(i: int, mode) -> str:
    if mode.kind == "oscillatory":
        return f"mode {i + 1}: {mode.frequency_hz:.4g} Hz, ζ = {mode.damping_ratio + 0.0:.3g}"
    return f"mode {i + 1}: {mode.kind}, s = {mode.eigenvalue.real:.4g} 1/s"


def _reduced_check(scene, result) -> str:
    """The cross-check line against the reduced route's linearization (or why there is none)."""
    from ..run.reduced import ReducedModel

    try:
        check = result.cross_check(ReducedModel.from_scene(scene))
    except InputError as exc:
        return f"reduced route: not compared ({exc})"
    verdict = "agree" if check.difference <= 1e-8 else "DISAGREE"
    return (f"reduced route ([reduced] coordinates at q = {np.round(check.q, 10).tolist()}): the roots s "
            f"{verdict}, largest difference {check.difference:.2g} of max|s|")


# --- fit -------------------------------------------------------------------------------------


def _pairs(items: list[str], option: str) -> dict[str, str]:
    out = {}
    for item in items:
        for part in (item.split(",") if option != "--observe" else [item]):
            name, sep, value = part.partition("=")
            if not sep or not name.strip() or not value.strip():
                raise InputError(f"{option} takes NAME=VALUE, got {part!r}")
            out[name.strip()] = value.strip()
    return out


def _numbers(pairs: dict[str, str], option: str) -> dict[str, float]:
    try:
        return {k: float(v) for k, v in pairs.items()}
    except ValueError:
        raise InputError(f"{option} values must be numbers, got {pairs}") from None


def _bounds(items: list[str]) -> dict[str, tuple[float, float]]:
    out = {}
    for name, value in _pairs(items, "--bounds").items():
        low, sep, high = value.partition(":")
        try:
            out[name] = (float(low) if low.strip() else -math.inf, float(high) if high.strip() else math.inf)
        except ValueError:
            sep = ""
        if not sep:
            raise InputError(f"--bounds takes NAME=LOW:HIGH, got {name}={value!r}")
    return out


def _fit(args) -> int:
    """Fit --params to DATA: report on stdout; DIR/fit.json, fit.csv, fit.png, residuals.png and
    trajectory.npz (the fitted run); with several DATA files, DIR/fits.csv (one row each)."""
    from ..analysis.fitting.fit import fit
    from ..analysis.fitting.measurements import read_measurements

    scene = load_scene(args.scene, args.overrides)
    file = args.scene
    names = [p.strip() for p in args.params.split(",") if p.strip()]
    options = {"observables": _pairs(args.observe, "--observe"),
               "start": _numbers(_pairs(args.start, "--start"), "--start"),
               "bounds": _bounds(args.bounds), "sigma": args.sigma, "max_nfev": args.max_runs}
    if len(args.data) > 1:
        return _fit_many(args, scene, names, options)
    data = read_measurements(args.data[0])
    t0 = scene.settings["t_start"]
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            result = fit(scene.system, data, names, t_start=t0, **options)
    except RunInterrupted as exc:  # asked for: one line, not an error
        _say_stopped(f"scene file {file}: {exc}")
        return 130
    except SimulationError as exc:
        _say_error(f"scene file {file}: {exc}")
        return 1
    except InputError as exc:
        raise _scene_error(exc, file) from None
    outs = OutputSet(_out_dir(args, "fit"), ["fit.json", "fit.csv", "fit.png", "residuals.png",
                                             "trajectory.npz"]).open()
    from ..analysis.fitting.report import observable_series, save_fit_figures, write_fit_csv, write_fit_json
    from ..model.structure import assemble
    from ..run.simulate import simulate

    written = [write_fit_json(result, outs.path("fit.json")), write_fit_csv(result, outs.path("fit.csv"))]
    model = assemble(scene.system).with_parameters(result.values)
    t_end = max(float(data.t[-1]), t0 + 1e-9)
    grid = np.linspace(t0, t_end, max(200, 4 * len(data.t)))
    run = simulate(scene.system, t_end, t_start=t0, t_eval=grid, method="dopri", rtol=1e-10, atol=1e-12,
                   parameters=result.values, model=model)
    run.info["fit"] = result.to_dict()
    written.append(run.save(outs.path("trajectory.npz")))
    try:
        formulas = dict(zip(result.outputs, result.formulas, strict=True))
        curve = (run.t, observable_series(model, run, formulas))
        written += save_fit_figures(result, outs.path("fit.png"), outs.path("residuals.png"), curve=curve)
    except ImportError as exc:
        _say(f"{PROG}: warning: figures skipped ({exc})", always=True)
    written = outs.commit(written)
    if not args.quiet:
        print(f"scene: {scene.name} ({file}); data: {data.source}, {data.count} values of "
              f"{', '.join(data.names)} at {len(data.t)} times")
        print(result.table())
        print("wrote: " + ", ".join(str(p) for p in written))
    return 0 if result.success else 1


def _fit_many(args, scene, names, options) -> int:
    """One fit per DATA file (here or on Dask): DIR/fits.csv, one row each."""
    import csv
    import io

    from ..run.trajectory import atomic_write
    from ..sweeps.fits import fit_sweep

    sweep = fit_sweep(args.scene, args.data, names, overrides=args.overrides, scheduler=args.scheduler,
                      workers=args.workers, **{k: v for k, v in options.items() if v is not None})
    outs = OutputSet(_out_dir(args, "fit"), ["fits.csv"]).open()
    columns = ["data", *[c for n in names for c in (n, f"se_{n}")], "chi2", "dof", "reduced_chi2", "nfev",
               "status"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(sweep.rows)
    atomic_write(outs.path("fits.csv"), lambda f: f.write(buf.getvalue().encode("utf-8")))
    written = outs.commit([outs.path("fits.csv")])
    if not args.quiet:
        print(f"scene: {scene.name} ({args.scene}); {len(sweep.rows)} fits ({sweep.where}), "
              f"{sweep.failed} not converged")
        for row in sweep.rows:
            values = ", ".join(f"{n} = {row[n]:.6g} ± {row[f'se_{n}']:.2g}" for n in names if n in row)
            print(f"  {row['data']}: {values or row['status']}")
        print("wrote: " + ", ".join(str(p) for p in written))
    return 0 if not sweep.failed else 1
