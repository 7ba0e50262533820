"""Reporting an Equilibrium: the plain-text report, its JSON and the statics figure."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .statics import FORCE_RTOL, LENGTH_RTOL, Equilibrium


def accuracy(eq: Equilibrium) -> tuple[float, float]:
    """``(metres, newtons)``: how well the solve determines positions and forces — its
    convergence tolerances (``LENGTH_RTOL`` × the configuration's size, ``FORCE_RTOL`` × the
    largest force), or the residuals it reached where those are larger. A value below them is
    round-off: the report shows it as 0."""
    x = np.asarray(eq.x, dtype=float).reshape(-1, 3)
    size = max(float(np.max(np.linalg.norm(x, axis=1), initial=0.0)),
               float(np.max(np.ptp(x, axis=0))) if len(x) > 1 else 0.0) or 1.0
    forces = [np.asarray(eq.applied_forces), np.asarray(eq.constraint_forces)]
    force_scale = max(float(np.max(np.abs(f), initial=0.0)) for f in forces) or 1.0
    metres = max(LENGTH_RTOL * size, float(eq.max_constraint_residual))
    newtons = max(FORCE_RTOL * force_scale, float(eq.virtual_work_residual),
                  float(eq.constraint_virtual_work_residual))
    return metres, newtons


def _num(value: float, below: float) -> str:
    """``value`` to 6 digits, or 0 when it is below ``below`` (round-off; never "-0")."""
    return "0" if abs(value) <= below or value == 0 else f"{float(value):.6g}"


def _vec(v, below: float = 0.0) -> str:
    return "(" + ", ".join(_num(float(c), below) for c in v) + ")"


def format_equilibrium(eq: Equilibrium, title: str | None = None) -> str:
    """A plain-text report: positions, multipliers, reactions, stability, residuals. Values
    below the solve's accuracy (``accuracy``, said once at the top) are shown as 0."""
    names = eq.particle_names or [f"p{i}" for i in range(len(eq.x))]
    metres, newtons = accuracy(eq)
    out = [title] if title else []
    out.append(f"equilibrium at t = {eq.t:g} s ({eq.method}, {eq.iterations} iterations)")
    out.append(f"accuracy of the solve: positions {metres:.1g} m, forces {newtons:.1g} N "
               "(values below it are shown as 0)")
    out.append("positions [m], applied force F and constraint force (Jᵀλ)_i [N]:")
    for i, n in enumerate(names):
        out.append(
            f"  {n}: x = {_vec(eq.x[i], metres)}, F = {_vec(eq.applied_forces[i], newtons)}, "
            f"constraint force = {_vec(eq.constraint_forces[i], newtons)}"
        )
    if len(eq.multipliers):
        out.append("multipliers λ (force on particle i is (Jᵀλ)_i; N for rows in metres):")
        scales = eq.row_scales if eq.row_scales is not None and len(eq.row_scales) == len(eq.multipliers) \
            else np.ones(len(eq.multipliers))
        for label, v, scale in zip(eq.constraint_labels, eq.multipliers, scales, strict=True):
            out.append(f"  {_num(v, newtons / max(float(scale), 1e-300)):>12}  {label}")
    if eq.slack:
        out.append("one-sided constraints slack at the equilibrium (not touching there, or their force "
                   "would have the forbidden sign; multiplier 0): " + ", ".join(eq.slack))
    if eq.anchor_reactions:
        out.append("support reactions (force the support exerts; the load on it is the negative) [N]:")
        for label, f in eq.anchor_reactions:
            out.append(f"  {_vec(f, newtons)}  {label}")
    verdict = {True: "STABLE (strict minimum of V on the constraints)",
               False: "UNSTABLE (a negative eigenvalue)",
               None: "NEUTRAL (zero eigenvalues: soft modes)" if eq.conservative
               else "not assessed (forces are not conservative)"}[eq.stable]
    if eq.stable is None and eq.velocity_constraints:
        verdict = "not decided by the energy method (velocity constraints: see below)"
    if getattr(eq, "undecided_by_self_stress", False):
        verdict = ("not decided: negative ω² at the minimum-norm multipliers, but redundant constraints "
                   "carry a self-stress that changes them (another valid split may hold the motions)")
    out.append(f"stability: {verdict}")
    # round-off here too: ω² below the verdict's tolerance is 0, and an eigenvalue of the
    # tangent-space Hessian below the same fraction of the largest one
    omega2 = np.asarray(eq.frequencies_squared if eq.frequencies_squared is not None else [], float)
    eig = np.asarray(eq.eigenvalues, float)
    relative = eq.stability_tolerance / max(float(np.max(np.abs(omega2), initial=0.0)), 1e-300)
    eig_zero = min(relative, 1.0) * float(np.max(np.abs(eig), initial=0.0))
    out.append(
        "  tangent-space eigenvalues of ∇²(V − λ·f) [N/m]: "
        + (", ".join(_num(e, eig_zero) for e in eig) or "none (no freedom)")
    )
    if len(omega2):
        out.append(
            "  squared frequencies ω² of small oscillations [1/s²]: "
            + ", ".join(_num(e, eq.stability_tolerance) for e in omega2)
            + "  (zero below the round-off of the stiffness: Equilibrium.stability_tolerance)"
        )
    for k, mode in enumerate(eq.soft_modes):  # unit shapes: components below 1e-9 are round-off
        moving = [f"{names[i]} {_vec(mode[i], 1e-9)}" for i in range(len(mode))
                  if np.linalg.norm(mode[i]) > 1e-9]
        out.append(f"  soft mode {k + 1}: " + "; ".join(moving))
    if eq.velocity_constraints:
        out.append(eq.velocity_constraints)
    # V is known to (largest force) × (position accuracy)
    energy_zero = metres * max(float(np.max(np.abs(eq.applied_forces), initial=0.0)), newtons)
    V = float(eq.potential_energy)
    out.append(f"potential energy V = {'0' if abs(V) <= energy_zero else f'{V:.10g}'} J")
    out.append(
        f"virtual-work residual max|δW| (unit δx) = {eq.virtual_work_residual:.3g} J/m; "
        f"constraint forces' virtual work {eq.constraint_virtual_work_residual:.3g} J/m; "
        f"max constraint residual {eq.max_constraint_residual:.3g}"
    )
    return "\n".join(out)


