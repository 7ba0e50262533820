"""``constrained run``: simulate a scene with its own settings, write its outputs (one
consistent set: trajectory.npz, .csv, figures, the viewer page), print the report and check
its [expect]; the progress display; a trajectory as CSV."""

from __future__ import annotations

import csv
import gc
import io
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..bulk import collector_paused
from ..errors import InputError, RunInterrupted, SimulationError
from ..output.output_set import OutputSet
from ..run.trajectory import QUANTITIES, Trajectory, atomic_write
from ..scene.load import Scene, check_expectations, check_regular_start, load_scene
from .text import PROG, _end_time, _fmt_correction, _fmt_value, _say, _say_error, _say_stopped, _scene_error


def _run(args) -> int:
    with collector_paused():  # (nested: the collector stays off until the scene is frozen below)
        scene = load_scene(args.scene, args.overrides)
        if getattr(args, "as_command", False):  # (not in-process: tests, notebooks keep their collector)
            # The command runs this one scene: what it read lives to its end, and the collector's
            # later passes need not walk it (0.12 s of them at 10⁴ particles, in the run's setup).
            gc.freeze()
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
    from ..output.figure_process import FigureProcess

    outs = OutputSet(out_dir, _run_files()).open()
    stop = None  # the SimulationError of a run that stopped early (RunInterrupted: Ctrl-C)
    written: list[Path] = []
    # The solvers detect non-finite values themselves and stop with a SimulationError;
    # NumPy's floating-point warnings on the way there would only repeat it, noisily.
    # The figures are drawn by a helper process that imports matplotlib during the run.
    # (started before the progress bar: no tqdm thread exists yet when it forks)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"), \
            (FigureProcess() if kinds else _no_figures()) as figures, \
            _progress(args.quiet, s["t_start"], s["t_end"]) as progress:
        try:
            result = scene.run(quantities=quantities, progress=progress, model=scene.loaded_model())
            trajectory = result.trajectory
        except SimulationError as exc:  # what was computed is written as the run's set
            stop, trajectory = exc, exc.trajectory
        except InputError as exc:
            raise _scene_error(exc, file) from None
        if stop is not None and not isinstance(stop, RunInterrupted):  # a run that had to stop: its data
            if trajectory is not None and len(trajectory.t):
                written.append(trajectory.save(outs.path("trajectory.npz"), quantities=quantities))
        elif trajectory is not None and len(trajectory.t):  # done, or interrupted: the whole set
            # a second Ctrl-C left the derived quantities out: their figures cannot be drawn
            kinds = [k for k in kinds if k not in trajectory.info.get("quantities_skipped", ())]
            try:
                _write_run_outputs(scene, trajectory, quantities, kinds, viewer, figures, outs, progress,
                                   written)
            except KeyboardInterrupt:  # Ctrl-C while writing: keep the files already whole
                if figures is not None:
                    figures.close(abandon=True)
                if not written:
                    raise
                stop = stop or RunInterrupted("interrupted (Ctrl-C) while the files were written; the run "
                                              f"itself reached t_end = {trajectory.t[-1]:g} s")
    if stop is not None:
        message = f"scene file {file}: {stop}"
        if written:
            saved = outs.commit(written)
            if isinstance(stop, RunInterrupted):  # every file put in place: figures the helper
                # finished before Ctrl-C reached it are whole and kept too, so named here
                message += "; written: " + ", ".join(str(p) for p in outs.committed)
            else:
                message += f"; what was computed up to t = {trajectory.t[-1]:.6g} s is saved in {saved[0]}"
        if isinstance(stop, RunInterrupted):  # asked for: one line, not an error
            _say_stopped(message)
            return 130
        _say_error(message)
        return 1
    written = outs.commit(written)
    if not args.quiet:
        _summary(scene, file, trajectory, written)
    return _report_expectations(scene, trajectory, args.quiet, result.expectations)


class _no_figures:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def _write_run_outputs(scene, trajectory, quantities, kinds, viewer, figures, outs, progress,
                       written: list) -> None:
    """trajectory.npz, .csv, the figures and the viewer page of a run, into the run's output set
    (committed by the caller), each appended to ``written`` once whole; the progress display
    counts the files. A requested file that cannot be written fails the run (OSError: exit 2,
    nothing of the set committed)."""
    count = 1 + ("csv" in scene.outputs["formats"]) + len(kinds) + bool(viewer)
    progress.stage("writing", count, unit="file")
    if kinds:  # the helper draws the figures while this process writes the data files
        figures.start(trajectory, kinds, outs.dir, system=scene.system)
    written.append(trajectory.save(outs.path("trajectory.npz"), quantities=quantities))
    progress.advance()
    if "csv" in scene.outputs["formats"]:
        path = outs.path("trajectory.csv")
        text = trajectory_csv(trajectory, quantities)
        atomic_write(path, lambda f: f.write(text.encode("utf-8")))
        written.append(path)
        progress.advance()
    if viewer:
        from ..output.viewer import write_viewer

        page = outs.dir / "viewer.html"
        written.append(write_viewer(trajectory, page, system=scene.system, title=scene.name))
        progress.advance()
    if kinds:
        try:
            written.extend(figures.wait(progress.advance))
        except ImportError as exc:  # no matplotlib: the data files are the run's set
            _say(f"{PROG}: warning: plots skipped ({exc})", always=True)
        except RuntimeError as exc:  # a figure that cannot be drawn: a failed run, as a failed write
            raise OSError(None, str(exc), None) from None


def _run_files() -> list[str]:
    """The files ``run`` owns in its --out folder: a new run replaces all of them (figures drawn
    by ``plot`` from the earlier trajectory included)."""
    from ..scene.load import OUTPUT_PLOTS  # not constrained.plot: that imports matplotlib (0.25 s)

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
        + (f" (velocities: {tr.info['velocity_degrees_of_freedom']}, velocity constraints)"
           if "velocity_degrees_of_freedom" in tr.info else "")
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
    from ..run.event_records import report_lines

    lines += report_lines(tr.info, tr.events)
    if tr.energy is not None and len(tr.energy):
        drift = float(np.max(np.abs(tr.energy - tr.energy[0])))
        conserving = not set(tr.info.get("active_terms", ())) & {
            "rheonomic", "dissipation", "applied_force", "time_dependent_forces"}
        conserving = conserving and not any(r.energy_lost > 0 for r in tr.events)
        if conserving:
            text = f"energy drift: max |E - E0| = {drift:.3g} J"
            e0 = abs(float(tr.energy[0]))
            if 0 < drift <= e0:
                text += f" (relative {drift / e0:.3g})"
            elif drift:  # E0 ~ 0 where the potential's zero is the start: a ratio would mean nothing
                text += f" (|E0| = {e0:.3g} J, below the drift: no relative figure)"
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
        from ..manifold.constraint_report import constraint_report
    except ImportError:
        return None
    return constraint_report(scene.system).degrees_of_freedom
