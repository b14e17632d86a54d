"""What a running agent and the team server publish to ROS 2 (slam.io.ros2), read from their state as they go."""
