"""Documented command chains that must hold end to end: ``import-dose`` → ``export-dose`` (the
import's own unit), and ``dose4d --like --target-uncertainty`` (a structure of the mesh, the
voxel-only runs at the same histories; the region used recorded, a missed target said)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pydicom
import pytest

from tetdose.cli import main
from tetdose.core.image import Image
from tetdose.core.io import write_image
from tetdose.coupling.tally_csv import TetTally, write_tally_csv
from tetdose.motion.phases import PhaseSeries

from helpers import box_mesh, grid_for

PLAN = """[[beam]]
type = "point"
energy_mev = 1.0
position_mm = [12.0, 10.0, -100.0]
direction = [0.0, 0.0, 1.0]
half_angle_deg = 8.0
[regions]
tumour = 1
[prescription]
structure = "tumour"
dose_gy = 2.0
metric = "mean"
"""


@pytest.fixture(scope="module")
def d(tmp_path_factory) -> Path:
    """A water CT (HU 0), two phases of a mesh inside it (region 1 = tumour, 2 = rest), a
    plan prescribing the tumour's mean dose, and two per-tet energy tallies."""
    d = tmp_path_factory.mktemp("chains")
    grid = grid_for([0, 0, 0], [24, 20, 16], [2.0, 2.0, 2.0])
    write_image(d / "ct.nrrd", Image(np.zeros(grid.shape, np.int16), grid))
    mesh = box_mesh([3, 3, 2], [21, 17, 14], (3, 3, 2), jitter=0.2)
    ones = np.ones(mesh.n_points)
    mesh = mesh.with_data(point_data={"density": ones},
                          cell_data={"region": np.where(mesh.centroids_mm[:, 0] < 12, 1, 2)})
    PhaseSeries(mesh, np.stack([mesh.points_mm, mesh.points_mm + [0, 0, 0.5]]),
                density_g_cm3=np.stack([ones, ones])).write(d / "phases")
    (d / "plan.toml").write_text(PLAN)
    rng = np.random.default_rng(0)
    for k in range(2):
        write_tally_csv(d / f"t{k}.csv", TetTally("energy", rng.gamma(2, 1, mesh.n_tets), None))
    return d


def test_import_dose_then_export_dose_writes_a_relative_rt_dose(d, tmp_path, capsys):
    """Issue 27: export-dose refused import-dose's default unit "Gy per source particle"."""
    assert main(["import-dose", "-q", "--phases", str(d / "phases"), "--dose", str(d / "t0.csv"),
                 str(d / "t1.csv"), "-o", str(tmp_path / "imp")]) == 0
    with pytest.warns(UserWarning, match="no reference_ct"):
        assert main(["export-dose", "-q", "--dose", str(tmp_path / "imp" / "accumulated.vtu"),
                     "--like", str(d / "ct.nrrd"), "-o", str(tmp_path / "rd.dcm")]) == 0
    out = capsys.readouterr().out
    assert "Gy per source particle (DoseUnits RELATIVE: not absolute" in out
    rd = pydicom.dcmread(tmp_path / "rd.dcm")
    assert rd.DoseUnits == "RELATIVE" and "per source particle" in rd.SeriesDescription
    assert np.max(rd.pixel_array) > 0


def test_export_dose_refuses_a_unit_it_cannot_write_naming_the_fix(d, tmp_path, capsys):
    assert main(["import-dose", "-q", "--phases", str(d / "phases"), "--dose", str(d / "t0.csv"),
                 str(d / "t1.csv"), "--unit", "cGy", "-o", str(tmp_path / "imp")]) == 0
    code = main(["export-dose", "-q", "--dose", str(tmp_path / "imp" / "accumulated.vtu"),
                 "--like", str(d / "ct.nrrd"), "-o", str(tmp_path / "rd.dcm")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "'cGy'" in err[0] and "import-dose --unit" in err[0] and "Gy per fraction" in err[0]
    assert not (tmp_path / "rd.dcm").exists()


def test_dose4d_like_with_a_target_uncertainty_uses_the_mesh_structure(d, tmp_path):
    """Issue 27: dose4d --like --target-uncertainty failed after the hybrid runs, asking for
    --labels (dose4d has none). The voxel-only runs get their phase's histories; a target
    missed is said on the terminal; the record names the region used (the prescription's)."""
    argv = ["dose4d", "-q", "--phases", str(d / "phases"), "--plan", str(d / "plan.toml"),
            "--like", str(d / "ct.nrrd"), "--physics", "kerma", "--histories", "4000",
            "--batches", "8", "--target-uncertainty", "0.01%", "-o", str(tmp_path / "d4")]
    with pytest.warns(UserWarning, match="target uncertainty 0.01 % of the mean dose in "
                      "'tumour' was not reached") as said:  # the CLI prints warnings as lines
        assert main(argv) == 0
    assert len([w for w in said if "not reached" in str(w.message)]) == 2  # one per phase
    summary = json.loads((tmp_path / "d4" / "summary.json").read_text())
    targets = [p["target"] for p in summary["phases"]]
    assert [t["region"] for t in targets] == ["tumour", "tumour"]
    assert [t["reached"] for t in targets] == [False, False]
    assert [t["histories"] for t in targets] == [4000, 4000]


def test_dose4d_voxel_runs_take_the_histories_their_phase_needed(d):
    from tetdose.core.io import read_ct
    from tetdose.dose.dose4d import run_dose4d
    from tetdose.transport import Plan, TransportSettings

    series = PhaseSeries.read(None, d / "phases")
    st = TransportSettings(4000, 40, 3, physics="kerma", target_uncertainty=0.3)
    result = run_dose4d(series, Plan.from_toml(d / "plan.toml"), st, ct_hu=read_ct(d / "ct.nrrd"))
    hybrid = [r.n_histories for r in result.results]
    assert all(r.extra["target"]["reached"] for r in result.results) and max(hybrid) < 4000
    assert [r.n_histories for r in result.voxel.results] == hybrid


@pytest.mark.filterwarnings("ignore:prescribed mean:UserWarning")  # few histories on purpose
def test_dose4d_dose_to_water_records_the_tracked_ratios_per_phase(d, tmp_path):
    """dose4d --dose-to water: every phase converted per tet from its tracked electron fluence,
    the per-tet ratios in each phase's VTU, the method and fallback count in summary.json."""
    from tetdose.core.io import read_mesh

    assert main(["dose4d", "-q", "--phases", str(d / "phases"), "--plan", str(d / "plan.toml"),
                 "--histories", "300", "--batches", "2", "--electron-cutoff-mev", "0.5",
                 "--dose-to", "water", "-o", str(tmp_path / "d4")]) == 0
    summary = json.loads((tmp_path / "d4" / "summary.json").read_text())
    assert summary["dose_to"] == "water" and "tracked" in summary["dose_to_water"]["method"]
    for phase, vtu in zip(summary["phases"], sorted((tmp_path / "d4").glob("phase_*.vtu")),
                          strict=True):
        rec = phase["dose_to_water"]
        assert 0 <= rec["cells_fallback"] < rec["cells_dosed"]
        s = read_mesh(vtu).cell_data["s_w_m"]
        assert np.all((s > 0.98) & (s < 1.03))  # soft tissue (density 1): 1.00–1.02
