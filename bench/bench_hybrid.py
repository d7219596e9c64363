"""Hybrid transport speed: an organ mesh inside a clinical-size CT vs the CT's voxels alone.

Run: ``NUMBA_CACHE_DIR=... .venv/bin/python bench/bench_hybrid.py [HISTORIES] [EDGE_MM] [SLICES]``
(defaults 200 000, 5.5, 100). The thorax phantom's lungs, vessels and tumour are meshed as one
conforming mesh (``EDGE_MM`` sets its size: 7 mm gives 49 k tets, 5.5 mm ≈ 100 k); its CT is resampled
(trilinear) onto a 512 × 512 × SLICES grid over the phantom (0.78 × 0.59 × 2.4 mm for 100
slices), the size of a clinical thorax CT. A 6 × 6 cm² 1.25 MeV parallel field crosses the
right lung and the tumour from the front. Printed, all in one process, 1 numba thread, best CPU
time of several runs:

* world build time (overlaps of the mesh with the CT, per-voxel boundary-triangle lists) and the
  lists' memory;
* time per history, hybrid vs voxels alone on the same CT (the issue's target: ≤ 1.5×), and the
  mesh alone in vacuum for reference;
* the share of the hybrid's time in each mode, from its tet crossings and voxel steps priced at
  the per-crossing and per-step cost of the mesh-alone and voxel-alone runs;
* mesh ↔ voxel switches per history and lost photons.
"""

from __future__ import annotations

import sys
import time

import numba
import numpy as np
import SimpleITK as sitk

from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image
from tetdose.mapping import map_density
from tetdose.phantoms import make_phantom, mesh_labels
from tetdose.transport import PhotonSource, Plan, TransportSettings, World, simulate
from tetdose.transport.run.job import build_job

MOVING = ("lung", "vessels", "tumour")


def clinical_ct(ct: Image, slices: int) -> Image:
    """``ct`` resampled (trilinear, HU) onto 512 × 512 × ``slices`` voxels over its extent."""
    lo, hi = ct.grid.bounds_grid_frame()
    size = np.array([512, 512, slices])
    spacing = (hi - lo) / size
    origin = ct.grid.index_to_physical(np.zeros((1, 3)))[0] - 0.5 * ct.grid.spacing_mm \
        + 0.5 * spacing
    ref = sitk.Image([int(s) for s in size], sitk.sitkFloat32)
    ref.SetSpacing(spacing.tolist())
    ref.SetOrigin(origin.tolist())
    ref.SetDirection(ct.grid.direction.ravel().tolist())
    src = sitk.Cast(ct.to_sitk(), sitk.sitkFloat32)
    out = sitk.Resample(src, ref, sitk.Transform(), sitk.sitkLinear, -1000.0)
    return Image.from_sitk(out)


def best_cpu(world, plan, settings, repeat=3):  # noqa: ANN001, ANN201
    runs = [simulate(world, plan, settings, progress=False) for _ in range(repeat)]
    return min(runs, key=lambda r: r.extra["cpu_s"])


def main(n_hist: int, edge_mm: float, slices: int) -> None:
    numba.set_num_threads(1)
    ph = make_phantom("thorax", seed=1, size="medium")
    label_of = {name: label for label, name in ph.label_names.items()}
    t0 = time.perf_counter()
    mesh = mesh_labels(ph.labels, [label_of[n] for n in MOVING], edge_mm)
    ct = clinical_ct(ph.ct, slices)
    mapped = map_density(mesh, ct).mesh
    print(f"organ mesh {mesh.n_tets} tets ({', '.join(MOVING)}), CT {ct.grid.size} "
          f"({ct.grid.spacing_mm.round(2).tolist()} mm), mapped in {time.perf_counter() - t0:.0f} s")
    density = ct.with_array(HUCalibration.schneider2000().density(ct.array).astype(np.float64))
    tumour = mesh.centroids_mm[mesh.region == label_of["tumour"]].mean(axis=0)
    plan = Plan((PhotonSource("parallel", tumour - [0, 300.0, 0], [0, 1, 0], energies_mev=[1.25],
                              field_mm=[60.0, 60.0], field_x_direction=[1, 0, 0]),))
    # 2 batches: the 26 M-voxel tally rows (8 B per voxel and batch, zeroed and summed per run)
    # would otherwise dominate the time of runs this short; they cost voxels and hybrid alike.
    settings = TransportSettings(n_hist, 2, 1, physics="kerma")
    hybrid = World(mesh=mapped, density=density)
    t0 = time.perf_counter()
    job, _ = build_job(hybrid, plan, settings)
    build_s = time.perf_counter() - t0
    g = job.geom
    lists_mb = (g.tri_start.nbytes + g.tri_items.nbytes) / 2**20
    voxels_mb = (g.vox.density.nbytes + g.vox.material.nbytes) / 2**20
    print(f"world build {build_s:.1f} s; boundary faces {len(g.tet.bnd_tet)}, triangle lists "
          f"over {int(np.prod(g.tri_n))} voxels of the mesh's box: {len(g.tri_items)} entries, "
          f"{lists_mb:.1f} MiB (voxel arrays {voxels_mb:.0f} MiB)")
    for world in (hybrid, World(density=density), World(mesh=mapped)):  # compile / load
        simulate(world, plan, TransportSettings(20, 2, physics="kerma"), progress=False)
    res = {name: best_cpu(w, plan, settings) for name, w in
           (("hybrid", hybrid), ("voxels", World(density=density)), ("mesh", World(mesh=mapped)))}
    per = {k: r.extra["cpu_s"] / n_hist * 1e6 for k, r in res.items()}
    for k, r in res.items():
        c = r.record()
        print(f"  {k:6s}: {per[k]:6.2f} µs/history (1 core), {c['tet_crossings'] / n_hist:6.1f} "
              f"crossings and {c['voxel_steps'] / n_hist:6.1f} voxel steps per history, "
              f"{c['mesh_voxel_switches'] / n_hist:5.2f} switches/history, "
              f"{c['lost_photons']} lost, {c['relocations']} relocations")
    print(f"  hybrid / voxels time per history: {per['hybrid'] / per['voxels']:.2f}× "
          f"(target ≤ 1.5×)")
    h, v, m = (res[k].record() for k in ("hybrid", "voxels", "mesh"))
    per_step = res["voxels"].extra["cpu_s"] / max(v["voxel_steps"], 1)
    per_cross = res["mesh"].extra["cpu_s"] / max(m["tet_crossings"], 1)
    t_mesh, t_vox = h["tet_crossings"] * per_cross, h["voxel_steps"] * per_step
    total = res["hybrid"].extra["cpu_s"]
    print(f"  hybrid time share (priced by the single-mode runs, physics included): mesh "
          f"{100 * t_mesh / total:.0f} %, voxels {100 * t_vox / total:.0f} %, rest "
          f"(switches, triangle tests) {100 * (1 - (t_mesh + t_vox) / total):.0f} %")


if __name__ == "__main__":
    args = sys.argv[1:]
    main(int(float(args[0])) if args else 200_000, float(args[1]) if len(args) > 1 else 5.5,
         int(args[2]) if len(args) > 2 else 100)
