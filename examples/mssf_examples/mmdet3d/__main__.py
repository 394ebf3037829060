"""``python -m mssf_examples.mmdet3d``: see :mod:`mssf_examples.mmdet3d.cli`."""

import sys

from .cli import main

sys.exit(main())
