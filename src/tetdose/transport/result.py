"""DoseResult: per-batch energy tallies → dose mean and standard deviation [Gy], energy ledger.

With B batches of n_b histories, the batch estimate of cell c is x_bc = E_bc / n_b (MeV per
source particle). The dose is ``D = P·J_PER_MEV·ΣE_bc/N / m_c`` [Gy] with P the normalization
particles, m_c the cell mass [kg]; its standard deviation is that of the mean of the batch
estimates, ``σ = P·J_PER_MEV/m_c · sqrt(Σ_b (x_bc − x̄_c)² / (B(B−1)))`` (OpenMC
``Tally.std_dev``). Cells of zero mass report zero dose.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose._constants import G_PER_KG, J_PER_MEV
from tetdose._typing import FloatArray, IntArray
from tetdose.errors import GeometryMismatchError
from tetdose.image import Image, ImageGrid
from tetdose.mesh import TetMesh

LEDGER_KEYS = ("source_mev", "deposited_mev", "escaped_mev", "cutoff_mev", "lost_mev")


@dataclass(frozen=True, eq=False)
class DoseResult:
    """Outcome of one transport run (model in, results out).

    ``energy_per_batch_mev`` (B, n_cells) energy tallied per batch; ``histories_per_batch`` (B,);
    ``mass_g`` (n_cells,); ``ledger_per_batch_mev`` (B, 5) columns :data:`LEDGER_KEYS`;
    ``counts_per_batch`` (B, 4): lost photons, relocations, secondaries dropped off a full stack,
    tetrahedron crossings (0 on voxels).
    """

    energy_per_batch_mev: FloatArray
    histories_per_batch: IntArray
    mass_g: FloatArray
    ledger_per_batch_mev: FloatArray
    counts_per_batch: IntArray
    particles: float
    seed: int
    estimator: str
    geometry: str
    wall_s: float
    version: str
    grid: ImageGrid | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def n_histories(self) -> int:
        return int(self.histories_per_batch.sum())

    @property
    def n_batches(self) -> int:
        return len(self.histories_per_batch)

    def _gy_per_mev(self) -> FloatArray:
        kg = self.mass_g / G_PER_KG
        return np.divide(self.particles * J_PER_MEV, kg, out=np.zeros_like(kg), where=kg > 0)

    @property
    def energy_mev(self) -> FloatArray:
        """Mean energy per source particle in each cell [MeV]."""
        return self.energy_per_batch_mev.sum(axis=0) / self.n_histories

    @property
    def dose_gy(self) -> FloatArray:
        """Dose per cell [Gy] for ``particles`` source particles."""
        return self.energy_mev * self._gy_per_mev()

    @property
    def dose_std_gy(self) -> FloatArray:
        """Standard deviation of :attr:`dose_gy` from the spread of the batch estimates [Gy]."""
        x = self.energy_per_batch_mev / self.histories_per_batch[:, None]
        b = self.n_batches
        var = ((x - x.mean(axis=0)) ** 2).sum(axis=0) / (b * (b - 1))
        return np.sqrt(var) * self._gy_per_mev()

    @property
    def relative_uncertainty(self) -> FloatArray:
        """σ/D per cell (0 where the dose is 0)."""
        d = self.dose_gy
        return np.divide(self.dose_std_gy, d, out=np.zeros_like(d), where=d > 0)

    @property
    def ledger(self) -> dict[str, float]:
        """Energy ledger per source particle [MeV]: source = deposited + escaped + cutoff + lost."""
        tot = self.ledger_per_batch_mev.sum(axis=0) / self.n_histories
        return {k: float(v) for k, v in zip(LEDGER_KEYS, tot, strict=True)}

    @property
    def lost_photons(self) -> int:
        return int(self.counts_per_batch[:, 0].sum())

    @property
    def relocations(self) -> int:
        return int(self.counts_per_batch[:, 1].sum())

    @property
    def crossings(self) -> int:
        """Tetrahedron crossings of all photons (a speed measure; 0 for voxel runs)."""
        return int(self.counts_per_batch[:, 3].sum())

    def record(self) -> dict[str, Any]:
        """The JSON run record: settings, ledger, counters, timing and version."""
        return {
            "histories": self.n_histories, "batches": self.n_batches, "seed": self.seed,
            "estimator": self.estimator, "geometry": self.geometry,
            "normalization_particles": self.particles, "ledger": self.ledger,
            "lost_photons": self.lost_photons, "relocations": self.relocations,
            "stack_overflows": int(self.counts_per_batch[:, 2].sum()),
            "tet_crossings": self.crossings,
            "wall_s": self.wall_s, "version": self.version, "units": {"dose": "Gy"},
            "max_dose_gy": float(self.dose_gy.max()), **self.extra,
        }

    def save_json(self, path: str | os.PathLike[str]) -> Path:
        """Write :meth:`record` as JSON (atomic)."""
        path = Path(path)
        with atomic_write_file(path) as tmp:
            tmp.write_text(json.dumps(self.record(), indent=2) + "\n")
        return path

    def to_mesh(self, mesh: TetMesh) -> TetMesh:
        """``mesh`` with cell_data ``dose`` and ``dose_std`` [Gy]."""
        if self.geometry != "mesh" or mesh.n_tets != len(self.mass_g):
            raise GeometryMismatchError(
                f"this {self.geometry} result has {len(self.mass_g)} cells, the mesh has "
                f"{mesh.n_tets} tetrahedra; pass the mesh the dose was computed on")
        return mesh.with_data(cell_data={"dose": self.dose_gy, "dose_std": self.dose_std_gy})

    def to_images(self) -> tuple[Image, Image]:
        """(dose, dose_std) images [Gy] on the voxel grid of a voxel run."""
        if self.grid is None:
            raise GeometryMismatchError("a mesh result has no voxel grid; use to_mesh(mesh)")
        shape = self.grid.shape
        return (Image(self.dose_gy.reshape(shape), self.grid),
                Image(self.dose_std_gy.reshape(shape), self.grid))
