"""One conforming multi-label tetrahedral mesh of a label image, by level-set discretisation (MMG).

Method (MMG: Dapogny, Dobrzynski & Frey, J. Comput. Phys. 262 (2014) 358–378; multi-material
level sets, Mmg v5.5+; bound through ``mmgpy``):

1. **Distance fields.** φ_l = signed distance [mm] of every selected label l and φ_0 = −φ_union
   of the unselected rest (:mod:`tetdose.meshing.distance`), lightly smoothed. The labels are
   the Voronoi-like partition {x : φ_l(x) < φ_m(x) ∀ m ≠ l}, whose interface between touching
   labels l | m is the zero set of ψ_lm = (φ_l − φ_m)/2 — the same surface seen from both sides,
   so nested labels (tumour in lung) and side-by-side labels (liver next to kidney) are alike.
2. **Background mesh.** A Kuhn grid of the labels' box (edge = the largest target size) is
   adapted by MMG to the size field s(x) = min_l (h_s,l + g|φ_l(x)|), g = ``GRADING``, fine
   (h_s,l = h_l/2, at least one voxel) near every label surface and graded away from it: the
   zero sets of the piecewise-linear φ are then accurate where they matter (a 6 mm uniform
   background shrank a 2.5 cm tumour by 17 %).
3. **Volume.** Per label, the constant shift δ_l for which {ψ_l < δ_l}, ψ_l = (φ_l − min_m φ_m)/2
   on the background mesh, has exactly the voxel volume (:func:`levelset.volume_shift`); δ is a
   fraction of a voxel (it takes back the blur's curvature shift and the linear interpolation's
   corner cutting).
4. **Discretisation.** Labels are cut out batch by batch, the smallest first (inner labels
   before the ones around them): MMG's level-set mode splits the still-unassigned material along
   ψ_l = (φ_l − min_{m unassigned} φ_m)/2 into label l and the rest, keeping every label already
   cut (multi-material table, ``split = 0``). Labels far enough apart share one MMG call on
   ψ_B = min_{l∈B} ψ_l when that changes no zero crossing of any ψ_l (:func:`_next_batch`): the
   9 largest labels of the real abdomen map take 6 calls instead of 9 and all 31 took 11–14 on
   coarser backgrounds, each call a pass over the whole mesh (chains of touching labels keep
   their order and set the count).
   The tetrahedra of the rest are dropped at the end.
5. **Remeshing.** MMG remeshes the labelled mesh with a target edge h_l per label (local
   parameters on tetrahedron references), a Hausdorff tolerance on the interfaces and a size
   gradation, without ridge detection (``angle=0``: ridges kept as sharp lines left 3× more
   slivers on touching boxes); interfaces between labels stay shared surfaces, so the result is
   conforming. Slivers MMG leaves are then removed (:mod:`tetdose.meshing.quality`: vertex
   relocation, edge removal and 2-3 flips inside one label, flat surface tetrahedra deleted or
   given to the label across, :mod:`tetdose.meshing.flips`): every tetrahedron ≥ 10°.

The output is deterministic for the same input and options (MMG is sequential and seedless).
The numpy steps run with one BLAS thread: a threaded BLAS rounds a product differently with two
threads than with one, and MMG turned that last-bit difference into another mesh (stop 38: the
real lung CT's labels gave meshes up to 0.23 mm apart at ``OPENBLAS_NUM_THREADS`` 1 and 2).

**Bounded work.** Before MMG runs, :func:`estimate` predicts the final and background tetrahedra,
the peak memory and the time from the labels' voxel volumes V_l and target edges h_l (constants
below, measured on this project's runs); a ``budget`` refuses a job beyond it, and ``progress``
receives one event per stage and per cut (the CLI runs all this in a child process,
:mod:`tetdose.meshing.worker`, so that Ctrl-C and SIGTERM end MMG at once). A label that the
distance-field blur leaves without any inside (less than about 2×2×3 voxels) is refused before
MMG, naming it, instead of vanishing in the level-set cut.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Callable, Iterable, Mapping
from typing import Any, NamedTuple

import numpy as np
from threadpoolctl import threadpool_limits

from tetdose._optional import import_optional
from tetdose._typing import FloatArray, IntArray
from tetdose.core import tetgrid
from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh, compact_points, signed_volumes_mm3
from tetdose.errors import MeshError
from tetdose.meshing import levelset
from tetdose.meshing.checks import dihedral_angles_deg
from tetdose.meshing.distance import DistanceField, signed_distance
from tetdose.meshing.labels import checked_label_ids, default_sizes_mm
from tetdose.meshing.quality import removed_slivers

#: Blur of the distance fields [voxels], against the voxel staircase.
SMOOTHING_VOX = 0.75
#: Background size near a label surface, as a fraction of the label's target edge (at least one
#: voxel). 1.0 (with GRADING 1.0) meshed 9 abdomen labels in 90 s instead of 347 s but moved a
#: small box touching another by 3.5 % and made MMG's final remesh fail on the 31-label map.
SURFACE_FRACTION = 0.5
#: Growth of the background size with the distance to the nearest surface [mm/mm]. 1.0 shrank
#: the 31-label abdomen background from 1.9 M to 570 k tets, but with SURFACE_FRACTION 0.5 the
#: final remesh of 9 labels then ran > 5 min CPU (64 s at 0.5): kept at 0.5 until understood.
GRADING = 0.5
#: Hausdorff tolerance on the interfaces, as a fraction of the label's target edge.
HAUSD_FRACTION = 0.1
#: Size gradation between neighbouring edges (MMG ``hgrad``).
HGRAD = 1.4
#: Tetrahedra with a smaller dihedral angle [°] get their free vertices relocated (quality.py).
MIN_DIHEDRAL_DEG = 12.0
#: Smallest dihedral angle [°] every tetrahedron must reach (issue #11); below it, a warning.
REQUIRED_DIHEDRAL_DEG = 10.0
#: Smallest edge MMG may make, as a fraction of the smallest target edge (fewer slivers).
HMIN_FRACTION = 0.25


#: Final tetrahedra ≈ TETS_PER_H3 · Σ_l V_l / h_l³ + TETS_PER_H2 · Σ_lm A_lm / min(h_l, h_m)²
#: (V_l voxel volume, A_lm voxel-face area between labels l and m or the outside): fitted to
#: MMG's meshes of boxes, nested cubes and spheres (15–28 k tets, within a factor 1.5) and to
#: the real lung (44 k tets at h = 12 mm).
TETS_PER_H3 = 20.0
TETS_PER_H2 = 25.0
#: Peak memory: the process with its libraries, plus this much per final tetrahedron [B]
#: (measured 1.0–1.1 GB peak for 64–215 k tets, 0.31 GB before meshing).
BASE_BYTES = 400e6
BYTES_PER_TET = 6000.0
#: Time [s] ≈ S_FIXED + final tets · (S_PER_TET + S_PER_TET_LABEL · n_labels): fitted to
#: 16–28 k tets / 2–3 labels in 10–25 s (this machine, shared) and 693 k tets / 31 labels in
#: 17 min (README): MMG's final remesh slows down with many packed labels.
S_FIXED = 3.0
S_PER_TET = 6e-4
S_PER_TET_LABEL = 3e-5


class MeshingEstimate(NamedTuple):
    """What a meshing job will take (see :func:`estimate`): tetrahedra, memory [B], time [s]."""

    n_tets: int
    memory_bytes: float
    seconds: float

    def describe(self) -> str:
        return (f"about {_count(self.n_tets)} tets, {self.memory_bytes / 1e9:.1f} GB, "
                f"{duration_text(self.seconds)}")


class Budget(NamedTuple):
    """Limits of a meshing job: time [s] and memory [B] (None: no limit)."""

    max_seconds: float | None = None
    max_bytes: float | None = None


#: Progress callback: ``progress(event, info)`` with event "start" (info: estimate, labels),
#: "background" (tets), "cut" (labels, done, total, elapsed_s, left_s), "remesh", "done".
Progress = Callable[[str, dict[str, Any]], None]


def _count(n: float) -> str:
    if n >= 1e9:
        return f"{n / 1e9:.3g} G"
    return f"{n / 1e6:.3g} M" if n >= 1e6 else f"{n / 1e3:.3g} k" if n >= 1e3 else f"{n:.0f}"


def duration_text(seconds: float) -> str:
    if seconds < 10:
        return f"{seconds:.2g} s"
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def estimate(volumes_mm3: Mapping[int, float], sizes_mm: Mapping[int, float],
             face_areas_mm2: Mapping[tuple[int, int], float] | None = None) -> MeshingEstimate:
    """Tetrahedra, peak memory and time of meshing labels of voxel volumes ``volumes_mm3`` [mm³]
    with target edges ``sizes_mm`` [mm]; ``face_areas_mm2``: (l, m) → voxel-face area between
    labels l and m (0: outside), see :func:`face_areas_mm2` (constants of this module: a model,
    good to a factor of ~2)."""
    n = sum(TETS_PER_H3 * v / sizes_mm[lab] ** 3 for lab, v in volumes_mm3.items())
    for (a, b), area in (face_areas_mm2 or {}).items():
        h = min(sizes_mm.get(a, math.inf), sizes_mm.get(b, math.inf))
        if math.isfinite(h):
            n += TETS_PER_H2 * area / h**2
    n = max(n, 1.0)
    seconds = S_FIXED + n * (S_PER_TET + S_PER_TET_LABEL * len(volumes_mm3))
    return MeshingEstimate(int(n), BASE_BYTES + BYTES_PER_TET * n, seconds)


def face_areas_mm2(arr: np.ndarray, ids: Iterable[int], spacing_mm: FloatArray
                   ) -> dict[tuple[int, int], float]:
    """Voxel-face area [mm²] between each pair of labels (l < m; labels not in ``ids`` count as
    the outside, 0) of the label array ``arr`` (numpy order z, y, x)."""
    ids = [int(v) for v in ids]
    lut = np.zeros(int(arr.max()) + 1, dtype=np.int64)
    lut[ids] = np.arange(1, len(ids) + 1)
    code = lut[np.asarray(arr, dtype=np.int64)]
    n = len(ids) + 1
    names = [0, *ids]
    out: dict[tuple[int, int], float] = {}
    for axis in range(3):
        a = np.moveaxis(code, axis, 0)
        lo, hi = a[:-1], a[1:]
        diff = lo != hi
        pair = np.minimum(lo[diff], hi[diff]) * n + np.maximum(lo[diff], hi[diff])
        # numpy axis z, y, x ↔ spacing index 2, 1, 0: a face normal to axis has the other two
        area = float(np.prod(np.delete(np.asarray(spacing_mm)[::-1], axis)))
        for key, count in zip(*np.unique(pair, return_counts=True), strict=True):
            k = (names[int(key) // n], names[int(key) % n])
            out[k] = out.get(k, 0.0) + float(count) * area
    return out


def available_memory_bytes() -> float | None:
    """Memory this process may still use [B]: MemAvailable of /proc/meminfo (Linux), else the
    physical memory, else None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def check_budget(est: MeshingEstimate, budget: Budget, n_labels: int) -> None:
    """Refuse a job whose estimate exceeds ``budget`` (MeshError naming the way out)."""
    over = []
    if budget.max_bytes is not None and est.memory_bytes > budget.max_bytes:
        over.append(f"{est.memory_bytes / 1e9:.3g} GB of memory (available: "
                    f"{budget.max_bytes / 1e9:.3g} GB)")
    if budget.max_seconds is not None and est.seconds > budget.max_seconds:
        over.append(f"{duration_text(est.seconds)} (limit {duration_text(budget.max_seconds)}, "
                    "--max-minutes)")
    if over:
        raise MeshError(f"meshing {n_labels} label{'s' * (n_labels != 1)} into about "
                        f"{_count(est.n_tets)} tets would "
                        f"need {' and '.join(over)}; give larger target sizes (--size-mm), mesh "
                        "fewer labels (--label), or pass --force to run it anyway")


