"""Work-precision measurement: what accuracy costs in time, per method and tolerance.

For each (method, tolerance) the scene is simulated once to warm up, then ``repeats`` times;
the row records the end-position error against a reference, the largest constraint and
velocity residuals, the energy drift (where energy is conserved), the median wall time of the
warm runs, steps and evaluations, and apart from them ``compile_time_s``: what the first run
cost beyond a warm one (the C compile of a step loop, once per machine and model, then cached;
about 0 when the cache is warm). The work-precision figure plots the warm wall time.

The reference is the most accurate route available: ``projection`` at rtol = atol = 1e-13,
checked against ``idas`` at the same tolerance. Their disagreement bounds the reference's
own error; errors below it are reported as not measurable, and the result says so (as for
chaotic scenes over long horizons).
"""

from __future__ import annotations

import csv
import io
import math
import os
import statistics
import sys
import tempfile
import time
from contextlib import contextmanager, redirect_stderr
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, RunInterrupted, SimulationError
from ..model.structure import assemble
from ..run.simulate import simulate
from ..run.trajectory import atomic_write
from .symmetry import jacobi_integral

DEFAULT_METHODS = ("dopri", "projection", "projection:CVODES", "baumgarte", "idas", "ggl", "rattle")
DEFAULT_TOLERANCES = (1e-6, 1e-8, 1e-10, 1e-12)
#: rattle is fixed-step: tolerance k of the list maps to the k-th of these steps (continued
#: 1e-4, 3e-5, ... by :func:`rattle_steps` for longer lists).
RATTLE_STEPS = (1e-2, 3e-3, 1e-3, 3e-4)


def rattle_steps(count: int) -> list[float]:
    """rattle's ``count`` steps: 1e-2, 3e-3, 1e-3, 3e-4, 1e-4, ... (dt_k = 10^(-2 - k/2) rounded
    to one digit: two steps per decade, as many as tolerances given, none dropped)."""
    return [float(f"{10.0 ** (-2 - k / 2):.0e}") for k in range(count)]


def check_tolerances(tolerances) -> tuple[float, ...]:
    """The tolerances of a bench, loosest first: finite, 0 < rtol < 1, strictly decreasing
    (a repeated value measures the same thing twice; the k-th also picks rattle's k-th step)."""
    tols = tuple(float(t) for t in tolerances)
    if not tols:
        raise InputError("no tolerances given: pass e.g. --tolerances 1e-6,1e-8,1e-10")
    bad = [t for t in tols if not (math.isfinite(t) and 0 < t < 1)]
    if bad:
        raise InputError(f"tolerances must be numbers between 0 and 1 (exclusive), got {bad[0]!r}: "
                         "a relative tolerance of 0 asks for no error at all, which no method reaches")
    for a, b in zip(tols[:-1], tols[1:], strict=True):
        if not b < a:
            raise InputError(
                f"tolerances must be strictly decreasing, loosest first (got {a:g} then {b:g}): a "
                "repeated value measures the same runs twice and the k-th tolerance also picks rattle's "
                "k-th step; give them as e.g. 1e-6,1e-8,1e-10")
    return tols
COLUMNS = ("method", "rtol", "dt", "error", "constraint_residual", "velocity_residual",
           "energy_drift", "wall_time_s", "compile_time_s", "steps", "nfev", "status")


class _Skip(Exception):
    """No numerical cross-check needed: the reference is a closed form."""


