"""The module import graph of tetdose, read statically with ast: the layers of LAYERS (lower never
imports higher), no module imports another
module's private names (``from x import _y``), and the imports have no cycle — neither at module
level nor through imports deferred into functions (a deferred import that closes a loop is a
layering fault hidden from the interpreter; imports under ``if TYPE_CHECKING:`` do not count
for cycles, but do for the layers).
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
    """``tetdose.pkg._mod`` (and ``tetdose.pkg.sub._mod``) serves the top-level package
    ``tetdose.pkg`` only; the shared infrastructure ``tetdose._x`` serves every module."""
    found = []
    for module in MODULES:
        for base, name, _ in _imports(module):
            target = f"{base}.{name}" if name and f"{base}.{name}" in MODULES else base
            parent, _, leaf = target.rpartition(".")
            top = ".".join(parent.split(".")[:2])
            if (leaf.startswith("_") and not leaf.startswith("__") and parent != "tetdose"
                    and not (module == top or module.startswith(top + "."))):
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


#: The layer order, lowest first: a module may import its own package (top-level package under
#: ``tetdose``), any package of a lower layer, and none of its own layer or above. Deferred imports
#: (inside functions) and ``TYPE_CHECKING`` imports count too: a lower layer that needs a higher
#: one's object asks for it through a protocol (e.g. :class:`tetdose.dicom.rt_dose.Plan`).
LAYERS = (
    ("infra",),        # tetdose._constants, _typing, _jit, _random, _optional, _atomic, _checks, errors
    ("core",),         # mesh, image, overlap, mass, transfer, voxelize, io, calibration
    ("dicom",),        # DICOM building blocks, CT series, RT Struct, RT Dose
    ("plan",),         # beams, spectra, prescription, MU calibration, Plan, RT Plan
    ("mapping", "meshing"),
    ("motion", "phantoms"),
    ("transport",),
    ("dose",),
    ("coupling",),
    ("compare",),
    ("study",),
    ("cli", "api"),    # "api": tetdose/__init__.py, which re-exports the public names
    ("__main__",),     # python -m tetdose → cli.main
)
_LAYER = {pkg: i for i, names in enumerate(LAYERS) for pkg in names}


def _package(module: str) -> str:
    """The top-level package of a tetdose module: ``tetdose.transport.run.job`` → ``transport``;
    ``tetdose._atomic`` and ``tetdose.errors`` → ``infra``; ``tetdose`` itself → ``api``."""
    parts = module.split(".")
    if len(parts) == 1:
        return "api"
    if parts[1].startswith("_") and parts[1] != "__main__" or parts[1] in ("errors", "_moved"):
        return "infra"
    return parts[1]


def test_every_top_level_package_has_a_layer():
    missing = {_package(m) for m in MODULES} - set(_LAYER)
    assert not missing, f"packages without a layer in LAYERS: {sorted(missing)}"


def test_layer_finder_flags_an_upward_import():
    assert _LAYER[_package("tetdose.core.mesh")] < _LAYER[_package("tetdose.transport.run.job")]
    assert _package("tetdose._atomic") == "infra" and _package("tetdose") == "api"


def test_no_import_reaches_up_or_sideways():
    found = []
    for module in MODULES:
        if module == "tetdose._moved":  # the deprecated-path aliases name every layer on purpose
            continue
        own = _package(module)
        for base, name, kind in _imports(module):
            target = f"{base}.{name}" if name and f"{base}.{name}" in MODULES else _owner(base)
            other = _package(target)
            if other != own and _LAYER[other] >= _LAYER[own]:
                found.append(f"{module} ({own}) imports {target} ({other}) [{kind}]")
    assert not found, ("imports from the same or a higher layer (see LAYERS):\n" + "\n".join(found))


def test_at_most_ten_modules_at_the_top():
    top = [p.name for p in SRC.glob("*.py") if p.name not in ("__init__.py", "__main__.py")]
    assert len(top) <= 12, f"{len(top)} modules directly in src/tetdose: {sorted(top)}"