def _i32(a: np.ndarray) -> np.ndarray:
    """C-contiguous int32 (the binding reads raw memory: a column-permuted view is F-ordered)."""
    return np.ascontiguousarray(a, dtype=np.int32)


def _mmg():  # noqa: ANN202 - module
    return import_optional("mmgpy", "meshing", "conforming meshing of labels with MMG")


def conforming_mesh(labels: Image, label_ids: Iterable[int] | None = None,
                    size_mm: float | Mapping[int, float] | None = None, *,
                    smoothing_vox: float = SMOOTHING_VOX, keep_volume: bool = True,
                    budget: Budget | None = None, progress: Progress | None = None) -> TetMesh:
    """One conforming tetrahedral mesh of the labels ``label_ids`` (default: all ≠ 0).

    Parameters
    ----------
    labels : Image
        Integer label image (0 = background; any orthonormal direction).
    label_ids : iterable of int, optional
        Labels to mesh; each becomes a region (``mesh.region``), sharing vertices and faces with
        the labels it touches. Unselected labels count as outside.
    size_mm : float or {label: float}, optional
        Target edge [mm], one for all or per label; missing labels get
        :func:`~tetdose.meshing.labels.default_sizes_mm` (from each label's size and thickness).
    smoothing_vox : float
        Gaussian blur [voxels] of the distance fields (0 = none: a faint voxel staircase stays).
    keep_volume : bool
        Shift each label's level set so that its volume equals its voxel volume (step 3).
    budget : Budget, optional
        Refuse (MeshError) before MMG runs if :func:`estimate` exceeds it.
    progress : callable, optional
        ``progress(event, info)`` per stage and per cut (see :data:`Progress`).
    """
    mmgpy = _mmg()
    say = progress or (lambda event, info: None)
    with threadpool_limits(limits=1, user_api="blas"):  # the same mesh whatever the BLAS threads
        stage = _prepared(mmgpy, labels, label_ids, size_mm, smoothing_vox, keep_volume, budget,
                          say)
        points, tets, refs = _cut_labels(mmgpy, stage.points, stage.tets, stage.phi, stage.order,
                                         progress=say)
        say("remesh", {"tets": len(tets)})
        mesh = _remeshed(mmgpy, points, tets, refs, stage.sizes, labels.grid.spacing_mm)
    say("done", {"tets": mesh.n_tets})
    return mesh


