"""Adaptive SIFT, stereo-constrained matching, triangulation and the feature format."""
