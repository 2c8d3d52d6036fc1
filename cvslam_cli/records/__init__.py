"""The records every stage exchanges: log records, the feature set, pose tables, the landmark
map, and the array aliases and the one shape validator they are checked with.

The lowest floor of the package after `geometry/` (DESIGN.md section 6): these modules import
only numpy, the standard library, `cvslam_cli.errors` and `cvslam_cli.geometry` (and
`arrays.py` only numpy, so that `geometry/` can use its aliases too). No I/O, no algorithms:
`io/` reads and writes these records, the stages compute them.
"""
