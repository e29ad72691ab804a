"""Shared probabilistic 3-D voxel map from all rovers' stereo (Sujan 2002, ch. 3.2)."""
