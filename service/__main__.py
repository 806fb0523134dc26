"""`python -m service [run|record|replay|demo-bag ...]`: the same as `deform-service`."""

import sys

from service.cli import main

sys.exit(main())
