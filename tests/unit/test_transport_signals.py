"""A transport run stops on Ctrl-C / SIGTERM within about a kernel call (~1 s), not a batch.

Batches run in short kernel calls (:class:`tetdose.transport.run.job.Pace`): the rows are bitwise
those of one call per batch group, whatever the cut (kerma and dose mode, hybrid world), and a
``tetdose dose`` with 10¹¹ histories exits 130 / 143 seconds after the signal, leaving nothing.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tetdose.core.image import Image
from tetdose.core.io import write_image
from tetdose.transport import PhotonSource, Plan, TransportSettings, World
from tetdose.transport.run.job import Pace, build_job, cross_sections, run_batches

from helpers import box_mesh, grid_for, interrupt


class _Cut(Pace):
    """Calls of a fixed, odd number of histories per batch (never adapted)."""

    def update(self, histories: int, seconds: float) -> None:
        pass


@pytest.mark.parametrize("physics", ["kerma", "dose"])
def test_batches_cut_into_short_calls_give_the_same_bits(physics):
    grid = grid_for((-30, -30, -30), (30, 30, 30), (6.0, 6.0, 6.0))
    world = World(mesh=box_mesh((-12, -12, -12), (12, 12, 12), (3, 3, 3), jitter=0.2, seed=2),
                  density=Image(np.ones(grid.shape), grid))
    world.mesh.point_data["density"] = np.full(world.mesh.n_points, 1.5)
    beam = PhotonSource("parallel", [0, 0, -40], [0, 0, 1], energies_mev=[2.0], field_mm=[30, 30])
    plan = Plan((beam,))
    settings = TransportSettings(1003, 5, 7, physics=physics)
    job, _ = build_job(world, plan, settings)
    xs = cross_sections(job, settings)
    whole = run_batches(job, xs, settings, 1, 4)
    cut = run_batches(job, xs, settings, 1, 4, _Cut(histories=17))
    assert np.any(whole[0] > 0) and whole[2].sum() > 0
    for a, b in zip(whole, cut, strict=True):
        np.testing.assert_array_equal(a, b)


def test_pace_aims_at_its_call_time():
    pace = Pace(target_s=0.25, histories=100)  # 100 histories took 0.05 s: 500 take 0.25 s
    pace.update(100, 0.05)
    assert pace.histories == 500
    pace.update(500, 10.0)  # far too long: at most ÷4 at once
    assert pace.histories == 125
    pace.update(125, 0.0)
    assert pace.histories == 1000


@pytest.fixture(scope="module")
def water(tmp_path_factory) -> Path:
    """A 60 mm water cube CT (0 HU) and a plan.toml with one parallel 1.25 MeV beam."""
    d = tmp_path_factory.mktemp("water")
    grid = grid_for((-30, -30, -30), (30, 30, 30), (6.0, 6.0, 6.0))
    write_image(d / "ct.nrrd", Image(np.zeros(grid.shape, np.int16), grid))
    (d / "plan.toml").write_text(
        '[[beam]]\ntype = "parallel"\nposition_mm = [0, 0, -40]\ndirection = [0, 0, 1]\n'
        'energy_mev = 1.25\nfield_mm = [20, 20]\n')
    return d


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)],
                         ids=["ctrl-c", "sigterm"])
def test_dose_stops_mid_transport_within_seconds(water, tmp_path, sig, code):
    out = tmp_path / "new" / "dose.nrrd"
    proc = subprocess.Popen([sys.executable, "-m", "tetdose", "dose", "--ct", str(water / "ct.nrrd"),
                             "--plan", str(water / "plan.toml"), "--physics", "kerma",
                             "--histories", "1e11", "-q", "-o", str(out)],
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        lines = []
        for line in proc.stderr:  # the time estimate comes just before the transport starts
            lines.append(line)
            if "will take about" in line or "error" in line:
                break
        assert any("will take about" in ln for ln in lines), "".join(lines)
        time.sleep(1.0)  # well inside the batches (one batch is 10¹⁰ histories)
        assert proc.poll() is None
        got, rest, seconds = interrupt(proc, sig, timeout_s=60)
        assert got == code and seconds < 5.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "interrupted; no partial output was kept" in rest
    assert "Traceback" not in rest
    assert not out.parent.exists()  # the folder it created is gone, with every temporary


@pytest.mark.parametrize(("exc", "code"), [(KeyboardInterrupt, 130), ("Terminated", 143)])
def test_a_signal_while_the_parser_imports_the_commands_exits_130_or_143(monkeypatch, capsys,
                                                                          exc, code):
    """Ctrl-C in the seconds `tetdose` spends importing its command modules for the parser gave
    a traceback and no exit code 130 (the handlers were set after parsing)."""
    import tetdose.cli as cli

    error = cli.Terminated if exc == "Terminated" else exc

    def interrupted():
        raise error

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert cli.main(["dose", "--help"]) == code
    assert capsys.readouterr().err == "tetdose: interrupted; no partial output was kept\n"
