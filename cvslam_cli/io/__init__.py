"""All file I/O: MCAP logs in and out, dataset importers, run directories, trajectories.

The estimation core never imports from here; stages pass it arrays and records.
"""
