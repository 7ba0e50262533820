"""``--set`` overrides: ``"KEY=VALUE"`` strings applied to a scene's TOML data.

KEY is a dotted path (``simulate.t_end``, ``parameters.k``), with entries of arrays of
tables addressed by index (``particles[0].mass``) or by name (``particles.p1.mass``); VALUE
is read as a TOML value. ``data_copy`` copies TOML-like data several times faster than
``copy.deepcopy``.
"""

from __future__ import annotations

import copy
import re
import sys
from collections.abc import Iterable, Mapping
from typing import Any

from .. import tomlparse
from ..errors import SceneError


def apply_overrides(raw: Mapping, overrides: Iterable[str] | None, *, file=None) -> dict:
    """A deep copy of ``raw`` with ``--set`` overrides ``"KEY=VALUE"`` applied.

    KEY is a dotted path (``simulate.t_end``, ``parameters.k``, ``reduced.initial.th1``);
    entries of ``[[particles]]``, ``[[constraints]]``, ``[[effects]]`` are addressed by index
    (``particles[0].mass``) or by their ``name`` (``particles.p1.mass``). VALUE is read as a
    TOML value (``2``, ``[1, 0, 0]``, ``"sin(t)"``); a bare word that is not TOML is a string.
    Keys that do not exist are added, so that validation refuses them like keys in the file.
    """
    out, _ = _apply_overrides(raw, list(overrides or []), None if file is None else str(file))
    return out


def parse_override(text: str, *, file=None) -> tuple[list[str | int], Any]:
    """Split ``"KEY=VALUE"`` into the key path (names and indices) and the parsed value."""
    if not isinstance(text, str) or "=" not in text:
        raise SceneError(
            f"--set {text!r}: expected KEY=VALUE, e.g. simulate.t_end=2",
            file=file,
            key=text.strip() if isinstance(text, str) and text.strip() else None,
        )
    key, value = text.split("=", 1)
    key = key.strip()
    if not _KEY_RE.fullmatch(key):
        raise SceneError(
            f"--set {text!r}: {key!r} is not a key path (write e.g. simulate.t_end, "
            "particles.p1.mass or particles[0].mass)",
            file=file,
            key=key or None,
        )
    tokens: list[str | int] = []
    try:
        for name, index in _TOKEN_RE.findall(key):
            tokens.append(name if name else int(index))
        return tokens, _parse_value(value.strip())
    except SceneError:
        raise
    except ValueError:  # (int() refuses more than sys.get_int_max_str_digits() digits)
        raise SceneError(f"--set {key[:60]}=…: a number too long to read (an integer of more than "
                         f"{sys.get_int_max_str_digits()} digits)", file=file, key=key[:60]) from None


# --- overrides -------------------------------------------------------------------------------

#: A name segment: letters (any script: particle and parameter names are identifiers, and
#: ``ballé``, ``λ`` are identifiers), digits, ``_`` and ``-``; then ``[index]`` suffixes.
_NAME = r"(?:[^\W]|-)+"
_SEG = rf"{_NAME}(?:\[[0-9]+\])*"
_KEY_RE = re.compile(rf"{_SEG}(?:\.{_SEG})*")
_TOKEN_RE = re.compile(rf"({_NAME})|\[([0-9]+)\]")


#: A decimal number as TOML writes one (no leading zeros, digits on both sides of the point).
_NUMBER_RE = re.compile(r"[+-]?(?:0|[1-9][0-9]*)(?:(\.[0-9]+)?([eE][+-]?[0-9]+)?)")


_NUMBERS_RE = re.compile(rf"\[\s*(?:{_NUMBER_RE.pattern}\s*,\s*)*{_NUMBER_RE.pattern}\s*,?\s*\]")


def _parse_value(text: str):
    number = _NUMBER_RE.fullmatch(text)
    if number:  # the common case, read as TOML would without its parser
        return float(text) if number.group(1) or number.group(2) else int(text)
    if _NUMBERS_RE.fullmatch(text):  # a list of such numbers (a position, a vector)
        return [_parse_value(entry.strip()) for entry in text.strip()[1:-1].split(",") if entry.strip()]
    try:
        return tomlparse.loads(f"value = {text}")["value"]
    except (tomlparse.TOMLDecodeError, RecursionError):
        pass
    try:
        return float(text) if any(c in text for c in ".eE") or text.lower() in ("inf", "nan") else int(text)
    except ValueError:
        return text


def _apply_overrides(raw: Mapping, overrides: list[str], file: str | None):
    """Apply overrides; returns the new dict and [(canonical key path, override text)]."""
    out = data_copy(dict(raw))
    applied: list[tuple[str, str]] = []
    for text in overrides:
        tokens, value = parse_override(text, file=file)
        key = text.split("=", 1)[0].strip()
        cur: Any = out
        canon = ""
        for pos, tok in enumerate(tokens):
            last = pos == len(tokens) - 1
            if isinstance(tok, int):
                if not isinstance(cur, list):
                    raise SceneError(
                        f"--set {text}: {canon or 'the scene'} is not a list, it cannot be indexed",
                        file=file,
                        key=key,
                    )
                if tok >= len(cur):
                    raise SceneError(
                        f"--set {text}: index {tok} is out of range ({canon} has {len(cur)} entries)",
                        file=file,
                        key=key,
                    )
                canon = f"{canon}[{tok}]"
                if last:
                    cur[tok] = value
                else:
                    cur = cur[tok]
                continue
            if isinstance(cur, list):
                found = [i for i, e in enumerate(cur) if isinstance(e, dict) and e.get("name") == tok]
                if not found:
                    names = [e.get("name") for e in cur if isinstance(e, dict) and "name" in e]
                    listed = ", ".join(map(str, names)) or "none has a name"
                    raise SceneError(
                        f"--set {text}: {canon} has no entry named '{tok}' ({listed}); "
                        f"address entries by name or by index, e.g. {canon}[0]",
                        file=file,
                        key=key,
                    )
                canon = f"{canon}[{found[0]}]"
                if last:
                    cur[found[0]] = value
                else:
                    cur = cur[found[0]]
                continue
            if not isinstance(cur, dict):
                raise SceneError(
                    f"--set {text}: {canon} is a value ({cur!r}), not a table",
                    file=file,
                    key=key,
                )
            canon = f"{canon}.{tok}" if canon else tok
            if last:
                cur[tok] = value
            else:
                if tok not in cur:
                    if isinstance(tokens[pos + 1], int):
                        raise SceneError(
                            f"--set {text}: the scene has no list '{canon}' to index",
                            file=file,
                            key=key,
                        )
                    cur[tok] = {}
                cur = cur[tok]
        applied.append((canon, text.strip()))
    return out, applied


def _override_origin(key: str | None, applied: list[tuple[str, str]]) -> str | None:
    if not key:
        return None
    for canon, text in reversed(applied):
        if key == canon or any(a.startswith(b + c) for a, b in ((key, canon), (canon, key)) for c in ".["):
            return text if len(text) <= 80 else text[:77] + "..."
    return None

def data_copy(value):
    """A deep copy of TOML-like data (dicts, lists, scalars), several times faster than
    ``copy.deepcopy``; anything else is deep-copied the usual way."""
    if isinstance(value, dict):
        return {k: data_copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [data_copy(v) for v in value]
    if value is None or isinstance(value, str | int | float | bool | tuple):
        return value if not isinstance(value, tuple) else copy.deepcopy(value)
    return copy.deepcopy(value)
