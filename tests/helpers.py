"""Small mesh and image builders shared by the lead's tests (obviously-correct constructions)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh

#: Kuhn (Freudenthal) split of the unit cube into 6 tetrahedra along the 0–7 diagonal; corners
#: numbered by bits (x = 1, y = 2, z = 4). Consistent on a grid, hence conforming.
KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7],
                 [0, 4, 6, 7]])


def box_mesh(lo, hi, n, *, jitter: float = 0.0, seed: int = 0) -> TetMesh:
    """A box [lo, hi] (mm) of n = (nx, ny, nz) cubes, 6 tets each; interior points jittered by
    ``jitter`` × cell size (seeded)."""
    lo, hi, n = np.asarray(lo, float), np.asarray(hi, float), np.asarray(n)
    axes = [np.linspace(lo[d], hi[d], n[d] + 1) for d in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    def pid(i, j, k):
        return (k * (n[1] + 1) + j) * (n[0] + 1) + i
    tets = []
    for k in range(n[2]):
        for j in range(n[1]):
            for i in range(n[0]):
                corner = [pid(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)) for c in range(8)]
                tets.extend([[corner[v] for v in t] for t in KUHN])
    if jitter:
        rng = np.random.default_rng(seed)
        h = (hi - lo) / n
        interior = np.all((pts > lo + 1e-9) & (pts < hi - 1e-9), axis=1)
        pts[interior] += rng.uniform(-jitter, jitter, (interior.sum(), 3)) * h
    return TetMesh(pts, np.array(tets)).with_fixed_orientation()


def grid_for(lo, hi, spacing, direction=None) -> ImageGrid:
    """An axis-aligned grid whose voxels' outer faces are exactly the box [lo, hi] (mm)."""
    lo, hi, spacing = (np.asarray(v, float) for v in (lo, hi, spacing))
    size = np.round((hi - lo) / spacing).astype(int)
    return ImageGrid(lo + spacing / 2, spacing, np.eye(3) if direction is None else direction,
                     tuple(size))


def density_image(grid: ImageGrid, fn) -> Image:
    """Image of fn(x, y, z) [g/cm³] sampled at voxel centres."""
    c = grid.voxel_centers_mm()
    return Image(fn(c[:, 0], c[:, 1], c[:, 2]).reshape(grid.shape), grid)


#: An identity-like calibration (HU value = density × 1000) so tests can state densities directly.
MILLI = HUCalibration.linear(0.001, 0.0, hu_range=(0.0, 1e6))


def as_hu(image: Image) -> Image:
    """Density image → HU image under :data:`MILLI`."""
    return image.with_array(image.array * 1000.0)


def ray_interval(v: np.ndarray, p: np.ndarray, d: np.ndarray) -> tuple[float, float]:
    """(t_in, t_out) of the ray p + t·d (t ≥ 0) in the tetrahedron with corners ``v`` (4, 3),
    by clipping against its four face half-spaces (t_in > t_out: the ray misses it)."""
    t_in, t_out = 0.0, np.inf
    for f in range(4):
        a, b, c = v[[i for i in range(4) if i != f]]
        nrm = np.cross(b - a, c - a)
        if np.dot(nrm, v[f] - a) > 0:
            nrm = -nrm
        den, dist = np.dot(nrm, d), np.dot(nrm, a - p)
        if den > 0:
            t_out = min(t_out, dist / den)
        elif den < 0:
            t_in = max(t_in, dist / den)
        elif dist < 0:
            t_in = np.inf
    return t_in, t_out


TESTS_DIR = Path(__file__).resolve().parent


def same_bits_with_one_or_two_threads(tmp_path: Path, imports_from: Path, run: str) -> None:
    """Run ``run`` (Python code that leaves a transport result in ``r``) in fresh processes with
    1 and 2 numba threads, ``imports_from`` (a tests folder) and tests/ on ``sys.path``; assert
    the per-batch energies and ledgers are non-zero and the same bit for bit."""
    script = tmp_path / "repro.py"
    script.write_text(
        "import sys\nimport numpy as np\n"
        f"sys.path[:0] = [{str(imports_from)!r}, {str(TESTS_DIR)!r}]\n" + textwrap.dedent(run)
        + "\nnp.save(sys.argv[1], np.concatenate([r.energy_per_batch_mev.ravel(), "
          "r.ledger_per_batch_mev.ravel()]))\n")
    out = {}
    for threads in (1, 2):
        path = tmp_path / f"t{threads}.npy"
        subprocess.run([sys.executable, str(script), str(path)], check=True, timeout=900,
                       env={**os.environ, "NUMBA_NUM_THREADS": str(threads)})
        out[threads] = np.load(path)
    assert out[1].sum() > 0
    np.testing.assert_array_equal(out[1], out[2])


def interrupt(proc, sig: int, timeout_s: float) -> tuple[int, str, float]:
    """Send ``sig`` to a running CLI subprocess as the terminal does (Ctrl-C: its process group)
    or as ``kill`` does (SIGTERM); returns (exit code, the rest of its stderr, seconds it took)."""
    import signal
    import time

    sent = time.monotonic()
    if sig == signal.SIGINT:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    rest = proc.stderr.read()
    code = proc.wait(timeout=timeout_s)
    return code, rest, time.monotonic() - sent
