"""Imports of optional extras, with an error that names the extra to install."""

from __future__ import annotations

import importlib
from types import ModuleType

from tetdose.errors import TetdoseError


def import_optional(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module`` or raise :class:`TetdoseError` saying ``purpose`` needs ``tetdose[extra]``.

    (After highdicom's ``import_optional_dependency``.)
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise TetdoseError(
            f"{purpose} needs {module.split('.')[0]}: install tetdose[{extra}] "
            f"(pip install 'tetdose[{extra}]')"
        ) from exc
