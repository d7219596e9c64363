"""Per-label unstructured tetrahedral meshes (legacy, non-conforming): marching cubes, then gmsh.

Optional extra ``tetdose[meshing]`` (scikit-image, gmsh; imported lazily). Without it, use the
dependency-free structured mesher :func:`tetdose.phantoms.mesh_labels`.

Method, per label:

1. **Surface**: marching cubes (Lewiner et al. 2003, ``skimage.measure.marching_cubes``) of the
   label's indicator at level ½, optionally blurred first by a Gaussian of
   ``smoothing_sigma_vox`` voxels (light smoothing; a blur of σ moves a surface of principal
   curvatures κ₁, κ₂ inwards by about σ²(κ₁ + κ₂)/2, σ²/r for a sphere). Vertices are mapped
   to the patient frame by the image geometry, p = origin + D (spacing ⊙ (i, j, k)), so any
   orthonormal direction (flipped axes included) is honoured.
2. **Shells**: the triangulation is split into connected closed shells; nesting (the winding
   number of one shell's vertex about another, Van Oosterom & Strackee 1983 solid angles) tells
   outer shells (even depth) from cavities (odd depth, attached to their enclosing shell).
3. **Volume mesh** (gmsh, Geuzaine & Remacle 2009): per outer shell and its cavities, the
   triangles become a discrete surface, ``classifySurfaces`` splits it into parametrizable
   patches (``createGeometry``), the patches are remeshed at ``target_edge_mm`` and the
   enclosed volume is filled by 3-D Delaunay with ``Mesh.MeshSizeMax = target_edge_mm``.

Labels are meshed **separately**: two touching labels get non-conforming interfaces (no shared
vertices; gaps or overlaps of about the surface chord error h²/(8R)). Where a conforming
multi-region mesh is needed (transport walks across regions), use ``mesh_labels``.
"""

from __future__ import annotations

import math
import multiprocessing
import sys
import warnings
from collections.abc import Iterable

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tetdose._optional import import_optional
from tetdose._typing import FloatArray, IntArray
from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh, compact_points
from tetdose.errors import ImageError, MeshError

#: Feature angle for ``classifySurfaces``: π keeps marching-cubes staircase steps from being
#: taken as sharp edges (a smaller angle splits a voxelised sphere into hundreds of patches).
CLASSIFY_ANGLE_RAD = math.pi
#: Default time limit [s] for gmsh on one label (it runs in a child process).
GMSH_TIMEOUT_S = 600.0
#: How the gmsh child starts: fork on Linux (no ``if __name__ == "__main__"`` guard needed in
#: user scripts; the parent never initialises gmsh), spawn elsewhere (fork is unsafe on macOS).
START_METHOD = "fork" if sys.platform.startswith("linux") else "spawn"
#: Shells enclosing less than this many regular tetrahedra of edge h are dropped (with a warning).
MIN_SHELL_TETS = 1.0


def _optional():  # noqa: ANN202 - module objects
    purpose = "meshing a label image with gmsh (or use tetdose.phantoms.mesh_labels, no extra)"
    return (import_optional("gmsh", "meshing", purpose),
            import_optional("skimage.measure", "meshing", purpose))


def label_surface(labels: Image, label_id: int, *, smoothing_sigma_vox: float = 0.0
                  ) -> tuple[FloatArray, IntArray]:
    """Marching-cubes surface of ``labels == label_id``: vertices [mm] (patient frame), triangles.

    The indicator is cropped to the label's bounding box with two voxels of zero padding (so
    every shell is closed, also where the label touches the image border) and blurred by a
    Gaussian of ``smoothing_sigma_vox`` voxels when that is positive.
    """
    _, measure = _optional()
    mask = np.asarray(labels.array) == label_id
    if not mask.any():
        raise ImageError(f"no voxel carries label {label_id}; check the label ids")
    kji = np.nonzero(mask)
    lo = np.array([a.min() for a in kji])
    hi = np.array([a.max() for a in kji]) + 1
    pad = 2 + int(math.ceil(3.0 * max(smoothing_sigma_vox, 0.0)))
    crop = np.pad(mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float64), pad)
    if smoothing_sigma_vox > 0:
        crop = ndimage.gaussian_filter(crop, smoothing_sigma_vox)
    verts, tris, _, _ = measure.marching_cubes(crop, 0.5, allow_degenerate=False)
    index_ijk = (verts + (lo - pad))[:, ::-1]  # (k, j, i) of the crop → (i, j, k) of the image
    return labels.grid.index_to_physical(index_ijk), np.ascontiguousarray(tris, dtype=np.intp)


