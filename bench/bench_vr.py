"""Efficiency of dose mode's variance reduction on a small XVMC case (Kawrakow & Fippel, PMB
45:2163, 2000): ε = 1 / (σ² T), σ the median relative standard error over the voxels above 50 %
of D_max, T the CPU time of the run (``time.process_time``, one numba thread, kernels warm).

Run: ``NUMBA_CACHE_DIR=.numba-cache python bench/bench_vr.py [--side 150] [--field 60]
[--histories 20000] [--runs "analog:;split4:photon_splitting=4"]``. The phantom is a water cube
of ``--side`` mm in 5 mm voxels, the beam the Mohan 6 MV spectrum, parallel, ``--field`` mm
square, electrons cut off at 0.189 MeV (the XVMC paper's). Each run is a name and
``key=value`` overrides of :class:`~tetdose.transport.TransportSettings` (numbers parsed).
Printed per run: µs per history, median σ, ε and ε / ε(first run), electron tracks and steps
per history, and against the first run over the voxels of a fixed region (inside the field
10 mm from its edges, 20 mm to 70 % of the cube deep; a region chosen from noisy doses would
favour the noisier run): the RMS of
z = (D − D₀)/√(σ² + σ₀²) (≈ 1 when the two agree within statistics) and the relative
difference of their summed dose with its σ (a bias of the technique shows in either). Ratios
measured in one process are what to quote (the machine is shared).
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from tetdose.core.image import Image, ImageGrid
from tetdose.plan.spectra import named_spectrum
from tetdose.transport import PhotonSource, Plan, TransportSettings, simulate

VOXEL_MM = 5.0
BATCHES = 10


def phantom(side_mm: float) -> Image:
    """Water cube of ``side_mm`` in 5 mm voxels, front face at z = 0, axis on x = y = 0."""
    n = int(round(side_mm / VOXEL_MM))
    sp = np.full(3, VOXEL_MM)
    origin = np.array([-side_mm / 2, -side_mm / 2, 0.0]) + sp / 2
    return Image(np.ones((n, n, n)), ImageGrid(origin, sp, np.eye(3), (n, n, n)))


def plan(field_mm: float) -> Plan:
    e, w = named_spectrum("6MV")
    src = PhotonSource("parallel", (0.0, 0.0, -10.0), (0, 0, 1), energies_mev=e, line_weights=w,
                       field_mm=(field_mm, field_mm))
    return Plan((src,))


def stats(r) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # noqa: ANN001
    """Per-voxel (mean, σ) of the energy per history [MeV], and the per-batch rows."""
    e = r.energy_per_batch_mev / r.histories_per_batch[:, None]
    return e.mean(axis=0), e.std(axis=0, ddof=1) / np.sqrt(len(e)), e


def median_sigma(mean: np.ndarray, sd: np.ndarray) -> float:
    """Median relative standard error over the voxels above 50 % of the maximum."""
    hot = mean > 0.5 * mean.max()
    return float(np.median(sd[hot] / mean[hot]))


def agreement(ref: tuple, run: tuple, inner: np.ndarray) -> str:
    """RMS z per voxel of ``inner`` and its summed dose's relative difference ± σ (see module)."""
    (m0, s0, e0), (m, s, e) = ref, run
    hot = inner
    z = (m[hot] - m0[hot]) / np.hypot(s[hot], s0[hot])
    t0, t = e0[:, hot].sum(axis=1), e[:, hot].sum(axis=1)
    sd = np.hypot(t0.std(ddof=1) / np.sqrt(len(t0)), t.std(ddof=1) / np.sqrt(len(t)))
    return (f"rms z {np.sqrt(np.mean(z * z)):5.2f}  ΣD {100 * (t.mean() / t0.mean() - 1):+6.2f} "
            f"± {100 * sd / t0.mean():4.2f} %")


def parse_runs(text: str) -> list[tuple[str, dict]]:
    out = []
    for item in text.split(";"):
        name, _, kv = item.partition(":")
        kw = {}
        for pair in filter(None, kv.split(",")):
            k, _, v = pair.partition("=")
            try:
                kw[k] = int(v)
            except ValueError:
                try:
                    kw[k] = float(v)
                except ValueError:
                    kw[k] = v
        out.append((name, kw))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=float, default=150.0)
    ap.add_argument("--field", type=float, default=60.0)
    ap.add_argument("--histories", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--runs", default="analog:;split4:photon_splitting=4")
    args = ap.parse_args()
    numba.set_num_threads(1)
    rho, pl = phantom(args.side), plan(args.field)
    c = rho.grid.voxel_centers_mm()
    inner = ((np.abs(c[:, 0]) < args.field / 2 - 10) & (np.abs(c[:, 1]) < args.field / 2 - 10)
             & (c[:, 2] > 20) & (c[:, 2] < 0.7 * args.side))
    base = {"electron_cutoff_mev": 0.189}
    eps0 = ref = None
    for name, kw in parse_runs(args.runs):
        st = TransportSettings(args.histories, BATCHES, **{"seed": args.seed, **base, **kw})
        simulate(rho, pl, TransportSettings(BATCHES * 10, BATCHES, **{**base, **kw, "seed": 99}),
                 progress=False)  # warm: compile and tables
        c0 = time.process_time()
        r = simulate(rho, pl, st, progress=False)
        t = time.process_time() - c0
        st_run = stats(r)
        sig = median_sigma(*st_run[:2])
        eps = 1.0 / (sig * sig * t)
        eps0, ref = eps0 or eps, ref or st_run
        rec = r.record()
        print(f"{name:14s} {1e6 * t / args.histories:8.1f} µs/hist  σ {100 * sig:6.2f} %  "
              f"ε {eps:9.3g} /s  ×{eps / eps0:5.2f}  e-tracks/hist "
              f"{rec['electron_tracks'] / args.histories:6.2f}  steps/hist "
              f"{rec['electron_steps'] / args.histories:7.1f}  T {t:6.1f} s  "
              f"{agreement(ref, st_run, inner)}", flush=True)


if __name__ == "__main__":
    main()
