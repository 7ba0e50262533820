"""The package's real import graph (imports inside functions included), in layers.

    python tests/import_graph.py        # print the block docs/architecture.md holds

A module's layer is one more than the highest layer it imports from (the ground floor, 0,
imports nothing of the package). tests/test_project.py checks that docs/architecture.md
shows exactly this graph.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def graph() -> dict[str, set[str]]:
    """module (dotted, without the package prefix) -> the package modules it imports."""
    package = ROOT / "constrained"
    modules = {}
    for path in package.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    edges = {name: set() for name in modules}
    for name, path in modules.items():
        here = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                base = here.split(".")[: len(here.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
                for alias in node.names:
                    full = f"{target}.{alias.name}"
                    edges[name].add(full if full in modules else target)
            elif isinstance(node, ast.ImportFrom | ast.Import):
                for alias in node.names:
                    mod = node.module if isinstance(node, ast.ImportFrom) else alias.name
                    if mod and mod.startswith("constrained"):
                        edges[name].add(mod)
    short = {k: k.removeprefix("constrained.") for k in modules}
    return {short[k]: {short[t] for t in v if t in modules and t != k} for k, v in edges.items()
            if k != "constrained"}


#: The folders from the ground up: a module may import from its own folder and from folders below
#: its own, never from one above (the ground floor, "", is the package's top-level modules).
FOLDERS = ("", "codegen", "model", "manifold", "solvers", "run", "analysis", "scene", "output", "sweeps",
           "cli")


def folder(module: str) -> str:
    """the folder (subpackage) a module (dotted, without the package prefix) lives in."""
    head = module.split(".")[0]
    return head if head in FOLDERS else ""


def upward_imports(edges: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(importer, imported) pairs that climb from a folder to one above it."""
    rank = {name: k for k, name in enumerate(FOLDERS)}
    entry = {"__main__"}  # python -m constrained: the command, above everything
    return sorted((m, t) for m, targets in edges.items() if m not in entry for t in targets
                  if rank[folder(t)] > rank[folder(m)])


def layers(edges: dict[str, set[str]]) -> dict[str, int]:
    level: dict[str, int] = {}

    def of(name, seen=()):
        if name not in level:
            if name in seen:
                raise ValueError(f"import cycle through {name}")
            level[name] = 1 + max((of(t, (*seen, name)) for t in edges[name]), default=-1)
        return level[name]

    for name in edges:
        of(name)
    return level


def text() -> str:
    edges = graph()
    level = layers(edges)
    lines = ["folders (each imports only from those after its arrow):"]
    for name in reversed(FOLDERS):
        used = {folder(t) or "(ground)" for m, ts in edges.items()
                if folder(m) == name and m != "__main__" for t in ts}
        below = sorted(used - {name or "(ground)"},
                       key=lambda f: -FOLDERS.index("" if f == "(ground)" else f))
        lines.append(f"  {name or '(ground)'} ← {' '.join(below) if below else '—'}")
    lines.append("modules, in layers:")
    for k in range(max(level.values()) + 1):
        names = sorted(n for n in level if level[n] == k)
        lines.append(f"{k:>2}  " + ", ".join(
            n + (f" ← {' '.join(sorted(edges[n]))}" if edges[n] else "") for n in names))
    return "\n".join(lines)


if __name__ == "__main__":
    print(text())
