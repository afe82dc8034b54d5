"""Synthetic CVGL-style stereo data: rendering, rig protocols and HDF5 storage."""
