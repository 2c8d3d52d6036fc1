"""Dataset importers: EuRoC MAV (ASL layout) and KITTI odometry folders to cvslam MCAP logs.

Each importer reads and checks a dataset folder, converts its world frame to the nav frame
(NED) once, and writes one ROS 2 MCAP log with the default topic map of DESIGN.md section 4.
"""
