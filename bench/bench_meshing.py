"""Conforming multi-label meshing (MMG level sets): time, tets, checks; mapping error on the real
lung with organ-shaped meshes against the staircase meshes of bench_mapping.py.

    python bench/bench_meshing.py [mesh] [map] [--cases thorax thorax100k lung abdomen20 abdomen]
                                  [--lung-sizes 8 5]

- ``mesh``: the demo thorax (lungs + tumour, the regions that move; and all seven organ
  labels), a ~100 k-tet thorax (lungs 7 mm + tumour 3 mm), the real lung mask (default size and
  8 mm), a 20-label abdomen map (the 20 largest labels of the real TotalSegmentator map) and
  all 31 of its labels — wall and CPU time, tets, worst |volume error| per label, labels over
  the issue's limits, smallest / median dihedral angle, mean surface distance, coincident
  vertices; then the time of each step (distance fields + background + volume shifts, the
  level-set cuts and their number of MMG calls, the final remesh, the sliver pass). The
  machine's load average is printed: on the shared 2-core VM other jobs slow MMG
  (single-threaded) down, so CPU time is the steadier figure.
- ``map``: RMDE/ESD/median/eq. 23 of tetdose.map_density (l2) on the real lung CT, ROI = the
  lung mask on the CT grid, with organ-shaped meshes of the fine mask at ``--lung-sizes`` vs the
  staircase (tetdose.phantoms.mesh_labels on the mask resampled to the CT grid, 5 mm: 162 k tets).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def _summary(name: str, mesh, labels, dt: float, cpu: float) -> None:  # noqa: ANN001
    from tetdose.meshing import mesh_checks

    r = mesh_checks(mesh, labels)
    errs = [abs(e["volume_error_pct"]) for e in r["labels"].values()
            if e["volume_error_pct"] is not None]
    dist = [e["surface_distance_mean_mm"] for e in r["labels"].values()
            if "surface_distance_mean_mm" in e]
    small = sum(1 for e in r["labels"].values() if e["voxel_volume_cm3"] < 20
                and abs(e["volume_error_pct"]) > 3)
    large = sum(1 for e in r["labels"].values() if e["voxel_volume_cm3"] >= 20
                and abs(e["volume_error_pct"]) > 2)
    angles = r["min_dihedral_deg"]
    print(f"{name:<36}{len(r['labels']):>4}{mesh.n_tets:>9}{dt:>8.1f}{cpu:>8.1f}{max(errs):>9.2f}"
          f"{small + large:>6}{angles:>7.1f}{r['median_dihedral_deg']:>7.1f}"
          f"{np.mean(dist):>8.2f}{r['conformity']['coincident_vertices']:>5}", flush=True)
    print(_steps_line(), flush=True)


def _timed(fn):  # noqa: ANN001, ANN202
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


STEPS: dict[str, float] = {}
CUT_CALLS: list[list[int]] = []


def _spy_steps() -> None:
    """Wrap the mesher's steps (module attributes) to add their wall time to STEPS."""
    from tetdose.meshing import mmg

    def wrapped(name: str, key: str):  # noqa: ANN202
        fn = getattr(mmg, name)

        def timed(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            STEPS[key] = STEPS.get(key, 0.0) + time.perf_counter() - t0
            if name == "_next_batch":
                CUT_CALLS.append(out[0])
            return out
        setattr(mmg, name, timed)

    for name, key in (("_prepared", "fields+background+shift"), ("_cut_labels", "cuts"),
                      ("_next_batch", "batching"), ("_remeshed", "remesh+slivers"),
                      ("removed_slivers", "slivers")):
        wrapped(name, key)


def _steps_line() -> str:
    out = "    steps [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in STEPS.items())
    out += f"; {len(CUT_CALLS)} cut calls for {sum(map(len, CUT_CALLS))} labels"
    STEPS.clear()
    CUT_CALLS.clear()
    return out


def abdomen_labels(seg, n: int | None) -> list[int]:  # noqa: ANN001
    """The ``n`` largest labels of the abdomen map (all if None), by voxel count."""
    arr = np.asarray(seg.array)
    labs, counts = np.unique(arr[arr > 0], return_counts=True)
    order = np.argsort(-counts, kind="stable")
    return sorted(int(v) for v in labs[order][:n])


def bench_mesh(cases: list[str]) -> None:
    from tetdose.core.io import read_image
    from tetdose.meshing import conforming_mesh
    from tetdose.phantoms import ORGAN_REGIONS, THORAX_MOVING, make_phantom, organ_mesh

    _spy_steps()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'case':<36}{'lab':>4}{'tets':>9}{'wall s':>8}{'cpu s':>8}{'max|dV|%':>9}{'>lim':>6}"
          f"{'min°':>7}{'med°':>7}{'dist mm':>8}{'dup':>5}")
    p = make_phantom("thorax", seed=0, size="medium")
    all_organs = {lab: (lab,) for lab in (1, 2, 3, 5, 6, 7, 8)} | {3: (3, 4)}
    thorax = []
    if "thorax" in cases:
        thorax += [("demo thorax lungs+tumour (default h)", ORGAN_REGIONS["thorax"], None),
                   ("demo thorax 7 organ labels (default h)", all_organs, None)]
    if "thorax100k" in cases:
        thorax += [("thorax lungs+tumour, 7 mm (~100 k)", THORAX_MOVING, {3: 7.0, 6: 3.0})]
    for name, regions, size in thorax:
        (mesh, dt, cpu) = _timed(lambda r=regions, s=size: organ_mesh(p, r, s))
        merged = np.zeros(p.labels.array.shape, dtype=np.int32)
        for region, labs in regions.items():
            merged[np.isin(p.labels.array, labs)] = region
        _summary(name, mesh, p.labels.with_array(merged), dt, cpu)
    data = SHARED / "data"
    if not data.is_dir():
        print(f"{data} not found: real masks skipped")
        return
    lung = read_image(data / "lung-elastix" / "3DCT_lung_baseline_mask.mha")
    for size in (None, 8.0) if "lung" in cases else ():
        mesh, dt, cpu = _timed(lambda s=size: conforming_mesh(lung, [1], s))
        _summary(f"real lung mask, h {'default' if size is None else f'{size:g} mm'}", mesh, lung,
                 dt, cpu)
    seg = read_image(data / "abdomen-dicom" / "example_seg_dicom.nii.gz")
    for n in [n for case, n in (("abdomen20", 20), ("abdomen", None)) if case in cases]:
        ids = abdomen_labels(seg, n)
        mesh, dt, cpu = _timed(lambda ids=ids: conforming_mesh(seg, ids))
        _summary(f"abdomen map, {len(ids)} labels (default h)", mesh, seg, dt, cpu)


