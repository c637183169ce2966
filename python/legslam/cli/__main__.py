"""`python -m legslam.cli ...`, the same as the `legslam` command."""

import sys

from . import main

sys.exit(main())
