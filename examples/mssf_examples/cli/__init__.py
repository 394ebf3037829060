"""The commands of ``python -m mssf_examples`` (``mssf``): train, eval, convert-authors (:mod:`mssf_examples.cli.commands`)."""
