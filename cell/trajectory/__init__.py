"""Joint trajectories planned elsewhere: the type, its checks and its motion (model), files and ROS 2 bags."""
