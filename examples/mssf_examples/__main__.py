"""``python -m mssf_examples train|eval ...`` (run with ``PYTHONPATH=examples`` from the repository root).

Also the ``torchrun`` entry: ``torchrun --nproc_per_node N -m mssf_examples train ...`` (``docs/gpus.md``).
"""

import sys

from torch.distributed.elastic.multiprocessing.errors import record

from .cli import main

# record: a failing process writes its traceback where torchrun's failure summary shows it
sys.exit(record(main)())
