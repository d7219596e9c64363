"""PhaseSeries: one reference tetrahedral mesh and K moved point sets (breathing phases).

Every phase shares the reference's cells (same ids, same vertex order), so a tetrahedron keeps
its identity — and its mass (see :mod:`tetdose.motion.conserve`) — through the whole cycle.
Phases are labelled by their position in the breathing cycle in percent (0 % = end-inhale by
the 4D-CT convention) and carry a time weight (fraction of the cycle spent near that phase,
summing to 1), used when dose is accumulated over phases.

On disk a series is a folder with one VTU per phase (point_data ``density`` [g/cm³]) and a
ParaView collection ``phases.pvd`` (VTKFile type="Collection", one ``DataSet`` per phase with
``timestep`` = phase percent and ``weight`` = time weight), so the motion plays in ParaView.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose._typing import FloatArray
from tetdose.core.io import read_mesh, write_mesh
from tetdose.core.mesh import TetMesh
from tetdose.errors import MeshError, TopologyMismatchError

#: Name of the ParaView collection file written beside the phase VTUs.
PVD_NAME = "phases.pvd"
#: point_data name of the vertex density [g/cm³].
DENSITY = "density"


@dataclass(frozen=True, eq=False)
class PhaseSeries:
    """A reference mesh and K phase point sets sharing its topology.

    Parameters
    ----------
    reference : TetMesh
        The mesh the density was mapped on (reference phase, e.g. the planning CT).
    points_mm : (K, N, 3) float
        Vertex positions of each phase [mm].
    phase_percent : (K,) float, optional
        Position of each phase in the breathing cycle [% of the period]; default 100·k/K.
    time_weight : (K,) float, optional
        Fraction of the cycle represented by each phase (≥ 0, normalised to sum 1); default 1/K.
    density_g_cm3 : (K, N) float, optional
        Vertex density of each phase [g/cm³] once updated (see ``conserve.update_series``).
    """

    reference: TetMesh
    points_mm: FloatArray
    phase_percent: FloatArray | None = None
    time_weight: FloatArray | None = None
    density_g_cm3: FloatArray | None = None

    def __post_init__(self) -> None:
        ref = self.reference
        pts = np.ascontiguousarray(self.points_mm, dtype=np.float64)
        if pts.ndim == 2:
            pts = pts[None]
        if pts.ndim != 3 or pts.shape[1:] != ref.points_mm.shape:
            raise TopologyMismatchError(
                f"phase points have shape {pts.shape}, expected (K, {ref.n_points}, 3) for a "
                f"reference mesh with {ref.n_points} points; phases must share its topology"
            )
        k = len(pts)
        pct = (100.0 * np.arange(k) / k if self.phase_percent is None
               else np.asarray(self.phase_percent, dtype=np.float64).reshape(-1))
        w = (np.full(k, 1.0 / k) if self.time_weight is None
             else np.asarray(self.time_weight, dtype=np.float64).reshape(-1))
        if len(pct) != k or len(w) != k:
            raise MeshError(f"{k} phases but {len(pct)} phase percents and {len(w)} weights")
        if not (np.isfinite(pct).all() and np.all((pct >= 0) & (pct < 100))):
            raise MeshError(f"phase percents must lie in [0, 100) %, got {pct.tolist()}")
        if len(np.unique(pct)) != k:
            raise MeshError(f"two phases at one percent ({pct.tolist()} %): every phase needs its "
                            "own position in the cycle; give distinct --phase-percent values")
        if np.any(w < 0) or not np.isfinite(w).all() or w.sum() <= 0:
            raise MeshError(f"time weights must be finite, ≥ 0 and not all 0, got {w.tolist()}")
        object.__setattr__(self, "points_mm", pts)
        object.__setattr__(self, "phase_percent", pct)
        object.__setattr__(self, "time_weight", w / w.sum())
        if self.density_g_cm3 is not None:
            rho = np.asarray(self.density_g_cm3, dtype=np.float64)
            if rho.shape != (k, ref.n_points):
                raise MeshError(f"phase densities have shape {rho.shape}, expected "
                                f"({k}, {ref.n_points})")
            object.__setattr__(self, "density_g_cm3", rho)
        for i in range(k):
            self.mesh(i).check_cells(context=f"in phase {i} ({pct[i]:g} %) after deformation")

    @property
    def n_phases(self) -> int:
        return len(self.points_mm)

    def mesh(self, k: int) -> TetMesh:
        """Phase ``k`` as a TetMesh (its density in point_data ``density`` if known)."""
        m = self.reference.moved(self.points_mm[k])
        if self.density_g_cm3 is not None:
            m = m.with_data(point_data={DENSITY: self.density_g_cm3[k]})
        return m

    def with_density(self, density_g_cm3: FloatArray) -> PhaseSeries:
        """A copy carrying per-phase vertex densities (K, N) [g/cm³]."""
        return PhaseSeries(self.reference, self.points_mm, self.phase_percent, self.time_weight,
                           density_g_cm3)

    @classmethod
    def from_meshes(cls, reference: TetMesh, phases: Sequence[TetMesh], *,
                    phase_percent: Sequence[float] | None = None,
                    time_weight: Sequence[float] | None = None) -> PhaseSeries:
        """Build from phase meshes; the first cell differing from the reference is an error."""
        for i, m in enumerate(phases):
            try:
                reference.same_topology(m)
            except TopologyMismatchError as exc:
                raise TopologyMismatchError(f"phase {i}: {exc}") from None
        rho = None
        if phases and all(DENSITY in m.point_data for m in phases):
            rho = np.stack([np.asarray(m.point_data[DENSITY], dtype=np.float64).reshape(-1)
                            for m in phases])
        return cls(reference, np.stack([m.points_mm for m in phases]), phase_percent,
                   time_weight, rho)

    @classmethod
    def read(cls, reference: TetMesh | str | os.PathLike[str] | None,
             phases: Sequence[str | os.PathLike[str]] | str | os.PathLike[str], *,
             phase_percent: Sequence[float] | None = None) -> PhaseSeries:
        """Read phase VTUs (a list of files, or a folder holding ``phases.pvd``).

        With a folder, the phase percents and weights come from its collection file. Without a
        ``reference`` the first phase is taken as the reference.
        """
        pct, weight = phase_percent, None
        if isinstance(phases, str | os.PathLike):
            files, steps, weight = read_pvd(Path(phases) / PVD_NAME)
            pct = steps if pct is None else pct
        else:
            files = [Path(p) for p in phases]
        if not files:
            raise MeshError("no phase meshes given; pass one VTU per phase")
        meshes = [read_mesh(f) for f in files]
        if reference is None:
            reference = meshes[0]
        elif not isinstance(reference, TetMesh):
            reference = read_mesh(reference)
        return cls.from_meshes(reference, meshes, phase_percent=pct, time_weight=weight)

    def write(self, out_dir: str | os.PathLike[str], *, stem: str = "phase") -> list[Path]:
        """Write one VTU per phase and the ParaView collection ``phases.pvd``; atomic per file."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = [write_mesh(out / f"{stem}_{k:03d}.vtu", self.mesh(k))
                 for k in range(self.n_phases)]
        write_pvd(out / PVD_NAME, [p.name for p in paths], self.phase_percent, self.time_weight)
        return paths


