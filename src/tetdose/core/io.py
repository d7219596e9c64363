"""Reading and writing meshes (meshio) and images (SimpleITK); every write is atomic.

Besides the per-file checks, three policies hold for a whole command (the CLI sets them):

- :func:`tilted_policy`: tilted/sheared DICOM series resampled instead of refused;
- :func:`mesh_unit_policy`: the unit of the meshes' coordinates (``--mesh-unit``), and the check
  that every mesh read is plausible for every image read (:mod:`tetdose.core.units`: a mesh in
  metres is refused with the likely unit);
- ITK/GDCM messages (``WARNING: In …GDCMSeriesFileNames.cxx``) never reach the terminal raw:
  :func:`itk_messages` captures them while SimpleITK reads or writes and reports them as one-line
  warnings in tetdose's words (or drops them when tetdose's own error says more).

Label images have one rule (:func:`check_labels`): whole numbers only.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import warnings
from collections.abc import Iterator, Sequence
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._atomic import atomic_write_file, check_output_file, record_note
from tetdose.core.icrp145 import is_icrp145, read_icrp145
from tetdose.core.image import Image, ImageGrid, check_ct_hu
from tetdose.core.mesh import TetMesh, compact_points
from tetdose.core.units import MESH_UNITS, check_mesh_on_grid
from tetdose.errors import ImageError, MeshError, OptionError, OutputError

#: Relative tolerance on slice-to-slice spacing of a DICOM series.
SLICE_SPACING_RTOL = 1e-3
#: Largest |ImageOrientationPatient row·column| and | |row| − 1 | accepted (orthonormal).
ORIENTATION_TOL = 1e-4
#: Largest in-plane drift of slice positions against the orientation's normal [mm], as a
#: fraction of the slice stack's length (a gantry tilt of 0.06°) or 0.01 mm, whichever is larger.
SHEAR_REL_TOL = 1e-3
#: Coordinates beyond this [mm] (1 km) cannot be patient coordinates in mm.
MAX_COORD_MM = 1e6
#: Image file endings SimpleITK writes as 3-D images.
IMAGE_SUFFIXES = (".nrrd", ".nhdr", ".mha", ".mhd", ".nii", ".nii.gz", ".hdr", ".vtk", ".tif",
                  ".tiff", ".gipl", ".gipl.gz", ".hdf5", ".h5", ".mnc")
#: Mesh file endings meshio writes with tetrahedra (VTU recommended).
MESH_SUFFIXES = (".vtu", ".vtk", ".msh", ".xdmf", ".xmf", ".inp", ".mesh", ".meshb", ".med",
                 ".ele", ".node", ".h5m", ".f3grid", ".avs", ".dat", ".bdf", ".fem", ".nas",
                 ".exo", ".e", ".ex2", ".cgns", ".tec", ".ugrid", ".su2", ".vol", ".vol.gz")
#: cell_data names read as region labels, in order of preference.
REGION_NAMES = ("region", "gmsh:physical", "medit:ref", "CellEntityIds", "tetgen:ref")
#: Whether tilted/sheared DICOM series are resampled (:func:`tilted_policy`) or refused.
_RESAMPLE_TILTED: ContextVar[bool] = ContextVar("resample_tilted", default=False)
#: How the refusal of a tilted series names the way to allow it.
RESAMPLE_HINT = ("rerun with --resample-tilted (Python: resample_tilted=True) to resample it onto "
                 "an orthogonal grid (linear, −1000 HU outside), or resample the series first")


#: ITK/GDCM messages that tetdose's own error (or nothing) replaces: fragments → None.
_ITK_SILENT = ("No Series were found", "No Series can be found")
#: How the label-image rule names its fix.
LABEL_FIX = ("a segmentation resampled with linear interpolation mixes labels at their borders; "
             "resample it with nearest-neighbour interpolation (SimpleITK sitkNearestNeighbor)")


@dataclass
class _UnitPolicy:
    """The stated mesh unit (None: mm, not stated) and what was read so far."""

    unit: str | None
    meshes: list[tuple[str, np.ndarray, float]] = field(default_factory=list)
    grids: list[tuple[str, ImageGrid]] = field(default_factory=list)


_MESH_UNIT: ContextVar[_UnitPolicy | None] = ContextVar("tetdose_mesh_unit", default=None)


@contextlib.contextmanager
def mesh_unit_policy(unit: str | None = None) -> Iterator[None]:
    """During the block, meshes are read in ``unit`` ("mm", "cm", "m"; None: mm, not stated) —
    their points multiplied by :data:`~tetdose.core.units.MESH_UNITS` — and every mesh read is
    checked against every image read (:func:`tetdose.core.units.check_mesh_on_grid`)."""
    if unit is not None and unit not in MESH_UNITS:
        raise OptionError(f"mesh unit {unit!r} is unknown; use one of {', '.join(MESH_UNITS)}")
    token = _MESH_UNIT.set(_UnitPolicy(unit))
    if unit not in (None, "mm"):
        record_note("mesh_unit", unit)
    try:
        yield
    finally:
        _MESH_UNIT.reset(token)


def _seen_mesh(mesh: TetMesh, what: str) -> None:
    policy = _MESH_UNIT.get()
    if policy is None:
        return
    points = mesh.points_mm
    if len(points) > 20_000:
        points = points[np.linspace(0, len(points) - 1, 20_000).astype(np.intp)]
    entry = (what, np.array(points), float(mesh.volumes_mm3.sum()))
    policy.meshes.append(entry)
    for grid_what, grid in policy.grids:
        check_mesh_on_grid(entry[1], entry[2], grid, mesh_what=what, grid_what=grid_what,
                           unit=policy.unit)


def _seen_grid(image: Image, what: str) -> Image:
    policy = _MESH_UNIT.get()
    if policy is not None:
        policy.grids.append((what, image.grid))
        for mesh_what, points, volume in policy.meshes:
            check_mesh_on_grid(points, volume, image.grid, mesh_what=mesh_what, grid_what=what,
                               unit=policy.unit)
    return image


def _itk_text(raw: str) -> str:
    """``WARNING: In /…/itkX.cxx, line 101 / X (0x…): text`` → ``text`` (one line)."""
    lines = [ln.strip() for ln in raw.strip().splitlines() if ln.strip()]
    lines = [ln for ln in lines if not (ln.startswith(("WARNING: In ", "ERROR: In "))
                                        and ", line " in ln)]
    text = " ".join(" ".join(lines).split())
    m = re.match(r"^\w+ \(0x[0-9a-fA-F]+\): (.*)$", text)
    return m.group(1) if m else text


@contextlib.contextmanager
def itk_messages(what: str) -> Iterator[list[str]]:
    """Capture what ITK/GDCM would print during the block; yield the list they are added to.

    If the block succeeds, each message (except those tetdose's own checks replace) becomes
    one warning ``WHAT: SimpleITK reported: …``; if it raises, they are dropped — tetdose's
    error says what is wrong.
    """
    import SimpleITK as sitk

    said: list[str] = []

    class _Logger(sitk.LoggerBase):  # type: ignore[misc, name-defined]
        def DisplayText(self, t: str) -> None:  # noqa: N802 - ITK's names
            said.append(_itk_text(t))

        DisplayErrorText = DisplayWarningText = DisplayGenericOutputText = DisplayText  # noqa: N815
        DisplayDebugText = DisplayText  # noqa: N815

    logger = _Logger()
    previous = logger.SetAsGlobalITKLogger()
    try:
        yield said
    finally:
        previous.SetAsGlobalITKLogger()
    for text in dict.fromkeys(said):
        if text and not any(s in text for s in _ITK_SILENT):
            warnings.warn(f"{what}: SimpleITK reported: {text}", stacklevel=3)


def check_labels(image: Image, what: str = "the label image") -> Image:
    """``image`` with an integer array, or an :class:`ImageError`: the one rule for label images
    everywhere (``mesh --labels``, ``dose --labels``, ``compare --structures``, masks).

    Integer and boolean pixels pass; floating-point pixels pass only if every value is a whole
    number (then cast to int64); any fraction, NaN or infinity is refused naming a voxel and the
    fix (:data:`LABEL_FIX`).
    """
    arr = np.asarray(image.array)
    if arr.dtype.kind in "iub":
        return image
    if arr.dtype.kind != "f":
        raise ImageError(f"{what} has pixel type {arr.dtype}; give a scalar integer label image")
    bad = ~np.isfinite(arr) | (arr != np.rint(np.where(np.isfinite(arr), arr, 0.0)))
    if bad.any():
        k, j, i = (int(v) for v in np.argwhere(bad)[0])
        raise ImageError(f"{what} has non-integer values ({int(bad.sum())} voxels, e.g. "
                         f"{arr[k, j, i]:.4g} at i={i}, j={j}, k={k}): label images must hold "
                         f"whole numbers — {LABEL_FIX}")
    return image.with_array(arr.astype(np.int64))


def read_labels(path: str | os.PathLike[str], what: str | None = None) -> Image:
    """A label image checked by :func:`check_labels`."""
    return check_labels(read_image(path), what or f"the label image {path}")


@contextlib.contextmanager
def tilted_policy(resample: bool) -> Iterator[None]:
    """During the block, DICOM series read without an explicit ``resample_tilted`` resample a
    gantry tilt or sheared/skewed grid (``resample=True``) instead of refusing it."""
    token = _RESAMPLE_TILTED.set(bool(resample))
    try:
        yield
    finally:
        _RESAMPLE_TILTED.reset(token)


def read_mesh(path: str | os.PathLike[str], *, fix_orientation: bool = False) -> TetMesh:
    """Read a tetrahedral mesh with meshio (VTU/VTK, Gmsh, Abaqus .inp, TetGen, Medit …).

    Only ``tetra`` cells are kept; point and cell arrays are carried along. A region label is
    taken from the first cell array named in :data:`REGION_NAMES`. Inverted tetrahedra are an
    error unless ``fix_orientation`` is true (then two vertices of each are swapped). A
    ``.node``/``.ele`` with a ``.material`` file beside it is an ICRP-145-style phantom (cm,
    material densities): :func:`tetdose.core.icrp145.read_icrp145`.
    """
    import meshio

    path = Path(path)
    if not path.exists():
        raise MeshError(f"mesh file {path} does not exist")
    if is_icrp145(path):  # its own unit (cm), converted by the reader
        mesh = read_icrp145(path)[0]
        _seen_mesh(mesh, f"the mesh {path}")
        return mesh
    if path.is_file() and path.stat().st_size == 0:
        raise MeshError(f"mesh file {path} is empty; give a VTU/VTK/MSH/INP/MESH/ELE file")
    said = io.StringIO()
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            m = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types, even SystemExit
        why = str(exc) if not isinstance(exc, SystemExit) else said.getvalue()
        why = " ".join(why.split()) or type(exc).__name__
        raise MeshError(f"cannot read mesh {path}: {why}; give a VTU/VTK/MSH/INP/MESH/ELE file"
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
    points = np.asarray(m.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"{path}: points must be 3-D, got {points.shape[-1]} coordinates")
    policy = _MESH_UNIT.get()
    if policy is not None and policy.unit is not None:
        points = points * MESH_UNITS[policy.unit]
    point_data = {k: np.asarray(v) for k, v in m.point_data.items()}
    if len(np.unique(tets)) < len(points):  # surface-only nodes and the like
        points, tets, used = compact_points(points, tets)
        point_data = {k: v[used] for k, v in point_data.items()}
    mesh = TetMesh(points, tets, region, point_data, cell_data)
    far = np.abs(mesh.points_mm).max(axis=1) > MAX_COORD_MM
    if far.any():
        i = int(np.flatnonzero(far)[0])
        raise MeshError(
            f"{int(far.sum())} point(s) in {path} lie more than {MAX_COORD_MM / 1e6:g} km from the "
            f"origin (first: id {i} at {np.round(mesh.points_mm[i], 1).tolist()} mm); patient "
            "coordinates must be in mm — fix the mesh file"
        )
    if fix_orientation:
        mesh = mesh.with_fixed_orientation()
    mesh.check_cells(context=f"in {path}")
    _seen_mesh(mesh, f"the mesh {path}")
    return mesh


def write_mesh(path: str | os.PathLike[str], mesh: TetMesh, *,
               inputs: tuple[str | os.PathLike[str], ...] = ()) -> Path:
    """Write a mesh with all its arrays (VTU recommended); atomic, never onto one of ``inputs``.

    The extension (one of :data:`MESH_SUFFIXES`) chooses the format.
    """
    import meshio

    check_output_file(path, suffixes=MESH_SUFFIXES, inputs=inputs, what="mesh output")

    cell_data = {k: [np.asarray(v)] for k, v in mesh.cell_data.items()}
    if mesh.region is not None:
        cell_data["region"] = [mesh.region.astype(np.int32)]
    m = meshio.Mesh(mesh.points_mm, [("tetra", mesh.tets)], point_data=dict(mesh.point_data),
                    cell_data=cell_data)
    path = Path(path)
    with atomic_write_file(path, inputs=inputs) as tmp:
        meshio.write(tmp, m, file_format=_meshio_format(path))
    return path


def _meshio_format(path: Path) -> str | None:
    return {".vtu": "vtu", ".vtk": "vtk", ".msh": "gmsh", ".xdmf": "xdmf"}.get(path.suffix.lower())


def read_image(path: str | os.PathLike[str], *, resample_tilted: bool | None = None) -> Image:
    """Read a scalar image: a DICOM series folder, or a file SimpleITK reads (NRRD, MHA, NIfTI…).

    A DICOM folder must hold one CT series with uniformly spaced slices; values are returned in
    HU (RescaleSlope/Intercept applied). A tilted or sheared series is refused, or with
    ``resample_tilted`` (default: :func:`tilted_policy`) resampled (:mod:`tetdose.core.tilted`).
    """
    import SimpleITK as sitk

    path = Path(path)
    if not path.exists():
        raise ImageError(f"image {path} does not exist")
    if path.is_dir():
        return _read_dicom_series(path, resample_tilted)
    try:
        with itk_messages(str(path)):
            img = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise ImageError(f"cannot read image {path}: {_itk_text(str(exc).strip().splitlines()[-1])}"
                         ) from exc
    return _seen_grid(Image.from_sitk(img), f"the image {path}")


def read_ct(path: str | os.PathLike[str], *, resample_tilted: bool | None = None) -> Image:
    """Read a CT [HU] with :func:`read_image` and refuse what cannot be one
    (:func:`tetdose.core.image.check_ct_hu`: unsigned or 8-bit pixels, NaN voxels, values off the HU
    range).

    Parameters
    ----------
    path : str or path
        A DICOM CT series folder, or an NRRD / MHA / NIfTI file in Hounsfield units.
    resample_tilted : bool, optional
        Resample a gantry-tilted or sheared series onto an orthogonal grid instead of refusing it
        (default: the CLI's ``--resample-tilted`` policy, else refuse).

    Returns
    -------
    Image
        The CT [HU] on its grid (origin and spacing [mm], direction cosines).

    Raises
    ------
    ImageError
        Not a CT that can be used (modality, slice spacing, tilt, pixel type, values), with a
        one-line message naming the fix.
    """
    return check_ct_hu(read_image(path, resample_tilted=resample_tilted), f"the CT {path}")


def _read_dicom_series(folder: Path, resample_tilted: bool | None = None) -> Image:
    import SimpleITK as sitk

    reader = sitk.ImageSeriesReader()
    with itk_messages(str(folder)):
        series = reader.GetGDCMSeriesIDs(str(folder))
        if not series:
            raise ImageError(f"{folder} holds no DICOM image series; give the folder of one CT "
                             "series")
        if len(series) > 1:
            raise ImageError(f"{folder} holds {len(series)} series; give a folder with one CT "
                             "series")
        files = reader.GetGDCMSeriesFileNames(str(folder), series[0])
    return read_dicom_files(files, what=str(folder), resample_tilted=resample_tilted)


def read_dicom_files(files: Sequence[str | os.PathLike[str]], *, what: str,
                     headers: Sequence[Any] | None = None,
                     resample_tilted: bool | None = None) -> Image:
    """Read the slices ``files`` of one CT series (in slice order) as one image [HU].

    Checks (the error names ``what``): modality CT; every slice with the same rows, columns,
    pixel spacing and orientation; uniformly spaced slice positions along the slice normal (a
    missing or duplicate slice breaks it). ``headers``: the files' pydicom headers if already read.
    A gantry tilt, sheared slice positions or a non-orthonormal ImageOrientationPatient are
    refused unless ``resample_tilted`` (default: :func:`tilted_policy`); then the stack is
    resampled onto an orthogonal grid (:mod:`tetdose.core.tilted`), with a warning saying so.
    """
    import pydicom
    import SimpleITK as sitk

    files = [str(f) for f in files]
    if headers is None:
        headers = [pydicom.dcmread(f, stop_before_pixels=True) for f in files]
    modality = {str(h.get("Modality", "")) for h in headers}
    if modality != {"CT"}:
        raise ImageError(f"{what}: modality {sorted(modality)}, expected CT; give a CT series")
    resample = _RESAMPLE_TILTED.get() if resample_tilted is None else resample_tilted
    normal, skewed = _check_orientation(what, headers, allow=resample)
    _check_rescale(what, headers)
    _check_slice_geometry(headers, what)
    sheared = len(files) > 1 and _check_shear(what, headers, normal, allow=resample)
    if skewed or sheared:
        return _seen_grid(_read_tilted(files, headers, normal, what), f"the CT series {what}")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    with warnings.catch_warnings(), itk_messages(what):
        warnings.simplefilter("ignore")
        img = reader.Execute()
    return _seen_grid(check_ct_hu(Image.from_sitk(img), f"the CT series {what}"),
                      f"the CT series {what}")


def _read_tilted(files: list[str], headers: Sequence[Any], normal: np.ndarray,
                 what: str) -> Image:
    """A tilted/sheared/skewed series resampled onto an orthogonal grid (tetdose.core.tilted)."""
    import SimpleITK as sitk

    from tetdose.core.tilted import OUTSIDE_HU, resample_stack, stack_affine

    pos = np.array([[float(v) for v in h.ImagePositionPatient] for h in headers])
    order = np.argsort(pos @ normal, kind="stable")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([files[i] for i in order])
    with warnings.catch_warnings(), itk_messages(what):
        warnings.simplefilter("ignore")
        stack = sitk.GetArrayFromImage(reader.Execute())
    iop = np.array([float(v) for v in headers[0].ImageOrientationPatient])
    spacing = tuple(float(v) for v in headers[0].PixelSpacing)
    a, p0 = stack_affine(pos[order], iop[:3], iop[3:], spacing)  # type: ignore[arg-type]
    image = resample_stack(stack, a, p0)
    tilt = float(np.degrees(np.arccos(min(1.0, abs(a[:, 2] @ normal) / np.linalg.norm(a[:, 2])))))
    warnings.warn(f"{what}: tilted or sheared series (slice axis {tilt:.2f}° off the slice "
                  "normal) resampled onto an orthogonal grid (linear interpolation, "
                  f"{OUTSIDE_HU:g} HU outside the stack)", stacklevel=3)
    return check_ct_hu(image, f"the CT series {what}")


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


def _check_orientation(folder: Path, headers: list,  # type: ignore[type-arg]
                       allow: bool = False) -> tuple[np.ndarray, bool]:
    """The series' common ImageOrientationPatient → (unit slice normal, whether it is not
    orthonormal: refused unless ``allow``)."""
    try:
        iops = np.array([[float(v) for v in h.ImageOrientationPatient] for h in headers])
        np.array([[float(v) for v in h.ImagePositionPatient] for h in headers]).reshape(-1, 3)
    except (AttributeError, TypeError, ValueError) as exc:
        raise ImageError(f"{folder}: a slice lacks a valid ImageOrientationPatient or "
                         "ImagePositionPatient; give a complete CT series") from exc
    if iops.shape[1] != 6:
        raise ImageError(f"{folder}: ImageOrientationPatient must hold 6 numbers")
    if np.abs(iops - iops[0]).max() > ORIENTATION_TOL:
        raise ImageError(f"{folder}: the slices have different ImageOrientationPatient; give a "
                         "series whose slices share one orientation")
    row, col = iops[0, :3], iops[0, 3:]
    dev = max(abs(np.linalg.norm(row) - 1), abs(np.linalg.norm(col) - 1), abs(row @ col))
    skewed = dev > ORIENTATION_TOL
    if skewed and not allow:
        raise ImageError(
            f"{folder}: ImageOrientationPatient {iops[0].round(6).tolist()} is not orthonormal "
            f"(row·column = {row @ col:.3g}); refused, not resampled — {RESAMPLE_HINT}"
        )
    normal = np.cross(row, col)
    return normal / np.linalg.norm(normal), bool(skewed)


def _check_rescale(folder: Path, headers: list) -> None:  # type: ignore[type-arg]
    """RescaleSlope/Intercept, where present, must be finite numbers and the slope non-zero."""
    for h in headers:
        try:
            slope = float(h.get("RescaleSlope", 1.0))
            intercept = float(h.get("RescaleIntercept", 0.0))
        except (TypeError, ValueError) as exc:
            raise ImageError(f"{folder}: RescaleSlope/RescaleIntercept are not numbers; fix the "
                             "series headers") from exc
        if not (np.isfinite(slope) and np.isfinite(intercept) and slope != 0):
            raise ImageError(f"{folder}: RescaleSlope {slope:g}, RescaleIntercept {intercept:g} "
                             "cannot give HU; fix the series headers")


def _check_shear(folder: Path, headers: list, normal: np.ndarray,  # type: ignore[type-arg]
                 allow: bool = False) -> bool:
    """Whether slice positions drift in-plane along the stack (gantry tilt, sheared grid):
    refused unless ``allow``."""
    pos = np.array([[float(v) for v in h.ImagePositionPatient] for h in headers])
    along = pos @ normal
    first = int(np.argmin(along))
    rel = pos - pos[first]
    drift = rel - np.outer(along - along[first], normal)
    shear_mm = float(np.sqrt((drift**2).sum(axis=1)).max())
    length = float(along.max() - along.min())
    sheared = shear_mm > max(0.01, SHEAR_REL_TOL * length)
    if sheared and not allow:
        tilt = float(np.degrees(np.arctan2(shear_mm, length)))
        raise ImageError(
            f"{folder}: slice positions drift {shear_mm:.3g} mm in-plane over the {length:.4g} mm "
            f"stack (gantry tilt or sheared grid, ≈ {tilt:.2f}°); refused, not resampled — "
            f"{RESAMPLE_HINT}"
        )
    return bool(sheared)


def write_image(path: str | os.PathLike[str], image: Image, *, compress: bool = True,
                inputs: tuple[str | os.PathLike[str], ...] = ()) -> Path:
    """Write an image with SimpleITK (format from the extension, one of :data:`IMAGE_SUFFIXES`:
    .nrrd, .mha, .nii.gz …); atomic, never onto one of ``inputs``."""
    import SimpleITK as sitk

    check_output_file(path, suffixes=IMAGE_SUFFIXES, inputs=inputs, what="image output")
    path = Path(path)
    with atomic_write_file(path, inputs=inputs) as tmp, itk_messages(str(path)):
        try:
            sitk.WriteImage(image.to_sitk(), str(tmp), compress)
        except RuntimeError as exc:
            raise _write_error(exc, path) from exc
    return path


#: Below this many free bytes a failed write is taken for a full disk.
_FULL_BYTES = 1 << 20


def _write_error(exc: RuntimeError, path: Path) -> OutputError:
    """SimpleITK's write failure (a RuntimeError, also for a full disk) in tetdose's words."""
    try:
        st = os.statvfs(path.parent)
        full = st.f_bavail * st.f_frsize < _FULL_BYTES
    except OSError:
        full = False
    if full:
        return OutputError(f"no space left writing in {path.parent}; free some space or choose "
                           "another disk")
    return OutputError(f"cannot write image {path}: "
                       f"{_itk_text(str(exc).strip().splitlines()[-1])}")
