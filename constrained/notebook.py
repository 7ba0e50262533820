"""Jupyter display: the summary tables of ``_repr_html_`` and the views upper floors add.

A Trajectory, a Scene or a System writes its own summary table (``table``). What needs a
floor above the object's own — the interactive viewer of a trajectory lives in ``output/`` —
is a *view* that the package's entry (``constrained/__init__.py``) registers here, so that no
module imports upward: ``view("viewer", trajectory, system=...)`` returns its HTML, or "" when
none is registered. A view that fails shows a one-line note, never a traceback in the cell.
Ground floor: imports nothing of the package.
"""

from __future__ import annotations

import html
from collections.abc import Callable, Iterable

#: name -> function(obj, **options) -> HTML text
VIEWS: dict[str, Callable[..., str]] = {}


def register(name: str, function: Callable[..., str]) -> None:
    """Make ``view(name, ...)`` call ``function``."""
    VIEWS[name] = function


def view(name: str, obj, **options) -> str:
    """The HTML of the view ``name`` of ``obj`` ("" when no such view is registered)."""
    function = VIEWS.get(name)
    if function is None:
        return ""
    try:
        return function(obj, **options)
    except Exception as exc:  # noqa: BLE001 - a display must not raise into the notebook
        return f"<p><i>({html.escape(name)} not shown: {html.escape(f'{type(exc).__name__}: {exc}')})</i></p>"


def table(title: str, rows: Iterable[tuple[str, object]], *, note: str = "") -> str:
    """An HTML table of ``(key, value)`` rows under a bold ``title`` (every text escaped)."""
    body = "".join(
        f"<tr><th style='text-align:left;padding-right:1em'>{html.escape(str(key))}</th>"
        f"<td style='text-align:left'>{html.escape(str(value))}</td></tr>"
        for key, value in rows
    )
    tail = f"<div style='color:#666'>{html.escape(note)}</div>" if note else ""
    return f"<div><b>{html.escape(title)}</b><table>{body}</table>{tail}</div>"
