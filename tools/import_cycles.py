"""No import cycle among the scripts of a folder: `make lint` runs this beside import-linter.

import-linter checks the packages (core, plugins, libraries, tools: the contract "no cycles among
the modules of a package" in pyproject.toml). The folders of scripts are no packages — bench/,
tests/, examples/: each file is a top-level module to the others of its folder (`import plots`,
`from conftest import free_port`) — so this walks them: every import of a sibling, wherever it is
written (in a function, under TYPE_CHECKING: both are a dependency all the same), and fails naming
each cycle, file by file.

    python tools/import_cycles.py [ROOT]     (default: the repository this file is in)
"""

from __future__ import annotations

import ast
import os
import sys
from collections.abc import Iterator
from pathlib import Path

#: folders never walked: environments, caches, and packages' sources (import-linter's part)
SKIPPED = {".venv", ".tools", ".git", "__pycache__", "node_modules", "src", "dist", "build"}


def script_folders(root: Path) -> Iterator[Path]:
    """Every folder under ``root`` that holds Python files and is not a package."""
    for folder, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if d not in SKIPPED and not d.startswith("."))
        if "__init__.py" not in files and any(f.endswith(".py") for f in files):
            yield Path(folder)


def imported(source: str) -> set[str]:
    """The top-level names of the modules ``source`` imports, absolute imports only."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return names


def graph(folder: Path) -> dict[str, set[str]]:
    """Module -> the modules of the same folder it imports."""
    modules = {p.stem: p for p in folder.glob("*.py")}
    return {name: {other for other in imported(path.read_text()) if other in modules
                   and other != name}
            for name, path in modules.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each as a path
    through the component back to its first module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in sorted(edges[node]):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(path_through(edges, set(component)))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return found


def path_through(edges: dict[str, set[str]], component: set[str]) -> list[str]:
    """One cycle inside ``component``, as the modules it passes, the first again at its end."""
    start = min(component)
    seen = {start: ""}
    queue = [start]
    while queue:  # breadth first from start until an edge comes back to it
        node = queue.pop(0)
        for nxt in sorted(edges[node] & component):
            if nxt == start:
                path = [node]
                while seen[path[-1]]:
                    path.append(seen[path[-1]])
                return [*reversed(path), start]
            if nxt not in seen:
                seen[nxt] = node
                queue.append(nxt)
    raise AssertionError(f"no cycle through {start} in {sorted(component)}")


def problems(root: Path) -> list[str]:
    lines = []
    for folder in script_folders(root):
        for cycle in cycles(graph(folder)):
            where = folder.relative_to(root)
            lines.append(f"{where}/: import cycle " + " -> ".join(f"{m}.py" for m in cycle)
                         + ": move what both need to a module both import")
    return lines


def main() -> int:
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1]
    found = problems(root)
    for line in found:
        print(line)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