class _Stage(NamedTuple):
    """Steps 1–3 done: background mesh, fields on it (shifted), sizes [mm], cutting order."""

    points: FloatArray
    tets: IntArray
    phi: _Fields
    sizes: dict[int, float]
    order: list[int]


def _prepared(mmgpy, labels: Image, label_ids: Iterable[int] | None,  # noqa: ANN001
              size_mm: float | Mapping[int, float] | None, smoothing_vox: float,
              keep_volume: bool, budget: Budget | None = None,
              progress: Progress | None = None) -> _Stage:
    """Steps 1–3: distance fields, sizes, (budget,) background mesh, volume shifts."""
    arr = np.asarray(labels.array)
    ids = checked_label_ids(arr, label_ids)
    grid = labels.grid
    fields = {lab: signed_distance(arr == lab, grid, smoothing_vox=smoothing_vox) for lab in ids}
    targets = {lab: float(np.count_nonzero(arr == lab)) * grid.voxel_volume_mm3 for lab in ids}
    _refuse_vanishing(fields, targets, grid.voxel_volume_mm3, smoothing_vox)
    union = signed_distance(np.isin(arr, ids), grid, smoothing_vox=smoothing_vox)
    sizes = default_sizes_mm(targets, {lab: f.max_depth_mm for lab, f in fields.items()},
                             grid.spacing_mm)
    if isinstance(size_mm, Mapping):
        sizes.update({int(k): float(v) for k, v in size_mm.items()})
    elif size_mm is not None:
        sizes = dict.fromkeys(sizes, float(size_mm))
    bad = {k: v for k, v in sizes.items() if not (math.isfinite(v) and v > 0)}
    if bad:
        raise MeshError(f"target sizes must be positive mm, got {bad}; fix --size-mm")
    est = estimate(targets, sizes, face_areas_mm2(arr, ids, grid.spacing_mm))
    if budget is not None:
        check_budget(est, budget, len(ids))
    if progress is not None:
        progress("start", {"estimate": est, "labels": len(ids)})
    surface = {lab: max(SURFACE_FRACTION * sizes[lab], float(grid.spacing_mm.min())) for lab in ids}
    points, tets = _background(mmgpy, labels, fields, union, sizes, surface)
    if progress is not None:
        progress("background", {"tets": len(tets)})
    phi = _Fields(fields, union, points)
    if keep_volume:
        phi.shift_to_volumes(tets, targets, surface)
    order = sorted(ids.tolist(), key=lambda lab: (targets[lab], lab))
    return _Stage(points, tets, phi, sizes, order)


