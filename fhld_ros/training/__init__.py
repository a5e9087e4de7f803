"""Training the FHLD detector: cached windows (fhld_ros/data) read with augmentation
(dataset.py, augment.py), and `fhld train` (train.py: config.py, loop.py, resume.py,
distributed.py, runlog.py). How to run it: docs/training.md."""
