"""3D detection evaluation (:mod:`mssf_examples.evaluation.metrics`) under the exact, VoD and TJ4DRadSet protocols."""
