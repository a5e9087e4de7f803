"""Scoring lanes: the FHLD point metric and the ONCE-3DLanes lane metric (metrics.py), bags
scored with `fhld eval` (evaluate.py) and the fixed held-out test set (`fhld testset`)."""
