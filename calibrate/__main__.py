"""``python -m calibrate``: what ``deform calibrate`` runs (see :mod:`calibrate.cli`)."""

import sys

from calibrate.cli import command_age_s, main

sys.exit(main(age_s=command_age_s()))  # the time limit counts from the process's start (or its parent's)
