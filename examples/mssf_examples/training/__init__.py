"""Training: the train / predict loop and checkpoints, devices and processes, thread defaults, checkpoint allow-list, image pre-training."""
