"""Training the FHLD detector: simulator windows cached once (cache.py, samples.py), read with
augmentation (dataset.py), and the `fhld train` loop (train.py)."""