@dataclass
class BenchResult:
    scene: str
    t_end: float
    rows: list[dict] = field(default_factory=list)
    reference_error: float = float("nan")
    conserves_energy: bool = False
    notes: list[str] = field(default_factory=list)
    interrupted: bool = False  # Ctrl-C stopped it: the rows are those measured before
    stop: str = ""  # how the reference run ended ("completed", "terminal event", ...)
    t_stop: float = float("nan")  # where the reference run ended (t_end unless an event stopped it)

    def csv(self) -> str:
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in self.rows:
            writer.writerow({k: _fmt(row.get(k)) for k in COLUMNS})
        return buf.getvalue()

    def markdown(self) -> str:
        lines = [f"### Work-precision: {self.scene}, t_end = {self.t_end:g} s", ""]
        lines += [f"- {note}" for note in self.notes] + [""]
        early = math.isfinite(self.t_stop) and self.t_stop < self.t_end * (1 - 1e-12)
        where = f"at the stop, t = {self.t_stop:.6g} s" if early else "at t_end"
        lines.append(f"| method | rtol / dt | error {where} [m] | max constraint residual | "
                     "energy drift [J] | wall time [s] | first-run compile [s] | steps |")
        lines.append("|---|---|---|---|---|---|---|---|")
        for r in self.rows:
            setting = f"dt {r['dt']:g}" if r["method"] == "rattle" else f"{r['rtol']:g}"
            if r["status"] != "ok":
                lines.append(f"| {r['method']} | {setting} | {r['status']} | | | | | |")
                continue
            lines.append(
                f"| {r['method']} | {setting} | {_err(r['error'], self.reference_error)} | "
                f"{r['constraint_residual']:.1e} | {_fmt(r['energy_drift'])} | "
                f"{r['wall_time_s']:.3g} | {r['compile_time_s']:.3g} | {r['steps']} |"
            )
        return "\n".join(lines) + "\n"

    def figure(self):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=(11, 4.5))
        FigureCanvasAgg(fig)
        ax1, ax2 = fig.subplots(1, 2)
        floor = max(self.reference_error, 1e-16) if math.isfinite(self.reference_error) else 1e-16
        for method in dict.fromkeys(r["method"] for r in self.rows):
            rows = [r for r in self.rows if r["method"] == method and r["status"] == "ok"]
            if not rows:
                continue
            t = [r["wall_time_s"] for r in rows]
            ax1.loglog(t, [max(r["error"], floor) for r in rows], "o-", label=method)
            ax2.loglog(t, [max(r["constraint_residual"], 1e-17) for r in rows], "o-", label=method)
        if math.isfinite(self.reference_error) and self.reference_error > 0:
            ax1.axhline(self.reference_error, color="grey", ls="--", lw=1, label="reference accuracy")
        ax1.set(xlabel="wall time of a warm run [s] (no compile)", ylabel="position error at t_end [m]",
                title=f"Work-precision: {self.scene} (t_end = {self.t_end:g} s)")
        ax2.set(xlabel="wall time of a warm run [s] (no compile)", ylabel="max constraint residual |f| [m]",
                title="Constraint drift")
        for ax in (ax1, ax2):
            ax.grid(True, which="both", alpha=0.3)
            if ax.get_legend_handles_labels()[0]:  # (every row failed: nothing to name)
                ax.legend(fontsize=8)
        fig.tight_layout()
        return fig

    def write(self, out_dir) -> list[Path]:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = [out / "bench.csv", out / "bench.md", out / "bench.png"]
        atomic_write(paths[0], lambda f: f.write(self.csv().encode()))
        atomic_write(paths[1], lambda f: f.write(self.markdown().encode()))
        fig = self.figure()
        atomic_write(paths[2], lambda f: fig.savefig(f, format="png", dpi=110))
        return paths


