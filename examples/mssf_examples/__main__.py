"""``python -m mssf_examples train|eval ...`` (run with ``PYTHONPATH=examples`` from the repository root)."""

import sys

from .cli import main

sys.exit(main())
