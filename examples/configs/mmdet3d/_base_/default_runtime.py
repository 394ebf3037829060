# Runtime of the MSSF View-of-Delft configs (mmengine Runner; as mmdet3d's default_runtime, no visualiser).
default_scope = "mmdet3d"
custom_imports = dict(imports=["mssf_examples.mmdet3d.plugin"], allow_failed_imports=False)
default_hooks = dict(
    timer=dict(type="IterTimerHook"),
    logger=dict(type="LoggerHook", interval=50),
    param_scheduler=dict(type="ParamSchedulerHook"),
    checkpoint=dict(type="CheckpointHook", interval=1, max_keep_ckpts=3),
    sampler_seed=dict(type="DistSamplerSeedHook"),
)
env_cfg = dict(cudnn_benchmark=False, mp_cfg=dict(mp_start_method="fork", opencv_num_threads=0),
               dist_cfg=dict(backend="nccl"))
log_processor = dict(type="LogProcessor", window_size=50, by_epoch=True)
log_level = "INFO"
load_from = None  # a checkpoint of this model (e.g. to fine-tune); the image branch: its init_cfg (models/)
resume = False
randomness = dict(seed=0)
