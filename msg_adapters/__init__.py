"""ROS message <-> numpy adapters.

Nothing here imports rclpy at module level: the functions are duck-typed and work on rclpy
messages, rosbags dataclasses and mcap_ros2 decoded objects alike.
"""
