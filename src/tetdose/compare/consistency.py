"""The uncertainty side of a comparison: σ on the compared grid, the region compared (inside the
body, in tissue), the per-structure significance table, and γ's expected pass rate for noise.

**σ files.** A mesh dose's σ is its cell_data ``dose_std``; an image's is ``*_std`` beside it.

**σ of a mesh dose on voxels.** The transfer D_j = Σ_k D_k m_kj / Σ_k m_kj
(:func:`tetdose.core.transfer.mesh_dose_to_grid`) is linear in independent tet doses, so
σ_j = sqrt(Σ_k σ_k² m_kj²) / Σ_k m_kj.

**Region.** Points are compared inside the body outline, never in air: the voxels at least half
inside the mesh, inside the body (the CT's outline, :func:`tetdose.meshing.labels.body_mask`,
when the CT is given) and in tissue (density ≥ :data:`~tetdose.core.body.TISSUE_FLOOR_G_CM3`
when densities are known). The summary says which of these applied.

**γ and σ.** A pass rate below 100 % is expected from noise alone. Next to the measured rate the
report gives the rate two unbiased runs with these σ would reach: the noise-free dose is
estimated by the inverse-variance weighted mean t of both doses, and γ is evaluated between
t + σ_ref·z₁ and t + σ_ev·z₂ (independent standard normal z; :data:`GAMMA_RESAMPLES` draws, their
mean and spread). t keeps a little noise (σ_t² = σ_a²σ_b²/(σ_a² + σ_b²)), so the expected rate is
approximate — slightly low where the doses are very noisy.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._typing import BoolArray, FloatArray
from tetdose.compare.gamma import gamma_index
from tetdose.compare.noise_figures import sigma_maps_figure, significance_figure
from tetdose.compare.significance import normalised_difference, structure_significance
from tetdose.core.body import TISSUE_FLOOR_G_CM3
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap
from tetdose.core.transfer import weighted_pair_mass_g

#: Draws of the expected γ pass rate for two unbiased runs.
GAMMA_RESAMPLES = 2
#: At most this many points per draw (a seeded sample of the points above the threshold).
GAMMA_RESAMPLE_POINTS = 10_000


def mesh_std_to_grid(mesh: TetMesh, std_gy: FloatArray, grid: ImageGrid, overlap: Overlap
                     ) -> Image:
    """σ of the mesh dose put on ``grid`` (module docstring) [Gy]."""
    m_kj = weighted_pair_mass_g(mesh, overlap)
    s = np.asarray(std_gy, dtype=np.float64).ravel()
    var = np.bincount(overlap.voxel, weights=(s[overlap.tet] * m_kj) ** 2,
                      minlength=grid.n_voxels)
    mass = np.bincount(overlap.voxel, weights=m_kj, minlength=grid.n_voxels)
    out = np.divide(np.sqrt(var), mass, out=np.zeros_like(mass), where=mass > 0)
    return Image(out.reshape(grid.shape), grid)


def mesh_dose_std(mesh: TetMesh) -> FloatArray | None:
    """The per-tet σ [Gy] of a dose VTU (cell_data ``dose_std``), None when absent or all zero
    (an imported dose without σ is written with zeros)."""
    s = mesh.cell_data.get("dose_std")
    if s is None:
        return None
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    return s if np.any(s > 0) else None


def std_image_path(dose_path: str | Path) -> Path:
    """Where a dose image's σ lies: ``*_std`` beside it (dose.nrrd → dose_std.nrrd,
    accumulated_voxel_part.nrrd → accumulated_voxel_part_std.nrrd)."""
    path = Path(dose_path)
    stem, _, suffix = path.name.partition(".")
    return path.with_name(f"{stem}_std.{suffix}")


def read_dose_std_image(dose_path: str | Path, grid: ImageGrid) -> Image | None:
    """The σ image beside a dose image (:func:`std_image_path`), None when there is none."""
    from tetdose.core.io import read_image

    path = std_image_path(dose_path)
    if not path.exists():
        return None
    std = read_image(path)
    grid.require_same(std.grid, f"the dose {dose_path} and its σ {path}")
    return std.with_array(np.asarray(std.array, dtype=np.float64))


def compared_region(inside_mesh: BoolArray, body: BoolArray | None,
                    density: FloatArray | None) -> tuple[BoolArray, str]:
    """The compared voxels and the sentence saying which region it is (module docstring)."""
    region = np.asarray(inside_mesh, dtype=bool).copy()
    said = ["voxels at least half inside the mesh"]
    if body is not None:
        region &= np.asarray(body, dtype=bool)
        said.append("inside the body outline of the CT")
    if density is not None:
        rho = np.nan_to_num(np.asarray(density, dtype=np.float64), nan=0.0)
        region &= rho >= TISSUE_FLOOR_G_CM3
        said.append(f"in tissue (density ≥ {TISSUE_FLOOR_G_CM3:g} g/cm³)")
    else:
        said.append("(no densities: tissue not told from air)")
    return region, ", ".join(said)


def significance_table(a: FloatArray, sa: FloatArray, b: FloatArray, sb: FloatArray,
                       weight: FloatArray, masks: Mapping[str, BoolArray], fit_points: BoolArray
                       ) -> dict[str, Any]:
    """Per structure (name → mask, same shape as the doses): :func:`structure_significance`."""
    table: dict[str, Any] = {}
    for name, mask in masks.items():
        sel = np.asarray(mask, dtype=bool)
        if sel.sum() >= 2:
            table[name], _ = structure_significance(a[sel], sa[sel], b[sel], sb[sel],
                                                    weight[sel], fit_points[sel])
    return table


def expected_gamma_pass(ref: Image, s_ref: FloatArray, ev: Image, s_ev: FloatArray, *,
                        resamples: int = GAMMA_RESAMPLES, seed: int = 0,
                        **gamma_kwargs: Any) -> dict[str, float]:  # noqa: ANN401
    """The γ pass rate [%] two unbiased runs with σ ``s_ref`` and ``s_ev`` would reach (module
    docstring): mean and standard deviation over ``resamples`` draws."""
    r, e = np.asarray(ref.array, float), np.asarray(ev.array, float)
    vr, ve = np.asarray(s_ref, float) ** 2, np.asarray(s_ev, float) ** 2
    v = vr + ve
    t = np.divide(r * ve + e * vr, v, out=0.5 * (r + e), where=v > 0)
    rng = np.random.default_rng(seed)
    kwargs = {"max_points": GAMMA_RESAMPLE_POINTS, **gamma_kwargs}
    rates = []
    for _ in range(resamples):
        rr = ref.with_array(np.maximum(t + np.sqrt(vr) * rng.standard_normal(t.shape), 0.0))
        ee = ev.with_array(np.maximum(t + np.sqrt(ve) * rng.standard_normal(t.shape), 0.0))
        rates.append(gamma_index(rr, ee, seed=int(rng.integers(1 << 30)),
                                 **kwargs).pass_rate_percent)
    return {"expected_pass_rate_percent": float(np.mean(rates)),
            "expected_pass_rate_spread_percent": float(np.std(rates, ddof=1))
            if len(rates) > 1 else 0.0}


def pair_significance(ref: Image, s_ref: FloatArray, ev: Image, s_ev: FloatArray,
                      region: BoolArray, masks: Mapping[str, BoolArray], threshold_gy: float,
                      weight: FloatArray, *, k: int | None = None,
                      labels: tuple[str, str] = ("evaluated", "reference"),
                      unit: str = "Gy") -> tuple[dict[str, Any], list[Any]]:
    """One pair of doses on one grid: the significance table over ``region`` and each mask
    within it (fitted over the points ≥ ``threshold_gy`` of the reference), and, when ``k`` is
    given, the Δ/σ and σ-map figures of slice k."""
    e, r = np.asarray(ev.array, float), np.asarray(ref.array, float)
    above = region & (r >= threshold_gy)
    masks = {"compared region": region, **{n: region & np.asarray(m, bool)
                                           for n, m in masks.items()}}
    table = significance_table(e, s_ev, r, s_ref, weight, masks, above)
    figures: list[Any] = []
    if k is not None:
        z = normalised_difference(e, s_ev, r, s_ref)
        figures.append(significance_figure(ref, e - r, z, region, above, k=k, labels=labels,
                                           unit=unit))
        rel = [np.divide(s, d, out=np.zeros_like(d), where=d > 0) if np.any(s > 0) else None
               for s, d in ((s_ev, e), (s_ref, r))]
        figures.append(sigma_maps_figure(ref, rel[0], rel[1], region, k=k, labels=labels))
    return table, figures
