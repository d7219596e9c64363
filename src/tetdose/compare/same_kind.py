"""Two doses on the same cells: two dose images on one grid (phase vs phase, tetdose vs another
code's voxel dose, two seeds) or two per-tet doses on one mesh topology (phase vs phase on the
breathing mesh, tetdose's accumulation vs one imported with ``tetdose import-dose``).

No transfer is needed: cell i of one dose is cell i of the other (for phase meshes: the same
tissue element, wherever the phase moved it). Compared: the cells in tissue (density ≥
:data:`~tetdose.core.body.TISSUE_FLOOR_G_CM3`; for images with a CT also inside its body
outline). Reported as in :func:`tetdose.compare.comparison.compare_doses`: per structure the mean
relative difference of the first dose to the reference ± 1σ and the systematic part
(:mod:`tetdose.compare.significance`), DVHs with ±1σ bands and each point with its σ; for images
also γ (measured and expected for noise) and the Δ/σ and σ maps.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tetdose._constants import MM3_PER_CM3
from tetdose._typing import BoolArray, FloatArray
from tetdose.compare import report
from tetdose.compare.consistency import expected_gamma_pass, pair_significance, significance_table
from tetdose.compare.dvh_bands import banded_dvh, compare_points
from tetdose.compare.gamma import gamma_index
from tetdose.core.body import NEAR_MAX_SAID, TISSUE_FLOOR_G_CM3, near_max_gy
from tetdose.core.image import Image
from tetdose.core.mass import tet_mass_g
from tetdose.core.mesh import TetMesh
from tetdose.errors import GeometryMismatchError

LABELS = ("dose", "reference")


def _zeros_if_none(s: FloatArray | None, like: FloatArray) -> FloatArray:
    return np.zeros_like(like) if s is None else np.asarray(s, dtype=np.float64)


def _said(s: FloatArray | None) -> str:
    return "σ from the file (batches)" if s is not None else "no σ given: compared as exact"


def compare_images(a: Image, sa: Image | None, b: Image, sb: Image | None, *,
                   structures: Mapping[str, BoolArray] | None = None,
                   density: Image | None = None, body: BoolArray | None = None,
                   threshold_percent: float = 10.0, gamma_max_points: int | None = 200_000,
                   unit: str = "Gy") -> tuple[list[report.Figure], dict[str, Any]]:
    """Dose image ``a`` against the reference ``b`` (same grid), σ images optional."""
    a.grid.require_same(b.grid, "the dose and the reference dose")
    ea, eb = np.asarray(a.array, float), np.asarray(b.array, float)
    s_a = _zeros_if_none(None if sa is None else sa.array, ea)
    s_b = _zeros_if_none(None if sb is None else sb.array, eb)
    cm3 = a.grid.voxel_volume_mm3 / MM3_PER_CM3
    region = np.ones(ea.shape, bool) if body is None else np.asarray(body, bool)
    weight = np.full(ea.shape, cm3)
    said = "every voxel (no CT: tissue not told from air)"
    if density is not None:
        rho = np.asarray(density.array, float)
        region &= rho >= TISSUE_FLOOR_G_CM3
        weight = rho * cm3
        said = f"voxels inside the CT's body outline with density ≥ {TISSUE_FLOOR_G_CM3:g} g/cm³"
    norm = near_max_gy(np.where(region, eb, 0.0), cm3)
    if not norm > 0:
        raise GeometryMismatchError("the reference dose is zero in the compared region; compare "
                                    "doses of the same patient and plan")
    hot = np.argwhere(region & (eb >= 0.95 * norm))
    k = int(round(hot[:, 0].mean()))
    noisy = sa is not None or sb is not None
    table, figures = pair_significance(b, s_b, a, s_a, region, structures or {},
                                       threshold_percent / 100.0 * norm, weight,
                                       k=k if noisy else None, labels=LABELS, unit=unit)
    kw = {"dose_percent": 3.0, "dta_mm": 3.0, "threshold_percent": threshold_percent,
          "mask": region, "normalization_gy": norm}
    g = gamma_index(b, a, max_points=gamma_max_points, **kw)
    row = g.summary() | (expected_gamma_pass(b, s_b, a, s_a, **kw) if noisy
                         else {"expected_pass_rate_percent": 100.0})
    figures.append(report.gamma_figure(gamma_index(b, a, **(kw | {"mask": _slice(region, k)})),
                                       k=k, expected=row["expected_pass_rate_percent"]))
    masks = {"compared region": region, **{n: region & np.asarray(m, bool)
                                           for n, m in (structures or {}).items()}}
    dvh = _dvh_table({n: (ea[m], s_a[m], eb[m], s_b[m], np.full(int(m.sum()), cm3))
                      for n, m in masks.items() if m.any()}, unit, figures)
    summary = {"unit": unit, "region": {"description": said, "voxels": int(region.sum()),
                                        "reference_near_max_gy": norm, "near_max": NEAR_MAX_SAID},
               "uncertainty": {LABELS[0]: _said(sa), LABELS[1]: _said(sb)},
               "structures": table, "gamma": {row["criterion"]: row}, "dvh": dvh}
    return figures, summary


def compare_meshes(mesh: TetMesh, a: FloatArray, sa: FloatArray | None, ref_mesh: TetMesh,
                   b: FloatArray, sb: FloatArray | None, *, threshold_percent: float = 10.0,
                   unit: str = "Gy") -> tuple[list[report.Figure], dict[str, Any]]:
    """Per-tet dose ``a`` on ``mesh`` against ``b`` on ``ref_mesh`` (same tets), per region
    label; tissue from the meshes' point_data ``density`` when present."""
    if mesh.n_tets != ref_mesh.n_tets or not np.array_equal(mesh.tets, ref_mesh.tets):
        raise GeometryMismatchError(f"the two meshes have different tetrahedra ({mesh.n_tets} "
                                    f"and {ref_mesh.n_tets}); compare doses on one mesh topology "
                                    "(phases of one series, or a dose imported onto it)")
    a, b = np.asarray(a, float).ravel(), np.asarray(b, float).ravel()
    s_a, s_b = _zeros_if_none(sa, a), _zeros_if_none(sb, b)
    cm3 = ref_mesh.volumes_mm3 / MM3_PER_CM3
    region, weight = np.ones(len(a), bool), cm3
    said = "every tet (no density on the mesh: tissue not told from air)"
    if "density" in ref_mesh.point_data:
        weight = tet_mass_g(ref_mesh)
        region = weight / cm3 >= TISSUE_FLOOR_G_CM3
        said = f"tets with density ≥ {TISSUE_FLOOR_G_CM3:g} g/cm³ (the reference mesh's)"
    norm = near_max_gy(np.where(region, b, 0.0), cm3)
    masks = {"compared region": region}
    if ref_mesh.region is not None:
        masks |= {f"region {r}": region & (ref_mesh.region == r) for r in np.unique(ref_mesh.region)}
    table = significance_table(a, s_a, b, s_b, weight, masks,
                                  b >= threshold_percent / 100.0 * norm)
    figures: list[report.Figure] = []
    dvh = _dvh_table({n: (a[m], s_a[m], b[m], s_b[m], cm3[m]) for n, m in masks.items()
                      if m.any()}, unit, figures)
    summary = {"unit": unit, "region": {"description": said, "tets": int(region.sum()),
                                        "reference_near_max_gy": norm, "near_max": NEAR_MAX_SAID},
               "uncertainty": {LABELS[0]: _said(sa), LABELS[1]: _said(sb)},
               "structures": table, "dvh": dvh}
    return figures, summary


def _slice(region: BoolArray, k: int) -> BoolArray:
    out = np.zeros_like(region)
    out[k] = region[k]
    return out


def _dvh_table(parts: Mapping[str, tuple[FloatArray, ...]], unit: str,
               figures: list[report.Figure]) -> dict[str, Any]:
    """Banded DVHs of both doses per structure, each point with σ and its flag."""
    curves, table = {}, {}
    for name, (a, sa, b, sb, w) in parts.items():
        ha = banded_dvh(a, sa, w, name=LABELS[0])
        hb = banded_dvh(b, sb, w, name=LABELS[1])
        curves[name] = [ha, hb]
        table[name] = {"points": compare_points(ha, hb)}
    figures.append(report.dvh_figure(curves, unit=unit))
    return table
