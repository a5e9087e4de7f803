"""Windows with their lanes, shared by training and evaluation: simulated drives rendered into
BEV windows (samples.py), cached once on disk (cache.py, variation.py), and windows read from
recorded bags with their labels (bag_source.py)."""
