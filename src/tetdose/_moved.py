"""Old module paths of the 0.x layout, importable for one more release with a DeprecationWarning.

The pipeline layout (core → dicom → plan → mapping/meshing → motion → transport → dose → coupling →
compare → study → cli) moved modules; ``import tetdose.mesh`` still works and returns
:mod:`tetdose.core.mesh` itself (the same module object), after warning with the new path. The
table is also the README's "What moved" list. ``tetdose.transport.model`` maps to
:mod:`tetdose.plan.model`; its ``TransportSettings`` is now :mod:`tetdose.transport.run.settings`'s
(and, as before, ``tetdose.transport.TransportSettings``).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings
from types import ModuleType

#: Old module path → new module path.
MOVED = {
    "tetdose.mesh": "tetdose.core.mesh",
    "tetdose.image": "tetdose.core.image",
    "tetdose.tetgrid": "tetdose.core.tetgrid",
    "tetdose.mass": "tetdose.core.mass",
    "tetdose.transfer": "tetdose.core.transfer",
    "tetdose.voxelize": "tetdose.core.voxelize",
    "tetdose.tilted": "tetdose.core.tilted",
    "tetdose.io": "tetdose.core.io",
    "tetdose.calibration": "tetdose.core.calibration",
    "tetdose.body": "tetdose.core.body",
    "tetdose.mapping.overlap": "tetdose.core.overlap",
    "tetdose.transport.photon_source": "tetdose.plan.photon_source",
    "tetdose.transport.beams": "tetdose.plan.beams",
    "tetdose.transport.spectra": "tetdose.plan.spectra",
    "tetdose.prescription": "tetdose.plan.prescription",
    "tetdose.mu_calibration": "tetdose.plan.mu_calibration",
    "tetdose.transport.model": "tetdose.plan.model",
    "tetdose.dicom.rt_plan": "tetdose.plan.rt_plan",
    "tetdose.compare.rtstruct": "tetdose.dicom.rtstruct",
    "tetdose.transport.world": "tetdose.transport.geometry.world",
    "tetdose.transport.xs": "tetdose.transport.physics.xs",
    "tetdose.transport.materials": "tetdose.transport.physics.materials",
    "tetdose.transport.source": "tetdose.transport.sources.arrays",
    "tetdose.transport.result": "tetdose.transport.history.result",
    "tetdose.transport.job": "tetdose.transport.run.job",
    "tetdose.transport.distributed": "tetdose.transport.run.distributed",
    "tetdose.transport.buildup": "tetdose.dose.buildup",
    "tetdose.absolute_dose": "tetdose.dose.absolute",
    "tetdose.accumulate": "tetdose.dose.accumulate",
    "tetdose.dose4d": "tetdose.dose.dose4d",
}


class _Alias(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old path of :data:`MOVED` and loads it as the module at its new path."""

    def find_spec(self, fullname: str, path: object = None, target: object = None
                  ) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        new = MOVED[spec.name]
        warnings.warn(f"{spec.name} moved to {new}; import it from there (the old path goes in the "
                      "next release)", DeprecationWarning, stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module: ModuleType) -> None:
        """The module is the new one, already executed."""


def install() -> None:
    """Put the alias finder on :data:`sys.meta_path` (once)."""
    if not any(isinstance(f, _Alias) for f in sys.meta_path):
        sys.meta_path.append(_Alias())
