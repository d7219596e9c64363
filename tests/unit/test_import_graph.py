"""The module import graph of tetdose, read statically with ast: no module imports another
module's private names (``from x import _y``), and the module-level imports have no cycle.

Imports inside functions and under ``if TYPE_CHECKING:`` are deferred and do not take part in
the cycle check (they cannot fail at import time); they are held to the private-name rule.
"""

import ast
from pathlib import Path

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


def _deferred(tree: ast.Module) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        type_checking = isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        if type_checking or isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            ids |= {id(sub) for sub in ast.walk(node) if sub is not node}
    return ids


def _imports(module: str) -> list[tuple[str, str | None, bool]]:
    """(imported module, imported name or None, deferred) for every tetdose import."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    deferred = _deferred(tree)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, None, id(node) in deferred) for a in node.names
                    if a.name.split(".")[0] == "tetdose"]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            if base.split(".")[0] == "tetdose":
                out += [(base, a.name, id(node) in deferred) for a in node.names]
    return out


def test_no_module_imports_another_modules_private_names():
    found = []
    for module in MODULES:
        for base, name, _ in _imports(module):
            if (name and name.startswith("_") and not name.startswith("__")
                    and f"{base}.{name}" not in MODULES and _owner(base) != module):
                found.append(f"{module}: from {base} import {name}")
    assert not found, "private names imported across modules:\n" + "\n".join(found)


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


def test_module_level_imports_have_no_cycle():
    edges: dict[str, set[str]] = {m: set() for m in MODULES}
    for module in MODULES:
        for base, name, deferred in _imports(module):
            if deferred:
                continue
            target = f"{base}.{name}" if name and f"{base}.{name}" in MODULES else _owner(base)
            if target and target != module:
                edges[module].add(target)
    assert not _cycles(edges), f"import cycles: {_cycles(edges)}"
