"""`cvslam mosaic`: images projected on the ground with their poses, blended."""
