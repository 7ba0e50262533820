"""Ctrl-C in a subprocess, as the tests of prompt interrupts need it: start a command, wait
until it is busy (a predicate), send SIGINT, and time how long it takes to exit."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def env() -> dict:
    """The environment with this checkout first on PYTHONPATH."""
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def interrupt_when(args: list[str], busy: Callable[[], bool], *, cwd: Path, settle: float = 0.3,
                   timeout: float = 90.0) -> tuple[int, float, str]:
    """Run ``python -m constrained.cli ARGS``; once ``busy()`` holds (polled every 50 ms; the
    command must still be running), wait ``settle`` seconds and send SIGINT. Returns (exit
    status, seconds from SIGINT to exit, stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "constrained.cli", *args], env=env(), cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + timeout
        while not busy():
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "the command never got busy"
            time.sleep(0.05)
        time.sleep(settle)
        assert proc.poll() is None, "the command ended before it could be interrupted"
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        err = proc.communicate(timeout=60)[1]
        return proc.returncode, time.monotonic() - sent, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
