"""Where kerma ≠ dose: the field edge, measured (README "Where kerma ≠ dose").

Run: ``NUMBA_CACHE_DIR=... .venv/bin/python bench/bench_kerma_dose.py [HISTORIES]`` (default 2·10⁶).
A 40 × 40 mm² parallel field of 2 MeV photons and one of the Mohan 6 MV spectrum on water; the
lateral profile at 45–55 mm depth (1 mm voxels across the edge, the central 8 mm along the other
axis), dose with electrons (0.01 MeV cut-offs) and collision kerma, same seeds. Prints the
80 %–20 % penumbra width of each (linear interpolation between voxel centres, both edges
averaged) and the dose 3 mm outside the geometric edge relative to the centre; writes
``bench/out/kerma_dose_edge.png``. The build-up and lung figures are ``bench/bench_dose.py
buildup``'s.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from tetdose.core.image import Image, ImageGrid
from tetdose.plan.spectra import named_spectrum
from tetdose.transport import PhotonSource, Plan, TransportSettings, simulate

FIELD_MM = 40.0


def _plan(quality: str) -> Plan:
    if quality == "2MeV":
        energies, weights = [2.0], [1.0]
    else:
        energies, weights = named_spectrum(quality)
    return Plan((PhotonSource("parallel", (0.0, 0.0, -5.0), (0, 0, 1), energies_mev=energies,
                              line_weights=weights, field_mm=(FIELD_MM, FIELD_MM)),),
                materials={1: "water"})


def profile(quality: str, physics: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(x [mm] of voxel centres, dose per history across the field at 45–55 mm depth)."""
    spacing = np.array([1.0, 8.0, 10.0])
    grid = ImageGrid([-39.5, -8.0, 5.0], spacing, np.eye(3), (80, 3, 10))
    r = simulate(Image(np.ones(grid.shape), grid), _plan(quality),
                 TransportSettings(n, 10, 5, physics=physics, electron_cutoff_mev=0.01),
                 labels=Image(np.ones(grid.shape, np.int32), grid), progress=False)
    dose = r.dose_gy.reshape(grid.shape)[4:6, 1, :].mean(axis=0)
    return grid.origin_mm[0] + spacing[0] * np.arange(grid.size[0]), dose


def penumbra_mm(x: np.ndarray, d: np.ndarray) -> float:
    """80 %–20 % width [mm] of the normalised profile, mean of both edges."""
    centre = d[np.abs(x) < FIELD_MM / 4].mean()
    widths = []
    for xs, ds in ((x[x > 0], d[x > 0] / centre), (-x[x < 0][::-1], d[x < 0][::-1] / centre)):
        falling = ds[::-1], xs[::-1]  # increasing dose for np.interp
        widths.append(np.interp(0.2, *falling) - np.interp(0.8, *falling))
    return float(np.mean(widths))


def main() -> None:
    n = int(float(sys.argv[1])) if len(sys.argv) > 1 else 2_000_000
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
    for ax, quality in zip(axes, ("2MeV", "6MV"), strict=True):
        for physics, style in (("dose", "-"), ("kerma", "--")):
            x, d = profile(quality, physics, n)
            centre = d[np.abs(x) < FIELD_MM / 4].mean()
            outside = np.interp(FIELD_MM / 2 + 3.0, x, d) / centre
            print(f"{quality} {physics:5s}: 80-20 % penumbra {penumbra_mm(x, d):.2f} mm, "
                  f"3 mm outside the edge {100 * outside:.1f} % of the centre")
            ax.plot(x, d / centre, style, label=physics)
        ax.set_title(f"{quality}, {FIELD_MM:g} mm field, 45–55 mm depth", fontsize=9)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("relative to the centre")
        ax.legend()
    out = Path(__file__).parent / "out"
    out.mkdir(exist_ok=True)
    fig.savefig(out / "kerma_dose_edge.png", dpi=100)
    print(f"figure: {out / 'kerma_dose_edge.png'}")


if __name__ == "__main__":
    main()
