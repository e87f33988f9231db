"""Depth: EXR/NPY depth files, depth priors (plane sweep, video depth models), alignment to SfM points and
depth-map metrics."""
