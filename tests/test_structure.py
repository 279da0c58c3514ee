"""The package's layering, read from its source: no import cycle, nothing imports the command
line, and ``channel/`` and ``envs/`` stand alone at the bottom."""

import ast
from pathlib import Path

import sparsecomm

ROOT = Path(sparsecomm.__file__).parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The sparsecomm modules ``path`` imports anywhere (top level or inside functions)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for t in targets:
            while t and t not in modules:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def _graph() -> dict[str, set[str]]:
    paths = sorted(ROOT.rglob("*.py"))
    modules = {_module_name(p) for p in paths}
    return {_module_name(p): _imports(p, modules) for p in paths}


def test_import_graph_has_no_cycle():
    graph = _graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = path[path.index(nxt) :] + [nxt]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])


def test_nothing_imports_the_command_line():
    importers = sorted(m for m, deps in _graph().items() if "sparsecomm.cli" in deps)
    assert importers == []


def test_channel_and_envs_stand_alone():
    graph = _graph()
    for layer in ("sparsecomm.channel", "sparsecomm.envs"):
        for module, deps in graph.items():
            if module == layer or module.startswith(layer + "."):
                outside = sorted(d for d in deps if not d.startswith(layer) and d != "sparsecomm")
                assert outside == [], (module, outside)


def test_the_graph_reader_sees_real_imports():
    graph = _graph()
    # Known edges, top level and inside a package: the reader must find them.
    assert "sparsecomm.channel.quantizer" in graph["sparsecomm.channel.codes"]
    assert "sparsecomm.learner" in graph["sparsecomm.rl"]
    assert "sparsecomm.experiment" in graph["sparsecomm.cli"]
