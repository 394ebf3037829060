"""Compatibility layers: other code bases' weights and helpers for third-party libraries.

Each submodule is imported on its own (``from mssf_blocks.compat import <name>``); nothing here is
imported by ``import mssf_blocks``, and no submodule imports an optional dependency at module level.
"""
