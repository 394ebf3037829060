"""Rows of the "Common mistakes" table (tests/docs/test_docs_mistakes_table.py) proved by framework tests.

These need the real OpenPCDet / mmdetection3d and fixtures that take seconds to minutes (a built detector,
a training step, a clone of OpenPCDet), so the table's test does not rerun them: it checks that each
named test exists (parsed, not imported), and CI runs them in tests/integrations.
"""

from __future__ import annotations

from mistakes_registry import proved_by

PCDET = "tests/integrations/test_openpcdet_"

proved_by("OpenPCDet: a VoD frame with no radar point in range",
          f"{PCDET}sparse_frames.py::test_batch_with_an_empty_frame_trains_with_the_normal_frames_loss",
          f"{PCDET}sparse_frames.py::test_eval_one_epoch_with_an_empty_frame",
          f"{PCDET}sparse_frames.py::test_a_batch_of_one_empty_frame_is_skipped_in_training_and_empty_in_evaluation")
proved_by("OpenPCDet: VoxelNeXt's `MAX_OBJ_PER_SAMPLE`",
          f"{PCDET}sparse_frames.py::test_frame_with_fewer_voxels_than_max_obj_gets_its_own_class_labels",
          f"{PCDET}sparse_frames.py::test_per_frame_decoding_equals_the_stock_batched_decoding")
proved_by("OpenPCDet: `DATA_PATH` at `radar`",
          f"{PCDET}data_checks.py::test_data_path_without_the_infos_names_the_folder_they_were_built_for",
          f"{PCDET}data_checks.py::test_any_split_without_frames_says_why",
          f"{PCDET}data_checks.py::test_infos_of_another_sensor_folder_are_refused")
proved_by("OpenPCDet: 4-float points",
          f"{PCDET}data_checks.py::test_4_float_points_whose_size_divides_by_7_are_refused")
proved_by("OpenPCDet: `test.py` on a trained MSSF checkpoint",
          f"{PCDET}checkpoints.py::test_test_py_on_a_trained_checkpoint_needs_no_image_branch_file")
proved_by("OpenPCDet's documented commands on a machine without CUDA",
          f"{PCDET}cpu_route.py::test_the_documented_cpu_route_runs_on_an_unbuilt_clone")

# mmdetection3d rows
MM = "tests/integrations/test_mmdet3d_"
proved_by("mmdet3d: images stored resized", f"{MM}image_size.py::test_halved_images_with_full_size_calibration_warn",
          f"{MM}image_size.py::test_real_calibrations_against_resized_images")
proved_by("mmdet3d: the frozen image branch",
          f"{MM}image_weights.py::test_frozen_unloaded_branch_refused_at_the_first_training_step",
          f"{MM}image_weights.py::test_entry_refuses_before_building")
proved_by("mmdet3d: the HTC `init_cfg`", f"{MM}image_weights.py::test_documented_htc_snippets_load_the_branch")
proved_by("mmdet3d: a checkpoint whose pickle runs code", f"{MM}checkpoints.py::test_crafted_checkpoint_is_refused",
          f"{MM}checkpoints.py::test_allow_list_on_every_torch")
