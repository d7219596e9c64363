"""``tetdose export-phases`` and ``tetdose import-dose`` from the command line: outputs checked,
``tetdose compare`` reads the import, and bad input is one line, exit 2, nothing written
(the pattern of test_cli_errors.py)."""

from __future__ import annotations

import json
from pathlib import Path

import meshio
import numpy as np
import pytest

from tetdose.cli import main
from tetdose.core.icrp145 import read_icrp145
from tetdose.core.image import Image
from tetdose.core.io import write_image
from tetdose.core.mass import tet_mass_g
from tetdose.coupling.tally_csv import TetTally, write_tally_csv
from tetdose.coupling.threeddose import write_3ddose
from tetdose.motion.phases import PhaseSeries

from helpers import box_mesh, grid_for


@pytest.fixture(scope="module")
def d(tmp_path_factory) -> Path:
    """Two phases (rigid shift, same densities), tallies, voxel doses and bad variants."""
    d = tmp_path_factory.mktemp("coupling")
    m = box_mesh([-8, -6, -4], [8, 6, 4], (4, 3, 2), jitter=0.2, seed=2)
    rho = 0.3 + 0.06 * (m.points_mm[:, 0] + 8)
    pts = m.points_mm[None] + np.array([[0, 0, 0], [0, 0, 1.5]])[:, None, :]
    series = PhaseSeries(m, pts, density_g_cm3=np.stack([rho, rho]))
    series.write(d / "phases")
    rng = np.random.default_rng(0)
    for k in range(2):
        write_tally_csv(d / f"t{k}.csv", TetTally("energy", rng.gamma(2, 1, m.n_tets), None))
        write_tally_csv(d / f"g{k}.csv", TetTally("dose", rng.gamma(2, 1, m.n_tets), None))
    write_tally_csv(d / "short.csv", TetTally("energy", np.ones(m.n_tets - 1), None))
    grid = grid_for([-10, -8, -6], [10, 8, 8], [2.0, 2.0, 2.0])
    for k in range(2):
        write_3ddose(d / f"v{k}.3ddose", Image(rng.gamma(2, 1, grid.shape), grid))
    small = grid_for([-4, -8, -6], [10, 8, 8], [2.0, 2.0, 2.0])
    write_3ddose(d / "small.3ddose", Image(np.ones(small.shape), small))
    write_image(d / "v0.nrrd", Image(np.ones(grid.shape), grid))
    write_image(d / "ct.nrrd", Image(np.full(grid.shape, 40, np.int16), grid))  # HU
    (d / "dose.xyz").write_text("1 2 3\n")
    (d / "folder").mkdir()
    for k in range(2):
        (d / "folder" / f"phase_{k}.csv").write_bytes((d / f"t{k}.csv").read_bytes())
    return d


def _run(argv, d, o):
    return main([a.format(d=d, o=o) for a in argv])


def test_export_tetgen_and_abaqus_write_every_phase(d, tmp_path, capsys):
    assert _run(["export-phases", "-q", "--phases", "{d}/phases", "--format", "tetgen", "-o",
                 "{o}/tg"], d, tmp_path) == 0
    out = capsys.readouterr().out
    assert "mass error" in out
    rec = json.loads((tmp_path / "tg" / "export.json").read_text())
    assert [p["files"] for p in rec["phases"]] == [
        [f"phase_{p:05.1f}.{s}" for s in ("node", "ele", "material")] for p in (0.0, 50.0)]
    assert all(p["mass_error"] <= 1e-3 for p in rec["phases"])
    mm = meshio.read(tmp_path / "tg" / "phase_050.0.node")
    ref = PhaseSeries.read(None, d / "phases")
    np.testing.assert_allclose(mm.points * 10.0, ref.points_mm[1], atol=1e-8)
    with pytest.warns(UserWarning, match="6 density bins leave a mass error"):
        assert _run(["export-phases", "-q", "--phases", "{d}/phases", "--format", "abaqus",
                     "--density-bins", "6", "-o", "{o}/ab"], d, tmp_path) == 0
    assert sorted(p.name for p in (tmp_path / "ab").glob("[!.]*")) == [
        "export.json", "phase_000.0.inp", "phase_000.0.material", "phase_050.0.inp",
        "phase_050.0.material"]
    assert len(meshio.read(tmp_path / "ab" / "phase_000.0.inp").cells_dict["tetra"]) == \
        ref.reference.n_tets
    # doses [Gy] a code scored on the exported (binned) phases: energy = dose × binned mass
    for fmt in ("tg", "ab"):
        assert _run(["import-dose", "-q", "--phases", "{d}/phases", "--dose", "{d}/g0.csv",
                     "{d}/g1.csv", "--exported", f"{{o}}/{fmt}", "-o", f"{{o}}/imp_{fmt}"],
                    d, tmp_path) == 0
    binned = [tet_mass_g(read_icrp145(tmp_path / "tg" / f"phase_{p:05.1f}.node")[0])
              for p in (0.0, 50.0)]
    dose = [np.loadtxt(d / f"g{k}.csv", delimiter=",", skiprows=1)[:, 1] for k in range(2)]
    mass = [tet_mass_g(ref.mesh(k)) for k in range(2)]
    want = (dose[0] * binned[0] + dose[1] * binned[1]) / (mass[0] + mass[1])
    got = meshio.read(tmp_path / "imp_tg" / "accumulated.vtu").cell_data["dose"][0]
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert not np.allclose(got, (dose[0] * mass[0] + dose[1] * mass[1]) / (mass[0] + mass[1]))
    # the export's phases are matched to the series by percent, not by their order in the record
    from tetdose.coupling.export import exported_densities
    from tetdose.errors import MeshError

    before = exported_densities(tmp_path / "tg", ref.reference.n_tets, ref.phase_percent)
    rec_path = tmp_path / "tg" / "export.json"
    rec = json.loads(rec_path.read_text())
    rec["phases"].reverse()
    rec_path.write_text(json.dumps(rec))
    after = exported_densities(tmp_path / "tg", ref.reference.n_tets, ref.phase_percent)
    assert all(np.array_equal(a, b) for a, b in zip(before, after, strict=True))
    with pytest.raises(MeshError, match=r"exports phases at \[50.0, 0.0\] %, the phases are at"):
        exported_densities(tmp_path / "tg", ref.reference.n_tets, [0.0, 25.0])


