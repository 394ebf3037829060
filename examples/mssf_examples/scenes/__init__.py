"""Deterministic synthetic 4D-radar + camera scenes (:mod:`mssf_examples.scenes.synthetic`) and their camera, radar and layout parts."""
