"""Efficiency of dose mode's variance reduction on a small XVMC case (Kawrakow & Fippel, PMB
45:2163, 2000): ε = 1 / (σ² T), σ the median relative standard error over the voxels above 50 %
of D_max, T the CPU time of the run (``time.process_time``, one numba thread, kernels warm).

Run: ``NUMBA_CACHE_DIR=.numba-cache python bench/bench_vr.py [--side 150] [--field 60]
[--histories 20000] [--runs "analog:;split4:photon_splitting=4"]``. The phantom is a water cube
of ``--side`` mm in 5 mm voxels, the beam the Mohan 6 MV spectrum, parallel, ``--field`` mm
square, electrons cut off at 0.189 MeV (the XVMC paper's). Each run is a name and
``key=value`` overrides of :class:`~tetdose.transport.TransportSettings` (numbers parsed).
Printed per run: µs per history, median σ, ε and ε / ε(first run), electron tracks and steps
per history. Ratios measured in one process are what to quote (the machine is shared).
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


def median_sigma(r) -> float:  # noqa: ANN001
    """Median relative standard error over the voxels above 50 % of the maximum."""
    e = r.energy_per_batch_mev / r.histories_per_batch[:, None]
    mean = e.mean(axis=0)
    sd = e.std(axis=0, ddof=1) / np.sqrt(len(e))
    hot = mean > 0.5 * mean.max()
    return float(np.median(sd[hot] / mean[hot]))


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
    base = {"electron_cutoff_mev": 0.189}
    eps0 = None
    for name, kw in parse_runs(args.runs):
        st = TransportSettings(args.histories, BATCHES, args.seed, **{**base, **kw})
        simulate(rho, pl, TransportSettings(BATCHES * 10, BATCHES, 2, **{**base, **kw}),
                 progress=False)  # warm: compile and tables
        c0 = time.process_time()
        r = simulate(rho, pl, st, progress=False)
        t = time.process_time() - c0
        sig = median_sigma(r)
        eps = 1.0 / (sig * sig * t)
        eps0 = eps0 or eps
        rec = r.record()
        print(f"{name:14s} {1e6 * t / args.histories:8.1f} µs/hist  σ {100 * sig:6.2f} %  "
              f"ε {eps:9.3g} /s  ×{eps / eps0:5.2f}  e-tracks/hist "
              f"{rec['electron_tracks'] / args.histories:6.2f}  steps/hist "
              f"{rec['electron_steps'] / args.histories:7.1f}  T {t:6.1f} s", flush=True)


if __name__ == "__main__":
    main()
