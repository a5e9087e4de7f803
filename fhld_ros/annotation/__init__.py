"""The ONCE-3DLanes annotation pipeline (`fhld autolabel`): 3D lane labels from 2D image lane
labels and the LiDAR sweeps of the same drive (docs/annotation.md)."""