def work_precision(system, t_end: float, *, methods=DEFAULT_METHODS, tolerances=DEFAULT_TOLERANCES,
                   repeats: int = 3, name: str = "", progress=None, error_of=None,
                   reference_note: str = "") -> BenchResult:
    """Measure every (method, tolerance) on ``system`` up to ``t_end`` (see module doc).

    ``error_of(trajectory) -> float`` replaces the numerical reference, e.g. a scene's
    declared closed form (``scene.closed_form_error``); ``reference_note`` says what it is.
    """
    from ..solvers import METHODS

    unknown = [m for m in methods if m.split(":")[0] not in METHODS]
    if unknown:
        raise InputError(f"unknown method(s) {', '.join(unknown)} (known: {', '.join(METHODS)})")
    tolerances = check_tolerances(tolerances)
    if repeats < 1:
        raise InputError("repeats must be at least 1")
    result = BenchResult(scene=name or system.name or "scene", t_end=float(t_end))
    result.notes.append(
        f"wall time: the median of {repeats} run(s) after a warm-up run with the same settings; "
        "first-run compile: what the warm-up cost beyond a warm run (a step loop compiled to C "
        "once per machine and model, then cached; about 0 with a warm cache), not in the figure")
    # the method the notes name, not the default (dopri): its one-time compile belongs to its rows
    try:
        ref = simulate(system, t_end, method="projection", rtol=1e-13, atol=1e-13, t_eval=[0.0, t_end])
    except RunInterrupted:  # nothing measured yet: nothing to keep
        raise KeyboardInterrupt from None
    except SimulationError as exc:  # no reference, no error column: say so instead of a traceback
        raise SimulationError(
            "bench needs a reference run (projection at rtol = atol = 1e-13) to measure every "
            f"method's error against, and it failed: {str(exc).splitlines()[0]} — no method can be "
            "compared past that point; shorten t_end (--set simulate.t_end=...) to before it") from None
    x_ref = ref.x[-1]
    result.stop = str(ref.info.get("stop", ""))
    result.t_stop = float(ref.t[-1])
    if result.t_stop < float(t_end) * (1 - 1e-12):
        result.notes.append(
            f"the reference run ends at t = {result.t_stop:.10g} s ({result.stop or 'stopped'}), before "
            f"t_end = {float(t_end):g} s: every error is of the state where each run ends, and a run "
            "that ends otherwise (a missed or extra event) is marked as not comparable")
    if error_of is not None:
        closed = float(error_of(ref))
        result.notes.append(f"reference: {reference_note or 'the closed form'}; projection at rtol 1e-13 "
                            f"differs from it by {closed:.1e} (every error is against the closed form "
                            "itself, so none is hidden below that)")

        def measure(tr):
            return float(error_of(tr))
    else:
        def measure(tr):
            return float(np.max(np.abs(tr.x[-1] - x_ref)))
    try:
        if error_of is not None:
            raise _Skip
        check = simulate(system, t_end, method="idas", rtol=1e-13, atol=1e-13, t_eval=[0.0, t_end])
        result.reference_error = float(np.max(np.abs(check.x[-1] - x_ref)))
        result.notes.append(
            f"reference: projection at rtol 1e-13; idas at 1e-13 agrees within "
            f"{result.reference_error:.1e} m, so errors below that are not measurable"
        )
    except _Skip:
        pass
    except RunInterrupted:  # Ctrl-C stops the whole measurement, not just this run
        raise KeyboardInterrupt from None
    except (InputError, SimulationError) as exc:
        result.notes.append(f"reference: projection at rtol 1e-13 (not cross-checked: {exc})")
    if math.isfinite(result.reference_error) and result.reference_error > 1e-6:
        result.notes.append(
            "the reference itself cannot be trusted to better than "
            f"{result.reference_error:.1e} m at t_end (chaotic or very sensitive motion): judge "
            "the methods on constraint residual and energy drift, or shorten t_end"
        )
    model = assemble(system)  # one model for every run: solvers keep what they build on it
    model_terms = set(ref.info.get("active_terms", ()))
    frame_charge = None  # rheonomic: the moving frame's charge Q, the drift column then measures h − Q
    lost = sorted(model_terms & {"dissipation", "applied_force", "time_dependent_forces"})
    if lost:
        result.notes.append(f"energy drift: blank, no energy-like integral is conserved ({', '.join(lost)})")
    elif "rheonomic" in model_terms:
        frame_charge, why = jacobi_integral(model)
        if frame_charge is None:
            result.notes.append("energy drift: blank, the constraints depend on time and the energy function "
                                f"h is not conserved; no Jacobi integral found instead ({why})")
        else:
            result.notes.append(
                f"energy drift: of the Jacobi integral h − p·ξ (the energy in the frame moving with the "
                f"constraints: {why}; for a rotation p·ξ = ω L_axis), conserved although h is not")
    result.conserves_energy = not lost and ("rheonomic" not in model_terms or frame_charge is not None)
    for method in methods:
        try:
            with _casadi_stderr() as printed:
                _bench_method(result, system, t_end, method, tolerances, repeats, model, measure, progress,
                              frame_charge)
        except (KeyboardInterrupt, RunInterrupted):  # Ctrl-C: keep the rows done, say where it stopped
            result.interrupted = True
            result.notes.append(f"interrupted (Ctrl-C) during {method}: the table holds the rows measured "
                                "before; the rest were not run")
            _report_casadi_messages(result, method, printed)
            break
        _report_casadi_messages(result, method, printed)
    return result


def _bench_method(result, system, t_end, method, tolerances, repeats, model, measure, progress,
                  frame_charge=None) -> None:
    """The rows of one method: each setting timed ``repeats`` times, then measured densely."""
    name, _, base = method.partition(":")  # "projection:CVODES" picks a base integrator
    extra = {"base": base} if base else {}
    settings = (
        [dict(dt=dt) for dt in rattle_steps(len(tolerances))]
        if name == "rattle"
        else [dict(rtol=tol, atol=tol, **extra) for tol in tolerances]
    )
    for opts in settings:
        if progress:
            progress(method, opts)
        row = {"method": method, "rtol": opts.get("rtol", float("nan")),
               "dt": opts.get("dt", float("nan")), "status": "ok"}
        if opts.get("dt", 0.0) >= t_end:  # one step cut to t_end: every such row would be the same run
            row["status"] = f"skipped: step dt = {opts['dt']:g} s is not shorter than t_end = {t_end:g} s"
            result.rows.append(row)
            continue
        times, calls = [], []
        try:
            for _ in range(1 + repeats):  # the first: a warm-up (compiles what is compiled once)
                started = time.perf_counter()
                tr = simulate(system, t_end, method=name, t_eval=[0.0, t_end], model=model,
                              outputs={"energy", "constraint_residual", "velocity_residual"}, **opts)
                calls.append(time.perf_counter() - started)
                times.append(tr.stats["wall_time_s"])
        except RunInterrupted:  # Ctrl-C: not a failed method; the measurement stops
            raise KeyboardInterrupt from None
        except InputError as exc:  # the method refuses the scene: one row says why, not one per setting
            row["status"] = f"refused: {str(exc).splitlines()[0]}"
            result.rows.append(row)
            return
        except SimulationError as exc:
            row["status"] = f"failed: {str(exc).splitlines()[0][:120]}"
            result.rows.append(row)
            continue
        if not _same_end(tr, result):
            row["status"] = (f"not comparable: ended at t = {float(tr.t[-1]):.10g} s "
                             f"({tr.info.get('stop', '')}), the reference at {result.t_stop:.10g} s "
                             f"({result.stop})")
            result.rows.append(row)
            continue
        try:  # every step's residuals and energy (no output grid)
            dense = simulate(system, t_end, method=name, model=model, **opts,
                             outputs={"energy", "constraint_residual", "velocity_residual"})
        except RunInterrupted:
            raise KeyboardInterrupt from None
        except (InputError, SimulationError) as exc:
            row["status"] = f"failed without an output grid: {str(exc).splitlines()[0][:100]}"
            result.rows.append(row)
            continue
        row.update(
            error=measure(tr),
            constraint_residual=float(np.max(dense.constraint_residual)),
            velocity_residual=float(np.max(dense.velocity_residual)),
            energy_drift=_drift(dense, frame_charge) if result.conserves_energy else float("nan"),
            wall_time_s=statistics.median(times[1:]),
            compile_time_s=max(0.0, calls[0] - statistics.median(calls[1:])),
            steps=int(tr.stats.get("steps", 0)),
            nfev=int(tr.stats.get("nfev", 0)),
        )
        result.rows.append(row)


