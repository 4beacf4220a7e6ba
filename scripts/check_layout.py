"""Check the package layout of docs/architecture.md.

    python scripts/check_layout.py          # prints each problem; exit status 1 when there is one

- no import cycle between sellip's modules (imports inside functions count too);
- no module imports a package above its floor (model 0; capture, geometry 1; fit 2; report 3; bench 4;
  stages 5; the base modules jobs and timing import no other sellip package);
- no stage adapter imports another stage (``stages/_*.py`` are shared helpers, not stages);
- no module over MAX_MODULE_LINES lines; no function over MAX_FUNCTION_LINES lines whose docstring does not
  say why (a sentence starting "Long:").
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

FLOORS = {"jobs": -1, "timing": -1, "_exports": -1, "workflow_support": -1, "model": 0, "capture": 1, "geometry": 1,
          "fit": 2, "calibrate": 2, "report": 3, "bench": 4, "stages": 5, "cli": 6}
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


def main() -> int:
    src = Path(__file__).resolve().parents[1] / "src"
    found = problems(src)
    for line in found:
        print(line)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
