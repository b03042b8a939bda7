"""`python -m ldm`: the `ldm` command line."""

from ldm.cli import main

raise SystemExit(main())
