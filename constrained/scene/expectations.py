"""The [expect] table of a scene: checks of a finished run (closed forms, drifts, residuals,
periods, bounds) and which quantities they need. ``scene`` arguments are
:class:`constrained.scene.Scene` objects."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from ..model import expressions
from ..model.symbols import Symbols


@dataclass
class ExpectResult:
    """One [expect] check of a run: ``ok``, the ``value`` found, the ``tolerance``, a ``line``.

    ``by_construction``: the checked quantity is one the run enforces by construction — a
    constraint residual under a method that projects onto the constraints, or a formula that is
    a function of the constraints alone (a rod length): its passing is evidence of the method's
    projection, not of the dynamics, and reports say so.
    """

    key: str
    ok: bool
    value: float
    tolerance: float
    line: str
    by_construction: bool = False


_NEEDS = {
    "energy_drift": "energy",
    "constraint_residual": "constraint_residual",
    "velocity_residual": "velocity_residual",
}


def force_names(symbols: Symbols) -> dict:
    """``Fx_NAME, Fy_NAME, Fz_NAME``: constraint-force components, usable in [expect] formulas."""
    if not hasattr(symbols, "_expect_forces"):
        import casadi as ca

        symbols._expect_forces = ca.SX.sym("Fc", symbols.x.numel())
        symbols._expect_force_names = {
            f"F{axis}_{p.name}": symbols._expect_forces[3 * i + k]
            for i, p in enumerate(symbols.system.particles)
            for k, axis in enumerate("xyz")
        }
    return symbols._expect_force_names


def _uses_forces(text) -> bool:
    return isinstance(text, str) and any(re.fullmatch(r"F[xyz]_\w+", n) for n in expressions.free_names(text))


def expect_requirements(scene: Any) -> set[str]:
    """Trajectory quantities the scene's [expect] checks need (besides t, x, v)."""
    need = {_NEEDS[c["kind"]] for c in scene.expectations or () if c["kind"] in _NEEDS}
    if any(_uses_forces(c.get(k)) for c in scene.expectations or () for k in ("lhs", "rhs")):
        need.add("constraint_forces")
    return need


def _series(symbols: Symbols, text, traj, where: str) -> np.ndarray:
    """A formula in x_NAME, vx_NAME, Fx_NAME, ..., t and parameters, at every sample of ``traj``."""
    import casadi as ca

    forces = force_names(symbols)
    expr = ca.SX(symbols.parse(text, where, velocities=True, extra=forces))
    fun = ca.Function("expect", [symbols.x, symbols.v, symbols.t, symbols._expect_forces], [expr])
    n = len(traj.t)
    x = np.asarray(traj.x, float).reshape(n, -1).T
    v = np.asarray(traj.v, float).reshape(n, -1).T
    if _uses_forces(text):
        if traj.constraint_forces is None:
            raise InputError("uses constraint forces (F..._NAME) but the run has none", where=where)
        fc = np.asarray(traj.constraint_forces, float).reshape(n, -1).T
    else:
        fc = np.zeros_like(x)
    return np.asarray(fun.map(n)(x, v, np.asarray(traj.t, float)[None, :], fc)).ravel()


def drift(values: np.ndarray) -> tuple[float, str]:
    """max |Q − Q0| / |Q0| (absolute when Q0 = 0) and the words for it."""
    q0 = float(values[0])
    worst = float(np.max(np.abs(values - q0)))
    if q0 != 0.0:
        return worst / abs(q0), "relative"
    return worst, "absolute, initial value 0"


def period(t: np.ndarray, y: np.ndarray) -> float | None:
    """Mean time between upward crossings of the mid-level (max + min)/2; None if < 2."""
    mid = 0.5 * (float(np.max(y)) + float(np.min(y)))
    d = y - mid
    k = np.nonzero((d[:-1] < 0) & (d[1:] >= 0))[0]
    if len(k) < 2:
        return None
    crossings = t[k] - d[k] * (t[k + 1] - t[k]) / (d[k + 1] - d[k])
    return float(np.mean(np.diff(crossings)))