def _drift(tr, frame_charge=None) -> float:
    """max |h − h0| over a run, or of h − Q (the Jacobi integral) when the constraints move."""
    h = np.asarray(tr.energy, float).ravel()
    if frame_charge is not None:
        n = len(h)
        h = h - np.asarray(frame_charge.map(n)(np.asarray(tr.x, float).reshape(n, -1).T,
                                                 np.asarray(tr.v, float).reshape(n, -1).T,
                                                 np.asarray(tr.t, float).ravel()[None, :])).ravel()
    return float(np.max(np.abs(h - h[0])))


def _same_end(tr, result: BenchResult) -> bool:
    """Whether a run ended the way the reference did (same stop, at about the same time):
    its end state is then comparable with the reference's (|t − t_ref| ≤ 1e-3 max(t_ref, 1 s)
    for a terminal event, each run locating it on its own solution)."""
    if not math.isfinite(result.t_stop):
        return True
    t = float(tr.t[-1])
    if str(tr.info.get("stop", "")) != result.stop:
        return False
    return abs(t - result.t_stop) <= 1e-3 * max(abs(result.t_stop), 1.0)


#: CasADi messages a bench summarizes in a note instead of repeating: pattern -> plain words
_CASADI_NOTES = {
    "NLP is overconstrained": (
        "CasADi said {count} time(s) that an NLP \"is overconstrained\": {method} set up a "
        "system with more equations than unknowns (the constraints together with their time "
        "derivatives, which agree on the constraint manifold). It is a notice, not a failure: the "
        "rows are measured all the same, so judge {method} by its error and residual columns."
    ),
}


@contextmanager
def _casadi_stderr():
    """Capture what is printed on stderr inside the block — through ``sys.stderr`` (where
    CasADi's Python bindings send its warnings) and on file descriptor 2 (C code writing
    directly); yields the list of lines, filled at the end."""
    lines: list[str] = []
    sys.stderr.flush()
    python_level = io.StringIO()  # CasADi's Python bindings write through sys.stderr
    try:
        saved = os.dup(2)
    except OSError:  # no file descriptor 2: capture what goes through sys.stderr only
        saved = None
    with tempfile.TemporaryFile() as tmp:
        if saved is not None:
            os.dup2(tmp.fileno(), 2)
        try:
            with redirect_stderr(python_level):
                yield lines
        finally:
            if saved is not None:
                os.dup2(saved, 2)
                os.close(saved)
            tmp.seek(0)
            lines.extend(python_level.getvalue().splitlines())
            lines.extend(tmp.read().decode("utf-8", "replace").splitlines())


def _report_casadi_messages(result: BenchResult, method: str, lines: list[str]) -> None:
    """Known CasADi warnings become one note per method; anything else is printed as it was."""
    counts = dict.fromkeys(_CASADI_NOTES, 0)
    for line in lines:
        known = next((k for k in _CASADI_NOTES if k in line), None)
        if known:
            counts[known] += 1
        elif line.strip():
            print(line, file=sys.stderr)
    for key, count in counts.items():
        if count:
            result.notes.append(_CASADI_NOTES[key].format(count=count, method=method))


def _err(error: float, reference_error: float) -> str:
    if math.isfinite(reference_error) and error < reference_error:
        return f"< {reference_error:.1e} (reference limit)"
    return f"{error:.2e}"


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.6g}"
    return str(value)
