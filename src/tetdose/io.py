"""Reading and writing meshes (meshio) and images (SimpleITK); every write is atomic."""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._atomic import atomic_write_file
from tetdose.errors import ImageError, MeshError
from tetdose.image import Image
from tetdose.mesh import TetMesh

#: Relative tolerance on slice-to-slice spacing of a DICOM series.
SLICE_SPACING_RTOL = 1e-3
#: cell_data names read as region labels, in order of preference.
REGION_NAMES = ("region", "gmsh:physical", "medit:ref", "CellEntityIds", "tetgen:ref")


def read_mesh(path: str | os.PathLike[str], *, fix_orientation: bool = False) -> TetMesh:
    """Read a tetrahedral mesh with meshio (VTU/VTK, Gmsh, Abaqus .inp, TetGen, Medit …).

    Only ``tetra`` cells are kept; point and cell arrays are carried along. A region label is
    taken from the first cell array named in :data:`REGION_NAMES`. Inverted tetrahedra are an
    error unless ``fix_orientation`` is true (then two vertices of each are swapped).
    """
    import meshio

    path = Path(path)
    if not path.exists():
        raise MeshError(f"mesh file {path} does not exist")
    try:
        m = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types, even SystemExit
        raise MeshError(f"cannot read mesh {path}: {exc}; give a VTU/VTK/MSH/INP/MESH/ELE file"
                        ) from exc
    blocks = [i for i, c in enumerate(m.cells) if c.type == "tetra"]
    if not blocks:
        kinds = sorted({c.type for c in m.cells})
        raise MeshError(f"{path} has no tetrahedra (cell types: {kinds}); tetdose needs a "
                        "volume mesh of linear tetrahedra — mesh the surface first")
    tets = np.concatenate([m.cells[i].data for i in blocks])
    cell_data = {
        name: np.concatenate([np.asarray(arrs[i]) for i in blocks])
        for name, arrs in m.cell_data.items()
    }
    region = None
    for name in REGION_NAMES:
        if name in cell_data:
            region = cell_data.pop(name).astype(np.int64).reshape(-1)
            break
    used = np.unique(tets)
    points = np.asarray(m.points, dtype=np.float64)
    if points.shape[1] != 3:
        raise MeshError(f"{path}: points must be 3-D, got {points.shape[1]} coordinates")
    point_data = {k: np.asarray(v) for k, v in m.point_data.items()}
    if len(used) < len(points):
        # Drop points no tetrahedron uses (e.g. surface-only nodes), renumbering the cells.
        new_id = np.full(len(points), -1, dtype=np.intp)
        new_id[used] = np.arange(len(used))
        points, tets = points[used], new_id[tets]
        point_data = {k: v[used] for k, v in point_data.items()}
    mesh = TetMesh(points, tets, region, point_data, cell_data)
    if fix_orientation:
        mesh = mesh.with_fixed_orientation()
    mesh.check_cells(context=f"in {path}")
    return mesh


def write_mesh(path: str | os.PathLike[str], mesh: TetMesh) -> Path:
    """Write a mesh with all its arrays (VTU recommended); atomic."""
    import meshio

    cell_data = {k: [np.asarray(v)] for k, v in mesh.cell_data.items()}
    if mesh.region is not None:
        cell_data["region"] = [mesh.region.astype(np.int32)]
    m = meshio.Mesh(mesh.points_mm, [("tetra", mesh.tets)], point_data=dict(mesh.point_data),
                    cell_data=cell_data)
    path = Path(path)
    with atomic_write_file(path) as tmp:
        meshio.write(tmp, m, file_format=_meshio_format(path))
    return path


def _meshio_format(path: Path) -> str | None:
    return {".vtu": "vtu", ".vtk": "vtk", ".msh": "gmsh", ".xdmf": "xdmf"}.get(path.suffix.lower())


