"""tetdose.motion.source: one PhaseSeries from exactly one motion source, the reference checked
the same way for every source, and the mass report as plain CSV."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from tetdose.core.image import ImageGrid
from tetdose.core.io import write_mesh
from tetdose.errors import DensityError, MeshError, OptionError
from tetdose.motion.breathing import BreathingModel
from tetdose.motion.dvf import DisplacementField, write_dvf
from tetdose.motion.source import (
    MASS_REPORT_COLUMNS,
    check_reference,
    deform,
    mass_report_csv,
    phase_series,
)

from helpers import box_mesh


@pytest.fixture
def reference():
    mesh = box_mesh([10, 10, 10], [40, 34, 28], (3, 3, 2), jitter=0.15)
    rho = 0.3 + 0.02 * mesh.points_mm[:, 0]  # g/cm³, a gradient
    return mesh.with_data(point_data={"density": rho})


def test_breathing_source_is_the_breathing_model(reference):
    model = BreathingModel(6.0, 4.0, 3)
    got = phase_series(reference, breathing=model, n_phases=3)
    np.testing.assert_array_equal(got.points_mm, model.series(reference, 3).points_mm)


def test_dvf_source_moves_points_by_the_field(reference, tmp_path):
    """A uniform field u moves every vertex by u, exactly (trilinear of a constant)."""
    grid = ImageGrid([0, 0, 0], [5.0, 5.0, 5.0], np.eye(3), (12, 11, 10))
    u = np.array([1.5, -2.0, 0.75])
    files = []
    for k, scale in enumerate((0.0, 1.0)):
        files.append(write_dvf(tmp_path / f"dvf_{k}.nrrd",
                               DisplacementField(np.broadcast_to(scale * u, (*grid.shape, 3)),
                                                 grid)))
    series = phase_series(reference, dvfs=files, phase_percent=[0.0, 50.0])
    np.testing.assert_allclose(series.points_mm[0], reference.points_mm, atol=1e-12)
    np.testing.assert_allclose(series.points_mm[1], reference.points_mm + u, atol=1e-12)
    np.testing.assert_array_equal(series.phase_percent, [0.0, 50.0])


def test_phase_mesh_source_reads_the_files(reference, tmp_path):
    moved = reference.moved(reference.points_mm * 1.01)
    write_mesh(tmp_path / "p.vtu", moved)
    series = phase_series(reference, phases=[tmp_path / "p.vtu"])
    np.testing.assert_allclose(series.points_mm[0], moved.points_mm)


@pytest.mark.parametrize("sources", [{}, {"breathing": BreathingModel(), "phases": ["a.vtu"]}])
def test_exactly_one_source(reference, sources):
    with pytest.raises(OptionError, match="exactly one motion source"):
        phase_series(reference, **sources)


def test_reference_checked_for_every_source(reference):
    neg = reference.with_data(point_data={"density": reference.point_data["density"] - 1.0})
    with pytest.raises(DensityError, match="negative.*tetdose map"):
        phase_series(neg, breathing=BreathingModel())
    # the upper layer of cells on its own copies of the shared vertices: not conforming
    upper = reference.centroids_mm[:, 2] > 19.0
    shared = np.unique(reference.tets[upper])
    new_id = np.arange(reference.n_points)
    new_id[shared] = reference.n_points + np.arange(len(shared))
    tets = np.where(upper[:, None], new_id[reference.tets], reference.tets)
    pts = np.concatenate([reference.points_mm, reference.points_mm[shared]])
    split = type(reference)(pts, tets, point_data={"density": np.ones(len(pts))})
    with pytest.raises(MeshError, match="coincide"):
        check_reference(split)


def test_deform_conserves_mass_and_the_report_is_plain_csv(reference):
    series, reports = deform(phase_series(reference, breathing=BreathingModel(8.0), n_phases=4))
    text = mass_report_csv(series, reports)
    assert "np." not in text and "float64" not in text
    rows = list(csv.DictReader(io.StringIO(text)))
    assert tuple(rows[0]) == MASS_REPORT_COLUMNS and len(rows) == 4
    for row, r, w in zip(rows, reports, series.time_weight, strict=True):
        assert float(row["total_mass_g"]) == r.total_mass_g  # round trip, to the last bit
        assert float(row["time_weight"]) == float(w) == 0.25
        assert abs(float(row["mass_change_rel"])) < 1e-10
