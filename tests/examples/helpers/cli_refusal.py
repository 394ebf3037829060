"""The CLI's refusal of a bad input, as the misuse tests expect it: exit status 2, no traceback, one line."""

from __future__ import annotations

import pytest


def refused_line(argv, capsys) -> str:
    """Run ``python -m mssf_examples ARGV`` in this process; it must stop with status 2 and no traceback.
    Returns the last line of what it printed to stderr (argparse's ``error:`` line)."""
    from mssf_examples.cli import commands as cli

    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err.strip().splitlines()[-1]
