"""Clinical precision in clinical time (issue 30): the XVMC benchmark case on voxels, ompmc and tets.

The case of Kawrakow & Fippel (Phys. Med. Biol. 45 (2000) 2163, "Investigation of variance
reduction techniques for Monte Carlo photon dose calculation using XVMC"): a 6 MV beam (Mohan's
spectrum, tetdose's ``"6MV"``), parallel 100 × 100 mm² field, a 300 mm water cube in 5 mm voxels
(60³), electron cut-off 0.189 MeV kinetic (EGS's AE = 0.700 MeV), photon cut-off 0.01 MeV, one
thread. Run::

    NUMBA_CACHE_DIR=.numba-cache .venv/bin/python bench/bench_precision.py \\
        [--histories 1e6] [--ompmc-histories 1e5] [--tet-histories 1e6] [--no-ompmc] [--no-mesh] \\
        [--setting key=value ...] [--repeats K]

``--setting`` pairs go to :class:`~tetdose.transport.run.settings.TransportSettings` as given
(Python literals: ``--setting photon_splitting=20 --setting quasi_random=True``), for tetdose's
voxel and tet runs; ``--compare key=value`` runs the voxels a second time with those settings
added (another seed) and prints the gain in efficiency (same process, same region) and how the
two doses agree: their ratio summed over the region, the mean and sd of the per-voxel
z = ΔD/σ (0 and 1 if the change does not move the dose).

For each engine it prints the median relative σ over the scoring region, the CPU time T of the
run (``time.process_time``, one thread, the kernels compiled by a warm-up run first), its fixed
part T₀ (the same run with 100 histories: world build, tables, pilot — 0.65 s for the 215 622
tets, 0.06 s for the voxels), the efficiency ε = 1/(σ²(T − T₀)) and the time to a median 1 % σ,
T₀ + (T − T₀)·(σ/1 %)² (σ ∝ 1/√N; the fixed part is paid once, however long the run). The
region is the voxels whose dose, smoothed by a 3 × 3 × 3 box (so that
noise does not pick it), exceeds 50 % of the smoothed maximum, taken from tetdose's voxel run and
used for every engine (tets: those whose centroid lies in a region voxel). ompmc (EGSnrc physics,
``700icru``: the same 0.189 MeV cut-off, photon splitting 20; :mod:`tetdose.coupling.ompmc`, the
same source particles) runs on the same voxels in the same process; the ratio is ompmc's time
to 1 % over tetdose's.

The tet mesh: the same cube cut into cubes of edge 5·6^(1/3) mm (33³ cubes, 6 Kuhn tets each,
215 622 tets), so a tet has the mean mass of a voxel (125 mm³ of water); its time to a median 1 %
per-tet σ over the ratio to the voxels'. With the mesh also the vertex dose
(:func:`tetdose.dose.vertex.vertex_dose`): median σ over the region's vertices and its variance
gain over the per-tet dose.

Timings on the shared 2-core VM are noisy: the ratios printed are of runs in one process.
"""

from __future__ import annotations

import argparse
import ast
import os
import time

import numba
import numpy as np
from scipy import ndimage

from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.plan.model import Plan
from tetdose.plan.photon_source import PhotonSource
from tetdose.plan.spectra import named_spectrum
from tetdose.transport import simulate
from tetdose.transport.run.settings import TransportSettings

#: The XVMC case: cube edge, voxel edge [mm], field [mm], cut-offs [MeV].
CUBE_MM, VOXEL_MM, FIELD_MM = 300.0, 5.0, 100.0
ELECTRON_CUTOFF_MEV, PHOTON_CUTOFF_MEV = 0.189, 0.01
#: Cubes per side of the tet mesh: 6 tets per cube of edge 300/33 ≈ 9.09 mm ≈ 5·6^(1/3) mm.
MESH_CUBES = 33
OMPMC_SPLIT = 20
#: Histories of the run that measures a run's fixed cost (world build, tables, pilot).
FIXED_HISTORIES = 100


