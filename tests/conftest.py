"""Session-wide test setup: the tests directory is importable (``helpers``), plotting is headless."""

import os
import sys
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
sys.path.insert(0, str(Path(__file__).parent))

#: Reference data beside the checkout (``../shared``); tests that need it skip when absent.
SHARED = Path(__file__).resolve().parents[1].parent / "shared"
