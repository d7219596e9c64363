"""DoseResult: per-batch energy tallies → dose mean and standard deviation [Gy], energy ledger.

With B batches of n_b histories, the batch estimate of cell c is x_bc = E_bc / n_b (MeV per
source particle). The dose is ``D = P·J_PER_MEV·ΣE_bc/N / m_c`` [Gy] with P the normalization
particles, m_c the cell mass [kg]; its standard deviation is that of the mean of the batch
estimates, ``σ = P·J_PER_MEV/m_c · sqrt(Σ_b (x_bc − x̄_c)² / (B(B−1)))`` (OpenMC
``Tally.std_dev``). Cells of zero mass report zero dose.

A hybrid run (mesh inside a CT, :mod:`tetdose.transport.geometry.world`) has cells ``0 … M−1`` = tets
(mesh order) and ``M + j`` = voxel j; :meth:`DoseResult.mesh_part` and
:meth:`DoseResult.voxel_part` split it, and :meth:`DoseResult.combined` is the dose on the CT
grid with the mesh's energy put on the voxels through the exact overlaps, in proportion to mass:

    E_j = E_vox,j + Σ_k E_k · m_kj / m_k,      m_j = m_vox,j + Σ_k m_kj,      D_j = E_j / m_j

(m_vox,j the voxel part's mass: the voxel's density times its volume outside the mesh). The map
is linear, so it is applied to every batch row and the standard deviation follows as above.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp

from tetdose._atomic import atomic_write_file
from tetdose._constants import G_PER_KG, J_PER_MEV, MM3_PER_CM3
from tetdose._typing import FloatArray, IntArray
from tetdose.core.body import NEAR_MAX_SAID, near_max_gy
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.errors import GeometryMismatchError
from tetdose.plan.prescription import PER_PHOTON_UNIT

if TYPE_CHECKING:
    from tetdose.transport.geometry.world import MeshOnGrid

LEDGER_KEYS = ("source_mev", "deposited_mev", "escaped_mev", "cutoff_mev", "lost_mev")
COUNT_KEYS = ("lost_photons", "relocations", "stack_overflows", "tet_crossings", "voxel_steps",
              "mesh_voxel_switches", "missed_world")
#: Dose mode (coupled electron transport) adds the e± columns: continuous loss deposited, e±
#: escaped (a positron with its 2mc²), e± kinetic energy below the cut-off; and counters.
LEDGER_KEYS_DOSE = (*LEDGER_KEYS, "electron_deposited_mev", "electron_escaped_mev",
                    "electron_cutoff_mev", "roulette_mev")
COUNT_KEYS_DOSE = (*COUNT_KEYS, "electron_steps", "electron_tracks", "woodcock_steps")


class FrozenExtra(dict):
    """The ``extra`` record entries of a :class:`DoseResult`: a dict that refuses changes
    (``result.with_extra(key=value)`` returns a new result instead)."""

    def _refuse(self, *args: Any, **kwargs: Any) -> None:  # noqa: ANN401
        raise TypeError("a DoseResult is immutable: use result.with_extra(key=value)")

    __setitem__ = __delitem__ = update = pop = popitem = setdefault = clear = _refuse
    __ior__ = _refuse

    def __reduce__(self) -> tuple[Any, ...]:
        return FrozenExtra, (dict(self),)


@dataclass(frozen=True, eq=False)
class DoseResult:
    """Outcome of one transport run (model in, results out).

    ``energy_per_batch_mev`` (B, n_cells) energy tallied per batch; ``histories_per_batch`` (B,);
    ``mass_g`` (n_cells,); ``ledger_per_batch_mev`` (B, 5) columns :data:`LEDGER_KEYS`;
    ``counts_per_batch`` (B, 7): lost photons, relocations, secondaries dropped off a full stack,
    tetrahedron crossings, voxel steps, mesh ↔ voxel switches, source photons that missed the
    world (:data:`COUNT_KEYS`). Dose mode (electron transport) has 9 ledger and 10 counter
    columns (:data:`LEDGER_KEYS_DOSE`, :data:`COUNT_KEYS_DOSE`; lost counts every particle);
    ``extra["physics"]`` says which the dose is.
    ``geometry``: "mesh", "voxel" or "hybrid"; ``n_tets`` leading cells are tetrahedra;
    ``on_grid`` (hybrid only) the mesh's overlap pairs with the grid, for :meth:`combined`;
    ``water_ratio`` (n_cells,) the s_w,m each cell's energy was multiplied by (dose to water
    from the tracked electron fluence, ``extra["dose_to_water"]``), else None.
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
    n_tets: int = 0
    on_grid: MeshOnGrid | None = None
    water_ratio: FloatArray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "extra", FrozenExtra(self.extra))

    def with_extra(self, **entries: Any) -> DoseResult:  # noqa: ANN401
        """A new result whose record carries ``entries`` besides (or instead of) ``extra``'s."""
        return replace(self, extra={**self.extra, **entries})

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
        keys = LEDGER_KEYS if len(tot) == len(LEDGER_KEYS) else LEDGER_KEYS_DOSE
        return {k: float(v) for k, v in zip(keys, tot, strict=True)}

    @property
    def absorbed_mev(self) -> float:
        """Energy that stays in the world per source particle [MeV]: the deposited and cut-off
        columns of photons and, in dose mode, of e± (what the tallies hold in an analog run)."""
        return sum(v for k, v in self.ledger.items() if k.endswith(("deposited_mev", "cutoff_mev")))

    @property
    def escaped_mev(self) -> float:
        """Energy leaving the world per source particle [MeV], photons and e±."""
        return sum(v for k, v in self.ledger.items() if k.endswith("escaped_mev"))

    @property
    def ledger_closure(self) -> float:
        """|source − Σ every other ledger column| / source: how well the energy ledger closes
        (photon and, in dose mode, electron columns; round-off only)."""
        led = self.ledger
        source = led["source_mev"]
        rest = sum(v for k, v in led.items() if k != "source_mev")
        return abs(source - rest) / source if source > 0 else 0.0

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

    @property
    def _count_keys(self) -> tuple[str, ...]:
        return COUNT_KEYS if self.counts_per_batch.shape[1] == len(COUNT_KEYS) else COUNT_KEYS_DOSE

    def near_max_dose_gy(self, tet_volume_mm3: FloatArray | None = None) -> float:
        """The near-maximum dose in tissue [Gy], D0.1cm³ over the cells denser than
        :data:`~tetdose.core.body.TISSUE_FLOOR_G_CM3` (:func:`tetdose.core.body.near_max_gy`):
        over the grid's voxels (a hybrid run's combined dose; density = mass / voxel volume),
        or over the tets given their volumes [mm³]; NaN when neither is known."""
        if self.grid is not None:
            res = self.combined()
            cm3 = self.grid.voxel_volume_mm3 / MM3_PER_CM3
            return near_max_gy(res.dose_gy, cm3, res.mass_g / cm3)
        if tet_volume_mm3 is None:
            return float("nan")
        cm3 = np.asarray(tet_volume_mm3, dtype=np.float64) / MM3_PER_CM3
        return near_max_gy(self.dose_gy[:len(cm3)], cm3, self.mass_g[:len(cm3)] / cm3)

    def record(self, tet_volume_mm3: FloatArray | None = None) -> dict[str, Any]:
        """The JSON run record: settings, ledger, counters, timing and version; the
        near-maximum dose in tissue (:meth:`near_max_dose_gy`, ``tet_volume_mm3`` for a mesh
        run)."""
        return {
            "histories": self.n_histories, "batches": self.n_batches, "seed": self.seed,
            "estimator": self.estimator, "geometry": self.geometry,
            "normalization_particles": self.particles, "ledger": self.ledger,
            **{k: int(v) for k, v in zip(self._count_keys, self.counts_per_batch.sum(axis=0),
                                         strict=True)},
            "n_tets": self.n_tets, "n_voxels": len(self.mass_g) - self.n_tets,
            "wall_s": self.wall_s, "version": self.version,
            "units": {"dose": PER_PHOTON_UNIT},
            "near_max_dose_gy": self.near_max_dose_gy(tet_volume_mm3), "near_max": NEAR_MAX_SAID,
            **self.extra,
        }

    def save_json(self, path: str | os.PathLike[str], tet_volume_mm3: FloatArray | None = None
                  ) -> Path:
        """Write :meth:`record` as JSON (atomic)."""
        path = Path(path)
        with atomic_write_file(path) as tmp:
            tmp.write_text(json.dumps(self.record(tet_volume_mm3), indent=2) + "\n")
        return path

    def _part(self, cells: slice, geometry: str, grid: ImageGrid | None) -> DoseResult:
        return replace(self, energy_per_batch_mev=self.energy_per_batch_mev[:, cells],
                       mass_g=self.mass_g[cells], geometry=geometry, grid=grid,
                       n_tets=self.n_tets if geometry == "mesh" else 0, on_grid=None,
                       extra=dict(self.extra),
                       water_ratio=None if self.water_ratio is None else self.water_ratio[cells])

    def mesh_part(self) -> DoseResult:
        """The tetrahedra's cells (a mesh result; the ledger stays the whole run's)."""
        if self.n_tets == 0:
            raise GeometryMismatchError("this voxel result has no mesh part")
        return self if self.geometry == "mesh" else self._part(slice(0, self.n_tets), "mesh", None)

    def voxel_part(self) -> DoseResult:
        """The voxels' cells (a voxel result on the grid; voxels inside the mesh have no mass
        here and report zero dose)."""
        if self.grid is None:
            raise GeometryMismatchError("this mesh result has no voxel part")
        return self if self.geometry == "voxel" else self._part(slice(self.n_tets, None), "voxel",
                                                                self.grid)

    def combined(self) -> DoseResult:
        """Mesh and voxel energy together on the CT grid (module docstring): a voxel result."""
        if self.geometry != "hybrid" or self.on_grid is None:
            return self.voxel_part()
        og, m = self.on_grid, self.n_tets
        m_k = self.mass_g[:m]  # a tet partly outside the grid keeps its outside share there
        frac = np.divide(og.mass_g, m_k[og.tet], out=np.zeros_like(og.mass_g),
                         where=m_k[og.tet] > 0)
        cols, inv = np.unique(og.voxel, return_inverse=True)
        share = sp.csr_matrix((frac, (og.tet, inv)), shape=(m, len(cols)))
        energy = self.energy_per_batch_mev[:, m:].copy()
        energy[:, cols] += (share.T @ self.energy_per_batch_mev[:, :m].T).T
        mass = self.mass_g[m:].copy()
        np.add.at(mass, og.voxel, og.mass_g)
        ratio = self.water_ratio
        if ratio is not None:  # energy-weighted: D_w / D_m of the combined energies
            medium = self.energy_per_batch_mev.sum(axis=0) / ratio
            e_m = medium[m:].copy()
            e_m[cols] += share.T @ medium[:m]
            e_w = energy.sum(axis=0)
            ratio = np.divide(e_w, e_m, out=ratio[m:].copy(), where=e_m > 0)
        return replace(self, energy_per_batch_mev=energy, mass_g=mass, geometry="voxel",
                       n_tets=0, on_grid=None, extra=dict(self.extra), water_ratio=ratio)

    def to_mesh(self, mesh: TetMesh) -> TetMesh:
        """``mesh`` with cell_data ``dose`` and ``dose_std`` [Gy] (the mesh part of a hybrid), and
        ``s_w_m`` (:attr:`water_ratio`) for dose to water from the tracked fluence."""
        if self.n_tets != mesh.n_tets:
            raise GeometryMismatchError(
                f"this {self.geometry} result has {self.n_tets} tetrahedra, the mesh has "
                f"{mesh.n_tets}; pass the mesh the dose was computed on")
        part = self.mesh_part()
        data = {"dose": part.dose_gy, "dose_std": part.dose_std_gy}
        if part.water_ratio is not None:
            data["s_w_m"] = part.water_ratio
        return mesh.with_data(cell_data=data)

    def to_images(self) -> tuple[Image, Image]:
        """(dose, dose_std) images [Gy] on the grid: a voxel run's, or a hybrid run's combined
        dose (:meth:`combined`)."""
        if self.grid is None:
            raise GeometryMismatchError("a mesh result has no voxel grid; use to_mesh(mesh)")
        res = self.combined()
        shape = self.grid.shape
        return (Image(res.dose_gy.reshape(shape), self.grid),
                Image(res.dose_std_gy.reshape(shape), self.grid))
