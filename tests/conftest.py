"""Session-wide test setup: the tests directory is importable (``helpers``), plotting is headless."""

import os
import sys
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
sys.path.insert(0, str(Path(__file__).parent))

#: Reference data beside the checkout (``../shared``); tests that need it skip when absent.
SHARED = Path(__file__).resolve().parents[1].parent / "shared"

#: Under pytest-xdist (`make test` runs ``-n 2 --dist loadfile --no-loadscope-reorder``) the files
#: are handed to the workers in this order, the rest after them in collection order. Cold, the
#: first compiles the dose-mode transport kernels (~5 min); meanwhile the other worker meshes, then
#: compiles kernels that one does not (Woodcock's, kerma mode's), so the two rarely compile the same
#: kernel at once; the demo, the longest file, comes once the dose kernels are in the cache. Ending
#: on short files keeps both workers busy to the end (two cold runs: they finished 3 and 8 s apart).
FIRST = ("unit/test_cli_errors.py", "unit/test_meshing_conforming.py", "unit/test_overlap_polyhedron.py",
         "unit/test_phantoms_organ.py", "unit/test_meshing_batches.py", "unit/test_mesh_signals.py",
         "unit/test_meshing.py", "verification/test_woodcock.py", "unit/test_register.py",
         "unit/test_coupling_ompmc.py", "verification/test_demo.py", "unit/test_boundaries.py")


def pytest_collection_modifyitems(config, items):
    """In an xdist worker, move the files of :data:`FIRST` to the front (stable otherwise)."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return
    tests = Path(__file__).parent
    rank = {name: i for i, name in enumerate(FIRST)}

    def key(item):
        return rank.get(item.path.relative_to(tests).as_posix(), len(FIRST))

    items.sort(key=key)
