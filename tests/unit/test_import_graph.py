"""The module import graph of tetdose, read statically with ast: no module imports another
module's private names (``from x import _y``), and the imports have no cycle — neither at module
level nor through imports deferred into functions (a deferred import that closes a loop is a
layering fault hidden from the interpreter). Imports under ``if TYPE_CHECKING:`` (annotations
only) do not count.
"""

import ast
from pathlib import Path

import pytest

import tetdose

SRC = Path(tetdose.__file__).parent
PACKAGE = SRC.parent


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(SRC.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _owner(name: str) -> str:
    """The tetdose module that defines ``name`` (a module, or its longest module prefix)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def _inside(tree: ast.Module, functions: bool) -> set[int]:
    """ids of the nodes under ``if TYPE_CHECKING:`` (and inside functions if ``functions``)."""
    ids = set()
    for node in ast.walk(tree):
        type_checking = isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        if type_checking or (functions and isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)):
            ids |= {id(sub) for sub in ast.walk(node) if sub is not node}
    return ids


def _imports(module: str) -> list[tuple[str, str | None, str]]:
    """(imported module, imported name or None, "module" | "deferred" | "typing") for every
    tetdose import of ``module``."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    typing, lazy = _inside(tree, False), _inside(tree, True)

    def kind(node: ast.AST) -> str:
        return "typing" if id(node) in typing else "deferred" if id(node) in lazy else "module"

    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, None, kind(node)) for a in node.names
                    if a.name.split(".")[0] == "tetdose"]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            if base.split(".")[0] == "tetdose":
                out += [(base, a.name, kind(node)) for a in node.names]
    return out


def test_no_module_imports_another_modules_private_names():
    found = []
    for module in MODULES:
        for base, name, _ in _imports(module):
            if (name and name.startswith("_") and not name.startswith("__")
                    and f"{base}.{name}" not in MODULES and _owner(base) != module):
                found.append(f"{module}: from {base} import {name}")
    assert not found, "private names imported across modules:\n" + "\n".join(found)


def test_private_modules_are_imported_only_inside_their_package():
    """``tetdose.pkg._mod`` serves ``tetdose.pkg`` (and its subpackages) only; the shared
    infrastructure ``tetdose._x`` serves every module."""
    found = []
    for module in MODULES:
        for base, name, _ in _imports(module):
            target = f"{base}.{name}" if name and f"{base}.{name}" in MODULES else base
            parent, _, leaf = target.rpartition(".")
            if (leaf.startswith("_") and not leaf.startswith("__") and parent != "tetdose"
                    and not (module == parent or module.startswith(parent + "."))):
                found.append(f"{module} imports {target}")
    assert not found, "private modules imported from another package:\n" + "\n".join(found)


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of more than one module (iterative Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups = []
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                group = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    group.append(w)
                    if w == v:
                        break
                if len(group) > 1:
                    groups.append(sorted(group))
    return groups


def test_cycle_finder_finds_a_planted_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def _graph(kinds: set[str]) -> dict[str, set[str]]:
    edges: dict[str, set[str]] = {m: set() for m in MODULES}
    for module in MODULES:
        for base, name, kind in _imports(module):
            target = f"{base}.{name}" if name and f"{base}.{name}" in MODULES else _owner(base)
            if kind in kinds and target and target != module:
                edges[module].add(target)
    return edges


@pytest.mark.parametrize("kinds", [{"module"}, {"module", "deferred"}],
                         ids=["module-level", "with-deferred"])
def test_imports_have_no_cycle(kinds):
    cycles = _cycles(_graph(kinds))
    assert not cycles, f"import cycles (modules importing each other, directly or around): {cycles}"
