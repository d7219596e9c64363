"""Kernel modules import only math, numpy, numba (llvmlite for intrinsics) and tetdose's kernel-safe
modules (STYLE.md)."""

import ast
from pathlib import Path

ALLOWED = {"math", "numpy", "numba", "llvmlite", "typing", "tetdose._constants", "tetdose._typing",
           "tetdose._random", "tetdose._jit"}
SRC = Path(__file__).resolve().parents[2] / "src" / "tetdose"


def kernel_modules():
    return [p for p in SRC.rglob("_*.py") if p.name not in {"__init__.py", "__main__.py"}
            and ("kernel" in p.name or p.parent.name == "transport" or p.name == "_random.py")]


def test_kernel_imports():
    assert kernel_modules(), "no kernel modules found"
    for path in kernel_modules():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            for name in names:
                sibling = name.startswith("tetdose.") and (
                    name.rsplit(".", 1)[-1].startswith("_") and path.parent.name in name)
                assert name.split(".")[0] in ALLOWED or name in ALLOWED or sibling, (
                    f"{path.relative_to(SRC)} imports {name}")
