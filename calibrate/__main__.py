"""``python -m calibrate``: what ``deform calibrate`` runs (see :mod:`calibrate.cli`)."""

import sys

from calibrate.cli import main

sys.exit(main())
