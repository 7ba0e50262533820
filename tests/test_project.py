"""The repository's promises: README commands, CI script, style."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

from conftest import ROOT


def readme_command(marker: str) -> str:
    text = (ROOT / "README.md").read_text()
    match = re.search(rf"<!-- {marker} -->\s*```bash\n(.+?)\n```", text)
    assert match, f"README.md lacks the {marker} block"
    return match.group(1)


def test_readme_run_command_names_a_bundled_scene():
    cmd = readme_command("run-command")
    scene = re.search(r"constrained run (\S+)", cmd).group(1)
    assert (ROOT / scene).is_file()
    assert "pip install ." in cmd


def test_ci_runs_the_readme_test_command():
    cmd = readme_command("test-command")
    assert "pytest" in cmd and 'pip install ".[test]"' in cmd and "--all" in cmd
    script = (ROOT / ".ci" / "run").read_text()
    assert "test-command" in script


def test_code_is_ruff_clean():
    ruff = shutil.which("ruff") or str(ROOT / ".venv" / "bin" / "ruff")
    result = subprocess.run([ruff, "check", "constrained", "tests"], cwd=ROOT,
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_no_eval_or_exec_in_the_package():
    for path in (ROOT / "constrained").rglob("*.py"):
        source = path.read_text()
        assert not re.search(r"(?<![\w.])(eval|exec)\(", source), path
    assert sys.version_info >= (3, 11)


def test_no_import_cycles_counting_imports_inside_functions():
    """The package's modules import in one direction (DESIGN.md, "Solver core")."""
    from import_graph import graph, layers

    edges = graph()
    level = layers(edges)  # raises on a cycle, naming a module on it
    assert all(level[t] < level[m] for m, targets in edges.items() for t in targets)


def test_folders_import_downward_only():
    """cli → sweeps, output → scene → analysis → run → solvers → manifold → model → codegen → the
    ground floor: no module imports from a folder above its own (docs/architecture.md)."""
    from import_graph import FOLDERS, graph, upward_imports

    assert upward_imports(graph()) == []
    package = ROOT / "constrained"
    folders = {p.name for p in package.iterdir() if (p / "__init__.py").is_file()}
    assert folders == set(FOLDERS) - {""}, "a new folder needs its place in import_graph.FOLDERS"


def test_modules_and_folders_stay_small():
    """A module over ~500 lines, or a folder over ~12 modules, is asking to be split."""
    package = ROOT / "constrained"
    long = {str(p.relative_to(package)): n for p in package.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 530}
    assert not long, long
    def modules(folder):
        return [p for p in folder.glob("*.py") if p.name not in ("__init__.py", "__main__.py")]

    crowded = {str(d.relative_to(package)): n for d in package.rglob("*") if d.is_dir()
               and (n := len(modules(d))) > 12}
    assert not crowded, crowded


def test_architecture_shows_the_real_import_graph():
    from import_graph import text

    doc = (ROOT / "docs" / "architecture.md").read_text()
    assert text() in doc, "docs/architecture.md: run python tests/update_import_graph.py"
