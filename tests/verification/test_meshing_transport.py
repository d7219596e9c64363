"""10⁶ photons crossing every interface of a conforming MMG mesh: none lost (slow)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mmgpy", reason="mmgpy not installed (extra tetdose[meshing])")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "unit"))
from test_meshing_conforming import BOX3, INNER_C, SIZES, _scene  # noqa: E402

from tetdose.meshing import conforming_mesh  # noqa: E402
from tetdose.transport import PhotonSource, Plan, TransportSettings, simulate  # noqa: E402


@pytest.mark.slow
def test_million_photons_cross_every_interface_none_lost() -> None:
    mesh = conforming_mesh(_scene(), None, SIZES)
    mesh = mesh.with_data(point_data={"density": np.full(mesh.n_points, 0.3)})
    box3 = 0.5 * (np.array(BOX3[0]) + np.array(BOX3[1]))
    # Isotropic point sources inside the inner sphere (crosses 2|1 and 1|outside) and inside
    # box 3 (crosses 3|4 and both boxes' outer surfaces), 1 MeV, thin material: most photons
    # leave through every interface on their way.
    plan = Plan((PhotonSource("point", list(INNER_C)), PhotonSource("point", box3.tolist())))
    result = simulate(mesh, plan, TransportSettings(n_histories=1_000_000, n_batches=10, seed=3,
                                                    physics="kerma"),
                      progress=False)
    assert result.lost_photons == 0
    assert result.crossings > 5_000_000  # every history crossed several tetrahedra
    ledger = result.ledger
    assert ledger["escaped_mev"] > 0.5 * ledger["source_mev"]
    region_dose = {r: result.dose_gy[mesh.region == r].max() for r in (1, 2, 3, 4)}
    assert all(d > 0 for d in region_dose.values())
