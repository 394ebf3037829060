"""``python -m mssf_examples train|eval ...``, also installed as the console script ``mssf train|eval ...``.

Installed with ``pip install "mssf-blocks[examples]"`` (the wheel holds this package); from a clone,
``pip install -e ".[examples]"`` (what ``make test`` / ``make demo`` do in ``.venv``), or without any
install ``PYTHONPATH=src:examples python -m mssf_examples ...``.

Also the ``torchrun`` entry: ``torchrun --nproc_per_node N -m mssf_examples train ...`` (``docs/gpus.md``).
"""

import sys

from torch.distributed.elastic.multiprocessing.errors import record


def entry() -> None:
    """Run the CLI and exit with its status (the ``mssf`` console script and ``python -m mssf_examples``)."""
    try:
        from .cli.commands import main
    except ImportError as exc:  # an examples dependency is missing: say which extra brings it
        if exc.name and exc.name.split(".")[0] in ("spconv", "cumm", "tqdm", "PIL"):
            sys.exit(f"mssf_examples needs {exc.name.split('.')[0]}: pip install \"mssf-blocks[examples]\" "
                     f"(from a clone: pip install -e \".[examples]\")")
        raise
    # record: a failing process writes its traceback where torchrun's failure summary shows it
    sys.exit(record(main)())


if __name__ == "__main__":
    entry()
