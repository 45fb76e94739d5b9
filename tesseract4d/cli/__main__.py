"""``python -m tesseract4d.cli``: the same entry point as the ``tesseract4d`` console script."""

import sys

from tesseract4d.cli import main

sys.exit(main())
