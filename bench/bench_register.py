"""Bench of 4D-CT registration (``tetdose.motion.register``): time per phase, 2 SimpleITK threads.

Run: ``python bench/bench_register.py [--cases demo,large,lung] [--bspline]``. Prints figures;
asserts nothing. Cases:

* ``demo``: the demo's thorax phantom CT (``make_phantom("thorax", size="medium")``, the grid
  ``tetdose demo`` voxelizes the phases on), phase = CT pulled back by a 10 mm breathing field;
* ``large``: a 512×512×100 clinical-size CT made from the real abdomen series in ``../shared``
  (20 slices of 512×512, stacked five times, mirrored so slices stay continuous), same motion;
* ``lung``: the real lung CT of ``../shared`` (57×78×64), with the known-motion error inside the
  lung (mean, 95th percentile) as in ``tests/verification/test_register_real.py``.

``--bspline`` also times the B-spline method on ``lung`` (slow: minutes).
The phase images are made by a direct pull-back I(y + v(y)) with a smooth field v (its accuracy
does not matter for timing). The 10-phase figure is 9 registrations (the reference is free).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from tetdose.image import Image, ImageGrid
from tetdose.io import read_image
from tetdose.motion.register import RegistrationSettings, register

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
THREADS = 2


def pulled_back(ct: Image, amplitude_mm: float) -> Image:
    """CT pulled back by v = smooth caudal shift, largest at the image's lower third."""
    g = ct.grid
    coarse = ImageGrid(g.origin_mm, g.spacing_mm * np.array(g.size) / 16, g.direction, (17, 17, 17))
    p = coarse.voxel_centers_mm().reshape(*coarse.shape, 3)
    lo, hi = g.origin_mm[2], g.index_to_physical(np.array([0, 0, g.size[2] - 1.0]))[2]
    t = (p[..., 2] - lo) / (hi - lo)
    v = np.zeros_like(p)
    v[..., 2] = amplitude_mm * np.exp(-((t - 0.3) / 0.4) ** 2)
    v[..., 1] = -0.3 * v[..., 2]
    vf = sitk.GetImageFromArray(v, isVector=True)
    vf.SetOrigin(tuple(coarse.origin_mm))
    vf.SetSpacing(tuple(coarse.spacing_mm))
    vf.SetDirection(tuple(coarse.direction.ravel()))
    src = ct.with_array(np.asarray(ct.array, dtype=np.float32)).to_sitk()
    tr = sitk.DisplacementFieldTransform(sitk.Cast(vf, sitk.sitkVectorFloat64))
    return Image(sitk.GetArrayFromImage(sitk.Resample(src, src, tr, sitk.sitkLinear, -1000.0)),
                 g)


def large_ct() -> Image:
    ab = read_image(SHARED / "abdomen-dicom" / "series")
    a = ab.array
    stack = np.concatenate([a, a[::-1], a, a[::-1], a])
    g = ab.grid
    return Image(stack, ImageGrid(g.origin_mm, g.spacing_mm, g.direction, (*g.size[:2], len(stack))))


def time_one(label: str, ct: Image, settings: RegistrationSettings) -> float:
    phase = pulled_back(ct, 10.0)
    t = time.perf_counter()
    _, report = register(ct, phase, settings=settings, percent=50.0)
    s = time.perf_counter() - t
    print(f"{label}: CT {ct.grid.size} ({ct.grid.n_voxels / 1e6:.1f} M voxels), "
          f"{settings.method}: {s:.1f} s per phase (report {report.seconds:.1f} s; metric "
          f"{report.metric_before_hu2:.4g} → {report.metric_after_hu2:.4g} HU², det J "
          f"{report.jacobian_min:.2f}…{report.jacobian_max:.2f}); 10-phase 4D-CT ≈ {9 * s:.0f} s",
          flush=True)
    return s


def lung_case(settings: RegistrationSettings) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from known_motion import breathing_field, warp

    ct = read_image(SHARED / "lung-elastix" / "3DCT_lung_baseline_small.mha")
    mask = sitk.Resample(sitk.ReadImage(str(SHARED / "lung-elastix" / "3DCT_lung_baseline_mask.mha")),
                         ct.to_sitk(), sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    lung = sitk.GetArrayFromImage(mask).ravel() > 0
    u = breathing_field(12.0, -1380.0, centre_xy_mm=(-80.0, -40.0), width_xy_mm=(90.0, 110.0))
    phase = warp(ct, u)
    t = time.perf_counter()
    field, report = register(ct, phase, settings=settings, percent=50.0)
    s = time.perf_counter() - t
    err = np.linalg.norm(field.vectors_mm.reshape(-1, 3) - u(ct.grid.voxel_centers_mm()), axis=1)[lung]
    print(f"lung (real CT, known 12 mm breathing), {settings.method}: {s:.1f} s; error in lung "
          f"mean {err.mean():.2f} mm, p95 {np.percentile(err, 95):.2f} mm, max {err.max():.2f} mm;"
          f" det J {report.jacobian_min:.2f}…{report.jacobian_max:.2f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default="demo,large,lung")
    ap.add_argument("--bspline", action="store_true")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}; SimpleITK threads {THREADS}")
    settings = RegistrationSettings(threads=THREADS)
    t = time.perf_counter()
    register(*(2 * [Image(np.zeros((8, 8, 8)) + 40.0, ImageGrid([0, 0, 0], [1, 1, 1], np.eye(3),
                                                                  (8, 8, 8)))]),
             mask=np.ones((8, 8, 8), bool), settings=RegistrationSettings(shrink=(1,),
                                                                          iterations=(1,)))
    print(f"warm-up {time.perf_counter() - t:.2f} s")
    cases = args.cases.split(",")
    if "demo" in cases:
        from tetdose.phantoms import make_phantom

        time_one("demo thorax phantom", make_phantom("thorax", size="medium").ct, settings)
    if "large" in cases and (SHARED / "abdomen-dicom").exists():
        time_one("large (abdomen ×5)", large_ct(), settings)
    if "lung" in cases and (SHARED / "lung-elastix").exists():
        lung_case(settings)
        if args.bspline:
            lung_case(RegistrationSettings(method="bspline", iterations=(30, 20, 5), threads=THREADS))


if __name__ == "__main__":
    main()
