"""One run's output files as one consistent set.

A verb that writes into ``--out DIR`` (run, bench, statics, crosscheck, path, plot) writes
every file into a staging folder beside DIR (``.DIR.staging-<pid>-<id>``) and, once all are
written, puts them into DIR together. The files a verb *owns* are the names it writes (for
``run``: the trajectory files and every figure kind, also those ``plot`` drew from an earlier
trajectory); a new set replaces all of them, so an earlier run's csv or figures never stay
beside a new trajectory:

- DIR does not exist, or holds only files the verb owns: the staging folder is renamed to
  DIR (the old DIR renamed away first, then deleted). A run killed at any moment leaves the
  old set or the new set, never a mix.
- DIR holds other files too (another verb's outputs, the user's own files): the new files
  are renamed into DIR one by one (each rename is atomic), then the owned files the new set
  lacks are deleted. The window for a mix is the microseconds of those renames, not the
  seconds of drawing figures.

A run that stops (bad input, an exception, Ctrl-C) removes its staging folder and leaves DIR
as it was; a staging folder left by a killed process is removed by the next run into the
same DIR. A run that had to stop with a partial trajectory commits that trajectory as its
set, so DIR never shows it beside figures of an earlier run.
"""

from __future__ import annotations

import os
import re
import shutil
import uuid
from pathlib import Path

from ..errors import InputError

__all__ = ["OutputSet", "user_path", "discard_uncommitted"]

_STAGING = re.compile(r"^\.(?P<name>.+)\.(?:staging|old)-(?P<pid>\d+)-[0-9a-f]+$")


def user_path(path) -> str:
    """``path`` with a staging folder replaced by the output folder it stands for (for messages)."""
    parts, out = list(Path(str(path)).parts), []
    for part in parts:
        m = _STAGING.match(part)
        if m:
            if out and out[-1] == m.group("name"):
                continue  # staged inside the folder itself
            part = m.group("name")
        out.append(part)
    return str(Path(*out)) if out else str(path)


class OutputSet:
    """``with OutputSet(out_dir, owns) as outs:`` write to ``outs.dir / name`` (or
    ``outs.path(name)``), then ``outs.commit()`` -> the final paths. Leaving the block without
    committing discards what was written. ``owns``: the file names the new set supersedes
    (besides those it writes), deleted when it lacks them."""

    def __init__(self, out_dir, owns=()):
        self.out = Path(out_dir)
        self.owns = set(owns)
        self.run_id = uuid.uuid4().hex[:12]
        self.final = self.out.absolute()
        if not self.final.name:
            raise InputError(f"--out {out_dir}: give a folder, not the file system root")
        tag = f"{os.getpid()}-{self.run_id}"
        self.dir = self.final.parent / f".{self.final.name}.staging-{tag}"
        self._old = self.final.parent / f".{self.final.name}.old-{tag}"
        self._created: list[Path] = []
        self.committed: list[Path] | None = None

    # --- life cycle ---------------------------------------------------------------------------
    def open(self) -> OutputSet:
        """Like entering the ``with`` block; ``discard_uncommitted()`` (or ``close()``) ends it."""
        self.__enter__()
        _OPEN.append(self)
        return self

    def close(self) -> None:
        """Discard what was written unless committed (idempotent)."""
        self.__exit__(None, None, None)
        if self in _OPEN:
            _OPEN.remove(self)

    def __enter__(self) -> OutputSet:
        if self.final.exists() and not self.final.is_dir():
            raise InputError(f"--out {self.out} exists and is not a directory")
        try:
            missing = []
            parent = self.final.parent
            while not parent.exists():
                missing.append(parent)
                parent = parent.parent
            if not parent.is_dir():
                raise NotADirectoryError(20, "Not a directory", str(parent))
            for d in reversed(missing):
                d.mkdir()
                self._created.append(d)
            self._sweep_stale()
            try:
                self.dir.mkdir()
            except OSError:
                if not self.final.is_dir():
                    raise
                # the parent is not writable, the folder is: stage inside it (no swap then)
                self.dir = self.final / self.dir.name
                self.dir.mkdir()
        except OSError as exc:
            self._remove_created()
            raise InputError(f"cannot write the output folder {self.out}: "
                             f"{exc.strerror or exc}; choose another --out") from None
        return self

    def __exit__(self, *exc) -> bool:
        if self.dir.exists():
            shutil.rmtree(self.dir, ignore_errors=True)
        if self.committed is None:
            self._remove_created()
        return False

    def path(self, name: str) -> Path:
        """Where to write the file ``name`` of this set."""
        return self.dir / name

    # --- commit -----------------------------------------------------------------------------
    def commit(self, written=None) -> list[Path]:
        """Put the set into the output folder; returns the final paths (of ``written``, staged
        paths, in that order, or of every file written)."""
        for leftover in self.dir.glob(".*"):  # a temporary of a writer stopped mid-write: not of the set
            if leftover.is_file():
                leftover.unlink()
        names = sorted(p.name for p in self.dir.iterdir())
        try:
            present = set(os.listdir(self.final)) if self.final.is_dir() else set()
            ours = present & (self.owns | set(names))
            others = present - ours
            swap = (not others and self.dir.parent == self.final.parent and not self.final.is_symlink()
                    and not _holds_cwd(self.final))
            if swap:  # the whole folder is this set's: swap it
                if self.final.is_dir():
                    try:
                        os.rename(self.final, self._old)
                    except OSError:  # a mount point, a busy folder: file by file
                        swap = False
            if swap:
                os.rename(self.dir, self.final)
                shutil.rmtree(self._old, ignore_errors=True)
            else:
                for n in names:
                    os.replace(self.dir / n, self.final / n)
                for n in ours - set(names):
                    try:
                        (self.final / n).unlink()
                    except FileNotFoundError:
                        pass
                    except IsADirectoryError:
                        shutil.rmtree(self.final / n, ignore_errors=True)
        except OSError as exc:
            raise InputError(f"cannot write the output folder {self.out}: {exc.strerror or exc}; "
                             "choose another --out") from None
        self.committed = [self.out / n for n in names]
        if written is None:
            return list(self.committed)
        return [self.out / Path(p).name for p in written]

    # --- helpers ----------------------------------------------------------------------------
    def _sweep_stale(self) -> None:
        """Remove staging folders (and swapped-out old folders) of dead processes."""
        for entry in self.final.parent.iterdir():
            m = _STAGING.match(entry.name)
            if not m or m.group("name") != self.final.name or not entry.is_dir():
                continue
            if _alive(int(m.group("pid"))):
                continue
            if ".old-" in entry.name and not self.final.exists():
                # killed between the two renames of a swap: the old set is the last whole one
                os.rename(entry, self.final)
                continue
            shutil.rmtree(entry, ignore_errors=True)

    def _remove_created(self) -> None:
        for d in reversed(self._created):
            try:
                d.rmdir()
            except OSError:
                break
        self._created = []


_OPEN: list[OutputSet] = []


def discard_uncommitted() -> None:
    """Close every set opened with ``open()`` (the command line calls this when a verb ends)."""
    for outs in list(_OPEN):
        outs.close()


def _holds_cwd(folder: Path) -> bool:
    """Whether ``folder`` is the working directory or one of its parents (never renamed)."""
    try:
        cwd = Path.cwd().resolve()
        folder = folder.resolve()
    except OSError:
        return True
    return cwd == folder or folder in cwd.parents


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # this process stages only under its fresh run id
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
