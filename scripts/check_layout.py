"""Check the package layout of docs/architecture.md.

    python scripts/check_layout.py          # prints each problem; exit status 1 when there is one

- no import cycle between sellip's modules (imports inside functions count too);
- no module imports a package above its floor (model 0; capture, geometry 1; fit 2; report 3; bench 4;
  stages 5; the base modules jobs, timing, settings and workflow_support import no other sellip package);
- no stage adapter imports another stage (``stages/_*.py`` are shared helpers, not stages);
- no module, test, benchmark or script takes another module's private name (``_x``: ``from m import _x``,
  ``m._x``, ``setattr(m, "_x", ...)``), and what a file outside a package takes from it is listed in the
  package's ``__init__`` (its lazy export table);
- no module over MAX_MODULE_LINES lines; no function over MAX_FUNCTION_LINES lines whose docstring does not
  say why (a sentence starting "Long:").
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

FLOORS = {"jobs": -1, "timing": -1, "_exports": -1, "workflow_support": -1, "yaml_files": -1, "settings": -1,
          "model": 0, "capture": 1, "geometry": 1, "fit": 2, "calibrate": 2, "report": 3, "bench": 4, "stages": 5,
          "cli": 6}
MAX_MODULE_LINES = 650
MAX_FUNCTION_LINES = 80


def module_name(path: Path, src: Path) -> str:
    return ".".join(path.relative_to(src).with_suffix("").parts).removesuffix(".__init__")


def imports(path: Path, src: Path) -> set[str]:
    """The sellip modules ``path`` imports (``from sellip.x import y``: sellip.x, and sellip.x.y when a module)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if (isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "sellip"
                and not node.level):
            found.add(node.module)
            for alias in node.names:
                candidate = src / (node.module.replace(".", "/") + f"/{alias.name}.py")
                if candidate.is_file():
                    found.add(f"{node.module}.{alias.name}")
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "sellip"}
    return found


def floor(module: str) -> int | None:
    parts = module.split(".")
    return FLOORS.get(parts[1]) if len(parts) > 1 else None


