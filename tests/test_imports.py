"""Import hygiene of the product packages (issue 28): no module imports another module's
private name, and no module-level import cycle (imports under `TYPE_CHECKING` or inside a
function are not counted)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calibrators", "app", "detectors", "bench")


def private_imports(source: str) -> list[str]:
    """`module.name` of every `from <project module> import _name` in `source`."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module \
                and node.module.split(".")[0] in PACKAGES:
            found += [f"{node.module}.{a.name}" for a in node.names
                      if a.name.startswith("_") and not a.name.startswith("__")]
    return found


def module_imports(source: str, modules: set[str]) -> set[str]:
    """The project modules of `modules` that `source` imports at module level: `from p import
    m` counts the submodule `p.m` (not the package `p`) when `p.m` is a module."""
    out: set[str] = set()

    def visit(nodes: list[ast.stmt]) -> None:
        for n in nodes:
            if isinstance(n, ast.If) and "TYPE_CHECKING" in ast.unparse(n.test):
                visit(n.orelse)
            elif isinstance(n, ast.ImportFrom) and n.module:
                subs = {f"{n.module}.{a.name}" for a in n.names} & modules
                out.update(subs | ({n.module} if len(subs) < len(n.names) else set()))
            elif isinstance(n, ast.Import):
                out.update(a.name for a in n.names)
            elif isinstance(n, ast.If | ast.Try | ast.With | ast.ClassDef):
                for block in ("body", "orelse", "finalbody"):
                    visit(getattr(n, block, []))
                for handler in getattr(n, "handlers", []):
                    visit(handler.body)

    visit(ast.parse(source).body)
    return out & modules


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = stack[stack.index(v):]
            del stack[stack.index(v):]
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return sorted(found)


def project_modules() -> dict[str, Path]:
    modules = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def test_the_checks_find_a_private_import_and_a_cycle():
    assert private_imports("from calibrators.x import a, _b\n") == ["calibrators.x._b"]
    assert private_imports("from numpy import _core\nfrom calibrators.x import __all__\n") == []
    mods = {"p", "p.a", "p.b"}
    assert module_imports("from p import a\nif TYPE_CHECKING:\n    import p.b\n", mods) == {"p.a"}
    assert cycles({"p.a": {"p.b"}, "p.b": {"p.a"}, "p": {"p.a"}}) == [["p.a", "p.b"]]
    assert cycles({"p.a": {"p.b"}, "p.b": set(), "p": {"p.a"}}) == []


def test_no_product_module_imports_a_private_name():
    offenders = [f"{path.relative_to(ROOT)}: {name}" for path in project_modules().values()
                 for name in private_imports(path.read_text(encoding="utf-8"))]
    assert offenders == []


def test_no_module_level_import_cycle():
    modules = project_modules()
    graph = {name: module_imports(path.read_text(encoding="utf-8"), set(modules))
             for name, path in modules.items()}
    assert cycles(graph) == []
