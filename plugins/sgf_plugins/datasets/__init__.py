"""Dataset adapters for recorded data: the folder format, KITTI odometry, EuRoC/ASL and ROS bags."""
