"""The layering of the code, read from the source (ast; nothing is imported or run):

    dualnerf/      the model library               imports none of the packages below
    pipeline/      the generic engine              imports none of the packages below
    stages/        one module per stage            may import dualnerf and pipeline
    experiments/   workflows, report, CLI          may import dualnerf, pipeline and stages
    tests/, benchmarks/                            may import anything; only they import experiments

No cycle among the top-level packages, no arrow against that order, and no cycle among the modules inside
each package. Every import counts, also one inside a function (a lazy import is still a dependency).
`from package import name` is an arrow to the submodule `package.name` when there is one, else to the
package; the implicit import of a parent package (its __init__) is not an arrow.
"""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {"dualnerf": set(), "pipeline": set(), "stages": {"dualnerf", "pipeline"},
          "experiments": {"dualnerf", "pipeline", "stages"},
          "benchmarks": {"dualnerf", "pipeline", "stages", "experiments"},
          "tests": {"dualnerf", "pipeline", "stages", "experiments", "benchmarks"}}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for package in LAYERS for p in sorted((ROOT / package).rglob("*.py"))}


MODULES = _modules()


def _imported(module: str, path: Path) -> set[str]:
    """The project modules that `module` imports, anywhere in its source."""
    names: set[str] = set()
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:
                names.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base)
    found = set()
    for name in names:
        parts = name.split(".")
        for i in range(len(parts), 0, -1):        # the longest prefix that is a project module
            if ".".join(parts[:i]) in MODULES:
                found.add(".".join(parts[:i]))
                break
    return found - {module}


EDGES = {module: _imported(module, path) for module, path in MODULES.items()}


def _top(module: str) -> str:
    return module.split(".")[0]


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of `graph` as [a, b, ..., a], or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)) is not None:
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)) is not None:
            return cycle
    return None


def test_the_source_is_found():
    assert {"experiments.cli", "experiments.workflow.expand", "stages.evaluate", "pipeline.store",
            "dualnerf.idu"} <= set(MODULES)
    assert "stages.layout" in EDGES["stages.evaluate"]            # relative and lazy imports are read
    assert "experiments.workflow.grid" in EDGES["experiments.workflow.load"]


def test_no_arrow_against_the_layers():
    wrong = sorted(f"{module} imports {target}" for module, targets in EDGES.items() for target in targets
                   if _top(target) != _top(module) and _top(target) not in LAYERS[_top(module)])
    assert wrong == [], "imports against the layering (module docstring):\n" + "\n".join(wrong)


def test_no_cycle_among_the_packages():
    graph: dict[str, set[str]] = {}
    for module, targets in EDGES.items():
        graph.setdefault(_top(module), set()).update(_top(t) for t in targets if _top(t) != _top(module))
    assert _find_cycle(graph) is None


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_no_cycle_among_the_modules_of(package):
    graph = {m: {t for t in targets if _top(t) == package} for m, targets in EDGES.items() if _top(m) == package}
    cycle = _find_cycle(graph)
    assert cycle is None, f"import cycle in {package}/: {' -> '.join(cycle)}"


def test_the_engine_names_no_application():
    """pipeline/ is generic: no logger, module or package of the application in its code."""
    for path in sorted((ROOT / "pipeline").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "getLogger" and node.args:
                name = node.args[0]
                text = name.value if isinstance(name, ast.Constant) else ast.unparse(name)
                assert "dualnerf" not in text and "stages" not in text, f"{path.name}: logger {text}"
