"""Doses back in (issue 21 part 3): .3ddose read exactly from a file written here by its
documented layout, per-tet tally CSVs, voxel dose onto the tets by energy and back, and the
accumulation over phases equal to the per-phase energy over the mesh mass."""

from __future__ import annotations

import numpy as np
import pytest

from tetdose._constants import J_PER_MEV
from tetdose.core.image import Image
from tetdose.core.mass import tet_mass_g
from tetdose.core.overlap import compute_overlap
from tetdose.coupling.import_dose import import_doses, phase_dose
from tetdose.coupling.tally_csv import TetTally, read_tally_csv, write_tally_csv
from tetdose.coupling.threeddose import read_3ddose, write_3ddose
from tetdose.errors import DoseError, GeometryMismatchError, ImageError, OptionError
from tetdose.motion.phases import PhaseSeries

from helpers import box_mesh, grid_for


def _write_3ddose_by_hand(path, bx, by, bz, dose, unc):
    """DOSXYZnrc manual layout: counts; x, y, z boundaries [cm]; doses; relative errors; x
    fastest. Blocks deliberately broken over lines of 5 numbers, as DOSXYZnrc does."""
    def block(values):
        vals = [repr(float(v)) for v in values]
        return "\n".join(" ".join(vals[i:i + 5]) for i in range(0, len(vals), 5))
    nx, ny, nz = len(bx) - 1, len(by) - 1, len(bz) - 1
    flat_d = [dose[i, j, k] for k in range(nz) for j in range(ny) for i in range(nx)]
    flat_u = [unc[i, j, k] for k in range(nz) for j in range(ny) for i in range(nx)]
    path.write_text(f"  {nx}  {ny}  {nz}\n" + "\n".join(block(b) for b in (bx, by, bz, flat_d,
                                                                             flat_u)) + "\n")


def test_3ddose_written_by_its_documented_layout_reads_back_exactly(tmp_path):
    rng = np.random.default_rng(1)
    bx, by, bz = np.linspace(-3, 3, 7), np.linspace(-1, 1.5, 6), np.linspace(10, 12.4, 4)
    dose = rng.gamma(2.0, 1e-15, (6, 5, 3))  # indexed [i, j, k] like the manual
    unc = rng.uniform(0.001, 0.2, dose.shape)
    _write_3ddose_by_hand(tmp_path / "a.3ddose", bx, by, bz, dose, unc)
    d, u = read_3ddose(tmp_path / "a.3ddose")
    assert d.grid.size == (6, 5, 3) and d.array.shape == (3, 5, 6)
    for i, j, k in np.ndindex(6, 5, 3):
        assert d.array[k, j, i] == dose[i, j, k] and u.array[k, j, i] == unc[i, j, k]
    np.testing.assert_allclose(d.grid.spacing_mm, [10.0, 5.0, 8.0], rtol=1e-12)
    np.testing.assert_allclose(d.grid.origin_mm, [-25.0, -7.5, 104.0], rtol=1e-12)
    write_3ddose(tmp_path / "b.3ddose", d, u)  # and our writer's output by the same layout
    d2, u2 = read_3ddose(tmp_path / "b.3ddose")
    np.testing.assert_allclose(d2.array, d.array, rtol=1e-9)
    np.testing.assert_allclose(u2.array, u.array, rtol=1e-9)
    tokens = (tmp_path / "b.3ddose").read_text().split()
    assert tokens[:3] == ["6", "5", "3"] and float(tokens[3]) == pytest.approx(-3.0)


def test_3ddose_refuses_non_uniform_and_truncated_files(tmp_path):
    d = np.ones((2, 2, 2))
    _write_3ddose_by_hand(tmp_path / "n.3ddose", [0, 1, 3], [0, 1, 2], [0, 1, 2], d, d)
    with pytest.raises(ImageError, match="equal"):
        read_3ddose(tmp_path / "n.3ddose")
    text = (tmp_path / "n.3ddose").read_text().split()
    (tmp_path / "t.3ddose").write_text(" ".join(text[:-3]))
    with pytest.raises(ImageError, match="truncated"):
        read_3ddose(tmp_path / "t.3ddose")


