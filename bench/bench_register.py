"""Bench of 4D-CT registration (``tetdose.motion.register``): time per phase, 2 SimpleITK threads.

Run: ``python bench/bench_register.py [--cases demo,large,lung] [--before] [--dose] [--bspline]``.
Prints figures and ratios; asserts nothing. Every case times the present defaults and, in the same
process, the settings before the speed-up (``BEFORE_SPEEDUP``: whole image, 100/60/40 iterations,
no warm start) where it says so. Cases:

* ``demo``: the demo's thorax phantom CT (``make_phantom("thorax", size="medium")``, the grid
  ``tetdose demo`` voxelizes the phases on); a 10-phase 4D-CT made from it by pulling it back with
  a breathing field of amplitude 10 mm × sin²(π(k − 5)/10), reference phase 5 (50 %), registered
  by ``register_4dct`` (nine registrations) with the settings before and now;
* ``large``: a 512×512×100 clinical-size CT made from the real abdomen series in ``../shared``
  (20 slices of 512×512, stacked five times, mirrored so slices stay continuous), one phase at
  10 mm (``--before``: also with the old settings, +5 min);
* ``lung``: the real lung CT of ``../shared`` (57×78×64): one phase with the known 12 mm breathing
  of ``tests/verification/test_register_real.py`` and a 10-phase 4D-CT of it (amplitude
  12 mm × sin²), with the error inside the lung (mean, 95th percentile; worst phase), before / now.

``--dose`` also runs the demo study (``run_study(StudyConfig())``, as ``tetdose demo``) in this
process and prints its 4D dose stage's time against the demo's 10-phase registration (the issue's
target: registration faster than that stage); run it with the numba cache warm (after ``make
demo`` or a first run), else the stage includes compiling the transport kernels. ``--bspline``
also times the B-spline method on ``lung`` (slow: minutes). The phase images of ``demo`` and
``large`` are made by a direct pull-back I(y + v(y)) with a smooth field v (its accuracy does not
matter for timing).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import read_image
from tetdose.motion.register import BEFORE_SPEEDUP, RegistrationSettings, register, register_4dct

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
THREADS = 2
N_PHASES, REFERENCE = 10, 5


def amplitudes(peak_mm: float) -> list[float]:
    """Breathing amplitude of each phase relative to the reference: peak × sin²(π(k − 5)/10)."""
    return [peak_mm * float(np.sin(np.pi * (k - REFERENCE) / N_PHASES)) ** 2
            for k in range(N_PHASES)]


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
          f"{settings.method}: {s:.1f} s per phase (registration {report.seconds:.1f} s; metric "
          f"{report.metric_before_hu2:.4g} → {report.metric_after_hu2:.4g} HU², det J "
          f"{report.jacobian_min:.2f}…{report.jacobian_max:.2f}); 10-phase 4D-CT ≈ {9 * s:.0f} s",
          flush=True)
    return s


def time_series(label: str, phases: list[Image], settings: RegistrationSettings) -> tuple[
        float, float, list]:
    """Wall and CPU seconds of ``register_4dct`` on the phases (reference 5), and its results."""
    t, cpu = time.perf_counter(), time.process_time()
    out = register_4dct(phases, REFERENCE, settings=settings)
    wall, cpu = time.perf_counter() - t, time.process_time() - cpu
    metric = max(r.metric_after_hu2 for _, r in out)
    print(f"{label}: 10-phase 4D-CT {wall:.1f} s (CPU {cpu:.1f} s, load "
          f"{os.getloadavg()[0]:.1f}); worst metric after {metric:.4g} HU², det J ≥ "
          f"{min(r.jacobian_min for _, r in out):.2f}", flush=True)
    return wall, cpu, out


def before_after(label: str, phases: list[Image], now: RegistrationSettings,
                 before: RegistrationSettings) -> tuple[float, list, list]:
    """Before, now, before again (the load drifts): ratio of the means; now's wall time."""
    b1, cb1, out_b = time_series(f"{label}, before", phases, before)
    n, cn, out_n = time_series(f"{label}, now", phases, now)
    b2, cb2, _ = time_series(f"{label}, before (again)", phases, before)
    print(f"{label}: now / before = {n / (0.5 * (b1 + b2)):.2f} wall, "
          f"{cn / (0.5 * (cb1 + cb2)):.2f} CPU", flush=True)
    return n, out_b, out_n


