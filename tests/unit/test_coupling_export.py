"""Phases out (issue 21 part 2): density binning within its mass bound, and the TetGen/ICRP-145
and Abaqus files read back by meshio and by independent readers written here from the formats'
documentation (TetGen's fformats pages, the ICRP-145 material layout Geant4's TETModelImport
parses, MCNP 6.3 manual §8.7 for the Abaqus input)."""

from __future__ import annotations

import re

import meshio
import numpy as np
import pytest

from tetdose.core.icrp145 import read_icrp145
from tetdose.core.io import read_mesh
from tetdose.core.mass import tet_mass_g
from tetdose.coupling.abaqus import read_abaqus, write_abaqus
from tetdose.coupling.binning import bin_densities
from tetdose.coupling.export import conforming_geometry
from tetdose.coupling.tetgen import write_tetgen
from tetdose.errors import OptionError
from tetdose.transport.physics.materials import MATERIALS, material_for_density

from helpers import box_mesh


@pytest.fixture(scope="module")
def mesh():
    """A jittered box whose density spans lung, fat, soft tissue and bone, smooth in space."""
    m = box_mesh([-30, -20, -10], [30, 20, 10], (9, 6, 4), jitter=0.25, seed=3)
    x, y, z = m.points_mm.T
    rho = 0.26 + 0.9 * (x + 30) / 60 + 0.25 * np.sin(y / 7) ** 2 + 0.01 * z
    return m.with_data(point_data={"density": rho})


def _binned_error(m, b):
    """ε and Δ recomputed from the material table (independent of BinnedPhase's properties)."""
    exact = m.volumes_mm3 * m.point_data["density"][m.tets].mean(axis=1) / 1000.0
    rho = {mat.id: mat.density_g_cm3 for mat in b.materials}
    binned = m.volumes_mm3 * np.array([rho[i] for i in b.material_id]) / 1000.0
    return np.abs(binned - exact).sum() / exact.sum(), (binned.sum() - exact.sum()) / exact.sum()


def test_default_binning_keeps_the_mass_within_a_tenth_of_a_percent(mesh):
    b = bin_densities(mesh)
    eps, delta = _binned_error(mesh, b)
    assert eps <= 1e-3 and abs(delta) <= 1e-6, (eps, delta)
    np.testing.assert_allclose([b.mass_error, b.total_mass_change], [eps, delta], atol=1e-12)
    np.testing.assert_allclose(b.mass_g, tet_mass_g(mesh), rtol=1e-15)
    fewer = bin_densities(mesh, n_bins=len(b.materials) - 1)
    assert _binned_error(mesh, fewer)[0] > 1e-3 * (1 - 1e-6)  # the default is the fewest


def test_bins_are_capped_error_falls_with_more_and_classes_are_kept(mesh):
    errors = []
    for n in (5, 8, 16, 64):
        b = bin_densities(mesh, n_bins=n)
        assert len(b.materials) <= n
        errors.append(_binned_error(mesh, b)[0])
        mean_rho = mesh.point_data["density"][mesh.tets].mean(axis=1)
        cls = np.array(["air", "lung", "adipose", "soft_tissue", "cortical_bone"])[
            material_for_density(mean_rho)]
        comp = {m.id: m.composition for m in b.materials}
        assert [comp[i] for i in b.material_id] == cls.tolist()
    assert errors == sorted(errors, reverse=True) and errors[-1] < errors[0] / 10
    with pytest.raises(OptionError, match="composition"):
        bin_densities(mesh, n_bins=2)