def _shells(tris: IntArray, n_verts: int) -> list[IntArray]:
    """Triangle ids of each connected shell (triangles linked through shared vertices)."""
    rows = np.repeat(np.arange(len(tris)), 3)
    graph = coo_matrix((np.ones(rows.size), (rows, tris.ravel() + len(tris))),
                       shape=(len(tris) + n_verts,) * 2)
    _, comp = connected_components(graph, directed=False)
    comp = comp[: len(tris)]
    return [np.flatnonzero(comp == c) for c in np.unique(comp)]


def winding_number(point_mm: FloatArray, triangles_mm: FloatArray) -> float:
    """Σ signed solid angles / 4π of a closed triangulation (T, 3, 3) seen from a point.

    tan(Ω/2) = a·(b×c) / (|a||b||c| + (a·b)|c| + (a·c)|b| + (b·c)|a|) (Van Oosterom &
    Strackee 1983); ±1 inside (sign = orientation), 0 outside.
    """
    r = triangles_mm - point_mm
    a, b, c = r[:, 0], r[:, 1], r[:, 2]
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb
           + np.einsum("ij,ij->i", b, c) * la)
    return float(2.0 * np.arctan2(num, den).sum() / (4.0 * math.pi))


def enclosed_volume_mm3(verts_mm: FloatArray, tris: IntArray) -> float:
    """|Σ p0·(p1×p2)| / 6 over the triangles of closed shells (divergence theorem)."""
    p = verts_mm[tris]
    return abs(float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum()) / 6.0)


def shell_groups(verts_mm: FloatArray, tris: IntArray, min_volume_mm3: float = 0.0
                 ) -> list[list[IntArray]]:
    """Group the shells into solids: [outer shell's triangle ids, cavity ids, …] per solid.

    Nesting depth d(s) = number of shells whose winding number about a vertex of s is ±1:
    even → outer boundary, odd → cavity of the deepest shell enclosing it. Shells enclosing
    less than ``min_volume_mm3`` are dropped with a warning.
    """
    shells = _shells(tris, len(verts_mm))
    volumes = np.array([enclosed_volume_mm3(verts_mm, tris[s]) for s in shells])
    small = volumes < min_volume_mm3
    if small.any():
        warnings.warn(f"dropped {small.sum()} surface shell(s) enclosing {volumes[small].sum():.4g}"
                      f" mm³ in all, smaller than one tetrahedron of the target size; "
                      "lower target_edge_mm to keep them", stacklevel=3)
    shells = [s for s, drop in zip(shells, small, strict=True) if not drop]
    inside = np.zeros((len(shells), len(shells)), dtype=bool)  # inside[i, j]: shell i in shell j
    for i, si in enumerate(shells):
        probe = verts_mm[tris[si[0], 0]]
        for j, sj in enumerate(shells):
            inside[i, j] = i != j and abs(winding_number(probe, verts_mm[tris[sj]])) > 0.5
    depth = inside.sum(axis=1)
    groups = {i: [shells[i]] for i in np.flatnonzero(depth % 2 == 0)}
    for i in np.flatnonzero(depth % 2 == 1):
        parent = next(j for j in np.flatnonzero(inside[i]) if depth[j] == depth[i] - 1)
        groups[parent].append(shells[i])
    return list(groups.values())


