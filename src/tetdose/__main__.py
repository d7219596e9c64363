"""``python -m tetdose`` runs the command-line interface."""

import sys

from tetdose.cli import main

sys.exit(main())
