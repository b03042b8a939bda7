"""`python -m laas.cli`: the `laas` command line (the worker's `--processes` children run
it so)."""

import sys

from laas.cli import main

sys.exit(main())
