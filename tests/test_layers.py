"""The layers hold: tools over daemon over analysis over protocol, the product never imports the benchmarks, no
module imports itself round a circle, and none is past 1,000 lines.

import-linter reads the contracts from ``pyproject.toml`` and the code under the package names it is installed
as (``.typecheck/ballbar``); CI runs the same command.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from itertools import pairwise
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_no_package_imports_one_above_it() -> None:
    lint = Path(sys.executable).with_name("lint-imports")
    out = subprocess.run([str(lint), str(ROOT / "pyproject.toml")], cwd=ROOT / ".typecheck", capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "2 kept, 0 broken" in out.stdout, out.stdout[-2000:]


PACKAGES = ("ballbar.protocol", "ballbar.analysis", "ballbar.daemon", "ballbar.tools")


def _modules() -> dict[str, Path]:
    """Every module of :data:`PACKAGES` (subpackages too, ``tools/bench`` among them) and ``ballbar`` itself, by
    its installed name: the folders as ``[tool.setuptools.package-dir]`` maps them."""
    dirs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    out = {"ballbar": ROOT / dirs["ballbar"] / "__init__.py"}
    for pkg in PACKAGES:
        top = ROOT / dirs[pkg]
        for path in sorted(top.rglob("*.py")):
            parts = path.relative_to(top).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join((pkg, *parts))] = path
    return out


def _imports(name: str, path: Path, known: set[str]) -> dict[str, int]:
    """The modules of ``known`` that module ``name`` imports, each with the line of its first import.

    Every import statement counts, wherever it is: at module level, under ``if TYPE_CHECKING:`` and inside a
    function (an import put off until a call is still a dependency, and a circle through it is still one).
    ``from pkg import name`` imports ``pkg`` (Python runs its ``__init__`` and asks it for ``name``, through its
    module ``__getattr__`` where it has one) and, where ``pkg.name`` is a module, that module too; ``import a.b``
    imports ``a.b`` alone (the parent packages Python loads first are not counted: a package's ``__init__`` may
    import its own submodules).
    """
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: dict[str, int] = {}

    def add(target: str, line: int) -> None:
        while target and target not in known:  # ``import ballbar.x.y`` where y is an attribute: the module x
            target = target.rpartition(".")[0]
        if target and target != name:
            out.setdefault(target, line)

    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name, node.lineno)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            add(base, node.lineno)
            for alias in node.names:
                if f"{base}.{alias.name}" in known:
                    add(f"{base}.{alias.name}", node.lineno)
    return out


def _strongly_connected(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Tarjan's strongly connected components of ``graph`` with more than one module, each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _cycle(graph: dict[str, dict[str, int]], component: list[str]) -> list[str]:
    """A shortest circle through the component's first module, as ``a -> b`` steps with each import's line."""
    start, members = component[0], set(component)
    came: dict[str, str] = {}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for w in sorted(graph[v]):
            if w == start:
                path = [v]
                while path[-1] != start:
                    path.append(came[path[-1]])
                path.reverse()
                steps = [*path, start]
                return [f"{a} -> {b} (line {graph[a][b]})" for a, b in pairwise(steps)]
            if w in members and w not in came:
                came[w] = v
                queue.append(w)
    raise AssertionError(f"no circle found in {component}")


def test_no_module_imports_itself_round_a_circle() -> None:
    """The layers hold between packages; a circle inside one (``daemon.cli`` <-> ``daemon.commands``) passes
    them.  Every product module is parsed (:func:`_imports` says which imports count: all of them, those inside
    functions too) and each strongly connected component of the graph named with a circle through it."""
    modules = _modules()
    known = set(modules)
    graph = {name: _imports(name, path, known) for name, path in modules.items()}
    assert len(graph) > 100 and "ballbar.daemon.cli" in graph and "ballbar.tools.bench" in graph, sorted(graph)
    assert "ballbar.daemon.commands" in graph["ballbar.daemon.cli"]  # inside main(): imports in functions count
    documents = graph["ballbar.protocol.messages.documents"]
    assert {"ballbar.protocol.messages", "ballbar.protocol.messages.events", "ballbar"} <= set(documents)
    circles = [" / ".join(_cycle(graph, c)) for c in _strongly_connected(graph)]
    assert not circles, "import circles:\n" + "\n".join(circles)


MAX_LINES = 1000  # a module past this does more than one job (issue 32 §3; STYLE.md: about 800 is a good guide)


def test_no_module_is_past_max_lines() -> None:
    """Every module under ``protocol/``, ``analysis/``, ``daemon/`` and ``tools/`` (``tools/bench`` too; the tests
    are not among them) has at most :data:`MAX_LINES` lines: one past it is split along its jobs."""
    modules = _modules()
    assert len(modules) > 100 and {"ballbar.tools.bench.bench_daemon", "ballbar.daemon.mcap.writer"} <= set(modules)
    lines = {name: len(path.read_text().splitlines()) for name, path in modules.items()}
    assert max(lines.values()) > MAX_LINES // 2  # the lines are counted (a module of this size exists)
    long = sorted(f"{modules[name].relative_to(ROOT)}: {n}" for name, n in lines.items() if n > MAX_LINES)
    assert not long, f"past {MAX_LINES} lines:\n" + "\n".join(long)
