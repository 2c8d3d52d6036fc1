"""Simulation: ground-truth motion, sensors, and scenes for `cvslam simulate`."""