def test_tally_csv_bases_relative_errors_and_count_check(tmp_path):
    (tmp_path / "a.csv").write_text("# MCNP elemental edit\nelement,energy_mev,rel_err\n"
                                    "2,4.0,0.5\n1,2.0,0.1\n3,0,0\n")
    t = read_tally_csv(tmp_path / "a.csv", 3)
    assert t.kind == "energy"
    np.testing.assert_allclose(t.value, [2.0, 4.0, 0.0])
    np.testing.assert_allclose(t.sigma, [0.2, 2.0, 0.0])
    write_tally_csv(tmp_path / "b.csv", TetTally("dose", t.value, t.sigma))
    back = read_tally_csv(tmp_path / "b.csv", 3)
    assert back.kind == "dose" and np.array_equal(back.value, t.value)
    with pytest.raises(DoseError, match="holds 3 tets, the mesh has 4"):
        read_tally_csv(tmp_path / "a.csv", 4)
    (tmp_path / "c.csv").write_text("tet,dose_gy\n0,1\n0,2\n-1,3\n")
    with pytest.raises(DoseError, match="every tet once"):
        read_tally_csv(tmp_path / "c.csv", 3)


@pytest.fixture(scope="module")
def phase_mesh():
    m = box_mesh([-9, -7, -5], [9, 7, 5], (5, 4, 3), jitter=0.2, seed=5)
    x, y, z = m.points_mm.T
    return m.with_data(point_data={"density": 0.9 + 0.01 * x + 0.005 * y * z / 5})


def _box_overlap_mm3(grid, lo, hi):
    """Vol(voxel ∩ box) [mm³] per flat voxel id, analytically (axis-aligned grid and box)."""
    edges = [grid.origin_mm[a] + (np.arange(grid.size[a] + 1) - 0.5) * grid.spacing_mm[a]
             for a in range(3)]
    lens = [np.clip(np.minimum(e[1:], hi[a]) - np.maximum(e[:-1], lo[a]), 0, None)
            for a, e in enumerate(edges)]
    return np.einsum("k,j,i->kji", lens[2], lens[1], lens[0]).ravel()


def test_voxel_dose_on_tets_and_back_conserves_energy(phase_mesh, tmp_path):
    """Voxels → tets → voxels: the voxel energy inside the mesh, Σ_v D_v ρ_v Vol(v ∩ mesh)
    (the box's volume analytically), is what the tets receive and what goes back."""
    grid = grid_for([-12, -10, -8], [12, 10, 8], [2.0, 2.5, 2.0])
    rng = np.random.default_rng(4)
    dose = Image(rng.gamma(3.0, 1.0, grid.shape), grid)
    rel = dose.with_array(rng.uniform(0.01, 0.05, grid.shape))
    rho = Image(rng.uniform(0.2, 1.5, grid.shape), grid)
    write_3ddose(tmp_path / "p.3ddose", dose, rel)
    pd = phase_dose(tmp_path / "p.3ddose", phase_mesh, density=rho)
    rho_v = rho.array.ravel()
    e_in_mesh = float(np.sum(dose.array.ravel() * rho_v * _box_overlap_mm3(grid, *phase_mesh
                                                                           .bounds_mm())))
    ov = compute_overlap(phase_mesh, grid)
    w = ov.volume_mm3 * rho_v[ov.voxel]  # ρ_v Vol(v ∩ k), pair by pair
    m_vox_k = np.bincount(ov.tet, weights=w, minlength=phase_mesh.n_tets)
    assert float(np.dot(pd.dose_gy, m_vox_k)) == pytest.approx(e_in_mesh, rel=1e-12)
    back = np.bincount(ov.voxel, weights=pd.dose_gy[ov.tet] * w, minlength=grid.n_voxels)
    assert float(back.sum()) == pytest.approx(e_in_mesh, rel=1e-12)
    assert pd.dose_std_gy is not None and np.all(pd.dose_std_gy > 0)
    assert np.all(pd.dose_std_gy <= pd.dose_gy.max() * 0.05)  # averaging only shrinks σ
    write_3ddose(tmp_path / "u.3ddose", dose.with_array(np.full(grid.shape, 2.5)))
    np.testing.assert_allclose(phase_dose(tmp_path / "u.3ddose", phase_mesh).dose_gy, 2.5,
                               rtol=1e-12)  # default density: the mesh voxelized
    small = grid_for([-8, -10, -8], [12, 10, 8], [2.0, 2.5, 2.0])
    write_3ddose(tmp_path / "s.3ddose", Image(np.ones(small.shape), small))
    with pytest.raises(GeometryMismatchError, match="does not cover the mesh"):
        phase_dose(tmp_path / "s.3ddose", phase_mesh)


