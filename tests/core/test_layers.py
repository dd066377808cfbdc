"""The house rules, read from the source (README, "Architecture"): the layers import only downwards,
no two modules import each other (directly or round a longer circle), modules and functions stay
small, and every `noqa` says why."""

import ast
import io
import re
import tokenize
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("mono_hdr_plugin", "backbones")
SCRIPTS = ("benchmarks", "examples", "tools")  # held to the size rules too
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60

# Which layers each layer may import (README, "Architecture"). The package root holds only the
# version, so every layer may read it. Nothing in mono_hdr_plugin imports `backbones`: backbones
# arrive through the registry's entry points.
MAY_IMPORT = {
    "core": {"core"},
    "data": {"core", "data"},
    "methods": {"core", "methods"},
    "backbones": {"core", "data", "backbones"},
    "training": {"core", "data", "methods", "training"},
    "apps": {"core", "data", "methods", "training", "apps"},
    "root": set(),
}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_modules() -> dict[str, Path]:
    return {module_name(path): path for top in PACKAGES for path in sorted((ROOT / top).rglob("*.py"))}


def layer(module: str) -> str:
    parts = module.split(".")
    if parts[0] == "backbones":
        return "backbones"
    return "root" if len(parts) == 1 else parts[1]


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(node: ast.AST) -> Iterator[ast.Import | ast.ImportFrom]:
    """Every import statement, also inside functions and classes, except under `if TYPE_CHECKING:`."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.Import | ast.ImportFrom):
            yield child
        elif isinstance(child, ast.If) and _is_type_checking(child.test):
            for branch in child.orelse:
                yield from _import_nodes(ast.Module(body=[branch], type_ignores=[]))
        else:
            yield from _import_nodes(child)


def _resolve(name: str, known: dict[str, Path]) -> str | None:
    """The longest known module `name` starts with (`a.b.Thing` -> `a.b`), None outside the packages."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        if ".".join(parts[:end]) in known:
            return ".".join(parts[:end])
    return None


def imports_of(module: str, known: dict[str, Path]) -> list[tuple[int, str]]:
    """(line, imported module) for every import of a package module; `from pkg import sub` imports pkg.sub."""
    path = known[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in _import_nodes(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        else:
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            targets = [f"{base}.{alias.name}" for alias in node.names]
        for target in targets:
            resolved = _resolve(target, known)
            if resolved is not None and resolved != module and (node.lineno, resolved) not in found:
                found.append((node.lineno, resolved))
    return found


def import_graph() -> dict[str, dict[str, int]]:
    """module -> {imported module: line of the first such import}."""
    known = package_modules()
    graph: dict[str, dict[str, int]] = {}
    for module in known:
        edges = graph.setdefault(module, {})
        for line, target in imports_of(module, known):
            edges.setdefault(target, line)
    return graph


def _strongly_connected(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Tarjan's components of more than one module, each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph[node]:
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def _circle(graph: dict[str, dict[str, int]], members: list[str]) -> list[str]:
    """One shortest import circle through the component's first module (breadth first)."""
    start, inside = members[0], set(members)
    paths = {start: [start]}
    queue = [start]
    while queue:
        node = queue.pop(0)
        for target in sorted(graph[node]):
            if target == start:
                return paths[node] + [start]
            if target in inside and target not in paths:
                paths[target] = paths[node] + [target]
                queue.append(target)
    raise AssertionError(f"no circle through {start}")


def python_files(*tops: str) -> list[Path]:
    return [path for top in tops for path in sorted((ROOT / top).rglob("*.py"))]


def test_no_layer_imports_upwards():
    known = package_modules()
    wrong = []
    for module, path in known.items():
        allowed = MAY_IMPORT[layer(module)]
        for line, target in imports_of(module, known):
            if layer(target) not in allowed | {"root"}:
                wrong.append(
                    f"{path.relative_to(ROOT)}:{line} imports {target} "
                    f"({layer(module)} may import only {', '.join(sorted(allowed))})"
                )
    assert not wrong, "imports against the layer rule (README, Architecture):\n" + "\n".join(wrong)


def test_no_import_circles():
    graph = import_graph()
    circles = []
    for members in _strongly_connected(graph):
        circle = _circle(graph, members)
        steps = [f"{a} (line {graph[a][b]})" for a, b in zip(circle, circle[1:])]
        circles.append(" -> ".join(steps + [circle[-1]]))
    assert not circles, (
        "import circles (lazy imports in functions count; only `if TYPE_CHECKING:` does not):\n" + "\n".join(circles)
    )


def test_no_module_over_the_size_limit():
    long = [
        f"{path.relative_to(ROOT)}: {count} lines"
        for path in python_files(*PACKAGES, *SCRIPTS)
        if (count := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    ]
    assert not long, f"modules over {MAX_MODULE_LINES} lines (split them by job):\n" + "\n".join(long)


def test_no_function_over_the_size_limit():
    long = []
    for path in python_files(*PACKAGES, *SCRIPTS):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                count = (node.end_lineno or node.lineno) - node.lineno + 1
                if count > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {count} lines")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long)


NOQA = re.compile(r"#\s*noqa\b")
NOQA_WITH_REASON = re.compile(r"#\s*noqa:\s*[A-Z]+[0-9]+(\s*,\s*[A-Z]+[0-9]+)*\s+-\s+\S")


def test_every_noqa_says_why():
    bare = []
    for path in python_files(*PACKAGES, *SCRIPTS, "tests"):
        tokens = tokenize.generate_tokens(io.StringIO(path.read_text()).readline)
        for token in tokens:
            if (
                token.type == tokenize.COMMENT
                and NOQA.search(token.string)
                and not NOQA_WITH_REASON.search(token.string)
            ):
                bare.append(f"{path.relative_to(ROOT)}:{token.start[0]}: {token.string}")
    assert not bare, (
        "write `# noqa: CODE - reason` (or fix the line); a noqa for a rule ruff does not "
        "check can go:\n" + "\n".join(bare)
    )


def test_the_checks_see_imports_in_functions_and_skip_type_checking(tmp_path, monkeypatch):
    """The seam itself: lazy imports count, `if TYPE_CHECKING:` does not, `from pkg import sub` is pkg.sub."""
    package = tmp_path / "mono_hdr_plugin"
    for folder in ("core", "training"):
        (package / folder).mkdir(parents=True)
        (package / folder / "__init__.py").write_text("")
    (package / "__init__.py").write_text("")
    (package / "training" / "loop.py").write_text("")
    (package / "core" / "lazy.py").write_text("def f():\n    from mono_hdr_plugin.training import loop\n")
    (package / "core" / "typed.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import mono_hdr_plugin.training.loop\n"
    )
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    monkeypatch.setitem(globals(), "PACKAGES", ("mono_hdr_plugin",))
    known = package_modules()
    assert imports_of("mono_hdr_plugin.core.lazy", known) == [(2, "mono_hdr_plugin.training.loop")]
    assert imports_of("mono_hdr_plugin.core.typed", known) == []


def test_the_circle_check_names_a_circle():
    graph = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3, "d": 4}, "d": {}}
    assert _strongly_connected(graph) == [["a", "b", "c"]]
    assert _circle(graph, ["a", "b", "c"]) == ["a", "b", "c", "a"]