def bench_map(args: argparse.Namespace) -> None:
    sys.path.insert(0, str(ROOT / "tests" / "verification"))
    sys.path.insert(0, str(ROOT / "tests"))
    import test_real_ct as rc  # the test module's loaders: one definition of the real cases

    from tetdose.mapping import map_density
    from tetdose.mapping.metrics import evaluate
    from tetdose.meshing import conforming_mesh
    from tetdose.phantoms import mesh_labels

    ct = rc.read_image(rc.LUNG_CT)
    mask = rc.read_image(rc.LUNG_MASK)
    lab = rc.resample_labels(mask, ct.grid)
    roi = lab.array == 1
    print(f"{'lung mesh':<28}{'tets':>8}{'mesh s':>8}{'RMDE %':>8}{'ESD %':>8}{'median %':>9}"
          f"{'eq.23 %':>8}")

    def row(name: str, mesh, dt: float) -> None:  # noqa: ANN001
        with warnings.catch_warnings():  # the smooth surface pokes < 0.01 % out of the CT
            warnings.simplefilter("ignore")
            dm = map_density(mesh, ct, solver="l2")
        ev = evaluate(ct, dm.mesh, dm.density_g_cm3, roi=roi, overlap=dm.overlap)
        m = ev.metrics
        med = float(np.median(ev.relative_error_pct.array[roi]))
        print(f"{name:<28}{mesh.n_tets:>8}{dt:>8.1f}{m.rmde_pct:>8.1f}{m.esd_pct:>8.1f}"
              f"{med:>9.1f}{m.mass_error_pct:>8.2f}", flush=True)

    if args.staircase:
        mesh, dt, _ = _timed(lambda: mesh_labels(lab, [1], 5.0))
        row("staircase 5 mm", mesh, dt)
    for size in args.lung_sizes:
        mesh, dt, _ = _timed(lambda s=size: conforming_mesh(mask, [1], s))
        row(f"organ-shaped {size:g} mm", mesh, dt)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", nargs="*", choices=("mesh", "map"), default=["mesh", "map"])
    parser.add_argument("--lung-sizes", type=float, nargs="*", default=[8.0, 5.0])
    parser.add_argument("--no-staircase", dest="staircase", action="store_false",
                        help="skip the staircase reference row")
    cases = ("thorax", "thorax100k", "lung", "abdomen20", "abdomen")
    parser.add_argument("--cases", nargs="*", choices=cases, default=list(cases),
                        help="meshing cases")
    args = parser.parse_args()
    if "mesh" in args.what:
        bench_mesh(args.cases)
    if "map" in args.what:
        bench_map(args)


if __name__ == "__main__":
    main()
