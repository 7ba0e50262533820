"""The compile cache kept within a size: ``CONSTRAINED_CACHE_LIMIT_MB`` (default 2,000 MB; 0
or ``none``: no limit).

A library loaded from the cache is marked used (its modification time set to now). After a
new library is written, if the cache's entries (each a library ``NAME_KEY.so`` and its record
``NAME_KEY.json``) together exceed the limit, the least recently used are removed, oldest
first, until they hold 80 % of it: a run that compiles several libraries does not scan the
folder at each one. The entry just written is never removed, nor anything but entries (the
signing key stays). A library another running process has loaded stays mapped after its file
is removed (POSIX), so eviction cannot break a run; that model just compiles again next time.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

DEFAULT_LIMIT_MB = 2000.0
#: After an eviction the entries hold this fraction of the limit.
LOW_WATER = 0.8

_warned: set[str] = set()


def limit_bytes() -> float | None:
    """The limit in bytes, or None for none (``CONSTRAINED_CACHE_LIMIT_MB``: a number of MB ≥ 0;
    anything else is named in one warning and the default used)."""
    text = os.environ.get("CONSTRAINED_CACHE_LIMIT_MB", "").strip()
    if not text:
        return DEFAULT_LIMIT_MB * 1e6
    if text.lower() == "none":
        return None
    try:
        mb = float(text)
    except ValueError:
        mb = -1.0
    if not mb >= 0 or mb == float("inf"):
        if text not in _warned:
            _warned.add(text)
            print(f"constrained: warning: CONSTRAINED_CACHE_LIMIT_MB={text!r} is not a size in MB (a number "
                  f"≥ 0, or none); using {DEFAULT_LIMIT_MB:g}", file=sys.stderr, flush=True)
        return DEFAULT_LIMIT_MB * 1e6
    return None if mb == 0 else mb * 1e6


def mark_used(library: Path) -> None:
    """Mark a cache entry used now (its library's modification time)."""
    try:
        os.utime(library)
    except OSError:  # (a read-only cache still serves)
        pass


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def evict(folder: Path, keep: Path) -> list[str]:
    """Remove the least recently used entries of ``folder`` (never ``keep``) while they exceed
    the limit, down to LOW_WATER of it; the names of the libraries removed."""
    limit = limit_bytes()
    if limit is None:
        return []
    entries = []
    for library in folder.glob("*.so"):
        try:
            used = library.stat().st_mtime
        except OSError:
            continue
        record = library.with_suffix(".json")
        entries.append((used, _size(library) + _size(record), library, record))
    total = sum(size for _, size, _, _ in entries)
    if total <= limit:
        return []
    removed = []
    for _, size, library, record in sorted(entries, key=lambda e: e[0]):
        if total <= LOW_WATER * limit:
            break
        if library == keep:
            continue
        try:  # the library first: a record without its library is never loaded
            library.unlink(missing_ok=True)
            record.unlink(missing_ok=True)
        except OSError:
            continue
        total -= size
        removed.append(library.name)
    return removed
