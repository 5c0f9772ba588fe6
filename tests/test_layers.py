"""The package's folders are its layers: every module imports only from its own layer or the layers below
(no import back up, no circle), at the top of the module."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "boxjax"

# Bottom to top. A top-level module is its own layer (so the shared modules cannot import each other in a
# circle either); a subpackage is one layer, whose modules may import each other without a circle.
LAYERS = (
    "config",
    "fileio",
    "mlp",
    "geometry",
    "planning",
    "massdist",
    "task",
    "boxfile",
    "config_io",
    "run_info",
    "viz",
    "sim",
    "prior",
    "blackbox",
    "estimator",
    "planners",
    "control",
    "robot",
    "training",
    "experiments",
    "cli",
    "__main__",
)
RANK = {name: i for i, name in enumerate(LAYERS)}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _imports(path: Path, known: set[str]) -> list[tuple[str, int, bool]]:
    """(module imported, line, at module level) for every import of a boxjax module in `path`."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("boxjax"):
            for a in node.names:
                full = f"{node.module}.{a.name}"
                out.append((full if full in known else node.module, node.lineno, id(node) in top))
        elif isinstance(node, ast.Import):
            out += [(a.name, node.lineno, id(node) in top) for a in node.names if a.name.startswith("boxjax")]
    return out


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None  # None: the package's face `boxjax` itself


def test_every_module_is_in_a_layer():
    missing = sorted({_layer(m) for m in _modules()} - set(LAYERS) - {None})
    assert not missing, f"add {missing} to LAYERS in tests/test_layers.py"


def test_imports_run_down_the_layers():
    mods = _modules()
    wrong = []
    for mod, path in mods.items():
        here = _layer(mod)
        for dep, line, _ in _imports(path, set(mods)):
            there = _layer(dep)
            if here is None or there is None:
                # the face imports lazily; a module may read `boxjax.__version__` (defined before any import)
                if there is None and dep == "boxjax" and here is not None:
                    names = _imported_names(path, line)
                    if names - {"__version__"}:
                        wrong.append(f"{mod}:{line} imports {sorted(names)} from the face `boxjax`")
                continue
            if RANK[there] > RANK[here]:
                wrong.append(f"{mod}:{line} ({here}) imports {dep} ({there}), a layer above")
    assert not wrong, "\n".join(wrong)


def _imported_names(path: Path, line: int) -> set[str]:
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.lineno == line and node.module == "boxjax":
            return {a.name for a in node.names}
        if isinstance(node, ast.Import) and node.lineno == line:
            return {"__version__"}  # `import boxjax` to read its version
    return set()


def test_no_import_circle():
    mods = _modules()
    graph = {
        m: {d for d, _, _ in _imports(p, set(mods)) if d in mods and d != "boxjax"} for m, p in mods.items()
    }
    # a package's face imports its modules; a module importing its own package's face would close a circle
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                raise AssertionError("import circle: " + " -> ".join(stack[stack.index(d) :] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_imports_inside_functions_only_in_the_cli():
    """Outside `boxjax.cli` (which imports per command, for start-up time) boxjax modules import each other
    at the top. The exceptions are listed with their reason."""
    allowed = {
        # the report still renders when the data-efficiency module cannot be imported (tested)
        ("boxjax.experiments.reproduce", "boxjax.experiments.data_efficiency"),
    }
    mods = _modules()
    inner = []
    for mod, path in mods.items():
        if mod.startswith("boxjax.cli") or mod == "boxjax":
            continue
        for dep, line, at_top in _imports(path, set(mods)):
            if not at_top and (mod, dep) not in allowed and _layer(dep) is not None:
                inner.append(f"{mod}:{line} imports {dep} inside a function")
    assert not inner, "\n".join(inner)
