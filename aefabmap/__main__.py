"""`python -m aefabmap ...`: the same command line as the `aefabmap` script."""

import sys

from aefabmap.cli.main import main

sys.exit(main())
