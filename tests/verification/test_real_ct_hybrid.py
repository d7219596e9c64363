"""The real-patient study on the real thorax CT in ../shared/data, through the CLI as a user runs
it: the lung (the part that moves) meshed from its mask, the rest of the body CT voxels.

``tetdose mesh`` (organ-shaped, MMG) → ``map`` → ``deform --breathing`` → ``dose4d --like CT``
(every phase in the hybrid world, the voxel-only reference on the same body) → ``compare``.
Checked: no photon lost, the ledger closes, the organ mesh's dose agrees with the voxel
engine's inside the mesh at matched resolution on the static phase, the combined accumulated
dose covers the body, and ``compare`` names the region it evaluated. ``slow``: run by ``make validate``.
"""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest
from test_real_ct import LUNG_CT, LUNG_MASK, _need, resample_labels

from tetdose.cli import main
from tetdose.compare.gamma import gamma_index
from tetdose.core.image import Image
from tetdose.core.io import read_image, read_mesh, write_image
from tetdose.core.overlap import compute_overlap
from tetdose.core.transfer import grid_dose_to_mesh, mesh_dose_to_grid

pytestmark = pytest.mark.slow

BEAM = textwrap.dedent("""
    [[beam]]
    type = "linac"
    spectrum = "6MV"
    isocenter = "lung"
    gantry_deg = {g}
    jaws_mm = [-40.0, 40.0, -40.0, 40.0]
""")


def test_real_thorax_lung_mesh_inside_the_ct(tmp_path):
    _need(LUNG_CT, LUNG_MASK)
    ct = read_image(LUNG_CT)
    mask = resample_labels(read_image(LUNG_MASK), ct.grid)
    labels = Image((np.asarray(mask.array) > 0).astype(np.uint8), ct.grid)
    write_image(tmp_path / "labels.nrrd", labels)
    (tmp_path / "plan.toml").write_text(
        "[regions]\nlung = 1\n" + "".join(BEAM.format(g=g) for g in (0.0, 120.0, 240.0)))
    run = [["mesh", "--labels", str(tmp_path / "labels.nrrd"), "--label", "1",
            "-o", str(tmp_path / "lung.vtu")],
           ["map", "--ct", str(LUNG_CT), "--mesh", str(tmp_path / "lung.vtu"),
            "-o", str(tmp_path / "mapped.vtu")],
           ["deform", "--mesh", str(tmp_path / "mapped.vtu"), "--breathing", "--n-phases", "3",
            "-o", str(tmp_path / "phases")],
           ["dose4d", "--physics", "kerma",
            "--phases", str(tmp_path / "phases"), "--plan", str(tmp_path / "plan.toml"),
            "--like", str(LUNG_CT), "--histories", "1e5", "-o", str(tmp_path / "d4")],
           ["compare", "--mesh-dose", str(tmp_path / "d4" / "accumulated.vtu"), "--voxel-dose",
            str(tmp_path / "d4" / "voxel" / "accumulated_energy_mass_transfer.nrrd"),
            "-o", str(tmp_path / "cmp")]]
    for argv in run:
        assert main([*argv, "-q"]) == 0, argv
    summary = json.loads((tmp_path / "d4" / "summary.json").read_text())
    assert summary["world"] == "hybrid"
    for ph in summary["phases"]:
        led = ph["ledger"]
        assert ph["lost_photons"] == 0 and ph["mesh_voxel_switches"] > 0
        rest = led["deposited_mev"] + led["escaped_mev"] + led["cutoff_mev"] + led["lost_mev"]
        assert rest == pytest.approx(led["source_mev"], rel=1e-9)
    # static phase at matched resolution: the voxel engine's dose seen on the mesh's tets
    phase0 = read_mesh(tmp_path / "d4" / "phase_000.0.vtu")
    vox0 = read_image(tmp_path / "d4" / "voxel" / "phase_000.0_dose.nrrd")
    ov = compute_overlap(phase0, ct.grid)
    mesh_img = mesh_dose_to_grid(phase0, phase0.cell_data["dose"], ct.grid, overlap=ov)
    vox_seen = mesh_dose_to_grid(phase0, grid_dose_to_mesh(phase0, vox0, overlap=ov), ct.grid,
                                 overlap=ov)
    inside = (ov.covered_volume_per_voxel_mm3() >= 0.5 * ct.grid.voxel_volume_mm3
              ).reshape(ct.grid.shape)
    g = gamma_index(vox_seen, mesh_img, dose_percent=3.0, dta_mm=3.0, mask=inside)
    print(f"real thorax, static phase, matched resolution inside the lung mesh: gamma 3%/3mm "
          f"{g.summary()['pass_rate_percent']:.1f} %")
    assert g.summary()["pass_rate_percent"] > 90.0
    combined = read_image(tmp_path / "d4" / "body" / "accumulated_combined.nrrd")
    body = np.asarray(ct.array) > -400
    assert combined.grid.same_as(ct.grid) and np.count_nonzero(combined.array[body]) > 0.5 * \
        np.count_nonzero(read_image(tmp_path / "d4" / "voxel" /
                                    "accumulated_energy_mass_transfer.nrrd").array[body])
    cmp = json.loads((tmp_path / "cmp" / "summary.json").read_text())
    assert cmp["region"]["voxels"] > 1000
