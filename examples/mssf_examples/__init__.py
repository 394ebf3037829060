"""Runnable examples for mssf-blocks: full radar-camera detectors built from the library's blocks."""
