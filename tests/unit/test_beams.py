"""Linac beams: IEC 61217 → DICOM patient frame conventions, apertures, named spectra, sampling.

Known cases (IEC 61217; DICOM PS3.3 C.8.8.25.6.2 patient positions): HFS gantry 0 the beam
travels anterior → posterior (+y); gantry 90 it comes from the patient's left (+x) travelling
−x; gantry 270 from the right; couch 90 turns the feet towards the gantry-90 side.
"""

import numpy as np
import pytest

from tetdose._random import seed_for
from tetdose.errors import PlanError
from tetdose.plan.beams import MLC, aperture_rectangles, beam_axes
from tetdose.plan.spectra import (
    CO60_LINES_MEV,
    DMAX_MM,
    NAMED_SPECTRA,
    _bins_to_lines,
    _read_bins,
    build_up_depth_mm,
    named_spectrum,
)
from tetdose.transport import Plan, TransportSettings
from tetdose.transport.sources._sample import sample_source
from tetdose.transport.sources.arrays import source_arrays


def _beam_dir(gantry, coll=0.0, couch=0.0, pos="HFS"):
    return -beam_axes(gantry, coll, couch, pos)[2]


@pytest.mark.parametrize(("pos", "gantry", "travel"), [
    ("HFS", 0, [0, 1, 0]),     # anterior → posterior
    ("HFS", 90, [-1, 0, 0]),   # from the patient's left
    ("HFS", 180, [0, -1, 0]),  # posterior → anterior
    ("HFS", 270, [1, 0, 0]),   # from the patient's right
    ("HFP", 0, [0, -1, 0]),    # prone: from above is from the back
    ("HFP", 90, [1, 0, 0]),    # prone: the +X_f side is the patient's right
    ("FFS", 0, [0, 1, 0]),
    ("FFS", 90, [1, 0, 0]),    # feet first: the +X_f side is the patient's right
    ("FFP", 0, [0, -1, 0]),
    ("FFP", 90, [-1, 0, 0]),
])
def test_gantry_direction_in_patient_frame(pos, gantry, travel):
    np.testing.assert_allclose(_beam_dir(gantry, pos=pos), travel, atol=1e-12)