def _refuse_vanishing(fields: Mapping[int, DistanceField], volumes_mm3: Mapping[int, float],
                      voxel_mm3: float, smoothing_vox: float) -> None:
    """A label with no inside left after the blur (max depth 0) would vanish in the cut: refuse
    it now, naming it, its voxels and the ways out."""
    gone = [lab for lab, f in fields.items() if not f.max_depth_mm > 0.0]
    if gone:
        lab = gone[0]
        n = round(volumes_mm3[lab] / voxel_mm3)
        more = f" (and {len(gone) - 1} more: {gone[1:6]})" if len(gone) > 1 else ""
        raise MeshError(f"label {lab} has {n} voxel{'s' * (n != 1)} ({volumes_mm3[lab]:.3g} mm³)"
                        f"{more}: too small or thin to mesh — after the {smoothing_vox:g}-voxel "
                        "blur nothing of it is inside (it needs about 2×2×3 voxels); leave it "
                        "out (--label the others), merge it into its neighbour, or lower --smooth")


class _Fields:
    """φ_l at the current vertices, with per-label level shifts; φ_0 = −φ_union (outside)."""

    def __init__(self, fields: dict[int, DistanceField], union: DistanceField,
                 points: FloatArray) -> None:
        self.fields, self.union = fields, union
        self.shift = dict.fromkeys(fields, 0.0)
        self.at(points)

    def at(self, points: FloatArray) -> None:
        """Sample every field at ``points`` [mm] (the current mesh vertices)."""
        self.points = points
        self.values = {lab: f(points) - 2.0 * self.shift[lab] for lab, f in self.fields.items()}
        self.values[0] = -self.union(points)

    def psi(self, lab: int, others: Iterable[int]) -> FloatArray:
        """ψ = (φ_lab − min_others φ)/2 [mm] at the current vertices."""
        rest = np.min([self.values[m] for m in others], axis=0)
        return 0.5 * (self.values[lab] - rest)

    def shift_to_volumes(self, tets: IntArray, targets: dict[int, float],
                         surface: dict[int, float]) -> None:
        """Step 3: per-label level shifts giving each label its voxel volume on ``tets``."""
        vols = np.abs(signed_volumes_mm3(self.points, tets))
        for _ in range(2):  # the shifts of touching labels interact: a second pass settles them
            for lab in self.fields:
                others = [m for m in self.values if m != lab]
                psi = self.psi(lab, others)[tets]
                delta = levelset.volume_shift(psi, vols, targets[lab], 0.5 * surface[lab])
                self.shift[lab] += delta
                self.values[lab] = self.values[lab] - 2.0 * delta