def _gmsh_solid(gmsh, verts_mm: FloatArray, tris: IntArray, shells: list[IntArray],  # noqa: ANN001
                target_edge_mm: float) -> tuple[FloatArray, IntArray]:
    """Tetrahedra of one solid (outer shell + cavities) in the current gmsh model."""
    used = np.unique(tris[np.concatenate(shells)])
    gmsh.model.add("solid")
    surface = gmsh.model.addDiscreteEntity(2)
    gmsh.model.mesh.addNodes(2, surface, used + 1, verts_mm[used].ravel())
    gmsh.model.mesh.addElementsByType(surface, 2, [], (tris[np.concatenate(shells)] + 1).ravel())
    gmsh.model.mesh.classifySurfaces(CLASSIFY_ANGLE_RAD, True, True, math.pi)
    gmsh.model.mesh.createGeometry()
    patches = [tag for _, tag in gmsh.model.getEntities(2)]
    loops = _surface_loops(gmsh, patches)
    volume_loops = [gmsh.model.geo.addSurfaceLoop(loop) for loop in loops]
    gmsh.model.geo.addVolume(volume_loops)
    gmsh.model.geo.synchronize()
    gmsh.option.setNumber("Mesh.MeshSizeMax", target_edge_mm)
    gmsh.model.mesh.generate(3)
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    _, tet_nodes = gmsh.model.mesh.getElementsByType(4)
    gmsh.model.remove()
    if len(tet_nodes) == 0:
        raise MeshError("gmsh's 3-D Delaunay produced no tetrahedra (self-touching surface?)")
    lookup = np.zeros(int(node_tags.max()) + 1, dtype=np.intp)
    lookup[node_tags.astype(np.intp)] = np.arange(len(node_tags))
    return coords.reshape(-1, 3), lookup[tet_nodes.astype(np.intp)].reshape(-1, 4)


def _gmsh_worker(conn, verts_mm: FloatArray, tris: IntArray,  # noqa: ANN001 - Connection
                 groups: list[list[IntArray]], target_edge_mm: float) -> None:
    """Child process: mesh every solid, send ("ok", [(points, tets), …]) or ("error", text)."""
    gmsh, _ = _optional()
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)  # reproducible node order
        conn.send(("ok", [_gmsh_solid(gmsh, verts_mm, tris, shells, target_edge_mm)
                          for shells in groups]))
    except Exception as exc:  # gmsh raises plain Exception with its last error
        conn.send(("error", str(exc)))
    finally:
        gmsh.finalize()
        conn.close()


def _gmsh_in_subprocess(verts_mm: FloatArray, tris: IntArray, groups: list[list[IntArray]],
                        target_edge_mm: float, timeout_s: float, label: int
                        ) -> list[tuple[FloatArray, IntArray]]:
    """Run :func:`_gmsh_worker` in a spawned process; a hang, crash or gmsh error → MeshError."""
    hint = ("; try smoothing_sigma_vox=1 (CLI --smooth 1) or a smaller target size (structures "
            "thinner than it cannot be remeshed)")
    ctx = multiprocessing.get_context(START_METHOD)
    receiver, sender = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_gmsh_worker, args=(sender, verts_mm, tris, groups, target_edge_mm),
                       daemon=True)
    proc.start()
    sender.close()
    status, payload = "error", f"no answer in {timeout_s:g} s"
    try:
        if receiver.poll(timeout_s):
            status, payload = receiver.recv()
            proc.join(timeout_s)
    except EOFError:
        proc.join()
        payload = f"the gmsh process crashed (exit code {proc.exitcode})"
    finally:
        if proc.is_alive():
            proc.kill()
            proc.join()
        receiver.close()
    if status != "ok":
        raise MeshError(f"gmsh could not mesh label {label}: {payload}{hint}")
    return payload


def _surface_loops(gmsh, patches: list[int]) -> list[list[int]]:  # noqa: ANN001
    """Patches grouped into closed shells by shared boundary curves, the outer shell first."""
    curves = {p: {abs(c) for _, c in gmsh.model.getBoundary([(2, p)], oriented=False)}
              for p in patches}
    loops: list[list[int]] = []
    for p in patches:
        linked = [loop for loop in loops if any(curves[p] & curves[q] for q in loop)]
        merged = [p] + [q for loop in linked for q in loop]
        loops = [loop for loop in loops if loop not in linked] + [merged]

    def extent(loop: list[int]) -> float:
        boxes = np.array([gmsh.model.getBoundingBox(2, p) for p in loop])
        return float(np.linalg.norm(boxes[:, 3:].max(axis=0) - boxes[:, :3].min(axis=0)))

    return sorted(loops, key=extent, reverse=True)


