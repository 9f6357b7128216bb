"""The package's layout rules: no import cycles, and the core knows nothing of its users."""

import ast
from pathlib import Path

import cutterpose

PKG = Path(cutterpose.__file__).parent
# the parts that use the core; the core (geometry, image, solvers, ...) must not import them
USERS = ("cutterpose.cli", "cutterpose.experiments", "cutterpose.service", "cutterpose.client")


def _module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
    """Every module's imports of other cutterpose modules, lazy (in-function) ones included."""
    graph = {}
    for path in PKG.rglob("*.py"):
        name = _module_name(path)
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                candidates = [target] + [f"{target}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                candidates = [a.name for a in node.names]
            else:
                continue
            deps.update(c for c in candidates if c.startswith("cutterpose"))
        graph[name] = deps
    # keep only edges to real modules; a package import means its __init__
    return {m: {d for d in ds if d in graph and d != m} for m, ds in graph.items()}


def _cycles(graph):
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def _without_package_inits(graph):
    # "from .x import y" inside package p also names p itself; a package's __init__ re-exporting
    # its submodules is not a cycle of the submodules
    inits = {m for m in graph if (PKG.parent / m.replace(".", "/") / "__init__.py").is_file()}
    return {m: ds - inits for m, ds in graph.items() if m not in inits}


def test_no_import_cycles():
    assert _cycles(_without_package_inits(_imports())) == []


def test_cycle_finder_sees_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_core_does_not_import_its_users():
    graph = _imports()
    core = [m for m in graph if not m.startswith(USERS) and m != "cutterpose"]
    offenders = {m: sorted(d for d in graph[m] if d.startswith(USERS)) for m in core}
    assert {m: d for m, d in offenders.items() if d} == {}
