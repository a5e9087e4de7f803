"""Readers for point-cloud files that `fhld import` turns into bags: PCD and KITTI `.bin`."""
