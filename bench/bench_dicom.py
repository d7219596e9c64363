"""Benchmark: DICOM CT series writing (512×512×120, slices/s) and RT Dose writing.

Run: ``python bench/bench_dicom.py [--slices 120]``. A small warm-up write comes first (imports,
pydicom's first-use costs), then the timed writes into a temporary folder.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from tetdose.core.image import Image, ImageGrid
from tetdose.dicom import write_ct_series, write_rt_dose


def synthetic(nx: int, ny: int, nz: int, lo: float, hi: float) -> Image:
    grid = ImageGrid((-250.0, -250.0, -300.0), (0.977, 0.977, 2.0), np.eye(3), (nx, ny, nz))
    values = np.random.default_rng(0).uniform(lo, hi, grid.shape)
    return Image(values, grid)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--slices", type=int, default=120)
    parser.add_argument("--size", type=int, default=512)
    args = parser.parse_args()
    n, nz = args.size, args.slices
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        t0 = time.perf_counter()
        write_ct_series(synthetic(32, 32, 4, -1000, 2000), out / "warmup")
        print(f"warm-up (4 slices 32×32): {time.perf_counter() - t0:.3f} s")

        ct = synthetic(n, n, nz, -1000, 2000)
        t0 = time.perf_counter()
        files = write_ct_series(ct, out / "ct")
        dt = time.perf_counter() - t0
        mb = sum(f.stat().st_size for f in files) / 1e6
        print(f"CT series {n}×{n}×{nz}: {dt:.2f} s, {nz / dt:.0f} slices/s, {mb / dt:.0f} MB/s")

        dose = synthetic(n // 2, n // 2, nz, 0.0, 60.0)
        for bits in (16, 32):
            t0 = time.perf_counter()
            write_rt_dose(dose, out / f"rd{bits}.dcm", frame_of_reference_uid="1.2.3", bits=bits)
            dt = time.perf_counter() - t0
            print(f"RT Dose {n // 2}×{n // 2}×{nz}, {bits}-bit: {dt:.2f} s")


if __name__ == "__main__":
    main()
