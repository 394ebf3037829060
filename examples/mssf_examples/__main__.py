"""``python -m mssf_examples train|eval ...``.

Installed with ``pip install "mssf-blocks[examples]"`` (the wheel holds this package); from a clone,
``make test`` / ``make demo`` install it in editable mode (or run with ``PYTHONPATH=examples``).

Also the ``torchrun`` entry: ``torchrun --nproc_per_node N -m mssf_examples train ...`` (``docs/gpus.md``).
"""

import sys

from torch.distributed.elastic.multiprocessing.errors import record

try:
    from .cli import main
except ImportError as exc:  # an examples dependency is missing: say which extra brings it
    if exc.name and exc.name.split(".")[0] in ("spconv", "cumm", "tqdm", "PIL"):
        sys.exit(f"python -m mssf_examples needs {exc.name.split('.')[0]}: pip install \"mssf-blocks[examples]\"")
    raise

# record: a failing process writes its traceback where torchrun's failure summary shows it
sys.exit(record(main)())
