"""Import hygiene of the product packages (issue 28): no module imports another module's
private name, no file outside a package imports that package's private modules (the tests
included: they use the names a package's `__init__` exports), and no module-level import
cycle (imports under `TYPE_CHECKING` or inside a function are not counted)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calibrators", "app", "detectors", "bench")
#: Where the private-module check looks: the product packages and their tests.
SCANNED = (*PACKAGES, "tests")
#: (file, private module) imports from outside the module's package that are allowed, each for
#: a reason the public names cannot serve. Keep it short: an entry no file needs fails the test.
ALLOWED_PRIVATE_MODULES = {
    # monkeypatch a module global that the library reads at call time (a block size, a
    # threshold), so a test reaches that path at a size it can afford
    ("tests/calibrators/boxes2d/test_coco_eval.py", "calibrators.boxes2d._match"),
    ("tests/calibrators/covariance/test_depth_blocks.py", "calibrators.covariance._depth_nll"),
    ("tests/calibrators/covariance/test_depth_blocks.py", "calibrators.covariance._spectral"),
    ("tests/calibrators/evaluation/test_matching.py", "calibrators.evaluation._matching"),
    ("tests/calibrators/fit/test_fit_stream.py", "calibrators.fit._stream"),
    ("tests/calibrators/fit/test_fit_stream.py", "calibrators.scores._temperature"),
    ("tests/calibrators/scores/test_temperature.py", "calibrators.scores._temperature"),
}


def private_imports(source: str) -> list[str]:
    """`module.name` of every `from <project module> import _name` in `source`."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module \
                and node.module.split(".")[0] in PACKAGES:
            found += [f"{node.module}.{a.name}" for a in node.names
                      if a.name.startswith("_") and not a.name.startswith("__")]
    return found


def private_module_imports(source: str, importer: str, modules: set[str],
                           is_package: bool = False) -> list[str]:
    """The private modules that `source`, the module `importer` (a package's `__init__` when
    `is_package`), imports from outside the package that owns them, in order, each once.

    A module of `modules` is private when a component of its dotted path starts with `_`
    (`__init__` and `__main__` aside); the package that owns it is the path before that
    component, and a module inside that package (or a subpackage of it) may import it.
    `from p import m` counts the module `p.m` when `p.m` is one of `modules`; relative imports
    resolve against `importer`."""
    package = importer.split(".") if is_package else importer.split(".")[:-1]
    roots = {m.split(".")[0] for m in modules}
    found: list[str] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            paths = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            paths = [module] + [f"{module}.{a.name}" for a in node.names
                                if f"{module}.{a.name}" in modules]
        else:
            continue
        for path in paths:
            parts = path.split(".")
            private = next((i for i, part in enumerate(parts) if part.startswith("_")
                            and part not in ("__init__", "__main__")), None)
            if parts[0] not in roots or not private:
                continue
            owner = ".".join(parts[:private])
            if importer != owner and not importer.startswith(owner + ".") \
                    and path not in found:
                found.append(path)
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


def project_modules(packages: tuple[str, ...] = PACKAGES) -> dict[str, Path]:
    modules = {}
    for package in packages:
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


def test_the_check_finds_a_private_module_imported_from_outside_its_package():
    mods = {"p", "p._a", "p.b", "p.b._c", "p.e", "q"}
    found = private_module_imports(
        "import p._a\nfrom p.b import _c\nfrom p.b._c import x\nfrom p import b\nimport q\n",
        "q", mods)
    assert found == ["p._a", "p.b._c"]
    # inside the package that owns it (or a subpackage of that), a private module is fine
    assert private_module_imports("import p._a\n", "p.b._c", mods) == []
    assert private_module_imports("from p.b import _c\n", "p.b", mods, is_package=True) == []
    assert private_module_imports("from p.b._c import x\n", "p.e", mods) == ["p.b._c"]
    # neither `__init__` / `__main__` nor a private name of a public module is a private module
    assert private_module_imports("import p.__main__\nfrom p.b import _name\n", "q", mods) == []
    assert private_module_imports("from numpy._core import x\n", "q", mods) == []   # not ours
    # relative imports resolve against the importing module
    assert private_module_imports("from .b import _c\n", "p.e", mods) == ["p.b._c"]
    assert private_module_imports("from . import _c\n", "p.b", mods, is_package=True) == []
    assert private_module_imports("from .._a import x\n", "p.b._c", mods) == []


def test_no_file_imports_a_private_module_of_another_package():
    modules = project_modules(SCANNED)
    offenders, allowed = [], set()
    for name, path in modules.items():
        rel = path.relative_to(ROOT).as_posix()
        for module in private_module_imports(path.read_text(encoding="utf-8"), name,
                                             set(modules), path.name == "__init__.py"):
            if (rel, module) in ALLOWED_PRIVATE_MODULES:
                allowed.add((rel, module))
            else:
                offenders.append(f"{rel}: {module}")
    assert offenders == []
    assert allowed == ALLOWED_PRIVATE_MODULES, "allowed imports no file makes any more"


def test_no_product_module_imports_a_private_name():
    offenders = [f"{path.relative_to(ROOT)}: {name}" for path in project_modules().values()
                 for name in private_imports(path.read_text(encoding="utf-8"))]
    assert offenders == []


def test_no_module_level_import_cycle():
    modules = project_modules()
    graph = {name: module_imports(path.read_text(encoding="utf-8"), set(modules))
             for name, path in modules.items()}
    assert cycles(graph) == []
