"""Re-export of :mod:`mssf_blocks.integrations.spconv` (the remedy ships in the library; see its docstring).

``enable_cpu_backward()`` makes spconv 2.3's backward pass run on CPU-only PyTorch builds; ``quiet()``
drops spconv's two spurious messages around the examples' spconv calls; ``dense()`` is
``SparseConvTensor.dense()`` without spconv's list indexing.
"""

from mssf_blocks.integrations.spconv import dense, enable_cpu_backward, quiet

__all__ = ["enable_cpu_backward", "quiet", "dense"]
