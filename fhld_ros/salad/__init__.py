"""SALAD (ONCE-3DLanes §4): monocular 3D lanes from one camera image, without IPM or
extrinsics. A segmentation branch finds lane pixels; a spatial branch regresses per pixel the
sub-pixel offsets (du, dv) and a depth residual on a per-row shift and scale; lanes are
clustered, back-projected with the intrinsics and fitted (decode.py)."""
