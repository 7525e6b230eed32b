"""LiDAR-initialised 3D Gaussian reconstruction of a driving scene (paper: Large-scale 3D Gaussian Reconstruction)."""
