"""The Triton backend of the sampling op (CUDA; CPU tensors under ``TRITON_INTERPRET=1``).

``launch.py`` projects every pixel into the kernels' value buffer and launches ``kernels.py`` (forward
and backward). Neither is imported by ``import mssf_blocks``: the op imports ``launch`` when the
backend first runs, so ``triton`` is imported only then.
"""