def lung_case(settings: RegistrationSettings, before: RegistrationSettings | None) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from known_motion import breathing_field, warp

    ct = read_image(SHARED / "lung-elastix" / "3DCT_lung_baseline_small.mha")
    mask = sitk.Resample(sitk.ReadImage(str(SHARED / "lung-elastix" / "3DCT_lung_baseline_mask.mha")),
                         ct.to_sitk(), sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    lung = sitk.GetArrayFromImage(mask).ravel() > 0
    centres = ct.grid.voxel_centers_mm()

    def field(amplitude_mm: float):  # noqa: ANN202
        return breathing_field(max(amplitude_mm, 1e-9), -1380.0, centre_xy_mm=(-80.0, -40.0),
                               width_xy_mm=(90.0, 110.0))

    def errors(f, u) -> np.ndarray:  # noqa: ANN001
        return np.linalg.norm(f.vectors_mm.reshape(-1, 3) - u(centres), axis=1)[lung]

    u = field(12.0)
    phase = warp(ct, u)
    t = time.perf_counter()
    f, report = register(ct, phase, settings=settings, percent=50.0)
    s = time.perf_counter() - t
    err = errors(f, u)
    print(f"lung (real CT, known 12 mm breathing), {settings.method}: {s:.1f} s; error in lung "
          f"mean {err.mean():.2f} mm, p95 {np.percentile(err, 95):.2f} mm, max {err.max():.2f} mm;"
          f" det J {report.jacobian_min:.2f}…{report.jacobian_max:.2f}", flush=True)
    if before is None:
        return
    us = [field(a) for a in amplitudes(12.0)]
    phases = [ct if k == REFERENCE else warp(ct, us[k]) for k in range(N_PHASES)]
    _, out_b, out_n = before_after("lung 4D-CT (12 mm)", phases, settings, before)
    for label, out in (("before", out_b), ("now", out_n)):
        errs = [errors(f, us[k]) for k, (f, _) in enumerate(out)]
        print(f"lung 4D-CT, {label}: worst phase error in lung mean "
              f"{max(e.mean() for e in errs):.3f} mm, p95 "
              f"{max(np.percentile(e, 95) for e in errs):.3f} mm, max "
              f"{max(e.max() for e in errs):.2f} mm", flush=True)


def demo_dose_seconds() -> float:
    """The 4D dose stage of the demo study (``tetdose demo`` defaults), run here, in seconds."""
    import tempfile

    from tetdose.study import StudyConfig, run_study

    with tempfile.TemporaryDirectory() as tmp:
        summary = run_study(StudyConfig(), Path(tmp) / "demo-out")
    print(f"demo study (tetdose demo): stages {summary['seconds']} s; load "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    return float(summary["seconds"]["dose"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default="demo,large,lung")
    ap.add_argument("--before", action="store_true",
                    help="large: also time the settings before the speed-up (+5 min)")
    ap.add_argument("--dose", action="store_true",
                    help="also run the demo study here and compare its 4D dose stage")
    ap.add_argument("--bspline", action="store_true")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}; SimpleITK threads {THREADS}")
    settings = RegistrationSettings(threads=THREADS)
    before = replace(BEFORE_SPEEDUP, threads=THREADS)
    t = time.perf_counter()
    register(*(2 * [Image(np.zeros((8, 8, 8)) + 40.0, ImageGrid([0, 0, 0], [1, 1, 1], np.eye(3),
                                                                  (8, 8, 8)))]),
             mask=np.ones((8, 8, 8), bool), settings=RegistrationSettings(shrink=(1,),
                                                                          iterations=(1,)))
    print(f"warm-up {time.perf_counter() - t:.2f} s")
    cases = args.cases.split(",")
    registration_10 = None
    if "demo" in cases:
        from tetdose.phantoms import make_phantom

        ct = make_phantom("thorax", size="medium").ct
        time_one("demo thorax phantom", ct, settings)
        phases = [ct if k == REFERENCE else pulled_back(ct, a)
                  for k, a in enumerate(amplitudes(10.0))]
        registration_10, _, _ = before_after("demo 4D-CT", phases, settings, before)
    if args.dose:
        dose = demo_dose_seconds()
        if registration_10 is not None:
            print(f"demo: 10-phase registration {registration_10:.1f} s / 4D dose stage "
                  f"{dose:.1f} s = {registration_10 / dose:.2f} (target < 1)", flush=True)
    if "large" in cases and (SHARED / "abdomen-dicom").exists():
        ct = large_ct()
        now = time_one("large (abdomen ×5), now", ct, settings)
        if args.before:
            old = time_one("large (abdomen ×5), before", ct, before)
            print(f"large: now / before = {now / old:.2f}", flush=True)
    if "lung" in cases and (SHARED / "lung-elastix").exists():
        lung_case(settings, before)
        if args.bspline:
            lung_case(RegistrationSettings(method="bspline", iterations=(30, 20, 5), threads=THREADS),
                      None)


if __name__ == "__main__":
    main()