def test_import_tallies_accumulates_and_compare_reads_it(d, tmp_path, capsys):
    assert _run(["import-dose", "-q", "--phases", "{d}/phases", "--dose", "{d}/folder", "-o",
                 "{o}/imp"], d, tmp_path) == 0
    acc = meshio.read(tmp_path / "imp" / "accumulated.vtu")
    ref = PhaseSeries.read(None, d / "phases")
    mass = np.stack([tet_mass_g(ref.mesh(k)) for k in range(2)])
    e = np.stack([np.loadtxt(d / f"t{k}.csv", delimiter=",", skiprows=1)[:, 1] for k in range(2)])
    want = (e * 1.602176634e-13).sum(0) / (mass.sum(0) / 1000.0)
    np.testing.assert_allclose(acc.cell_data["dose"][0], want, rtol=1e-9)
    summary = json.loads((tmp_path / "imp" / "summary.json").read_text())
    assert summary["units"]["dose"] == "Gy per source particle"
    assert (tmp_path / "imp" / "phase_050.0.vtu").exists()
    assert _run(["import-dose", "-q", "--phases", "{d}/phases", "--dose", "{d}/v0.3ddose",
                 "{d}/v1.3ddose", "-o", "{o}/vox"], d, tmp_path) == 0
    voxel = tmp_path / "vox" / "voxel"
    assert (voxel / "accumulated_direct_mapping.nrrd").exists()
    assert _run(["import-dose", "-q", "--phases", "{d}/phases", "--dose", "{d}/v0.3ddose",
                 "{d}/v1.3ddose", "--ct", "{d}/ct.nrrd", "{d}/ct.nrrd", "-o", "{o}/vct"],
                d, tmp_path) == 0  # the phases' CTs as the voxel densities
    with_ct = meshio.read(tmp_path / "vct" / "accumulated.vtu").cell_data["dose"][0]
    default = meshio.read(tmp_path / "vox" / "accumulated.vtu").cell_data["dose"][0]
    assert np.all(np.isfinite(with_ct)) and not np.allclose(with_ct, default)
    assert _run(["compare", "-q", "--mesh-dose", "{o}/vox", "--voxel-dose",
                 str(voxel / "accumulated_energy_mass_transfer.nrrd"), "-o", "{o}/cmp"],
                d, tmp_path) == 0
    assert (tmp_path / "cmp" / "report.html").exists()


IMPORT = ["import-dose", "-q", "--phases", "{d}/phases", "--dose", "{d}/t0.csv", "{d}/t1.csv",
          "-o", "{o}/imp"]
CASES = [
    ("dose-grid-not-covering", IMPORT[:5] + ["{d}/v0.3ddose", "{d}/small.3ddose"] + IMPORT[7:],
     ["does not cover the mesh"]),
    ("tally-count-differs", IMPORT[:5] + ["{d}/t0.csv", "{d}/short.csv"] + IMPORT[7:],
     ["holds 143 tets", "the mesh has 144"]),
    ("phase-count-mismatch", IMPORT[:5] + ["{d}/t0.csv"] + IMPORT[7:],
     ["1 dose files for 2 phases"]),
    ("unknown-format", IMPORT[:5] + ["{d}/t0.csv", "{d}/dose.xyz"] + IMPORT[7:],
     ["unknown dose format"]),
    ("density-count-mismatch", IMPORT[:-2] + ["--density", "{d}/v0.nrrd", "-o", "{o}/imp"],
     ["1 density images for 2 phases"]),
    ("export-unknown-format", ["export-phases", "-q", "--phases", "{d}/phases", "--format", "vtk",
                               "-o", "{o}/x"], ["invalid choice"]),
    ("export-too-few-bins", ["export-phases", "-q", "--phases", "{d}/phases", "--format",
                             "tetgen", "--density-bins", "1", "-o", "{o}/x"],
     ["composition classes"]),
]


def _state(folder: Path) -> list[tuple[str, int, int]]:
    """(name, size, mtime) of every file below ``folder``: an input changed shows here."""
    return sorted((str(p.relative_to(folder)), p.stat().st_size, p.stat().st_mtime_ns)
                  for p in folder.rglob("*") if p.is_file())


@pytest.mark.parametrize(("argv", "words"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_writes_nothing(d, tmp_path, capsys, argv, words):
    """As test_cli_errors.py: exit 2, one line naming the problem, no output, inputs untouched."""
    out = tmp_path / "out"
    out.mkdir()
    inputs = _state(d)
    code = _run(argv, d, out)
    err = [ln for ln in capsys.readouterr().err.splitlines()
           if ln.strip() and ": warning:" not in ln]
    assert (code, len(err)) == (2, 1), err
    assert err[0].startswith(f"tetdose {argv[0]}: error: ") and "Traceback" not in err[0]
    assert all(word in err[0] for word in words), (words, err[0])
    assert not any(out.iterdir()), "an output was written"
    assert _state(d) == inputs, "an input was changed"
