"""Atomic writes: a killed writer leaves the previous output whole, the next run cleans up after
it; inputs and foreign folders are never replaced."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from tetdose._atomic import (
    MARKER,
    atomic_write_dir,
    atomic_write_file,
    check_output_dir,
    output_policy,
)
from tetdose.errors import OutputError

#: A writer that starts replacing the output, says so, then hangs until it is killed.
WRITER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from tetdose._atomic import atomic_write_dir, atomic_write_file
    out, ready, kind = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    if kind == "dir":
        with atomic_write_dir(out) as tmp:
            (tmp / "a.txt").write_text("new")
            ready.write_text("writing")
            time.sleep(120)
    else:
        with atomic_write_file(out) as tmp:
            tmp.write_text("new")
            ready.write_text("writing")
            time.sleep(120)
""")


def _kill_mid_write(out: Path, kind: str, tmp_path: Path) -> None:
    ready = tmp_path / "ready"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(out), str(ready), kind])
    try:
        deadline = time.monotonic() + 60
        while not ready.exists():
            assert proc.poll() is None, "the writer ended early"
            assert time.monotonic() < deadline, "the writer never started writing"
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    ready.unlink()


def _siblings(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name != out.name)


@pytest.mark.parametrize("kind", ["dir", "file"])
def test_sigkill_mid_write_keeps_previous_output_and_next_run_cleans(tmp_path, kind):
    area = tmp_path / "area"
    area.mkdir()
    out = area / ("series" if kind == "dir" else "mesh.vtu")
    if kind == "dir":
        with atomic_write_dir(out) as d:
            (d / "a.txt").write_text("old")
    else:
        out.write_text("old")
    _kill_mid_write(out, kind, tmp_path)
    old = (out / "a.txt") if kind == "dir" else out
    assert old.read_text() == "old"  # the previous output is intact
    assert any(".part" in n for n in _siblings(out))  # the killed run's temporary is left…
    if kind == "dir":
        with atomic_write_dir(out) as d:
            (d / "a.txt").write_text("next")
    else:
        with atomic_write_file(out) as tmp:
            tmp.write_text("next")
    assert old.read_text() == "next"
    assert _siblings(out) == []  # …and the next run removed it


def test_output_caught_between_the_two_renames_is_restored(tmp_path):
    """A kill after moving the old folder aside but before renaming the new one in: the old
    folder sits in a stale ``.old`` temporary; the next write puts it back, then replaces it."""
    out = tmp_path / "series"
    stale_old = tmp_path / ".series.999999999-abcdefgh.old"  # a PID that cannot be running
    (stale_old / "x").mkdir(parents=True)
    (stale_old / "x" / "a.txt").write_text("old")
    (stale_old / "x" / MARKER).write_text("")
    with pytest.raises(RuntimeError), atomic_write_dir(out):
        raise RuntimeError("the next run fails too")
    assert (out / "a.txt").read_text() == "old"  # restored, not deleted
    assert _siblings(out) == []


def test_temporaries_of_a_running_writer_are_kept(tmp_path):
    out = tmp_path / "mesh.vtu"
    mine = tmp_path / f".mesh.vtu.{os.getpid()}-abcdefgh.part.vtu"  # this process is alive
    mine.write_text("in progress")
    with atomic_write_file(out) as tmp:
        tmp.write_text("x")
    assert mine.exists()


def test_inputs_are_never_replaced(tmp_path):
    ct = tmp_path / "ct.nrrd"
    ct.write_bytes(b"CT")
    with pytest.raises(OutputError, match="also an input"), atomic_write_file(ct, inputs=[ct]):
        pass
    with output_policy(inputs=[ct]):
        with pytest.raises(OutputError, match="holds the input"), atomic_write_dir(tmp_path):
            pass
        with pytest.raises(OutputError, match="also an input"), atomic_write_file(
                tmp_path / "sub" / ".." / "ct.nrrd"):
            pass
    assert ct.read_bytes() == b"CT"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ct.nrrd"]


def test_foreign_folder_is_refused_unless_forced(tmp_path):
    out = tmp_path / "results"
    out.mkdir()
    (out / "thesis.tex").write_text("mine")
    with pytest.raises(OutputError, match="did not write"), atomic_write_dir(out):
        pass
    assert (out / "thesis.tex").exists()
    with output_policy(force=True), atomic_write_dir(out) as d:  # the CLI's --overwrite
        (d / "a.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "a.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    check_output_dir(empty)  # an empty folder may be used


def test_folder_inside_another_atomic_write_gets_no_marker(tmp_path):
    with atomic_write_dir(tmp_path / "study") as d, atomic_write_dir(d / "ct") as inner:
        (inner / "1.dcm").write_text("x")
    assert sorted(p.name for p in (tmp_path / "study").iterdir()) == [MARKER, "ct"]
    assert [p.name for p in (tmp_path / "study" / "ct").iterdir()] == ["1.dcm"]


def test_dicom_series_folder_holds_only_dicom_and_is_recognised_as_ours(tmp_path):
    import numpy as np

    from tetdose.core.image import Image, ImageGrid
    from tetdose.dicom.ct_series import write_ct_series

    ct = Image(np.zeros((2, 3, 4), np.int16), ImageGrid([0, 0, 0], [1, 1, 1], np.eye(3), (4, 3, 2)))
    first = write_ct_series(ct, tmp_path / "ct")
    assert sorted(p.name for p in (tmp_path / "ct").iterdir()) == [p.name for p in first]
    write_ct_series(ct.with_array(ct.array + 5), tmp_path / "ct")  # ours: replaced
    (tmp_path / "ct" / "report.pdf").write_text("not ours")
    with pytest.raises(OutputError, match="--overwrite"):
        write_ct_series(ct, tmp_path / "ct")
    assert (tmp_path / "ct" / "report.pdf").exists()