def problems(src: Path) -> list[str]:
    graph, found = {}, []
    for path in sorted((src / "sellip").rglob("*.py")):
        module = module_name(path, src)
        graph[module] = {m for m in imports(path, src) if m != module and m != "sellip"}
        lines = path.read_text().splitlines()
        if len(lines) > MAX_MODULE_LINES:
            found.append(f"{path}: {len(lines)} lines (> {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse("\n".join(lines))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES and "Long:" not in (ast.get_docstring(node) or ""):
                    found.append(f"{path}:{node.lineno}: {node.name} is {length} lines (> {MAX_FUNCTION_LINES}) "
                                 "and its docstring does not say why (Long: ...)")
    for module, deps in graph.items():
        own = floor(module)
        for dep in deps:
            theirs = floor(dep)
            if own is not None and theirs is not None and theirs > own and dep.split(".")[1] != module.split(".")[1]:
                found.append(f"{module} imports {dep}, above its floor")
            if module.startswith("sellip.stages.") and dep.startswith("sellip.stages.") \
                    and not dep.split(".")[2].startswith("_"):
                found.append(f"{module} imports the stage {dep}")
    state: dict[str, int] = {}

    def visit(module: str, stack: list[str]) -> None:
        state[module] = 1
        for dep in sorted(graph.get(module, ())):
            if state.get(dep) == 1:
                found.append("import cycle: " + " -> ".join(stack[stack.index(dep):] + [dep]))
            elif dep not in state:
                visit(dep, stack + [dep])
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    return found




def is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def module_files(src: Path) -> dict[str, Path]:
    """{module name: file} of every sellip module."""
    return {".".join(p.relative_to(src).with_suffix("").parts).removesuffix(".__init__"): p
            for p in sorted((src / "sellip").rglob("*.py"))}


def package_exports(init: Path) -> dict[str, str] | None:
    """{name: module} of a package __init__ that calls lazy_exports(__name__, globals(), {module: (names)})."""
    for node in ast.walk(ast.parse(init.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "lazy_exports":
            table = ast.literal_eval(node.args[2])
            return {name: module for module, names in table.items() for name in names}
    return None


def references(path: Path, modules: dict[str, Path], exports: dict[str, dict[str, str]]):
    """(line, target module, name) for every name ``path`` takes from a sellip module: ``from M import name``,
    ``alias.name`` where alias is a module, ``setattr(alias, "name", ...)``; a name taken from a package is
    resolved to the module that defines it."""
    tree = ast.parse(path.read_text())
    aliases: dict[str, str] = {}
    found = []

    def resolve(module: str, name: str):
        if f"{module}.{name}" in modules:
            return None
        if module in exports and name in exports[module]:
            return f"{module}.{exports[module][name]}", name
        return module, name

    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "sellip" \
                and not node.level:
            for alias in node.names:
                if f"{node.module}.{alias.name}" in modules:
                    aliases[alias.asname or alias.name] = f"{node.module}.{alias.name}"
                else:
                    target = resolve(node.module, alias.name)
                    if target:
                        found.append((node.lineno, *target))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "sellip":
                    aliases[alias.asname or "sellip"] = alias.name if alias.asname else "sellip"

    def dotted(node):
        parts = []
        while isinstance(node, ast.Attribute):
            parts.append(node.attr)
            node = node.value
        if isinstance(node, ast.Name) and node.id in aliases:
            return [aliases[node.id]] + parts[::-1]
        return None

    for node in ast.walk(tree):
        chain = None
        if isinstance(node, ast.Attribute):
            chain = dotted(node)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) == "setattr" \
                and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) \
                and isinstance(node.args[1].value, str):
            head = dotted(node.args[0])
            if head:
                chain = head + [node.args[1].value]
        if not chain:
            continue
        names = ".".join(chain).split(".")
        for cut in range(len(names) - 1, 0, -1):
            module = ".".join(names[:cut])
            if module in modules:
                target = resolve(module, names[cut])
                if target:
                    found.append((node.lineno, *target))
                break
    return sorted(set(found))


def all_references(root: Path):
    """(file, line, its module or None, target module, name) for every file of src/, tests/, benchmarks/, scripts/;
    also the module table and the packages' export tables."""
    src = root / "src"
    modules = module_files(src)
    exports = {m: e for m, p in modules.items() if p.name == "__init__.py" and (e := package_exports(p)) is not None}
    out = []
    for folder in ("src", "tests", "benchmarks", "scripts"):
        for path in sorted((root / folder).rglob("*.py")):
            own = ".".join(path.relative_to(src).with_suffix("").parts).removesuffix(".__init__") \
                if folder == "src" else None
            for line, module, name in references(path, modules, exports):
                out.append((path, line, own, module, name))
    return out, modules, exports

def surface_problems(root: Path) -> list[str]:
    """No file takes another module's private name (``_x``), and a name that a file outside its package takes from
    a package with a lazy export table (``sellip._exports``) is listed in that package's ``__init__``."""
    found = []
    out, modules, exports = all_references(root)
    for path, line, own, module, name in out:
        where = f"{path.relative_to(root)}:{line}"
        if is_private(name) and own != module:
            found.append(f"{where}: takes {module}.{name}, a private name of another module (make it public)")
            continue
        package = ".".join(module.split(".")[:2])
        if package in exports and module != package and (own or "").split(".")[:2] != package.split(".") \
                and name not in exports[package] and name in defined_names(modules[module]):
            found.append(f"{where}: takes {module}.{name} from outside {package}, whose __init__ does not list it")
    return found


def defined_names(path: Path) -> set[str]:
    """The names a module defines at its top level (functions, classes, assignments)."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
    return names


def main() -> int:
    root = Path(__file__).resolve().parents[1]
    found = problems(root / "src") + surface_problems(root)
    for line in found:
        print(line)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