def _background(mmgpy, labels: Image, fields: dict[int, DistanceField],  # noqa: ANN001
                union: DistanceField, sizes: dict[int, float], surface: dict[int, float]
                ) -> tuple[FloatArray, IntArray]:
    """Kuhn grid of the labels' box, adapted by MMG to the surface size field (step 2)."""
    grid = labels.grid
    arr_union = union.phi_mm < 0
    kji = np.nonzero(arr_union)
    lo_idx = np.array([kji[2].min(), kji[1].min(), kji[0].min()]) + union.lo_ijk - 0.5
    hi_idx = np.array([kji[2].max(), kji[1].max(), kji[0].max()]) + union.lo_ijk + 0.5
    h = max(sizes.values())
    margin = 2.0 * max(surface.values()) + 2.0 * grid.spacing_mm.max()
    lo_q = lo_idx * grid.spacing_mm - margin
    hi_q = hi_idx * grid.spacing_mm + margin
    cells = tuple(int(n) for n in np.maximum(np.ceil((hi_q - lo_q) / h), 1))
    edge = (hi_q - lo_q) / np.array(cells)
    nodes_q = tetgrid.grid_nodes(lo_q, edge, cells)
    tets = tetgrid.grid_tets(cells, "kuhn")
    points = grid.origin_mm + nodes_q @ grid.direction.T
    if np.linalg.det(grid.direction) < 0:
        tets = tets[:, [0, 2, 1, 3]]
    for _ in range(2):  # the second pass samples the size field on the refined vertices
        target = np.full(len(points), h)
        for lab, f in fields.items():
            target = np.minimum(target, surface[lab] + GRADING * np.abs(f(points)))
        mesh = mmgpy.MmgMesh3D(np.ascontiguousarray(points), _i32(tets))
        mesh["metric"] = target.reshape(-1, 1)
        try:
            mesh.remesh(hgrad=2.0, hausd=h, verbose=-1)
        except RuntimeError as exc:
            raise MeshError(f"MMG could not build the background mesh ({exc}); try larger "
                            "target sizes (--size-mm)") from exc
        points = np.asarray(mesh.get_vertices(), dtype=np.float64)
        tets = np.asarray(mesh.get_tetrahedra(), dtype=np.intp)
    return points, tets


