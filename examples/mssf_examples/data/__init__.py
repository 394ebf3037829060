"""Dataset readers and writers (KITTI-format View-of-Delft / TJ4DRadSet trees), the batch every detector takes, augmentation."""