def test_distinct_densities_get_exact_bins_and_regions_take_plan_materials():
    """Tets of 3 distinct densities in one class: 3 bins are exact, 1 bin keeps the total."""
    m = box_mesh([0, 0, 0], [6, 2, 2], (3, 1, 1))
    m = type(m)(m.points_mm, m.tets, (m.centroids_mm[:, 0] // 2).astype(int)).split_by_region()
    rho = np.array([1.00, 1.02, 1.05])[m.region]
    m = m.with_data(point_data={"density": np.zeros(m.n_points)})
    m.point_data["density"][m.tets.ravel()] = np.repeat(rho, 4)
    exact = bin_densities(m, n_bins=3)
    assert len(exact.materials) == 3 and exact.mass_error < 1e-15
    assert sorted(mat.density_g_cm3 for mat in exact.materials) == [1.0, 1.02, 1.05]
    one = bin_densities(m, n_bins=1)
    assert one.materials[0].density_g_cm3 == pytest.approx(rho.mean(), rel=5e-8)  # equal volumes
    assert abs(one.total_mass_change) < 5e-8
    plan = bin_densities(m, region_materials={1: "muscle"})
    comp = {mat.id: mat.composition for mat in plan.materials}
    assert [comp[i] for i in plan.material_id] == [
        "muscle" if r == 1 else "soft_tissue" for r in m.region]


# --- independent readers, from the formats' documentation -------------------------------------

def _tetgen_reader(stem):
    """TetGen: '<n> <dim> <attrs> <markers>' then '<id> x y z', '<n> <4> <attrs>' then
    '<id> a b c d [attr]' ('#' comments); the material file as Geant4 reads it."""
    def rows(path):
        return [ln.split("#")[0].split() for ln in open(path) if ln.split("#")[0].strip()]
    node, ele = rows(f"{stem}.node"), rows(f"{stem}.ele")
    n = int(node[0][0])
    assert node[0][1:] == ["3", "0", "0"]
    pts = np.array([[float(v) for v in r[1:4]] for r in node[1:n + 1]])
    ids = [int(r[0]) for r in node[1:n + 1]]
    m = int(ele[0][0])
    assert ele[0][1:] == ["4", "1"]
    tets = np.array([[int(v) for v in r[1:5]] for r in ele[1:m + 1]]) - ids[0]
    mat = np.array([int(r[5]) for r in ele[1:m + 1]])
    materials = _geant4_material_read(open(f"{stem}.material").read())
    return pts, tets, mat, materials, ids


def _geant4_material_read(text):
    """Geant4's TETModelImport::MaterialRead, token by token (ICRP145_HumanPhantoms): read
    'C', name, density, 'g/cm3', 'mID'; then (ZAID, -fraction) pairs until a token 'C' (which it
    consumes) or the end of the file; repeat while not at the end."""
    tokens, pos, eof = text.split(), 0, False

    def read():
        nonlocal pos, eof
        if pos >= len(tokens):
            eof = True
            return ""
        pos += 1
        return tokens[pos - 1]

    materials = {}
    while not eof:
        read()
        name, rho = read(), float(read())
        read()
        mid = int(read().lstrip("m"))
        fractions = {}
        while True:
            t = read()
            if t == "C" or eof:
                break
            fractions[int(t) // 1000] = -float(read())
        materials[mid] = (name, rho, fractions)
    return materials


def test_tetgen_files_read_back_by_meshio_and_an_independent_reader(mesh, tmp_path):
    b = bin_densities(mesh)
    paths = write_tetgen(tmp_path / "ph", mesh.points_mm, mesh.tets, b.material_id, b.materials)
    assert [p.name for p in paths] == ["ph.node", "ph.ele", "ph.material"]
    pts, tets, mat, materials, ids = _tetgen_reader(tmp_path / "ph")
    assert ids[0] == 0  # Geant4 indexes its vertex vector with the node ids directly
    np.testing.assert_allclose(pts * 10.0, mesh.points_mm, rtol=1e-9, atol=1e-9)  # cm
    np.testing.assert_array_equal(tets, mesh.tets)
    np.testing.assert_array_equal(mat, b.material_id)
    assert sorted(materials) == [m.id for m in b.materials]
    for m in b.materials:
        name, rho, fr = materials[m.id]
        assert name == m.name and rho == m.density_g_cm3
        want = dict(zip(MATERIALS[m.composition].elements.tolist(),
                        MATERIALS[m.composition].weights, strict=True))
        assert fr.keys() == want.keys()
        np.testing.assert_allclose(list(fr.values()), list(want.values()), atol=5e-7)
    mm = meshio.read(tmp_path / "ph.node")
    np.testing.assert_allclose(mm.points * 10.0, mesh.points_mm, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(mm.cells_dict["tetra"], mesh.tets)
    np.testing.assert_array_equal(mm.cell_data["tetgen:ref"][0], b.material_id)


def test_icrp145_phantom_reads_as_a_mesh_with_the_binned_masses(mesh, tmp_path):
    b = bin_densities(mesh)
    write_tetgen(tmp_path / "ph", mesh.points_mm, mesh.tets, b.material_id, b.materials)
    for path in (tmp_path / "ph.node", tmp_path / "ph.ele"):
        read, materials = read_icrp145(path)
        assert read.n_tets == mesh.n_tets and len(materials) == len(b.materials)
        np.testing.assert_array_equal(read.region, b.material_id)
        np.testing.assert_allclose(tet_mass_g(read), b.binned_mass_g, rtol=1e-9)
        via_io = read_mesh(path)  # the read_mesh dispatch: cm → mm, densities per material
        np.testing.assert_allclose(tet_mass_g(via_io), b.binned_mass_g, rtol=1e-9)
        np.testing.assert_allclose(via_io.volumes_mm3.sum(), mesh.volumes_mm3.sum(), rtol=1e-9)
    points, tets = conforming_geometry(read)  # its region copies join again for an export
    np.testing.assert_allclose(points, mesh.points_mm, rtol=1e-11, atol=1e-11)
    np.testing.assert_array_equal(tets, mesh.tets)


def _abaqus_reader(path):
    """MCNP 6.3 §8.7.2: keyword lines '*KEY, p=v', data lines of comma-separated items."""
    blocks, lines = [], open(path).read().splitlines()
    for ln in lines:
        assert len(ln) <= 256
        if ln.startswith("**"):
            continue
        if ln.startswith("*"):
            key, *par = [s.strip() for s in ln[1:].split(",")]
            blocks.append((key.lower(), dict(p.split("=") for p in par), []))
        else:
            blocks[-1][2].append([s.strip() for s in ln.split(",") if s.strip()])
    return blocks


def test_abaqus_file_meets_the_mcnp_rules_and_reads_back(mesh, tmp_path):
    b = bin_densities(mesh, n_bins=12)
    write_abaqus(tmp_path / "ph.inp", mesh.points_mm, mesh.tets, b.material_id, b.materials)
    blocks = _abaqus_reader(tmp_path / "ph.inp")
    keys = [k for k, _, _ in blocks]
    assert keys[:4] == ["heading", "part", "node", "element"]
    assert keys.index("end part") < keys.index("assembly") < keys.index("instance") < \
        keys.index("end instance") < keys.index("end assembly") < keys.index("material")
    nodes = np.array([[float(v) for v in r] for r in blocks[2][2]])
    assert blocks[3][1] == {"type": "C3D4"}
    elems = np.array([[int(v) for v in r] for r in blocks[3][2]])
    np.testing.assert_array_equal(nodes[:, 0], np.arange(1, mesh.n_points + 1))
    np.testing.assert_allclose(nodes[:, 1:] * 10.0, mesh.points_mm, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(elems[:, 1:] - 1, mesh.tets)
    seen = np.zeros(mesh.n_tets, dtype=int)
    names = {}
    for key, par, data in blocks:
        if key == "elset":
            name = par["elset"]
            number = re.fullmatch(r".*material.*[_-]statistic[_-](\d+)", name)
            assert number, name
            ids = np.array([int(v) for r in data for v in r])
            assert all(len(r) <= 16 for r in data)
            assert np.all(b.material_id[ids - 1] == int(number.group(1)))
            seen[ids - 1] += 1
        if key == "material":
            names[int(re.search(r"[_-](\d+)$", par["name"]).group(1))] = par["name"]
            assert not re.search("material|statistic|tally|source", par["name"], re.I)
    assert np.all(seen == 1)  # every element in exactly one material (and statistic) set
    dens = {int(re.search(r"(\d+)$", blocks[i - 1][1]["name"]).group(1)): float(d[2][0][0])
            for i, d in enumerate(blocks) if d[0] == "density"}
    assert dens == {m.id: m.density_g_cm3 for m in b.materials}
    assert sorted(names) == [m.id for m in b.materials]
    mm = meshio.read(tmp_path / "ph.inp")
    np.testing.assert_allclose(mm.points * 10.0, mesh.points_mm, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(mm.cells_dict["tetra"], mesh.tets)
    for m in b.materials:
        sets = np.concatenate(mm.cell_sets[f"Set-material_statistic_{m.id}"])
        np.testing.assert_array_equal(np.sort(sets), np.flatnonzero(b.material_id == m.id))
    pts, tets, mat, rho = read_abaqus(tmp_path / "ph.inp")
    np.testing.assert_array_equal(tets, mesh.tets)
    np.testing.assert_array_equal(mat, b.material_id)
    assert rho == dens


def test_a_plan_composition_is_written_in_the_material_cards(tmp_path):
    """[materials.NAME] of the plan: its region's tets are binned under it and the .material
    file's m card holds its mass fractions (read back as ICRP-145 phantoms are)."""
    from tetdose.core.composition import material_from_symbols
    from tetdose.core.icrp145 import read_material_file
    from tetdose.errors import PlanError

    m = box_mesh([0, 0, 0], [6, 2, 2], (3, 1, 1))
    m = type(m)(m.points_mm, m.tets, (m.centroids_mm[:, 0] // 2).astype(int)).split_by_region()
    m = m.with_data(point_data={"density": np.full(m.n_points, 1.85)})
    bone = material_from_symbols("my_bone", {"H": 0.047234, "C": 0.14433, "N": 0.04199,
                                             "O": 0.446096, "Mg": 0.0022, "P": 0.10497,
                                             "S": 0.00315, "Ca": 0.20993, "Zn": 0.0001}, 1.85, "t")
    with pytest.raises(PlanError, match=r"define it as \[materials.my_bone\]"):
        bin_densities(m, region_materials={2: "my_bone"})
    b = bin_densities(m, region_materials={2: "my_bone"}, compositions={"my_bone": bone})
    assert {mat.composition for mat in b.materials} == {"my_bone", "cortical_bone"}
    paths = write_tetgen(tmp_path / "p", m.points_mm, m.tets, b.material_id, b.materials,
                         {**MATERIALS, "my_bone": bone})
    cards = read_material_file(paths[2])
    mine = next(c for c in cards.values() if c.name.startswith("my_bone"))
    assert dict(mine.mass_fractions)[20] == pytest.approx(0.20993, abs=1e-6)
    assert dict(mine.mass_fractions)[30] == pytest.approx(0.0001, abs=1e-6)


def test_icrp145_phantom_keeps_its_own_compositions(mesh, tmp_path):
    """The m cards of a phantom's .material file become plan compositions by material id."""
    from tetdose.core.icrp145 import phantom_compositions
    from tetdose.plan.model import Plan
    from tetdose.transport import PhotonSource
    from tetdose.transport.run.job import plan_media

    b = bin_densities(mesh)
    write_tetgen(tmp_path / "ph", mesh.points_mm, mesh.tets, b.material_id, b.materials)
    ids, comps = phantom_compositions(tmp_path / "ph.node")
    assert sorted(ids) == sorted(m.id for m in b.materials)
    for m in b.materials:
        mine = comps[ids[m.id]]
        assert mine.density_g_cm3 == m.density_g_cm3
        np.testing.assert_allclose(mine.weights, MATERIALS[m.composition].weights, atol=1e-6)
    plan = Plan((PhotonSource("point", [0.0, 0.0, 0.0], [0, 0, 1], energies_mev=np.ones(1),
                              line_weights=np.ones(1)),), materials=ids, compositions=comps)
    assert plan_media([ids[b.materials[0].id]], plan)[0] is comps[ids[b.materials[0].id]]
