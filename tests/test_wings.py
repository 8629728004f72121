"""The solver's layout: wings a student can find, imports that only go down, no cycle.

Layers, lowest first: the root utilities (`_ti`, `backend`, `errors`, `todo`, `metrics`, `method`),
`mesh`, `physics`, then `vbd` and `newton` side by side; `solver/__init__.py` (the public names) on
top. The graph is read from the source with `ast`, so it is checked without importing anything.
"""
import ast
from pathlib import Path

import pytest

SOLVER = Path(__file__).resolve().parents[1] / "solver"
RANK = {"mesh": 1, "physics": 2, "vbd": 3, "newton": 3}
WINGS = sorted(RANK)


def _module_name(path: Path) -> str:
    parts = path.relative_to(SOLVER.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path):
    """(target module, whether the import is at module level) for every import of `solver` code."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    top_level = {id(node) for node in tree.body}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names = [target] if node.module else [f"{target}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for name in names:
            if name == "solver" or name.startswith("solver.") or name.startswith("demo"):
                yield name, id(node) in top_level


def _rank(module: str) -> int:
    parts = module.split(".")
    if module == "solver":
        return 4
    if len(parts) > 1 and parts[1] in RANK:
        return RANK[parts[1]]
    return 0


def _graph():
    modules = {_module_name(p): p for p in SOLVER.rglob("*.py")}
    edges = {}
    for name, path in modules.items():
        edges[name] = [(t, top) for t, top in _imports(path)]
    return modules, edges


def test_the_wings_are_folders_and_the_root_stays_small():
    assert sorted(p.name for p in SOLVER.iterdir() if p.is_dir() and p.name != "__pycache__") == WINGS
    root_files = sorted(p.name for p in SOLVER.glob("*.py"))
    assert len(root_files) <= 8, root_files


def test_solver_never_imports_demo():
    _, edges = _graph()
    offenders = [(m, t) for m, ts in edges.items() for t, _ in ts if t.startswith("demo")]
    assert offenders == []


def test_nothing_imports_a_higher_layer():
    _, edges = _graph()
    upward = [(m, t) for m, ts in edges.items() if m != "solver" for t, _ in ts if _rank(t) > _rank(m)]
    assert upward == [], "imports going up a layer: " + ", ".join(f"{m} -> {t}" for m, t in upward)


def test_module_level_imports_have_no_cycle():
    modules, edges = _graph()

    def resolve(target):
        while target and target not in modules:
            target = target.rpartition(".")[0]
        return target

    graph = {m: sorted({resolve(t) for t, top in ts if top and resolve(t)} - {m}) for m, ts in edges.items()}
    # a package's __init__ importing its own modules is the package, not a cycle through it
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for n in graph[m]:
            if n.startswith(m + "."):
                continue
            if state.get(n) == "open":
                cycle = stack[stack.index(n):] + [n]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)
