"""Rotations, camera models and stereo rigs (pure numpy)."""