def _cut_labels(mmgpy, points: FloatArray, tets: IntArray, phi: _Fields,  # noqa: ANN001
                order: list[int], batched: bool = True, progress: Progress | None = None
                ) -> tuple[FloatArray, IntArray, IntArray]:
    """Step 4: split the unassigned material batch by batch (:func:`_next_batch`; one label
    per call if not ``batched``); drop what is left outside. A batch MMG cannot cut is retried
    one label at a time, so an error names the label."""
    out = max(order) + 1
    refs = np.full(len(tets), out, dtype=np.int64)
    pending, done = list(order), []
    single = set() if batched else set(order)
    start = time.monotonic()
    while pending:
        phi.at(points)
        batch, psi = _next_batch(phi, tets, pending, single)
        minus = out + 2  # a scratch reference for the batch's side of the cut
        mesh = mmgpy.MmgMesh3D(np.ascontiguousarray(points), _i32(tets))
        mesh.set_tetrahedra(_i32(tets), refs)
        mesh.set_multi_materials(
            [{"ref": out, "split": 1, "ref_minus": minus, "ref_plus": out + 1}]
            + [{"ref": r, "split": 0, "ref_minus": r, "ref_plus": r} for r in done])
        try:
            mesh.remesh_levelset(psi.reshape(-1, 1), noinsert=1, noswap=1, nomove=1,
                                 verbose=-1)
        except RuntimeError as exc:
            if len(batch) > 1:
                single.update(batch)
                continue
            raise MeshError(f"MMG could not cut label {batch[0]} out of the background ({exc}); "
                            f"give it a smaller target size (--size-mm {batch[0]}=H) or smooth "
                            "the labels") from exc
        out += 1
        points = np.asarray(mesh.get_vertices(), dtype=np.float64)
        t, r = mesh.get_tetrahedra_with_refs()
        tets, refs = np.asarray(t, dtype=np.intp), np.asarray(r, dtype=np.int64)
        cut = refs == minus
        if len(batch) == 1:
            refs[cut] = batch[0]
        else:  # each cut-out piece lies in the Voronoi cell of one batch label: the nearest
            phi.at(points)
            nearest = np.argmin([phi.values[lab][tets[cut]].mean(axis=1) for lab in batch], axis=0)
            refs[cut] = np.asarray(batch)[nearest]
        done += batch
        pending = [lab for lab in pending if lab not in batch]
        if progress is not None:
            elapsed = time.monotonic() - start
            progress("cut", {"labels": list(batch), "done": len(done), "total": len(order),
                             "elapsed_s": elapsed,
                             "left_s": elapsed / len(done) * len(pending)})
    missing = sorted(set(order) - set(np.unique(refs).tolist()))
    if missing:
        raise MeshError(f"label(s) {missing} vanished in the level-set discretisation; give "
                        "them a smaller target size (--size-mm L=H)")
    keep = refs != out
    points, tets, _ = compact_points(points, tets[keep])
    return points, tets, refs[keep]


