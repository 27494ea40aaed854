"""The import graph of the project's packages: one way (experiments -> wm -> sim_data), no cycles."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sim_data", "wm", "experiments")
LAYER = {"sim_data": 0, "wm": 1, "experiments": 2}


def _module(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _graph() -> dict:
    modules = {_module(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                # `from pkg import submodule` depends on the submodule (the package's __init__ runs
                # first in Python, but names nothing of its own here)
                subs = [f"{node.module}.{a.name}" for a in node.names]
                targets = subs if all(t in modules for t in subs) else [node.module] + subs
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            deps |= {t for t in targets if t in modules and t != name}
        graph[name] = deps
    return graph


def test_imports_run_one_way():
    for name, deps in _graph().items():
        for dep in deps:
            assert LAYER[dep.split(".")[0]] <= LAYER[name.split(".")[0]], f"{name} imports {dep}, against the layers"


def test_the_import_graph_has_no_cycle():
    graph = _graph()
    state: dict = {}

    def visit(node, path):
        state[node] = "open"
        for dep in sorted(graph[node]):
            if state.get(dep) == "open":
                raise AssertionError("import cycle: " + " -> ".join(path[path.index(dep):] + [dep]))
            if dep not in state:
                visit(dep, path + [dep])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])



def test_every_import_is_at_module_level():
    """No import hides inside a function (to dodge a cycle or defer a cost): a module's dependencies
    are what its top says."""
    hidden = []
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            for fn in ast.walk(ast.parse(path.read_text())):
                if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                    hidden += [f"{path.relative_to(ROOT)}:{n.lineno}" for n in ast.walk(fn)
                               if isinstance(n, ast.Import | ast.ImportFrom)]
    assert not hidden, f"imports inside functions: {hidden}"