def test_accumulated_dose_is_the_phase_energy_over_the_mesh_mass(phase_mesh, tmp_path):
    shifts = np.array([[0, 0, 0], [0.5, -1.0, 2.0], [1.0, 0.3, -1.5]])
    pts = phase_mesh.points_mm[None] + shifts[:, None, :]
    rho = np.repeat(phase_mesh.point_data["density"][None], 3, axis=0)
    series = PhaseSeries(phase_mesh, pts, time_weight=[0.5, 0.3, 0.2], density_g_cm3=rho)
    rng = np.random.default_rng(7)
    energy = rng.gamma(2.0, 1.0, (3, phase_mesh.n_tets))  # MeV per tet and phase
    files = []
    for k in range(3):
        files.append(write_tally_csv(tmp_path / f"t{k}.csv", TetTally("energy", energy[k],
                                                                      0.1 * energy[k])))
    res = import_doses(series, files)
    w = np.array([0.5, 0.3, 0.2])
    m = np.stack([tet_mass_g(series.mesh(k)) for k in range(3)]) / 1000.0  # kg
    want = (w[:, None] * energy * J_PER_MEV).sum(0) / (w[:, None] * m).sum(0)
    np.testing.assert_allclose(res.accumulated.dose_gy, want, rtol=1e-9)
    want_std = np.sqrt(((w[:, None] * 0.1 * energy * J_PER_MEV) ** 2).sum(0)) / (
        w[:, None] * m).sum(0)
    np.testing.assert_allclose(res.accumulated.dose_std_gy, want_std, rtol=1e-9)


def test_doses_pair_with_phases_by_the_numbers_in_their_names(phase_mesh, tmp_path):
    """Issue 27: ``phase_002.csv phase_000.csv phase_001.csv`` was paired by argument order
    (per-phase doses ×3.03, ×0.50, ×0.67); the names say the phase."""
    pts = phase_mesh.points_mm[None] + np.array([[0, 0, 0], [0.5, 0, 0], [1.0, 0, 0]])[:, None]
    rho = np.repeat(phase_mesh.point_data["density"][None], 3, axis=0)
    series = PhaseSeries(phase_mesh, pts, density_g_cm3=rho)
    energy = [np.full(phase_mesh.n_tets, e) for e in (1.0, 2.0, 3.0)]  # MeV per tet, phase k
    files = [write_tally_csv(tmp_path / f"phase_{k:03d}.csv", TetTally("energy", energy[k], None))
             for k in range(3)]
    res = import_doses(series, [files[2], files[0], files[1]])
    assert [p.source for p in res.phases] == [str(f) for f in files]
    for k in range(3):  # phase k got its own energy: dose = E / m per tet
        want = energy[k] * J_PER_MEV / (tet_mass_g(series.mesh(k)) / 1000.0)
        np.testing.assert_allclose(res.phases[k].dose_gy, want, rtol=1e-12)
    by_pct = [write_tally_csv(tmp_path / f"d_{p}%.csv", TetTally("energy", energy[k], None))
              for k, p in enumerate(("0", "33.3", "66.7"))]  # percentages in the names
    res = import_doses(series, by_pct[::-1])
    assert [p.source for p in res.phases] == [str(f) for f in by_pct]
    bad = {"carries no phase number": [files[0], files[1], tmp_path / "other.csv"],
           "both name phase 1": [files[0], files[1], files[1]],
           "neither the phases' percentages": [files[0], files[1], tmp_path / "phase_007.csv"]}
    for message, given in bad.items():
        with pytest.raises(OptionError, match=message):
            import_doses(series, given)


def test_phase_percents_must_be_distinct_and_in_the_cycle(phase_mesh):
    """Two phases at one percent wrote one phase_PPP.P output over the other."""
    from tetdose.errors import MeshError

    pts = np.repeat(phase_mesh.points_mm[None], 2, axis=0)
    with pytest.raises(MeshError, match="two phases at one percent"):
        PhaseSeries(phase_mesh, pts, phase_percent=[0.0, 0.0])
    with pytest.raises(MeshError, match=r"must lie in \[0, 100\)"):
        PhaseSeries(phase_mesh, pts, phase_percent=[0.0, 100.0])


def test_import_dose_density_in_hu_is_refused(phase_mesh, tmp_path, capsys):
    from tetdose.cli import main
    from tetdose.core.io import write_image

    pts = phase_mesh.points_mm[None]
    series = PhaseSeries(phase_mesh, pts, density_g_cm3=phase_mesh.point_data["density"][None])
    series.write(tmp_path / "phases")
    grid = grid_for([-12, -10, -8], [12, 10, 8], [2.0, 2.0, 2.0])
    write_3ddose(tmp_path / "p.3ddose", Image(np.ones(grid.shape), grid))
    write_image(tmp_path / "ct.nrrd", Image(np.full(grid.shape, 40.0), grid))  # HU, not g/cm³
    code = main(["import-dose", "--phases", str(tmp_path / "phases"), "--dose",
                 str(tmp_path / "p.3ddose"), "--density", str(tmp_path / "ct.nrrd"), "-o",
                 str(tmp_path / "out")])
    assert code == 2 and "denser than any material: a CT in HU?" in capsys.readouterr().err