def write_equilibrium_json(eq: Equilibrium, path) -> Path:
    """Write ``eq.to_dict()`` (the raw numbers) and the solve's ``accuracy`` as JSON, atomically."""
    from ..run.trajectory import atomic_write

    path = Path(path)
    metres, newtons = accuracy(eq)
    text = json.dumps({**eq.to_dict(), "accuracy": {"position_m": metres, "force_N": newtons}}, indent=2)
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))
    return path


def _numeric_point(point) -> np.ndarray | None:
    try:
        p = np.array([float(c) for c in point])
    except (TypeError, ValueError):
        return None
    return p if p.shape == (3,) and np.all(np.isfinite(p)) else None


def equilibrium_figure(eq: Equilibrium, system):
    """The configuration in its plane (the two axes of largest extent) with force arrows:
    applied forces (blue), constraint forces (red), support forces at fixed points (green)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ..model.constraints import Distance, Pin

    x = eq.x
    index = {n: i for i, n in enumerate(system.names)}
    links, anchors = [], []
    for c in system.constraints:
        if isinstance(c, Distance) and c.b is not None:
            links.append((x[index[c.a]], x[index[c.b]]))
        elif isinstance(c, Distance | Pin):
            p = _numeric_point(c.point)
            if p is not None:
                anchors.append(p)
                links.append((x[index[c.a]], p))
    pts = np.vstack([x, *anchors]) if anchors else x
    spread = np.ptp(pts, axis=0)
    axes = sorted(np.argsort(spread)[-2:].tolist())
    extent = float(max(np.max(spread), 1e-9))
    forces = [eq.applied_forces, eq.constraint_forces]
    fmax = max([float(np.max(np.linalg.norm(f, axis=1), initial=0.0)) for f in forces]
               + [float(np.linalg.norm(f)) for _, f in eq.anchor_reactions] + [1e-300])
    scale = 0.25 * extent / fmax

    fig = Figure(figsize=(7.0, 6.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    a, b = axes
    for p, q in links:
        ax.plot([p[a], q[a]], [p[b], q[b]], color="0.4", lw=1.5, zorder=1)
    for p in anchors:
        ax.plot(p[a], p[b], "^", color="k", ms=9, zorder=3)
    ax.plot(x[:, a], x[:, b], "o", color="k", mfc="white", ms=7, zorder=4)
    for i, n in enumerate(eq.particle_names):
        ax.annotate(n, (x[i, a], x[i, b]), textcoords="offset points", xytext=(5, 5), fontsize="small")

    tips = []

    def arrows(origins, vectors, colour, label):
        first = True
        for o, v in zip(origins, vectors, strict=True):
            if np.hypot(v[a], v[b]) * scale < 1e-6 * extent:
                continue
            ax.quiver(o[a], o[b], v[a] * scale, v[b] * scale, angles="xy", scale_units="xy", scale=1,
                      color=colour, width=0.005, zorder=5, label=label if first else None)
            tips.append([o[a] + v[a] * scale, o[b] + v[b] * scale])
            first = False

    arrows(x, eq.applied_forces, "C0", "applied force F")
    arrows(x, eq.constraint_forces, "C3", "constraint force (Jᵀλ)ᵢ")
    # support forces of rods and pins to the same fixed point are summed: the net reaction there
    net: dict[tuple, np.ndarray] = {}
    for label, f in eq.anchor_reactions:
        for c in system.constraints:
            fixed = isinstance(c, Pin) or (isinstance(c, Distance) and c.b is None)
            at = _numeric_point(c.point) if fixed and c.label == label else None
            if at is not None:
                key = tuple(np.round(at, 12))
                net[key] = net.get(key, np.zeros(3)) + f
                break
    arrows([np.array(k) for k in net], list(net.values()), "C2", "net support force at fixed point")
    if tips:
        ax.update_datalim(np.array(tips))
        ax.autoscale_view()
    verdict = {True: "stable", False: "unstable", None: "neutral / not assessed"}[eq.stable]
    ax.set_title(f"static equilibrium ({verdict}); arrows: {1 / scale:.3g} N per m")
    ax.set_xlabel(f"{'xyz'[a]} [m]")
    ax.set_ylabel(f"{'xyz'[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(fontsize="small")
    return fig


def save_equilibrium_figure(eq: Equilibrium, system, path) -> Path:
    """Draw :func:`equilibrium_figure` and save it as PNG, atomically."""
    from ..run.trajectory import atomic_write

    path = Path(path)
    fig = equilibrium_figure(eq, system)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    return path