def read_image(path: str | os.PathLike[str]) -> Image:
    """Read a scalar image: a DICOM series folder, or a file SimpleITK reads (NRRD, MHA, NIfTI…).

    A DICOM folder must hold one CT series with uniformly spaced slices; values are returned in
    HU (RescaleSlope/Intercept applied).
    """
    import SimpleITK as sitk

    path = Path(path)
    if not path.exists():
        raise ImageError(f"image {path} does not exist")
    if path.is_dir():
        return _read_dicom_series(path)
    try:
        img = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise ImageError(f"cannot read image {path}: {str(exc).strip().splitlines()[-1]}") from exc
    return Image.from_sitk(img)


read_ct = read_image


def _read_dicom_series(folder: Path) -> Image:
    import SimpleITK as sitk

    reader = sitk.ImageSeriesReader()
    series = reader.GetGDCMSeriesIDs(str(folder))
    if not series:
        raise ImageError(f"{folder} holds no DICOM image series")
    if len(series) > 1:
        raise ImageError(f"{folder} holds {len(series)} series; give a folder with one CT series")
    return read_dicom_files(reader.GetGDCMSeriesFileNames(str(folder), series[0]), what=str(folder))


def read_dicom_files(files: Sequence[str | os.PathLike[str]], *, what: str,
                     headers: Sequence[Any] | None = None) -> Image:
    """Read the slices ``files`` of one CT series (in slice order) as one image [HU].

    Checks (the error names ``what``): modality CT; every slice with the same rows, columns,
    pixel spacing and orientation; uniformly spaced slice positions along the slice normal (a
    missing or duplicate slice breaks it). ``headers``: the files' pydicom headers if already read.
    """
    import pydicom
    import SimpleITK as sitk

    files = [str(f) for f in files]
    if headers is None:
        headers = [pydicom.dcmread(f, stop_before_pixels=True) for f in files]
    modality = {str(h.get("Modality", "")) for h in headers}
    if modality != {"CT"}:
        raise ImageError(f"{what}: modality {sorted(modality)}, expected CT; give a CT series")
    _check_slice_geometry(headers, what)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = reader.Execute()
    return Image.from_sitk(img)


def _check_slice_geometry(headers: Sequence[Any], what: str) -> None:
    """Same in-plane geometry on every slice, and uniform slice spacing (see read_dicom_files)."""
    def plane(h: Any) -> tuple:
        return (int(h.get("Rows", 0)), int(h.get("Columns", 0)),
                tuple(round(float(v), 4) for v in h.get("PixelSpacing", [0, 0])),
                tuple(round(float(v), 4) for v in h.get("ImageOrientationPatient", [0] * 6)))

    kinds = {plane(h) for h in headers}
    if len(kinds) > 1:
        raise ImageError(
            f"{what}: slices differ in size, pixel spacing or orientation ({len(kinds)} kinds: "
            f"{sorted(kinds)[:2]} …); a series must have one geometry — export it again"
        )
    if len(headers) > 1:
        iop = np.array(headers[0].ImageOrientationPatient, dtype=float)
        normal = np.cross(iop[:3], iop[3:])
        pos = np.sort([float(np.dot(normal, h.ImagePositionPatient)) for h in headers])
        gaps = np.diff(pos)
        if gaps.min() <= 0 or (gaps.max() - gaps.min()) > SLICE_SPACING_RTOL * gaps.mean():
            raise ImageError(
                f"{what}: slice spacing is not uniform (gaps {gaps.min():.4g}…{gaps.max():.4g} mm"
                "); missing or duplicate slices — resample to a uniform grid first"
            )


def write_image(path: str | os.PathLike[str], image: Image, *, compress: bool = True) -> Path:
    """Write an image with SimpleITK (format from the extension: .nrrd, .mha, .nii.gz …); atomic."""
    import SimpleITK as sitk

    path = Path(path)
    with atomic_write_file(path) as tmp:
        sitk.WriteImage(image.to_sitk(), str(tmp), compress)
    return path