def closed_form_positions(scene: Any) -> list[dict]:
    """The ``[expect] closed_form`` entries whose left side is a position coordinate name."""
    names = {f"{axis}_{p.name}" for p in scene.system.particles for axis in "xyz"}
    return [c for c in scene.expectations or () if c["kind"] == "closed_form" and c["lhs"].strip() in names]


def closed_form_error(scene: Any, trajectory) -> tuple[float, list[str]] | None:
    """The largest |coordinate − closed form| at the last sample over the scene's
    ``[expect] closed_form`` entries for plain position coordinates (``x_NAME``, ``y_NAME``,
    ``z_NAME``), and their names; None when the scene declares none. Closed forms of other
    expressions (invariants such as a rod length) say nothing about the motion and are left out.

    This is the reference ``constrained bench`` uses when a scene has a closed form."""
    checks = closed_form_positions(scene)
    if not checks:
        return None
    symbols = Symbols(scene.system)
    worst = 0.0
    for c in checks:
        lhs = _series(symbols, c["lhs"], trajectory, c["key"])
        rhs = _series(symbols, c["rhs"], trajectory, f"{c['key']}[0]")
        worst = max(worst, float(abs(lhs[-1] - rhs[-1])))
    return worst, [c["lhs"] for c in checks]


def check_expectations(scene: Any, trajectory, model=None) -> list[ExpectResult]:
    """Evaluate the scene's [expect] checks on a finished ``trajectory``; one result each.

    A check whose data is missing (e.g. no energy in the trajectory) fails with a message.
    """
    if not scene.expectations:
        return []
    symbols = Symbols(scene.system)
    tr = trajectory
    t = np.asarray(tr.t, float)
    out = []

    method = (getattr(tr, "info", None) or {}).get("method")

    def result(c, ok, value, tol, text):
        verdict = "PASS" if ok else "FAIL"
        construction = _by_construction(c, symbols, tr, method)
        note = f" [by construction: {construction}; not evidence of the dynamics]" if construction else ""
        line = f"{verdict} {c['key']}: {text}{note}"
        out.append(ExpectResult(c["key"], bool(ok), float(value), float(tol), line, bool(construction)))

    for c in scene.expectations:
        try:
            _check_one(c, symbols, tr, t, model, result)
        except InputError as exc:
            result(c, False, math.nan, c.get("tol", 0.0), f"cannot be evaluated: {exc.reason}")
    return out


#: Methods whose every output lies on both constraint manifolds (projected, or mapped from q).
PROJECTING_METHODS = frozenset({"projection", "dopri", "rattle", "idas", "reduced"})


