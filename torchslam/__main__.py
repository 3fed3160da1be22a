"""``python -m torchslam``: the same entry point as the ``torchslam`` console script."""

import sys

from .cli import main

sys.exit(main())