def mesh_label_image(labels: Image, label_ids: Iterable[int] | None = None,
                     target_edge_mm: float = 6.0, *, smoothing_sigma_vox: float = 0.0,
                     timeout_s: float = GMSH_TIMEOUT_S) -> TetMesh:
    """Unstructured tetrahedral mesh of the labels ``label_ids`` (default: all ≠ 0), via gmsh.

    Parameters
    ----------
    labels : Image
        Integer label image (0 = background); its origin, spacing and direction are honoured.
    label_ids : iterable of int, optional
        Labels to mesh; each becomes a region (cell_data ``region``), meshed separately (see the
        module docstring: interfaces between touching labels do not conform).
    target_edge_mm : float
        Largest tetrahedron edge [mm] (gmsh ``Mesh.MeshSizeMax``), on the surface and inside.
    smoothing_sigma_vox : float
        Gaussian blur [voxels] of each label's indicator before marching cubes (0 = none).
    timeout_s : float
        Time limit [s] for gmsh per label. gmsh runs in a child process, so a hang or a crash
        on a difficult surface (structures thinner than ``target_edge_mm``) becomes a
        :class:`MeshError` instead of stopping the caller.
    """
    _optional()
    arr = np.asarray(labels.array)
    ids = _checked_ids(arr, label_ids)
    h = float(target_edge_mm)
    if not (math.isfinite(h) and h > 0):
        raise MeshError(f"target_edge_mm must be positive, got {target_edge_mm}")
    pairs = touching_pairs(arr, ids)
    if pairs:
        warnings.warn(f"labels {pairs} touch: each label is meshed separately, so their "
                      "interfaces do not conform (no shared vertices); use "
                      "tetdose.phantoms.mesh_labels for a conforming multi-region mesh",
                      stacklevel=2)
    min_volume = MIN_SHELL_TETS * h**3 / (6.0 * math.sqrt(2.0))
    points, tets, region, offset = [], [], [], 0
    for label in ids.tolist():
        verts, tris = label_surface(labels, label, smoothing_sigma_vox=smoothing_sigma_vox)
        groups = shell_groups(verts, tris, min_volume)
        for p, t in _gmsh_in_subprocess(verts, tris, groups, h, timeout_s, label):
            points.append(p)
            tets.append(t + offset)
            region.append(np.full(len(t), label, dtype=np.int64))
            offset += len(p)
    if not tets:
        raise MeshError(f"labels {ids.tolist()} gave no tetrahedra at target_edge_mm={h}; "
                        "lower the target size")
    kept, cells, _ = compact_points(np.concatenate(points), np.concatenate(tets))
    mesh = TetMesh(kept, cells, np.concatenate(region))  # gmsh keeps the surface's nodes too
    mesh = mesh.with_fixed_orientation()
    mesh.check_cells(context="in the gmsh label mesh")
    return mesh


def _checked_ids(arr: np.ndarray, label_ids: Iterable[int] | None) -> IntArray:
    """The sorted label ids to mesh, each present in the integer label array ``arr``."""
    if not np.issubdtype(arr.dtype, np.integer):
        raise ImageError(f"labels must be an integer image, got dtype {arr.dtype}; round it first")
    present = np.unique(arr)
    ids = present[present != 0] if label_ids is None else np.unique(list(label_ids))
    if ids.size == 0:
        raise ImageError("the label image has no non-zero label; nothing to mesh")
    missing = np.setdiff1d(ids, present)
    if missing.size:
        raise ImageError(f"no voxel carries label {', '.join(map(str, missing.tolist()))}; the "
                         f"image has labels {present[present != 0].tolist()[:30]}")
    return ids


def touching_pairs(arr: np.ndarray, ids: np.ndarray) -> list[tuple[int, int]]:
    """Pairs (a, b), a < b, of the labels in ``ids`` with face-adjacent voxels."""
    pairs = []
    for a in ids.tolist():
        near = np.unique(arr[ndimage.binary_dilation(arr == a)])
        pairs += [(a, int(b)) for b in near if b > a and b in ids]
    return pairs