def water_cube() -> Image:
    n = int(round(CUBE_MM / VOXEL_MM))
    half = CUBE_MM / 2
    grid = ImageGrid([-half + VOXEL_MM / 2, -half + VOXEL_MM / 2, VOXEL_MM / 2],
                     [VOXEL_MM] * 3, np.eye(3), (n, n, n))
    return Image(np.ones(grid.shape), grid)


def cube_mesh(cubes: int = MESH_CUBES) -> TetMesh:
    """The water cube as ``cubes``³ cubes of 6 Kuhn tets (density 1 g/cm³ on the vertices)."""
    half = CUBE_MM / 2
    ax = np.linspace(-half, half, cubes + 1)
    az = np.linspace(0.0, CUBE_MM, cubes + 1)
    z, y, x = np.meshgrid(az, ax, ax, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    k, j, i = np.meshgrid(*(np.arange(cubes),) * 3, indexing="ij")
    base = ((k * (cubes + 1) + j) * (cubes + 1) + i).ravel()
    off = np.array([((c >> 2) & 1) * (cubes + 1) ** 2 + ((c >> 1) & 1) * (cubes + 1) + (c & 1)
                    for c in range(8)])
    kuhn = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7],
                     [0, 4, 6, 7]])
    tets = (base[:, None, None] + off[kuhn][None]).reshape(-1, 4)
    mesh = TetMesh(pts, tets).with_fixed_orientation()
    return mesh.with_data(point_data={"density": np.ones(len(pts))})


def plan() -> Plan:
    energies, weights = named_spectrum("6MV")
    src = PhotonSource("parallel", [0.0, 0.0, -10.0], [0, 0, 1], energies_mev=energies,
                       line_weights=weights, field_mm=[FIELD_MM, FIELD_MM])
    return Plan((src,))


def parse_settings(pairs: list[str]) -> dict[str, object]:
    out: dict[str, object] = {}
    for pair in pairs:
        key, _, text = pair.partition("=")
        try:
            out[key.strip()] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            out[key.strip()] = text
    return out


def settings(n: int, extra: dict[str, object], seed: int = 1) -> TransportSettings:
    kw = {"energy_cutoff_mev": PHOTON_CUTOFF_MEV, "electron_cutoff_mev": ELECTRON_CUTOFF_MEV,
          **extra}
    return TransportSettings(int(n), 10, seed, **kw)


