"""The example detectors (:mod:`mssf_examples.models.detectors`), their backbones, heads, box ops, image branch, voxelisation and presets."""
