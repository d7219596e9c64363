"""`tetdose demo --quick` end to end: the report's numbers are sane and every DICOM file valid."""

import json
import shutil
import subprocess

import pytest

from tetdose import study
from tetdose._atomic import MARKER
from tetdose.cli import main


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo-out"
    assert main(["demo", "--quick", "-q", "-o", str(out)]) == 0
    return out, json.loads((out / "summary.json").read_text())


def test_report_numbers_are_sane(demo):
    out, s = demo
    ours = s["mapping"]["l2 exact (tetdose)"]
    assert ours["mass_error_in_mesh_pct"] < 1e-7  # mass-conserving mapping
    # Per structure only where the mesh covers it, like with like (issue 27: tumour read 8232 %).
    assert {"liver", "bone"} <= set(ours["not_meshed"])
    assert ours["tumour"]["mass_error_pct"] < 10.0 and ours["lung"]["mass_error_pct"] < 10.0
    assert ours["vessels"]["mass_error_pct"] < 30.0  # folded into the lung: not resolved
    # Breathing keeps the tumour's volume; the lung's changes (issue 27).
    tumour = s["phantom"]["labels"]["tumour"]
    for phase in s["motion"]:
        volumes = {r["region"]: r for r in phase["regions"]}
        assert abs(volumes[tumour]["total"]) < 0.03
    assert all(abs(p["mass_change_rel"]) < 1e-9 for p in s["motion"])  # over the whole cycle
    assert s["dose"]["ledger_closure_rel"] < 1e-9 and s["dose"]["lost_photons"] == 0
    matched = s["gamma"]["static phase, matched resolution: voxel vs mesh 3%/3mm global"]
    plain = s["gamma"]["static phase: voxel vs mesh 3%/3mm global"]
    # --quick: 2·10⁴ histories with electrons leave ~20 % of noise per voxel, so γ is mostly
    # noise (issue 28: two unbiased runs would pass only `expected_pass_rate_percent` at the
    # CT's resolution, ~48 % here). Seeing both doses at the mesh's resolution must help, and
    # reach about what noise alone allows; the full demo's figures are in the README.
    assert matched["pass_rate_percent"] > plain["pass_rate_percent"]
    assert matched["pass_rate_percent"] > plain["expected_pass_rate_percent"] - 5.0
    tumour = s["dvh"]["tumour"]
    assert tumour["mesh"]["Dmean"] > 0 and tumour["voxel EMT"]["Dmean"] > 0
    # The three accumulations agree on the tumour's mean dose within a few per cent.
    assert tumour["voxel EMT"]["Dmean"] / tumour["mesh"]["Dmean"] == pytest.approx(1.0, abs=0.15)
    html = (out / "report.html").read_text()
    assert html.count("<img") >= 8 and "data:image/png;base64," in html