def region(dose: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Voxels whose 3×3×3-smoothed dose exceeds 50 % of the smoothed maximum (flat mask)."""
    smooth = ndimage.uniform_filter(dose.reshape(shape), size=3, mode="nearest")
    return (smooth > 0.5 * smooth.max()).ravel()


def figures(name: str, rel: np.ndarray, cpu_s: float, n: int, fixed_s: float = 0.0
            ) -> dict[str, float]:
    """Print and return the run's figures. ``fixed_s``: the part of ``cpu_s`` a run pays once
    whatever its histories (world build, tables, pilot; a run of :data:`FIXED_HISTORIES`), so
    T(1 %) = fixed + (T − fixed)·(σ/1 %)² and ε = 1/(σ²(T − fixed))."""
    sigma = float(np.median(rel))
    transport = max(cpu_s - fixed_s, 1e-9)
    eff = 1.0 / (sigma**2 * transport)
    t1 = time_to_1pc(sigma, cpu_s, fixed_s)
    print(f"{name:<34} N {n:9.3g}  median σ {100 * sigma:6.2f} %  CPU {cpu_s:8.1f} s (fixed "
          f"{fixed_s:4.1f} s)  ε {eff:9.4g} /s  T(1 %) {t1:9.0f} s = {t1 / 60:6.1f} min",
          flush=True)
    return {"sigma": sigma, "cpu_s": cpu_s, "eff": eff, "t1": t1}


def time_to_1pc(sigma: float, cpu_s: float, fixed_s: float) -> float:
    """T(1 %) = fixed + (T − fixed)·(σ/1 %)² [s] (:func:`figures`)."""
    return fixed_s + max(cpu_s - fixed_s, 1e-9) * (sigma / 0.01) ** 2


def timed(fn, *args, **kw):  # noqa: ANN001, ANN002, ANN003, ANN201
    t0 = time.process_time()
    out = fn(*args, **kw)
    return out, time.process_time() - t0


def rel_sigma(dose: np.ndarray, std: np.ndarray, mask: np.ndarray) -> np.ndarray:
    d = dose[mask]
    return np.where(d > 0, std[mask] / np.where(d > 0, d, 1.0), np.inf)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--histories", type=float, default=1e6, help="tetdose voxels")
    ap.add_argument("--tet-histories", type=float, default=None, help="default: --histories")
    ap.add_argument("--ompmc-histories", type=float, default=1e5)
    ap.add_argument("--no-ompmc", action="store_true")
    ap.add_argument("--no-mesh", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=1,
                    help="with the mesh: time K pairs of voxel and tet runs, alternating, and "
                         "print the median tets / voxels ratio (this VM's speed drifts)")
    ap.add_argument("--setting", action="append", default=[], metavar="KEY=VALUE",
                    help="a TransportSettings field for tetdose's runs (repeatable)")
    ap.add_argument("--compare", action="append", default=[], metavar="KEY=VALUE",
                    help="run the voxels again with these settings added (KEY=VALUE;KEY=VALUE); "
                         "print the gain")
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    extra = parse_settings(args.setting)
    rho, pl = water_cube(), plan()
    print(f"XVMC case: 6 MV parallel {FIELD_MM:g}² mm², {CUBE_MM:g} mm water in {VOXEL_MM:g} mm "
          f"voxels, e⁻ cut-off {ELECTRON_CUTOFF_MEV} MeV; {numba.get_num_threads()} thread(s); "
          f"settings {extra or 'defaults'}; load {os.getloadavg()[0]:.1f} on {os.cpu_count()} "
          "cores", flush=True)
    t0 = time.perf_counter()
    simulate(rho, pl, settings(2000, extra), progress=False)  # compile / load the kernels
    print(f"warm-up (compile/load) {time.perf_counter() - t0:.0f} s", flush=True)
    n = int(args.histories)
    vox, cpu = timed(simulate, rho, pl, settings(n, extra), progress=False)
    fixed = timed(simulate, rho, pl, settings(FIXED_HISTORIES, extra), progress=False)[1]
    mask = region(vox.dose_gy, rho.grid.shape)
    print(f"region: {mask.sum()} voxels > 50 % of the smoothed D_max", flush=True)
    f_vox = figures("tetdose voxels", rel_sigma(vox.dose_gy, vox.dose_std_gy, mask), cpu, n,
                    fixed)
    for pair in args.compare:
        alt = {**extra, **parse_settings(pair.split(";"))}
        res, cpu2 = timed(simulate, rho, pl, settings(n, alt, seed=2), progress=False)
        f = figures(f"tetdose voxels {pair}", rel_sigma(res.dose_gy, res.dose_std_gy, mask),
                    cpu2, n, fixed)
        print(f"  gain in ε with {pair}: {f['eff'] / f_vox['eff']:.2f}×  (σ² ratio "
              f"{(f_vox['sigma'] / f['sigma']) ** 2:.2f}×, time ratio {cpu2 / cpu:.2f})")
        z = (res.dose_gy - vox.dose_gy)[mask] / np.hypot(res.dose_std_gy, vox.dose_std_gy)[mask]
        print(f"  dose with {pair} / without, summed over the region: "
              f"{res.dose_gy[mask].sum() / vox.dose_gy[mask].sum():.4f}; per voxel z = ΔD/σ: "
              f"mean {z.mean():+.3f}, sd {z.std():.3f} (independent seeds)")
    if not args.no_ompmc:
        run_ompmc(rho, pl, int(args.ompmc_histories), mask, f_vox, args.threads)
    if not args.no_mesh:
        n_t = int(args.tet_histories or n)
        mesh, f_tet, fixed_t = run_mesh(rho, pl, n_t, mask, f_vox, extra)
        pairs = [(cpu, f_tet["cpu_s"])]
        for _ in range(args.repeats - 1):
            pairs.append((timed(simulate, rho, pl, settings(n, extra), progress=False)[1],
                          timed(simulate, mesh, pl, settings(n_t, extra), progress=False)[1]))
        if len(pairs) > 1:
            ratios = [time_to_1pc(f_tet["sigma"], t, fixed_t) / time_to_1pc(f_vox["sigma"], v, fixed)
                      for v, t in pairs]
            print(f"  tets / voxels time to 1 %, {len(pairs)} alternating pairs: median "
                  f"{np.median(ratios):.2f} (" + ", ".join(f"{r:.2f}" for r in ratios) + "); CPU "
                  "[s] voxels / tets: " + ", ".join(f"{v:.1f} / {t:.1f}" for v, t in pairs))


def run_ompmc(rho: Image, pl: Plan, n: int, mask: np.ndarray, f_vox: dict[str, float],
              threads: int) -> None:
    from tetdose.coupling.ompmc import OmpmcOptions, simulate_ompmc

    opts = OmpmcOptions(pegs="700icru", electron_cutoff_mev=ELECTRON_CUTOFF_MEV,
                        n_split=OMPMC_SPLIT, threads=threads)
    st = TransportSettings(n, 10, 1, energy_cutoff_mev=PHOTON_CUTOFF_MEV)
    res, cpu = timed(simulate_ompmc, rho, pl, st, progress=False, options=opts)
    fixed = timed(simulate_ompmc, rho, pl, TransportSettings(FIXED_HISTORIES, 10, 1,
                                                             energy_cutoff_mev=PHOTON_CUTOFF_MEV),
                  progress=False, options=opts)[1]
    f = figures(f"ompmc voxels (split {OMPMC_SPLIT})", rel_sigma(res.dose_gy, res.dose_std_gy, mask),
                cpu, n, fixed)
    print(f"  ompmc / tetdose time to 1 %: {f['t1'] / f_vox['t1']:.2f}  (tetdose "
          f"{f['t1'] / f_vox['t1']:.2f}× faster; issue target ≥ 20×)", flush=True)


def run_mesh(rho: Image, pl: Plan, n: int, mask: np.ndarray, f_vox: dict[str, float],
             extra: dict[str, object]) -> tuple[TetMesh, dict[str, float], float]:
    """The tet cube's run and its vertex dose: (mesh, figures, fixed CPU [s])."""
    from tetdose.dose.vertex import vertex_dose

    mesh = cube_mesh()
    simulate(mesh, pl, settings(2000, extra), progress=False)
    res, cpu = timed(simulate, mesh, pl, settings(n, extra), progress=False)
    fixed = timed(simulate, mesh, pl, settings(FIXED_HISTORIES, extra), progress=False)[1]
    in_tet = mask[rho.grid.voxel_of(mesh.centroids_mm)]
    print(f"tet mesh: {mesh.n_tets} tets, median mass {np.median(res.mass_g) * 1e3:.1f} mg "
          f"(voxel {VOXEL_MM ** 3 / 1000 * 1e3:.1f} mg); {in_tet.sum()} tets in the region")
    f = figures("tetdose tets", rel_sigma(res.dose_gy, res.dose_std_gy, in_tet), cpu, n, fixed)
    print(f"  tets / voxels time to 1 %: {f['t1'] / f_vox['t1']:.2f}  (issue target ≤ 1.5)")
    (d_v, s_v), cpu_v = timed(vertex_dose, mesh, res)
    vmask = np.zeros(mesh.n_points, bool)
    vmask[np.unique(mesh.tets[in_tet])] = True
    p = mesh.points_mm
    vmask &= np.all(np.abs(p[:, :2]) < CUBE_MM / 2, axis=1) & (p[:, 2] > 0) & (p[:, 2] < CUBE_MM)
    fv = figures("tetdose vertex dose (interior)", rel_sigma(d_v, s_v, vmask), cpu + cpu_v, n,
                 fixed + cpu_v)
    print(f"  vertex dose: projection {cpu_v:.2f} s; variance gain over per-tet σ² "
          f"{(f['sigma'] / fv['sigma']) ** 2:.2f}×")
    return mesh, f, fixed


if __name__ == "__main__":
    main()