def test_couch_rotation_turns_the_lateral_beam_along_the_patient_axis():
    # Couch 90 (counter-clockwise from above) swings the feet to +X_f, where the gantry-90 source
    # is: the beam enters from the feet and travels to the head (+z) for HFS.
    np.testing.assert_allclose(_beam_dir(90, couch=90), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(_beam_dir(90, couch=270), [0, 0, -1], atol=1e-12)
    # The couch turns about the vertical: a gantry-0 beam does not change direction.
    np.testing.assert_allclose(_beam_dir(0, couch=37), [0, 1, 0], atol=1e-12)


def test_collimator_rotation_and_frame_handedness():
    xb, yb, zb = beam_axes(0, 0, 0, "HFS")
    # Gantry 0, collimator 0 (HFS): X jaws along the patient's left-right, Y jaws along the head.
    np.testing.assert_allclose(xb, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(yb, [0, 0, 1], atol=1e-12)
    # Collimator 90 (right-handed about Z_b, which points to the source): X_b → old Y_b.
    xb90, yb90, _ = beam_axes(0, 90, 0, "HFS")
    np.testing.assert_allclose(xb90, yb, atol=1e-12)
    np.testing.assert_allclose(yb90, -xb, atol=1e-12)
    for pos in ("HFS", "HFP", "FFS", "FFP"):
        ax = beam_axes(33, 21, 12, pos)
        np.testing.assert_allclose(ax @ ax.T, np.eye(3), atol=1e-12)
        # Every patient position is a proper rotation between two right-handed frames (IEC b
        # and DICOM LPS): a mirror in any table would give det = −1.
        assert np.linalg.det(ax) == pytest.approx(1.0)


def test_aperture_is_jaws_intersected_with_leaf_pairs():
    mlc = MLC([-20, -10, 0, 10, 20], [-5, -30, 0, 2, 5, 30, 0, 8])
    rects = aperture_rectangles([-25, 25, -15, 15], mlc)
    # pair 0: [-5, 5] × [-15, -10]; pair 1: [-25 (jaw), 25 (jaw)] × [-10, 0]; pair 2 closed;
    # pair 3: [2, 8] × [10, 15].
    np.testing.assert_allclose(rects, [[-5, 5, -15, -10], [-25, 25, -10, 0], [2, 8, 10, 15]])
    with pytest.raises(PlanError, match="overlap"):
        MLC([0, 1], [3, 2])


def test_named_spectra_keep_the_tabulated_fluence_and_mean_energy():
    e_high, per_mev = _read_bins("mohan6.csv")
    e, w = _bins_to_lines(e_high, per_mev)
    width = np.diff(np.concatenate([[0.0], e_high]))
    assert w.sum() == pytest.approx(np.dot(per_mev, width))  # bin fluence kept exactly
    mid = e_high - width / 2
    assert np.dot(e, w) / w.sum() == pytest.approx(np.dot(mid, per_mev * width) / w.sum())
    e6, w6 = named_spectrum("6MV")
    e15, w15 = named_spectrum("15 mv")
    assert e6.max() < 6.0 < e15.max() < 14.5  # lines inside the bins
    assert np.dot(e6, w6) / w6.sum() < np.dot(e15, w15) / w15.sum()
    np.testing.assert_allclose(named_spectrum("Co60")[0], CO60_LINES_MEV)
    with pytest.raises(PlanError, match="no citable 18MV"):
        named_spectrum("18MV")
    assert all(build_up_depth_mm(n) == DMAX_MM[n] for n in NAMED_SPECTRA)


def _samples(plan, n):
    src = source_arrays(plan, TransportSettings(n_histories=10, n_batches=2, physics="kerma"))
    out = np.empty((n, 7))
    for i in range(n):
        _, *vals = sample_source(src, np.uint64(seed_for(7, 0, i)), np.empty(0))
        out[i] = vals
    return out


def test_sampled_photons_start_at_the_source_and_cross_the_isocentre_plane_in_the_aperture():
    iso = np.array([10.0, -20.0, 30.0])
    plan = Plan.from_dict({"beam": [{
        "type": "linac", "spectrum": "Co60", "isocenter_mm": iso.tolist(), "gantry_deg": 90,
        "collimator_deg": 90, "sad_mm": 800.0, "jaws_mm": [-10, 30, -20, 5]}]})
    s = _samples(plan, 2000)
    xb, yb, zb = beam_axes(90, 90, 0, "HFS")
    np.testing.assert_allclose(s[:, 1:4], np.tile(iso + 800.0 * zb, (len(s), 1)))
    np.testing.assert_allclose(np.linalg.norm(s[:, 4:7], axis=1), 1.0)
    t = 800.0 / (s[:, 4:7] @ -zb)  # path length to the isocentre plane
    hit = s[:, 1:4] + t[:, None] * s[:, 4:7] - iso
    a1, a2 = hit @ xb, hit @ yb
    assert a1.min() >= -10 and a1.max() <= 30 and a2.min() >= -20 and a2.max() <= 5
    # Uniform over the aperture: each half of the field gets half the photons (±4σ).
    assert abs(np.mean(a1 < 10) - 0.5) < 4 * 0.5 / np.sqrt(len(s))
    assert set(np.round(s[:, 0], 4)) == set(CO60_LINES_MEV)


def test_segments_are_chosen_by_meterset_times_area_and_rectangles_by_area():
    """Equal fluence per MU: 3 MU through 600 mm² (two leaf pairs) against 1 MU through the
    default 100 × 100 mm² field: photons in proportion 3·600 : 1·10000."""
    mlc = {"boundaries_mm": [-20, 0, 20], "positions_mm": [-20, -5, -10, 15]}
    plan = Plan.from_dict({"beam": [
        {"type": "linac", "spectrum": "6MV", "isocenter_mm": [0, 0, 0], "weight": 3.0,
         "jaws_mm": [-40, 40, -20, 20], "mlc": mlc},
        {"type": "linac", "spectrum": "6MV", "isocenter_mm": [0, 0, 0], "gantry_deg": 180,
         "weight": 1.0}]})
    s = _samples(plan, 12000)
    from_front = s[:, 5] > 0  # gantry 0 travels +y
    q = 3 * 600 / (3 * 600 + 1 * 10000)
    assert abs(from_front.mean() - q) < 4 * np.sqrt(q * (1 - q) / len(s))
    f = s[from_front]
    t = 1000.0 / f[:, 5]
    x, z = f[:, 1] + t * f[:, 4], f[:, 3] + t * f[:, 6]
    lower = z < 0  # pair 0 open 10 mm wide, pair 1 open 20 mm: area fraction 10/30
    assert abs(lower.mean() - 1 / 3) < 4 * np.sqrt(2 / 9 / len(f))
    assert x[lower].min() >= -20 and x[lower].max() <= -10
    assert x[~lower].min() >= -5 and x[~lower].max() <= 15


def test_isocentre_by_structure_name_needs_the_geometry():
    plan = Plan.from_dict({"regions": {"tumour": 3}, "beam": [
        {"type": "linac", "spectrum": "6MV", "isocenter": "tumour"}]})
    assert plan.unresolved == ["tumour"]
    with pytest.raises(PlanError, match="needs the geometry"):
        source_arrays(plan, TransportSettings(n_histories=10, n_batches=2, physics="kerma"))
    from tetdose.core.image import Image, ImageGrid

    grid = ImageGrid(origin_mm=np.array([-10.0, 0.0, 5.0]), spacing_mm=np.array([2.0, 2.0, 2.0]),
                     direction=np.eye(3), size=(10, 10, 10))
    lab = np.zeros(grid.shape, dtype=np.int16)
    lab[2:4, 5:7, 1:3] = 3  # (k, j, i): i 1..2, j 5..6, k 2..3
    labels = Image(lab, grid)
    r = plan.resolved(Image(np.ones(grid.shape), grid), labels)
    np.testing.assert_allclose(r.treatment_beams[0].isocenter_mm,
                               [-10 + 2 * 1.5, 0 + 2 * 5.5, 5 + 2 * 2.5])
    assert len(r.sources) == 1
    with pytest.raises(PlanError, match=r"\[regions\]"):
        Plan.from_dict({"beam": [{"type": "linac", "spectrum": "6MV", "isocenter": "gtv"}]}
                       ).resolved(Image(np.ones(grid.shape), grid), labels)


def test_named_spectrum_in_simple_beams_and_linac_errors():
    plan = Plan.from_dict({"beam": [{"type": "parallel", "spectrum": "Co60",
                                     "position_mm": [0, 0, -100], "field_mm": [10, 10]}]})
    np.testing.assert_allclose(plan.sources[0].energies_mev, CO60_LINES_MEV)
    with pytest.raises(PlanError, match="exactly one of isocenter_mm"):
        Plan.from_dict({"beam": [{"type": "linac", "spectrum": "6MV"}]})
    with pytest.raises(PlanError, match="no opening"):
        Plan.from_dict({"beam": [{"type": "linac", "spectrum": "6MV", "isocenter_mm": [0, 0, 0],
                                  "jaws_mm": [10, -10, -5, 5]}]})
    with pytest.raises(PlanError, match=r"\[patient\] position .HFDL. is unknown"):
        Plan.from_dict({"patient": {"position": "HFDL"}, "beam": [
            {"type": "linac", "spectrum": "6MV", "isocenter_mm": [0, 0, 0]}]})


def test_build_up_mask_is_the_skin_layer_of_depth_dmax():
    from tetdose.core.image import Image, ImageGrid
    from tetdose.dose.buildup import build_up_fraction, build_up_mask

    grid = ImageGrid(np.zeros(3), np.full(3, 2.0), np.eye(3), (40, 40, 40))
    rho = np.zeros(grid.shape)
    rho[5:35, 5:35, 5:35] = 1.0  # a 60 mm water cube, skin at 10 mm from the grid edge
    mask = build_up_mask(Image(rho, grid), 15.0)
    # Voxel centres at 1, 3, …, 59 mm from the cube's face: those < 15 mm deep are 7 layers.
    line = mask[20, 20, 5:35]
    assert line.tolist() == [True] * 7 + [False] * 16 + [True] * 7
    assert not mask[rho == 0].any()
    core = np.zeros(grid.shape, dtype=bool)
    core[15:25, 15:25, 15:25] = True
    assert build_up_fraction(mask, core) == 0.0
    assert build_up_fraction(mask, rho > 0) == pytest.approx(1 - (16 / 30) ** 3)


def test_co60_with_capsule_scatter_keeps_its_lines_and_its_scattered_third():
    """rogers_co60.csv (counts per bin from 0.01 MeV divided by the bin width): the two line
    bins hold 0.53814 each of 1.6137 in total (EGSnrc co60.spectrum), so a third of the
    photons are scattered; no line lies below the spectrum's 0.01 MeV (empty first bin)."""
    e, w = named_spectrum("Co60-scatter")
    assert e.min() > 0.01 and e.max() < 1.3325 + 0.005
    line = (np.abs(e - 1.17) < 0.006) | (np.abs(e - 1.33) < 0.006)
    assert w[line].sum() / w.sum() == pytest.approx(2 * 0.53814 / 1.6136762, rel=1e-4)
    assert np.dot(e, w) / w.sum() < np.mean(CO60_LINES_MEV)  # softer than the bare lines


def test_linac_beam_takes_a_spectrum_file_relative_to_the_plan(tmp_path):
    (tmp_path / "my18.csv").write_text("energy_mev,weight\n2.0,3.0\n8.0,1.0\n")
    (tmp_path / "plan.toml").write_text(
        '[[beam]]\ntype = "linac"\nspectrum = "my18.csv"\nisocenter_mm = [0, 0, 0]\n')
    beam = Plan.from_toml(tmp_path / "plan.toml").treatment_beams[0]
    np.testing.assert_allclose(beam.energies_mev, [2.0, 8.0])
    np.testing.assert_allclose(beam.line_weights, [3.0, 1.0])
    with pytest.raises(PlanError, match="cannot read spectrum"):
        Plan.from_dict({"beam": [{"type": "linac", "spectrum": "none.csv",
                                  "isocenter_mm": [0, 0, 0]}]})