def write_pvd(path: Path, files: Sequence[str], timesteps: FloatArray,
              weights: FloatArray) -> Path:
    """Write a ParaView ``.pvd`` collection (VTK XML ``Collection``) listing ``files``; atomic."""
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for f, t, w in zip(files, timesteps, weights, strict=True):
        ET.SubElement(coll, "DataSet", timestep=repr(float(t)), group="", part="0", file=f,
                      weight=repr(float(w)))
    ET.indent(root)
    with atomic_write_file(path) as tmp:
        ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=True)
    return path


def read_pvd(path: Path) -> tuple[list[Path], FloatArray, FloatArray | None]:
    """Files, timesteps and (if present) weights listed by a ``.pvd`` collection."""
    if not path.exists():
        raise MeshError(f"{path} does not exist; give a folder written by `tetdose deform`")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise MeshError(f"{path} is not valid XML ({exc}); rewrite it with `tetdose deform`"
                        ) from exc
    sets = root.findall("./Collection/DataSet")
    if not sets:
        raise MeshError(f"{path} lists no DataSet; it is not a phase collection")
    files = [path.parent / d.attrib["file"] for d in sets]
    steps = np.array([float(d.attrib.get("timestep", i)) for i, d in enumerate(sets)])
    weights = (np.array([float(d.attrib["weight"]) for d in sets])
               if all("weight" in d.attrib for d in sets) else None)
    return files, steps, weights