def test_demo_is_absorbed_dose_and_every_figure_is_drawn(demo):
    """The demo transports electrons and says so; the build-up under the skin is measured (dose
    well below kerma at 2 mm, as 6 MV physics demands); every figure of the report exists as a
    non-empty PNG, with the dose slices over the CT and the dose-vs-kerma panel among them."""
    out, s = demo
    assert s["physics"]["physics"] == "dose" and s["dose"]["physics"] == "dose"
    assert s["physics"]["electron_cutoff_mev"] == s["config"]["electron_cutoff_mev"]
    beams = s["dose_vs_kerma"]["beams"]
    assert len(beams) == len(s["config"]["beam_angles_deg"])
    assert all(b["dose_over_kerma_at_2_mm"] < 0.85 for b in beams.values())
    # A structure with only a few grams in the field sits at the field's edge, where laterally
    # scattered electrons carry dose beyond the kerma (the quick demo's liver: 2.7 g, D/K 1.24).
    inside = [r for r in s["dose_vs_kerma"]["structures"].values() if r["in_field_mass_g"] > 10.0]
    assert len(inside) >= 3 and all(0 < r["dose_over_kerma"] < 1.2 for r in inside)
    figures = json.loads((out / "report" / "figures.json").read_text())
    names = set(figures)
    assert "dose_vs_kerma_beams" in names and "dvh" in names
    assert any(n.startswith("dose_slice_k") for n in names)
    for name in names:
        png = (out / "report" / f"{name}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5_000, name
    slice_data = next(v for k, v in figures.items() if k.startswith("dose_slice_k"))
    assert slice_data["contour_segments"]["tumour"] > 0 and slice_data["isodose_gy"][0] == 1.9


def test_outputs_exist_and_dicom_is_valid(demo):
    out, s = demo
    series = sorted((out / "ct4d" / "dicom").iterdir())
    assert len(series) == s["config"]["n_phases"]
    assert len(list((out / "ct4d" / "nrrd").glob("*.nrrd"))) == s["config"]["n_phases"]
    assert (out / "phases" / "phases.pvd").exists()
    assert (out / "dose4d" / "accumulated.vtu").exists() and (out / "rtdose.dcm").exists()
    if shutil.which("dciodvfy") is None:
        pytest.skip("dciodvfy (dicom3tools) not installed")
    files = [next(iter(sorted(d.iterdir()))) for d in series] + [out / "rtdose.dcm"]
    for f in files:
        res = subprocess.run(["dciodvfy", str(f)], capture_output=True, text=True)
        errors = [ln for ln in (res.stdout + res.stderr).splitlines() if ln.startswith("Error")]
        assert not errors, f"{f}: {errors}"


def test_interrupted_run_leaves_previous_output_untouched(tmp_path, monkeypatch):
    out = tmp_path / "demo-out"
    out.mkdir()
    (out / "keep.txt").write_text("previous run")
    (out / MARKER).write_text("")  # a previous run's output, which tetdose may replace

    def interrupt(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(study._Run, "mapping", interrupt)
    assert main(["demo", "--quick", "-q", "-o", str(out)]) == 130
    assert [p.name for p in tmp_path.iterdir()] == ["demo-out"]  # no temp folder left behind
    assert (out / "keep.txt").read_text() == "previous run"


def test_demo_splitting_options_reach_the_study(tmp_path, monkeypatch):
    """`demo --photon-splitting 32 --splitting-scheme repeat` runs the study's dose with XVMC's
    splitting along the ray, with quasi-random source photons unless `--no-quasi-random`; the
    default splits the source photon 64 times and later photons 32 times, a given count applies
    to every photon unless `--secondary-photon-splitting` says otherwise; a count below 1 is
    refused before anything runs."""
    from tetdose.cli import _demo

    seen = {}

    def fake_study(config, out, **_):  # noqa: ANN001, ANN003, ANN202
        seen["config"] = config
        return {"seconds": {}}

    monkeypatch.setattr(_demo, "run_study", fake_study)
    argv = ["demo", "--quick", "-q", "-o", str(tmp_path / "o"), "--histories", "2500"]
    assert main([*argv, "--photon-splitting", "32", "--splitting-scheme", "repeat"]) == 0
    c = seen.pop("config")
    assert (c.photon_splitting, c.splitting_scheme, c.histories) == (32, "repeat", 2500)
    assert c.secondary_photon_splitting is None and c.quasi_random  # the demo's default
    assert main(argv) == 0
    c = seen.pop("config")
    assert (c.photon_splitting, c.secondary_photon_splitting, c.splitting_scheme) == (
        64, 32, "repeat")
    assert main([*argv, "--photon-splitting", "16", "--secondary-photon-splitting", "4"]) == 0
    assert seen.pop("config").secondary_photon_splitting == 4
    assert main([*argv, "--splitting-scheme", "follow"]) == 0
    assert seen.pop("config").secondary_photon_splitting is None
    assert main([*argv, "--no-quasi-random"]) == 0
    assert not seen.pop("config").quasi_random
    assert main([*argv, "--photon-splitting", "0"]) == 2
    assert not seen


@pytest.mark.slow
def test_demo_tells_physics_from_noise(demo):
    """Every pair of the demo with σ on both sides is reported per structure with its mean
    relative difference ± 1σ and its systematic part; γ carries the pass rate noise alone would
    give; the DVH points carry σ; the Δ/σ and σ maps are drawn; air is not compared."""
    out, s = demo
    assert "tissue" in s["compared_region"]
    pairs = s["significance"]
    assert set(pairs) == {"static phase: voxel vs mesh",
                          "accumulated: energy/mass transfer vs mesh",
                          "accumulated: direct mapping vs mesh"}
    for rows in pairs.values():
        row = rows["compared region"]
        for key in ("mean_rel_diff", "mean_rel_diff_sigma"):
            assert abs(row[key]) <= 1.0, key
        assert row["mean_rel_diff_sigma"] > 0 and "systematic_fraction" in row
        # --quick: 2·10⁴ histories leave 30–50 % per voxel, too noisy for the mixture (said so)
        assert row["systematic_model"] in ("none", "all", "part") or "noise too high" in row[
            "systematic_model"]
    g = s["gamma"]["static phase: voxel vs mesh 3%/3mm global"]
    assert 0.0 < g["expected_pass_rate_percent"] <= 100.0
    assert s["dvh"]["tumour"]["mesh"]["sigma"]["D95"] > 0
    assert "significant" in s["dvh"]["tumour"]["points"]["mesh − voxel EMT"]["D95"]
    names = set(json.loads((out / "report" / "figures.json").read_text()))
    assert any(n.startswith("significance_k") for n in names)
    assert any(n.startswith("sigma_k") for n in names)


def _median_rel_sigma_pct(vtu, region, floor_gy, sel=None):  # noqa: ANN001, ANN202
    """Median σ/D [%] over a dose VTU's tets of ``region`` whose dose (or ``sel``) reaches the
    floor; a tet without dose counts as σ = ∞."""
    import meshio
    import numpy as np

    cells = {k: v[0] for k, v in meshio.read(vtu).cell_data.items()}
    if sel is None:
        sel = (cells["region"] == region) & (cells["dose"] >= floor_gy)
    d, s = cells["dose"][sel], cells["dose_std"][sel]
    return 100 * np.median(np.divide(s, d, out=np.full(len(d), np.inf), where=d > 0)), sel, cells


def test_summary_reports_the_tumour_per_tet_sigma(demo):
    """Issue 30: the summary reports the tumour's tets (count, median mass beside its CT voxels')
    and their median per-tet σ, accumulated and per phase, as read back from the written dose
    VTUs; K phases of equal weight give an accumulated σ about the phases' over √K."""
    import numpy as np

    out, s = demo
    p = s["precision"]["tumour"]
    tumour = s["phantom"]["labels"]["tumour"]
    voxel_mm3 = float(np.prod(s["phantom"]["spacing_mm"]))
    assert 0.8 < p["ct_voxel_mass_mg"] / voxel_mm3 < 1.1  # soft tissue [mg/mm³ = g/cm³]
    floor = 0.5 * 2.0  # half the 2 Gy prescription
    acc, sel, cells = _median_rel_sigma_pct(out / "dose4d" / "accumulated.vtu", tumour, floor)
    assert p["tets"] == int((cells["region"] == tumour).sum()) and p["tets_scored"] == sel.sum()
    assert 1e3 * np.median(cells["mass_g"][cells["region"] == tumour]) == pytest.approx(
        p["median_tet_mass_mg"], rel=1e-6)
    assert p["median_sigma_pct"]["accumulated"] == pytest.approx(acc, rel=1e-6)
    phases = sorted((out / "dose4d").glob("phase_*.vtu"))
    per = [_median_rel_sigma_pct(v, tumour, floor, sel)[0] for v in phases]
    assert p["median_sigma_pct"]["phases"] == pytest.approx(per, rel=1e-6)
    assert p["median_sigma_pct"]["phase_median"] == pytest.approx(np.median(per), rel=1e-6)
    assert acc == pytest.approx(np.median(per) / np.sqrt(len(per)), rel=0.3)
