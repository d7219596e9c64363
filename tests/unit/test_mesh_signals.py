"""`tetdose mesh` stopped mid-MMG: Ctrl-C (SIGINT to the terminal's process group) exits 130,
SIGTERM exits 143; both print the one "interrupted" line, write nothing, and leave no process
behind (MMG runs in a child, killed with its process group) — no deadlock, no MMG message."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from tetdose.core.image import Image, ImageGrid
from tetdose.core.io import write_image

from helpers import interrupt

pytest.importorskip("mmgpy")


def _tagged(tag: str) -> list[int]:
    """Processes whose environment holds ``tag`` (the command and its children)."""
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                if tag.encode() in Path(f"/proc/{pid}/environ").read_bytes():
                    found.append(int(pid))
            except OSError:
                pass
    return found


@pytest.fixture(scope="module")
def labels(tmp_path_factory) -> Path:
    """Two nested boxes: about 20 s of meshing, the background built after ~3 s."""
    g = ImageGrid(np.zeros(3), np.full(3, 2.0), np.eye(3), (30, 30, 30))
    arr = np.zeros(g.shape, np.int16)
    arr[4:26, 4:26, 4:26] = 1
    arr[10:20, 10:20, 10:20] = 2
    path = tmp_path_factory.mktemp("labels") / "labels.nrrd"
    write_image(path, Image(arr, g))
    return path


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc")
@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)],
                         ids=["ctrl-c", "sigterm"])
def test_mesh_stops_cleanly_on_a_signal(labels, tmp_path, sig, code):
    tag = f"TETDOSE_SIGNAL_TEST={uuid.uuid4().hex}"
    env = dict(os.environ, TETDOSE_SIGNAL_TEST=tag.split("=")[1])
    out = tmp_path / "out" / "mesh.vtu"
    proc = subprocess.Popen([sys.executable, "-m", "tetdose", "mesh", "--labels", str(labels),
                             "-o", str(out)], stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True)
    try:
        lines = []
        for line in proc.stderr:  # the child is in MMG once the background mesh is built
            lines.append(line)
            if "background mesh" in line or "error" in line:
                break
        assert any("background mesh" in ln for ln in lines), "".join(lines)
        assert len(_tagged(tag)) >= 2, "the mesher child is not running"
        time.sleep(0.2)  # a label's cut takes ~0.4 s on a fast host: stop inside the first
        got, rest, seconds = interrupt(proc, sig, timeout_s=30)
        assert got == code and seconds < 15.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = "".join(lines) + rest
    # a fast host may finish a label's cut (its progress line) before the signal arrives
    said = rest.strip().splitlines()
    assert said[-1:] == ["tetdose mesh: interrupted; no partial output was kept"], said
    assert all(ln.startswith("tetdose mesh: cut label") for ln in said[:-1]), said
    assert "Traceback" not in err and "MMG" not in err
    assert not (tmp_path / "out").exists(), "an output (or its folder) was written"
    deadline = time.monotonic() + 5
    while _tagged(tag) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _tagged(tag) == [], "a mesher process survived"
