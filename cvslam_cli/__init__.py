"""cvslam: cooperative stereo visual SLAM from MCAP logs."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cvslam")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"