def _next_batch(phi: _Fields, tets: IntArray, pending: list[int], single: set[int]
                ) -> tuple[list[int], FloatArray]:
    """The next labels to cut in one MMG call and their level set ψ_B = min_{l∈B} ψ_l [mm].

    Labels are taken in ``pending`` order (smallest first); a label joins the batch when, on
    every vertex of the tetrahedra its own zero set crosses, its ψ is the batch's smallest, and
    on the crossed tetrahedra of the labels already in, theirs stay the smallest. Then ψ_B has
    the zero crossings of each ψ_l on the same edges: the batched cut is the cut of each label
    alone. A label whose cell {ψ < 0} shares a tetrahedron with that of a label left out waits
    too, so touching labels are cut in ``pending`` order (inner before outer) as one at a time.
    ψ_l = (φ_l − min_{m ≠ l} φ_m)/2 over the unassigned labels and the outside.
    """
    stack = np.array([phi.values[m] for m in [0, *pending]])
    two = np.partition(stack, 1, axis=0)[:2]  # the smallest and second smallest φ per vertex
    first = np.argmin(stack, axis=0)
    psi_b = np.full(stack.shape[1], np.inf)
    crossed = np.zeros(stack.shape[1], dtype=bool)  # vertices of the batch's crossed tets
    waiting = np.zeros_like(crossed)  # vertices of the tets the cells of left-out labels touch
    batch: list[int] = []
    for idx, lab in enumerate(pending, start=1):
        psi = 0.5 * (stack[idx] - np.where(first == idx, two[1], two[0]))
        at = psi[tets]
        lo = at.min(axis=1) < 0
        zone = np.zeros_like(crossed)
        zone[tets[lo].ravel()] = True
        own = np.zeros_like(crossed)
        own[tets[lo & (at.max(axis=1) > 0)].ravel()] = True
        if batch and (lab in single or np.any(zone & waiting) or np.any(psi[own] > psi_b[own])
                      or np.any(psi[crossed] < psi_b[crossed])):
            waiting |= zone
            continue
        batch.append(lab)
        psi_b = np.minimum(psi_b, psi)
        crossed |= own
        if lab in single:
            break
    return batch, psi_b


def _remeshed(mmgpy, points: FloatArray, tets: IntArray, refs: IntArray,  # noqa: ANN001
              sizes: dict[int, float], spacing_mm: FloatArray) -> TetMesh:
    """Step 5: MMG remesh with a target edge per label; vertices compacted, cells oriented."""
    hmin = HMIN_FRACTION * min(sizes.values())
    error = None
    for ridges in (0, 1):  # without ridge detection first; MMG fails on some thin layers then
        mesh = mmgpy.MmgMesh3D(np.ascontiguousarray(points), _i32(tets))
        mesh.set_tetrahedra(_i32(tets), refs)
        mesh.set_local_parameters(
            [{"type": "tetrahedron", "ref": int(lab), "hmin": hmin, "hmax": float(h),
              "hausd": HAUSD_FRACTION * float(h)} for lab, h in sorted(sizes.items())])
        try:
            mesh.remesh(hmin=hmin, hmax=max(sizes.values()), angle=ridges,
                        hausd=HAUSD_FRACTION * min(sizes.values()), hgrad=HGRAD, verbose=-1)
        except RuntimeError as exc:
            error = exc
            continue
        break
    else:
        raise MeshError(f"MMG could not remesh the labels ({error}); try other target sizes "
                        "(--size-mm)") from error
    p = np.asarray(mesh.get_vertices(), dtype=np.float64)
    t, r = (np.asarray(a) for a in mesh.get_tetrahedra_with_refs())
    p, tt, _ = compact_points(p, t.astype(np.intp))
    oriented = TetMesh(p, tt, r.astype(np.int64)).with_fixed_orientation()
    result = TetMesh(*removed_slivers(oriented.points_mm, oriented.tets, oriented.region,
                                      MIN_DIHEDRAL_DEG))
    result.check_cells(context="in the MMG label mesh")
    angles = dihedral_angles_deg(result.points_mm, result.tets).min(axis=1)
    if (n_bad := int(np.count_nonzero(angles < REQUIRED_DIHEDRAL_DEG))):
        labels = sorted(np.unique(result.region[angles < REQUIRED_DIHEDRAL_DEG]).tolist())
        warnings.warn(f"{n_bad} tetrahedra of label(s) {labels} stay below "
                      f"{REQUIRED_DIHEDRAL_DEG:g}° (smallest {angles.min():.1f}°) after the "
                      "sliver repair; give those labels another target size (--size-mm L=H)",
                      stacklevel=2)
    return result
