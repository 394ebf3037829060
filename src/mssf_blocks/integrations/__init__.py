"""Adapters for detection frameworks (OpenPCDet, mmdetection3d).

Each submodule is imported on its own and is importable without its framework installed; the
framework itself is imported only where it is needed (registration, spconv tensors).
"""