def _by_construction(c, symbols: Symbols, tr, method: str | None) -> str:
    """Why check ``c`` holds by construction of the run, or "" when it is evidence."""
    import casadi as ca

    kind = c["kind"]
    if kind in ("constraint_residual", "velocity_residual"):
        return f"method '{method}' projects onto the constraints" if method in PROJECTING_METHODS else ""
    if (kind not in ("final", "closed_form", "bounds", "period") or _uses_forces(c["lhs"])
            or method not in PROJECTING_METHODS):
        return ""
    try:
        expr = ca.SX(symbols.parse(c["lhs"], c["key"], velocities=True))
    except InputError:
        return ""
    # one-sided constraints are not held throughout: a function of them is evidence
    rows = [e for con in symbols.system.constraints if not con.unilateral and con.level == "position"
            for e, _ in con.rows(symbols)]  # (velocity rows hold no function of x alone)
    if not rows or ca.depends_on(expr, symbols.v) or ca.depends_on(expr, symbols.t) or expr.is_constant():
        return ""
    f = ca.vertcat(*rows)
    grads = ca.Function("g", [symbols.x, symbols.t],
                        [ca.jacobian(f, symbols.x), ca.gradient(expr, symbols.x)])
    n = len(tr.t)
    for k in sorted({0, n // 2, n - 1}):
        J, g = (np.asarray(o, float) for o in grads(np.asarray(tr.x[k], float).ravel(), float(tr.t[k])))
        g = g.ravel()
        if not np.any(g):
            continue
        mu, *_ = np.linalg.lstsq(J.T, g, rcond=None)
        if np.linalg.norm(J.T @ mu - g) > 1e-8 * np.linalg.norm(g):
            return ""
    return f"{c['lhs']} is a function of the constraints, held by method '{method}'"


def _check_one(c, symbols, tr, t, model, result) -> None:
    """Evaluate one normalized [expect] check and report it through ``result``."""
    from ..analysis.symmetry import noether_charge

    kind, tol = c["kind"], c.get("tol", 0.0)
    if kind in _NEEDS:
        data = getattr(tr, _NEEDS[kind], None)
        if data is None or not len(data):
            result(c, False, math.nan, tol, f"the run has no {_NEEDS[kind]}")
            return
        data = np.asarray(data, float)
        if kind == "energy_drift":
            value, how = drift(data)
            ratio = " / |E0|" if data[0] != 0 else ""
            text = f"max |E - E0|{ratio} = {value:.3g} ({how}; E0 = {data[0]:.6g} J)"
        else:
            value = float(np.max(np.abs(data)))
            text = f"max = {value:.3g}"
        result(c, value <= tol, value, tol, f"{text}, tolerance {tol:g}")
    elif kind in ("final", "closed_form", "period"):
        lhs = _series(symbols, c["lhs"], tr, c["key"])
        rhs = _series(symbols, c["rhs"], tr, f"{c['key']}[0]")
        if kind == "final":
            value = abs(lhs[-1] - rhs[-1])
            text = (f"at t = {t[-1]:.6g} s {c['lhs']} = {lhs[-1]:.10g}, expected {rhs[-1]:.10g}, "
                    f"|difference| = {value:.3g}")
        elif kind == "closed_form":
            diff = np.abs(lhs - rhs)
            value = float(np.max(diff))
            text = (f"max |{c['lhs']} - ({c['rhs']})| over {len(t)} samples = {value:.3g} "
                    f"(at t = {t[int(np.argmax(diff))]:.4g} s)")
        else:
            found = period(t, lhs)
            if found is None:
                result(c, False, math.nan, tol, f"{c['lhs']} crosses its mid-level fewer than twice "
                       f"upward in t = {t[0]:g} .. {t[-1]:g} s: no period measured (run longer)")
                return
            value = abs(found - rhs[0])
            text = (f"period of {c['lhs']} = {found:.8g} s, expected {rhs[0]:.8g} s, "
                    f"|difference| = {value:.3g}")
        result(c, value <= tol, value, tol, f"{text}, tolerance {tol:g}")
    elif kind in ("bounds", "reaches"):
        y = _series(symbols, c["lhs"], tr, c["key"])
        lo, hi = c["lo"], c["hi"]
        inside = (y >= lo) & (y <= hi)
        span = f"[{lo:.10g}, {hi:.10g}]"
        if kind == "bounds":
            ok = bool(np.all(inside))
            text = f"{c['lhs']} ranges over [{np.min(y):.6g}, {np.max(y):.6g}], required within {span}"
            value = float(np.count_nonzero(~inside))
        else:
            ok = bool(np.any(inside))
            first = f"first at t = {t[int(np.argmax(inside))]:.4g} s" if ok else "never"
            text = (f"{c['lhs']} ranges over [{np.min(y):.6g}, {np.max(y):.6g}], must reach {span}: "
                    f"{first}")
            value = float(np.count_nonzero(inside))
        result(c, ok, value, 0.0, text)
    else:  # conserved
        try:
            q = noether_charge(model if model is not None else symbols.system, tr,
                               translation=c["translation"], rotation=c["rotation"])
        except InputError as exc:
            result(c, False, math.nan, tol, f"cannot be computed: {exc}")
            return
        value, how = drift(np.asarray(q, float))
        what = (f"rotation about axis {tuple(c['rotation'][0])} through {tuple(c['rotation'][1])}"
                if c["rotation"] is not None else f"translation along {tuple(c['translation'])}")
        result(c, value <= tol, value, tol,
               f"Noether charge of the {what}: Q0 = {q[0]:.8g}, "
               f"max |Q - Q0|{' / |Q0|' if q[0] != 0 else ''} = {value:.3g} ({how}), tolerance {tol:g}")
