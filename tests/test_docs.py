"""Every code block of README.md and docs/*.md runs as written.

The rules (what a reader following a page does):

* Each page runs top to bottom in a fresh temporary directory holding links to the
  checkout's ``scenarios/`` and ``benchmarks/``, so relative paths such as
  ``scenarios/double_pendulum.toml`` resolve and outputs (``out/…``) land in the temporary
  directory. ``constrained`` means this checkout's command (``python -m constrained.cli``).
* ``python`` blocks of one page run in order in one namespace, like the cells of a notebook
  (a later block may use names an earlier one defined, or files a shell block wrote).
* ``bash``/``sh`` blocks run line by line (``\\`` continues a line; ``#`` starts a comment);
  every command must exit 0, unless its line ends with ``# exits N``, then it must exit N.
  A line that installs (``pip install``, ``python3 -m venv``) is skipped: CI runs those as
  its own install and test steps (tests/test_project.py checks the README's two commands).
* ``toml`` blocks must parse.
* ``text`` blocks (output, diagrams) are not run. Every fence names its language, so that
  no command hides in an untagged block.
* A block preceded by ``<!-- slow -->`` runs in its own test, ``test_slow_block``. Such a block
  must not depend on what earlier blocks of its page did. Every docs test is marked ``slow``:
  left out of the developer's loop, run with ``--all`` as CI does.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LANGUAGES = {"python", "bash", "sh", "toml", "text"}
SKIPPED = re.compile(r"\bpip install\b|python3? -m venv\b")
EXITS = re.compile(r"#\s*exits\s+(\d+)\s*$")
FENCE = re.compile(r"^```(\S*)\s*$")


@dataclass
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    language: str
    code: str
    slow: bool

    @property
    def id(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks(page: Path) -> list[Block]:
    """The fenced code blocks of a Markdown page, in order."""
    out, lines = [], page.read_text(encoding="utf-8").splitlines()
    k = 0
    while k < len(lines):
        m = FENCE.match(lines[k])
        if not m:
            k += 1
            continue
        start = k
        k += 1
        body = []
        while k < len(lines) and lines[k].strip() != "```":
            body.append(lines[k])
            k += 1
        before = next((lines[j].strip() for j in range(start - 1, -1, -1) if lines[j].strip()), "")
        out.append(Block(page, start + 1, m.group(1), "\n".join(body) + "\n", before == "<!-- slow -->"))
        k += 1
    return out


def shell_commands(code: str) -> list[tuple[str, int]]:
    """``(command, expected exit status)`` per logical line of a shell block."""
    out, pending = [], ""
    for raw in code.splitlines():
        if raw.rstrip().endswith("\\"):
            pending += raw.strip()[:-1].strip() + " "
            continue
        line = (pending + raw.strip()).strip()
        pending = ""
        if not line or line.startswith("#") or SKIPPED.search(line):
            continue
        m = EXITS.search(line)
        out.append((line, int(m.group(1)) if m else 0))
    return out


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """A temporary directory where scenarios/ and benchmarks/ resolve, the page's cwd."""
    for name in ("scenarios", "benchmarks"):
        (tmp_path / name).symlink_to(ROOT / name, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    return tmp_path


def run_shell(block: Block, cwd: Path) -> None:
    # `constrained` is this checkout's command, whatever is installed
    prelude = f'constrained() {{ {shlex.quote(sys.executable)} -m constrained.cli "$@"; }}\n'
    for command, expected in shell_commands(block.code):
        proc = subprocess.run(["bash", "-c", prelude + command], cwd=cwd, capture_output=True, text=True,
                              stdin=subprocess.DEVNULL, timeout=600)
        assert proc.returncode == expected, (
            f"{block.id}: `{command}` exited {proc.returncode}, expected {expected}\n"
            f"--- stdout\n{proc.stdout[-3000:]}\n--- stderr\n{proc.stderr[-3000:]}")


def run_block(block: Block, namespace: dict, cwd: Path) -> None:
    if block.language == "python":
        try:
            exec(compile(block.code, block.id, "exec"), namespace)
        except Exception as exc:
            raise AssertionError(f"{block.id}: the Python block raised {type(exc).__name__}: {exc}") from exc
    elif block.language in ("bash", "sh"):
        run_shell(block, cwd)
    elif block.language == "toml":
        tomllib.loads(block.code)


ALL = [b for page in PAGES for b in blocks(page)]


def test_every_block_names_a_known_language():
    untagged = [f"{b.id} ({b.language or 'no language'})" for b in ALL if b.language not in LANGUAGES]
    assert not untagged, "fences without a known language: " + ", ".join(untagged)
    assert sum(b.language == "python" for b in ALL) >= 8 and sum(b.language == "bash" for b in ALL) >= 8


def test_shell_line_rules():
    code = ("python3 -m venv .venv && . .venv/bin/activate && pip install . && constrained run x\n"
            "constrained check a.toml   # a comment\n"
            "constrained run a.toml \\\n    --set simulate.t_end=2  # exits 1\n")
    assert shell_commands(code) == [("constrained check a.toml   # a comment", 0),
                                    ("constrained run a.toml --set simulate.t_end=2  # exits 1", 1)]


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_page(page, workdir):
    """The page's blocks, in order, in one temporary directory and one Python namespace."""
    namespace = {"__name__": "__docs__"}
    for block in blocks(page):
        if not block.slow:
            run_block(block, namespace, workdir)


SLOW = [b for b in ALL if b.slow]


@pytest.mark.slow
@pytest.mark.parametrize("block", SLOW, ids=[b.id for b in SLOW])
def test_slow_block(block, workdir):
    run_block(block, {"__name__": "__docs__"}, workdir)


CONTINUES = "# continues the block above"


def names_from_earlier_blocks(code: str) -> set[str]:
    """The names a Python block reads without defining or importing them itself (nor builtins)."""
    import ast
    import builtins

    tree = ast.parse(code)
    defined = set(dir(builtins))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            defined.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.Name) and not isinstance(node.ctx, ast.Load):
            defined.add(node.id)
        elif isinstance(node, ast.FunctionDef | ast.ClassDef):
            defined.add(node.name)
        elif isinstance(node, ast.arg):
            defined.add(node.arg)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            defined.add(node.name)
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)} - defined


def test_a_block_that_needs_an_earlier_one_says_so():
    """A reader copies one block: it runs on its own, or its first line says it continues the
    block above (issue 32)."""
    unsaid = [f"{b.id} (uses {', '.join(sorted(names))})" for b in ALL if b.language == "python"
              and (names := names_from_earlier_blocks(b.code)) and not b.code.startswith(CONTINUES)]
    assert not unsaid, f"start these blocks with '{CONTINUES}' or make them self-contained: {unsaid}"
    said = [b.id for b in ALL if b.language == "python" and b.code.startswith(CONTINUES)
            and not names_from_earlier_blocks(b.code)]
    assert not said, f"these blocks run on their own: drop '{CONTINUES}': {said}"
