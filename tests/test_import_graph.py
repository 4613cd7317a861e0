"""The project's import graph, read from the source with `ast`, has no cycles.

Counted: every `import` and `from … import` anywhere in a module (at module level, inside
functions, under `if TYPE_CHECKING`), relative ones resolved, and `importlib.import_module` with a
literal name. A function-level import is an edge too: it only defers a cycle to the first call.
Not counted: a package's implicit import before its submodule (a submodule that imports nothing
from its package's `__init__` does not depend on it), and names computed at run time.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dpmhw", "drivers", "calibration", "server", "firmware_mocks")

# The one cycle being broken elsewhere: the API process takes `describe_exit` from the supervisor
# that starts it (server.process → dpmhw.session.supervisor ↔ its import of server.process).
ALLOWED = {("server.process", "dpmhw.session.supervisor")}


def modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def imported_names(module: str, path: Path) -> set[str]:
    """Every dotted name `module` imports (for `from a import b`: both `a.b` and `a`)."""
    names = set()
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            source = ".".join(base + ([node.module] if node.module else []))
            names.update(f"{source}.{alias.name}" for alias in node.names)
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            names.add(node.args[0].value)
    return names


def graph() -> dict[str, set[str]]:
    mods = modules()

    def owner(name: str) -> str | None:  # the module a dotted name lives in: its longest module prefix
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    edges = {}
    for module, path in mods.items():
        targets = {owner(name) for name in imported_names(module, path)}
        edges[module] = {t for t in targets if t is not None and t != module and (module, t) not in ALLOWED}
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    out.append(sorted(component))
    return out


def test_the_reader_sees_every_kind_of_import_and_finds_a_cycle():
    """The checker itself: the import forms it must count, and a cycle it must report."""
    assert {"dpmhw.benchmarks.quality", "dpmhw.cluster.ray_pool"} <= set(modules())
    edges = graph()
    assert "dpmhw.cluster.passes" in edges["dpmhw.cluster.ray_pool"]  # module level
    assert "dpmhw.render.integrator" in edges["dpmhw.cluster.ray_pool"]  # inside a function
    assert "dpmhw.cli.render" in edges["dpmhw.cli"]  # `from package import submodule`
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    edges = graph()
    found = cycles(edges)
    detail = "\n".join(" ↔ ".join(c) + ": " + "; ".join(f"{a} → {b}" for a in c for b in sorted(edges[a] & set(c)))
                       for c in found)
    assert not found, f"import cycles:\n{detail}"
